"""Publishing one output file and its sidecars as a unit (issue 8, items 1-4).

- **Checked before any work** (:meth:`OutputSet.__init__`): the target is not a directory, its folder
  exists and is writable, the disk has room for the planned bytes, no sidecar name belongs to another
  output, and no other run is writing the same target (an exclusive lock, held until the end).
- **Staged under unique names** (``.NAME.PID-RANDOM.partial`` beside the target), so two runs never share
  a staging file; the staged files are removed on any failure (a full disk while writing leaves nothing).
- **Published in an order that never mixes runs**: the old sidecars go first, then the volume is renamed
  into place, then the new sidecars. A reader, or a run killed at any point, sees the previous volume
  (complete: its record is embedded in its own metadata), the new volume with or without its sidecars,
  never a volume beside another run's sidecars.

Sidecar names: ``STEM.cm2cl.json`` (the record) and ``STEM.cm2cl.log.csv`` (the iteration log), so they
cannot overwrite files that are not cm2cl's; a record whose ``output`` names another file is refused.
"""

from __future__ import annotations

import fcntl
import json
import os
import secrets
import shutil
from pathlib import Path

from ..errors import InputError
from .staging import alive
from .tiff import tiff_stem

#: fault injection for tests: CM2CL_FAULT=publish.<step> kills the process (SIGKILL) at that step
FAULT_ENV = "CM2CL_FAULT"
STEPS = ("staged", "old_sidecars_removed", "volume_published")


def fault_point(name: str) -> None:
    if os.environ.get(FAULT_ENV) == name:
        import signal

        os.kill(os.getpid(), signal.SIGKILL)


def exclusive_lock(path, refusal: str) -> int:
    """An exclusive, non-blocking lock on the file ``path`` (created if needed): its descriptor, held
    until closed; an InputError saying ``refusal`` when another process holds it."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        raise InputError(refusal) from exc
    return fd


def sidecar_names(target) -> dict[str, Path]:
    stem = tiff_stem(Path(target))
    return {"record": stem.with_name(stem.name + ".cm2cl.json"),
            "log": stem.with_name(stem.name + ".cm2cl.log.csv")}


def _remove_stale(parent: Path, names) -> None:
    """Staged files left by runs that were killed (their process is gone); called under the lock."""
    for name in names:
        for p in parent.glob(f".{name}.*-*.partial"):
            pid = p.name[len(name) + 2:].split("-", 1)[0]
            if pid.isdigit() and not alive(int(pid)):
                p.unlink(missing_ok=True)


class OutputSet:
    """``OutputSet(target, expected_bytes, inputs)``; ``staged(key)`` gives the temporary path of
    ``'volume'``, ``'record'`` or ``'log'``; ``publish()`` moves them in; ``close()`` releases the lock and
    removes what was not published. Use as a context manager."""

    def __init__(self, target, expected_bytes: int = 0, inputs=(), what: str = "--output"):
        self.target = Path(target)
        self.what = what
        t = self.target
        if t.is_dir():
            raise InputError(f"{what} '{t}': is a directory; give a file name (e.g. {t / 'volume.ome.tif'})")
        parent = t.parent if str(t.parent) else Path(".")
        if not parent.is_dir():
            raise InputError(f"{what} '{t}': folder '{parent}' does not exist")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise InputError(f"{what} '{t}': folder '{parent}' is not writable")
        for src in inputs:
            if src is not None and Path(src).exists() and t.exists() and t.resolve() == Path(src).resolve():
                raise InputError(f"{what} '{t}': would overwrite the input '{src}'")
        free = shutil.disk_usage(parent).free
        need = int(expected_bytes * 1.05) + (1 << 20)
        if expected_bytes and free < need:
            raise InputError(f"{what} '{t}': {free / 2**20:.0f} MiB free in '{parent}', the output needs "
                             f"about {need / 2**20:.0f} MiB")
        self.sidecars = sidecar_names(t)
        rec = self.sidecars["record"]
        if rec.exists():
            try:
                owner = json.loads(rec.read_text()).get("output")
            except (OSError, ValueError, AttributeError):
                owner = None
            if owner != t.name:
                raise InputError(f"{what} '{t}': '{rec}' exists and is not this output's record; not overwritten")
        self._lock_path = parent / f".{t.name}.cm2cl-lock"
        self._lock = exclusive_lock(self._lock_path, f"{what} '{t}': another run is writing it; wait for it or "
                                                     "choose another output")
        _remove_stale(parent, [t.name, self.sidecars["record"].name, self.sidecars["log"].name])
        tag = f"{os.getpid()}-{secrets.token_hex(4)}"
        self._staged = {"volume": parent / f".{t.name}.{tag}.partial",
                        "record": parent / f".{self.sidecars['record'].name}.{tag}.partial",
                        "log": parent / f".{self.sidecars['log'].name}.{tag}.partial"}
        self.published = False

    def staged(self, key: str) -> Path:
        return self._staged[key]

    def publish(self) -> None:
        fault_point("publish.staged")
        for key in ("record", "log"):
            if self.sidecars[key].exists():
                self.sidecars[key].unlink()
        fault_point("publish.old_sidecars_removed")
        os.replace(self._staged["volume"], self.target)
        fault_point("publish.volume_published")
        for key in ("log", "record"):
            if self._staged[key].exists():
                os.replace(self._staged[key], self.sidecars[key])
        self.published = True

    def close(self) -> None:
        for p in self._staged.values():
            if p.exists():
                p.unlink()
        if self._lock is not None:
            try:
                self._lock_path.unlink()
            except OSError:
                pass
            os.close(self._lock)
            self._lock = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

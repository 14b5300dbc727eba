"""Outputs that appear only when complete: output-folder checks, staged folders, JSON records."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["jsonable", "check_output_dir", "StagedOutput"]


def jsonable(obj):
    """Plain JSON types for numpy arrays and scalars, paths, tuples and dataclasses (recursively)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "__dataclass_fields__"):
        import dataclasses
        return jsonable(dataclasses.asdict(obj))
    return obj


def check_output_dir(outdir, record_name: str | None = None, expected_bytes: int = 0) -> Path:
    """The parent of an output folder, created if needed, checked before any work: an InputError if
    ``outdir`` is a file, its parent is not writable or lacks room for ``expected_bytes``, or it is a
    non-empty folder that is not a previous output of the same command (no ``record_name`` in it)."""
    out = Path(outdir)
    if out.exists() and not out.is_dir():
        raise InputError(f"output '{out}': exists and is not a directory")
    parent = out.resolve().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"output '{out}': cannot create its parent directory ({exc})") from exc
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"output '{out}': folder '{parent}' is not writable")
    free = shutil.disk_usage(parent).free
    if expected_bytes and free < int(expected_bytes * 1.05) + (1 << 20):
        raise InputError(f"output '{out}': {free / 2**20:.0f} MiB free in '{parent}', the output needs about "
                         f"{expected_bytes / 2**20:.0f} MiB")
    if record_name and out.is_dir() and any(out.iterdir()) and not (out / record_name).exists():
        raise InputError(f"output '{out}': a non-empty folder that is not a previous output of this "
                         f"command (no {record_name}); not replaced: choose a new or empty folder")
    return parent


def alive(pid: int) -> bool:
    """Whether process ``pid`` still runs (its staged files are not stale)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class StagedOutput:
    """Build a folder of outputs beside ``outdir`` and publish it whole when complete.

    ``with StagedOutput(outdir, record_name) as stage:`` gives ``stage.dir`` (a temporary folder next to
    ``outdir``) to write into; ``stage.publish(names, record_name, text)`` writes the JSON record into it
    and swaps it in for ``outdir``: the previous folder is renamed aside, the new one renamed into place,
    then the previous one removed. A reader or an interrupted run never finds new files beside old ones;
    a previous complete result is replaced only by a complete one. An existing non-empty ``outdir`` is
    accepted only when it holds ``record_name`` (it is a previous output of the same command), checked
    before any work; other folders are refused, not replaced. Staging folders left by killed runs are
    removed by the next run on the same output.
    """

    def __init__(self, outdir, record_name: str | None = None):
        import tempfile

        from .publish import exclusive_lock

        self.out = Path(outdir)
        parent = check_output_dir(self.out, record_name)
        self._lock_path = parent / f".{self.out.name}.cm2cl-lock"
        self._lock = exclusive_lock(self._lock_path, f"output '{self.out}': another run is writing it; wait for "
                                                     "it or choose another folder")
        for old in parent.glob(f".{self.out.name}.old-*"):
            pid = old.name.rsplit("-", 1)[-1]
            if pid.isdigit() and not alive(int(pid)):
                if not self.out.exists():
                    os.replace(old, self.out)   # a run killed mid-swap: the previous result comes back
                else:
                    shutil.rmtree(old, ignore_errors=True)
        for stale in parent.glob(f".{self.out.name}.partial-*"):
            pid = stale.name.rsplit("-", 2)[-2] if stale.name.count("-") >= 2 else ""
            if pid.isdigit() and not alive(int(pid)):
                shutil.rmtree(stale, ignore_errors=True)
        self.dir = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.partial-{os.getpid()}-", dir=parent))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(self.dir, 0o777 & ~umask)  # mkdtemp makes it private; the result is a normal folder

    def publish(self, names, record_name: str, text: str):
        out, tmp = self.out, self.dir
        (tmp / record_name).write_text(text)
        if not out.exists():
            os.replace(tmp, out)
            return
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        os.replace(out, old)          # from here the target is absent, never mixed
        from .publish import fault_point

        fault_point("swap.old_moved_aside")
        os.replace(tmp, out)
        shutil.rmtree(old, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.dir.exists():
            shutil.rmtree(self.dir, ignore_errors=True)
        if self._lock is not None:
            try:
                self._lock_path.unlink()
            except OSError:
                pass
            os.close(self._lock)
            self._lock = None
        return False

"""Publishing one output file and its sidecars as a unit (issue 8, items 1-4).

- **Checked before any work** (:func:`check_output_file`): the target is not a directory, its folder
  exists and is writable, the disk has room for the planned bytes, it is not an input, and no sidecar
  name belongs to another output. Nothing is created by the check.
- **One run per target**: :class:`OutputSet` takes an exclusive lock (``.NAME.cm2cl-lock``) before the
  work and holds it to the end: a second run on the same target is refused.
- **Staged under unique names** (``.NAME.PID-RANDOM.partial`` beside each final name), removed on any
  failure, so a full disk while writing leaves nothing.
- **Published as one unit** with a commit record (a journal, ``.NAME.cm2cl-publish``): once every member
  is staged, the journal naming the moves is written in one rename (the commit); then the previous
  unit's sidecars are removed, the volume is renamed into place, then the new sidecars, the record last.
  A reader never finds a volume beside another run's sidecars: each moment shows one run's files. A
  run killed before the commit leaves the previous result untouched; one killed after it is completed
  by the next run on the same target (under its lock, before anything else), so the target ends up
  holding the previous complete result or the new complete result.

Sidecar names: ``STEM.cm2cl.json`` (the record) and ``STEM.cm2cl.log.csv`` (the iteration log), plus
optional members (``extras``, e.g. the removed background); a name is overwritten only when it is
cm2cl's own (``.cm2cl.`` in it) and the record beside it names this output, or, for other names, when that
record lists it among its ``files``. Anything else is refused, never overwritten.
"""

from __future__ import annotations

import json
import os
import re
import secrets
from pathlib import Path

from ..errors import InputError
from .staging import (FAULT_ENV, alive, check_room, exclusive_lock, fault_point, make_parents, remove_empty,  # noqa: F401
                      release_lock)
from .tiff import tiff_stem

__all__ = ["OutputSet", "check_output_file", "sidecar_names", "STEPS", "FAULT_ENV", "fault_point",
           "exclusive_lock"]

#: the named steps of publishing (fault points ``publish.<step>``), in order; ``log`` and extras are
#: passed only when the unit has them
STEPS = ("staged", "committed", "old_removed", "volume", "log", "record")
SIDECARS = {"record": ".cm2cl.json", "log": ".cm2cl.log.csv"}
_PARTIAL = re.compile(r"\.(\d+)-[0-9a-f]{8}\.partial$")


def sidecar_names(target, extras: dict | None = None) -> dict[str, Path]:
    """{key: path} of the sidecars of ``target``: ``record`` and ``log``, and ``extras`` ({key: suffix})."""
    stem = tiff_stem(Path(target))
    return {key: stem.with_name(stem.name + suffix) for key, suffix in {**SIDECARS, **(extras or {})}.items()}


def _record_of(target: Path):
    """The record beside ``target`` as (exists, dict or None)."""
    rec = sidecar_names(target)["record"]
    if not rec.exists():
        return False, None
    try:
        doc = json.loads(rec.read_text())
    except (OSError, ValueError):
        return True, None
    return True, doc if isinstance(doc, dict) else None


#: the longest tag a staged name carries (a Linux pid and 8 hex digits; see OutputSet)
_LONGEST_TAG = "4194304-ffffffff"


def check_name_length(t: Path, names, what: str = "output") -> None:
    """Refuse an output whose own name, or a name staged beside it while it is written (``.NAME.TAG.partial``
    of it and of each of ``names``, the publish journal's), is longer than its folder allows, before any
    work (it used to fail after the solve and leave its lock)."""
    try:
        limit = os.pathconf(t.parent, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):   # no pathconf (Windows) or no such folder yet
        limit = 255
    staged = [f".{n}.{_LONGEST_TAG}.partial" for n in [t.name, *names]] + [f".{t.name}.cm2cl-publish.{_LONGEST_TAG}.partial"]
    longest = max(staged, key=len)
    if len(t.name) > limit or len(longest) > limit:
        raise InputError(f"{what} '{t.name}': a name of {len(t.name)} characters is too long for its folder "
                         f"({limit} at most, and the files staged beside it while it is written add "
                         f"{len(longest) - len(t.name)}); choose a name of at most {limit - (len(longest) - len(t.name))}")


def check_output_file(target, expected_bytes: int = 0, inputs=(), what: str = "output",
                      extras: dict | None = None) -> Path:
    """Check an output file and its sidecars before any work, creating nothing (InputError naming
    ``what`` otherwise). Returns its folder."""
    t = Path(target)
    parent = t.parent
    if not parent.is_dir():     # missing folders are made by OutputSet (checked here: writable, room)
        check_room(t, what, expected_bytes)
        return parent
    check_name_length(t, [p.name for p in sidecar_names(t, extras).values()], what)
    if t.is_dir():
        raise InputError(f"{what} '{t}': is a directory; give a file name (e.g. {t / 'volume.ome.tif'})")
    check_room(t, what, expected_bytes)
    for src in inputs:
        if src is not None and Path(src).exists() and t.exists() and t.resolve() == Path(src).resolve():
            raise InputError(f"{what} '{t}': would overwrite the input '{src}'")
    if (parent / f".{t.name}.cm2cl-publish").exists():
        return parent        # a killed run's publication: completed under the lock, then checked again
    exists, doc = _record_of(t)
    names = sidecar_names(t, extras)
    if exists and (doc or {}).get("output") != t.name:
        raise InputError(f"{what} '{t}': '{names['record']}' exists and is not this output's record; not overwritten")
    listed = set((doc or {}).get("files") or ())
    for key, path in names.items():   # the log too: a user's own OUT.cm2cl.log.csv is not ours to replace
        if key != "record" and path.exists() and path.name not in listed:
            raise InputError(f"{what} '{t}': '{path}' exists and is not this output's; not overwritten")
    return parent


class OutputSet:
    """``with OutputSet(target, expected_bytes, inputs, extras=...) as outset:`` checks and locks the
    target; ``outset.staged(key)`` is the temporary path of ``'volume'``, ``'record'``, ``'log'`` or an
    extra; ``outset.record_fields()`` are the keys the record must carry (``output``, ``files``);
    ``outset.publish()`` moves the staged members in as one unit. Leaving the block releases the lock and
    removes what was not published; an OSError while writing becomes one InputError."""

    def __init__(self, target, expected_bytes: int = 0, inputs=(), what: str = "output",
                 extras: dict | None = None):
        self.target = t = Path(target)
        self.what = what
        self.extras = dict(extras or {})
        self.parent = parent = check_output_file(t, expected_bytes, inputs, what, self.extras)
        self.sidecars = sidecar_names(t, self.extras)
        self._lock_path = parent / f".{t.name}.cm2cl-lock"
        self._journal = parent / f".{t.name}.cm2cl-publish"
        self._staged = {}
        self._committed = False
        self.published = False
        self._created = []      # the output's missing folders, made here, removed again if nothing is published
        try:
            self._created = make_parents(parent)
            if self._created:
                check_name_length(t, [p.name for p in self.sidecars.values()], what)
            self._lock = exclusive_lock(self._lock_path, f"{what} '{t}': another run is writing it; wait for it "
                                                         "or choose another output")
        except OSError as exc:
            remove_empty(self._created)
            raise InputError(f"{what} '{t}': cannot write in '{parent}' ({exc.strerror or exc})") from exc
        except BaseException:
            remove_empty(self._created)
            raise
        try:
            if self._journal.exists():        # a run killed after its commit: complete its publication
                self._roll_forward()
            self._remove_stale()
            check_output_file(t, 0, inputs, what, self.extras)   # again, on what the recovery left
        except BaseException:
            self.close()
            raise
        tag = f"{os.getpid()}-{secrets.token_hex(4)}"
        finals = {"volume": t, **self.sidecars}
        self._staged = {key: parent / f".{p.name}.{tag}.partial" for key, p in finals.items()}

    def staged(self, key: str) -> Path:
        return self._staged[key]

    def record_fields(self) -> dict:
        """What the record must say: the output it belongs to and the files of the unit, those staged so
        far and the record (so that the next run replaces exactly those); call it when the other
        members are written."""
        members = [p.name for k, p in self.sidecars.items() if k == "record" or self._staged[k].exists()]
        return {"output": self.target.name, "files": [self.target.name] + members}

    def _remove_stale(self) -> None:
        """Staged files left by runs killed before their commit (their process is gone)."""
        for final in [self.target, *self.sidecars.values(), self._journal]:
            for p in self.parent.glob(f".{final.name}.*.partial"):
                m = _PARTIAL.search(p.name)
                if m and p.name == f".{final.name}{m.group(0)}" and not alive(int(m.group(1))):
                    p.unlink(missing_ok=True)

    def publish(self) -> None:
        fault_point("publish.staged")
        finals = {"volume": self.target, **self.sidecars}
        order = ["volume"] + [k for k in finals if k not in ("volume", "record")] + ["record"]
        moves = [[k, self._staged[k].name, finals[k].name] for k in order if self._staged[k].exists()]
        if not moves or moves[0][0] != "volume":
            raise InputError(f"{self.what} '{self.target}': nothing to publish (the volume was not written)")
        exists, doc = _record_of(self.target)
        old = {p.name for p in self.sidecars.values()}
        old |= {n for n in (doc or {}).get("files") or () if isinstance(n, str) and "/" not in n
                and n != self.target.name and n.startswith(tiff_stem(self.target).name + ".")}
        tmp = self._journal.with_name(self._journal.name + f".{self._staged['volume'].name.split('.')[-2]}.partial")
        tmp.write_text(json.dumps({"moves": moves, "remove": sorted(old)}))
        os.replace(tmp, self._journal)    # the commit: from here the new unit is what the target holds
        self._committed = True
        fault_point("publish.committed")
        self._roll_forward()
        self.published = True

    def _roll_forward(self) -> None:
        """Carry out the journal's moves; each step is done at most once, so a run killed here is
        completed by the next one."""
        plan = json.loads(self._journal.read_text())
        moves = plan["moves"]
        if (self.parent / moves[0][1]).exists():     # the volume is not in place: the previous unit goes first
            for name in plan["remove"]:
                (self.parent / name).unlink(missing_ok=True)
            fault_point("publish.old_removed")
        for key, staged, final in moves:
            if (self.parent / staged).exists():
                os.replace(self.parent / staged, self.parent / final)
                fault_point(f"publish.{key}")
        self._journal.unlink()

    def close(self) -> None:
        keep = self._committed and self._journal.exists()     # publication under way: the next run completes it
        for p in self._staged.values():
            if p.exists() and not keep:
                p.unlink()
        if self._lock is not None:
            release_lock(self._lock, self._lock_path)
            self._lock = None
        if not self.published and not keep:
            remove_empty(self._created)
            self._created = []

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        self.close()
        if isinstance(exc, OSError):      # a full disk or a vanished folder while writing
            if self._committed and not self.published:
                raise InputError(f"{self.what} '{self.target}': publishing failed ({exc.strerror or exc}); the "
                                 "next run on this output completes it") from exc
            raise InputError(f"{self.what} '{self.target}': writing failed ({exc.strerror or exc}); nothing was "
                             "written") from exc
        return False

"""Outputs that appear only when complete: checks of an output location, locks, fault points, and
output folders staged beside their target and swapped in whole (:class:`StagedOutput`).

- **Checked before any work** (:func:`check_output_dir`, :func:`check_room`): nothing is created by a
  check; the nearest existing folder must be writable and have room for the planned bytes.
- **One run per target**: an exclusive lock file ``.NAME.cm2cl-lock`` beside the target, taken before
  the work and held until the end; a second run on the same target is refused.
- **Unique staging**: ``.NAME.partial-PID-RANDOM`` beside the target; removed on any failure, and
  staging left by a killed run is removed by the next run on the same target.
- **Swapped in whole**: a previous folder and the new one are exchanged in one step
  (``renameat2(RENAME_EXCHANGE)`` on Linux), so the target always holds a complete result, the previous
  one or the new one. Where the filesystem cannot exchange, the previous folder is renamed aside first;
  a run killed between the two renames leaves the target absent, never mixed, and the next run on the
  target puts the previous result back before anything else.

Fault points for tests: ``CM2CL_FAULT=<step>`` kills the process (SIGKILL) at that step,
``CM2CL_FAULT=<step>:pause`` stops it there (SIGSTOP) so that a test can look at the files first.
"""

from __future__ import annotations

import errno
import os
import shutil
import signal
import tempfile
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["jsonable", "check_output_dir", "check_room", "StagedOutput", "fault_point", "exclusive_lock",
           "release_lock", "exchange", "make_parents", "remove_empty", "FAULT_ENV", "FOLDER_STEPS"]

#: environment variable of the fault points (tests only)
FAULT_ENV = "CM2CL_FAULT"
#: the named steps of publishing a folder (:meth:`StagedOutput.publish`)
FOLDER_STEPS = ("folder.staged", "folder.swapped")


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


def fault_point(name: str) -> None:
    """Tests: ``CM2CL_FAULT=name`` kills this process here (SIGKILL, nothing cleaned up);
    ``CM2CL_FAULT=name:pause`` stops it here (SIGSTOP) until the test looks and kills it."""
    value = os.environ.get(FAULT_ENV)
    if value == name:
        os.kill(os.getpid(), signal.SIGKILL)
    elif value == f"{name}:pause":
        os.kill(os.getpid(), signal.SIGSTOP)


def alive(pid: int) -> bool:
    """Whether process ``pid`` still runs (its staged files are not stale); psutil's test, which on
    Windows does not send a signal (``os.kill(pid, 0)`` there would stop the process)."""
    import psutil

    return psutil.pid_exists(int(pid))


def _lock_nonblocking(fd: int) -> None:
    """An exclusive, non-blocking lock on the open file ``fd``: ``flock`` on POSIX, ``msvcrt.locking`` of
    its first byte on Windows; an OSError with EWOULDBLOCK / EAGAIN / EACCES when another process holds it."""
    try:
        import fcntl
    except ImportError:          # Windows
        import msvcrt

        os.lseek(fd, 0, os.SEEK_SET)
        msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
        return
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)


def exclusive_lock(path, refusal: str) -> int:
    """An exclusive, non-blocking lock on the file ``path`` (created if needed): its descriptor, held
    until :func:`release_lock` or close; an InputError saying ``refusal`` when another process holds it.
    A holder that unlinks the file when done (:func:`release_lock`) may do so between our open and our
    lock: the lock is then on a file nobody else sees, so it is taken again on the file at ``path``."""
    path = Path(path)
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            _lock_nonblocking(fd)
        except OSError as exc:
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES, getattr(errno, "EDEADLOCK", -1)):
                raise InputError(refusal) from exc
            raise
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)


def release_lock(fd: int, path) -> None:
    """Remove the lock file while still holding it, then release: no lock file is left behind."""
    try:
        Path(path).unlink()
    except OSError:
        pass
    os.close(fd)


def exchange(a, b) -> bool:
    """Swap the paths ``a`` and ``b`` in one atomic step (Linux ``renameat2(RENAME_EXCHANGE)``); False
    where the system or the filesystem cannot (the caller falls back to two renames)."""
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    if renameat2(at_fdcwd, os.fsencode(str(a)), at_fdcwd, os.fsencode(str(b)), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.EPERM):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _existing_ancestor(path: Path) -> Path:
    p = path.absolute().parent
    while not p.exists():
        p = p.parent
    return p


def check_room(out, what: str, expected_bytes: int = 0) -> Path:
    """The nearest existing folder above ``out``: an InputError if a file is in the way, if it is not
    writable, or if its disk has no room for ``expected_bytes`` (plus 5% and 1 MiB). Creates nothing."""
    folder = _existing_ancestor(Path(out))
    if not folder.is_dir():
        raise InputError(f"{what} '{out}': '{folder}' is a file, not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"{what} '{out}': folder '{folder}' is not writable")
    free = shutil.disk_usage(folder).free
    need = int(expected_bytes * 1.05) + (1 << 20)
    if expected_bytes and free < need:
        raise InputError(f"{what} '{out}': {free / 2**20:.0f} MiB free in '{folder}', the output needs about "
                         f"{need / 2**20:.0f} MiB")
    return folder


def check_output_dir(outdir, record_name: str | None = None, expected_bytes: int = 0, what: str = "output") -> Path:
    """Check an output folder before any work, creating nothing: an InputError if ``outdir`` is a file,
    the nearest existing folder above it is not writable or lacks room for ``expected_bytes``, or it is a
    non-empty folder that is not a previous output of the same command (no ``record_name`` in it).
    Returns the nearest existing folder."""
    out = Path(outdir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{what} '{out}': exists and is not a directory")
    folder = check_room(out, what, expected_bytes)
    if record_name and out.is_dir() and any(out.iterdir()) and not (out / record_name).exists():
        raise InputError(f"{what} '{out}': a non-empty folder that is not a previous output of this "
                         f"command (no {record_name}); not replaced: choose a new or empty folder")
    return folder


def make_parents(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; the ones created, deepest first."""
    missing = []
    p = folder.absolute()
    while not p.exists():
        missing.append(p)
        p = p.parent
    folder.mkdir(parents=True, exist_ok=True)
    return missing


def remove_empty(folders) -> None:
    for d in folders:
        try:
            d.rmdir()
        except OSError:
            break


class StagedOutput:
    """An output folder built beside ``outdir`` and swapped in whole when complete.

    ``with StagedOutput(outdir, record_name, expected_bytes) as stage:`` checks the target before any
    work (:func:`check_output_dir`), locks it against other runs, and gives ``stage.dir`` (a unique folder
    beside ``outdir``) to write into; ``stage.publish(record_name, text)`` writes the record there last
    and swaps the folder in for ``outdir``. Enter it before the long work: the lock is held from the
    check to the publication. On any failure nothing is left: the staging folder, the lock file and the
    parent folders this run created are removed; an ``OSError`` while writing becomes an InputError."""

    def __init__(self, outdir, record_name: str | None = None, expected_bytes: int = 0, what: str = "output"):
        self.out = Path(outdir)
        self.what = what
        self.record_name = record_name
        check_output_dir(self.out, record_name, expected_bytes, what)
        parent = self.out.absolute().parent
        self._lock = None
        self.dir = None
        self.published = False
        try:
            self._created = make_parents(parent)
        except OSError as exc:
            raise InputError(f"{what} '{self.out}': cannot create its folder ({exc.strerror})") from exc
        try:
            self._lock_path = parent / f".{self.out.name}.cm2cl-lock"
            self._lock = exclusive_lock(self._lock_path, f"{what} '{self.out}': another run is writing it; "
                                                         "wait for it or choose another output")
            self._recover(parent)
            check_output_dir(self.out, record_name, 0, what)    # again, after a killed run's result came back
            self.dir = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.partial-{os.getpid()}-", dir=parent))
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(self.dir, 0o777 & ~umask)  # mkdtemp makes it private; the result is a normal folder
        except BaseException as exc:
            self.close()
            if isinstance(exc, OSError):
                raise InputError(f"{what} '{self.out}': cannot write beside it ({exc.strerror})") from exc
            raise

    def _recover(self, parent: Path) -> None:
        """Under the lock: what killed runs left beside the target. A previous result renamed aside (the
        two-rename fallback) comes back if the target is absent; staging folders are removed."""
        for old in parent.glob(f".{self.out.name}.old-*"):
            pid = old.name.rsplit("-", 1)[-1]
            if pid.isdigit() and not alive(int(pid)):
                if not self.out.exists():
                    os.replace(old, self.out)
                else:
                    shutil.rmtree(old, ignore_errors=True)
        for stale in parent.glob(f".{self.out.name}.partial-*"):
            pid = stale.name.rsplit("-", 2)[-2] if stale.name.count("-") >= 2 else ""
            if pid.isdigit() and not alive(int(pid)):
                shutil.rmtree(stale, ignore_errors=True)

    def publish(self, record_name: str, text: str) -> None:
        """Write the record (last file), then swap the staged folder in for the target."""
        out, tmp = self.out, self.dir
        (tmp / record_name).write_text(text)
        fault_point("folder.staged")
        if not out.exists():
            os.rename(tmp, out)
        elif exchange(tmp, out):          # the target now holds the new result, tmp the previous one
            fault_point("folder.swapped")
            shutil.rmtree(tmp, ignore_errors=True)
        else:                             # no atomic exchange here: absent for a moment, never mixed
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            os.replace(out, old)
            fault_point("folder.old_moved_aside")
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        self.published = True

    def close(self) -> None:
        if self.dir is not None and self.dir.exists():
            shutil.rmtree(self.dir, ignore_errors=True)
        if self._lock is not None:
            release_lock(self._lock, self._lock_path)
            self._lock = None
        if not self.published:
            remove_empty(self._created)

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        self.close()
        if isinstance(exc, OSError):      # a full disk or a vanished folder while writing
            raise InputError(f"{self.what} '{self.out}': writing failed ({exc.strerror or exc}); nothing was "
                             "written" + (", the previous result is kept" if self.out.exists() else "")) from exc
        return False

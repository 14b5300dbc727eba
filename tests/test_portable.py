"""What keeps cm2cl starting on every OS (issue 26): the output lock without fcntl (Windows' msvcrt path,
exercised with a stand-in module), a liveness test that sends no signal, peak memory without resource."""

import errno
import os
import subprocess
import sys
import types

import pytest

from cm2cl.errors import InputError
from cm2cl.io import staging


def test_lock_takes_the_windows_path_where_fcntl_is_missing(tmp_path, monkeypatch):
    held = set()

    def locking(fd, mode, nbytes):
        key = os.fstat(fd).st_ino
        assert mode == fake.LK_NBLCK and nbytes == 1 and os.lseek(fd, 0, os.SEEK_CUR) == 0
        if key in held:
            raise OSError(errno.EACCES, "locked")
        held.add(key)

    fake = types.SimpleNamespace(LK_NBLCK=2, locking=locking)
    monkeypatch.setitem(sys.modules, "fcntl", None)      # import fcntl raises ImportError, as on Windows
    monkeypatch.setitem(sys.modules, "msvcrt", fake)
    lock = tmp_path / ".v.cm2cl-lock"
    fd = staging.exclusive_lock(lock, "another run holds it")
    with pytest.raises(InputError, match="another run holds it"):
        staging.exclusive_lock(lock, "another run holds it")
    staging.release_lock(fd, lock)
    assert not lock.exists()


def test_alive_and_peak_memory():
    assert staging.alive(os.getpid())
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    assert not staging.alive(p.pid)
    from cm2cl.solver.memory import peak_rss_bytes

    assert 10 * 2**20 < peak_rss_bytes() < 64 * 2**30

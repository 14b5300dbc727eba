"""Rates measured on a device in a fraction of a second: its copy-kernel bandwidth (the floor of every
memory-bound step) and the host <-> device transfer rate (what streamed slabs pay). The planner turns
them into an expected time per iteration."""

from __future__ import annotations

import time

import numpy as np

from . import kernels

__all__ = ["copy_rate", "transfer_rate"]


def _best(fn, sync, repeat=3) -> float:
    fn()
    sync()
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        sync()
        best = min(best, time.perf_counter() - t)
    return best


def copy_rate(rt, nbytes: int = 64 * 2**20) -> float:
    """Bytes per second a device copy kernel moves (read + write counted), float32, best of 3."""
    import pyopencl.array as cla

    n = int(nbytes) // 4
    a = cla.zeros(rt.queue, n, np.float32)
    b = cla.empty(rt.queue, n, np.float32)
    k = kernels.kernel(rt, "layout.cl", "copy_real", np.float32)
    t = _best(lambda: k(rt.queue, (n,), None, b.data, a.data, np.uint64(n)), rt.queue.finish)
    return 2 * n * 4 / t


def transfer_rate(rt, nbytes: int = 64 * 2**20) -> float:
    """Bytes per second of a host -> device copy followed by device -> host (both counted), best of 3."""
    import pyopencl.array as cla

    host = np.zeros(int(nbytes) // 4, np.float32)
    dev = cla.empty(rt.queue, host.size, np.float32)

    def both():
        dev.set(host)
        dev.get(ary=host)

    return 2 * host.nbytes / _best(both, rt.queue.finish)

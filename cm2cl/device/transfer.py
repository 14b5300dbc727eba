"""Host <-> device copies that overlap with compute: a second queue for copies, events that order it
against the device's work queue, and pinned (driver-allocated, mapped) host arrays.

The solver's streamed slabs (:mod:`cm2cl.solver.parts`) use this; it is the only place outside the
runtime that touches pyopencl's queues and events directly.
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl

__all__ = ["CopyQueue", "work_done", "wait_before_work", "pinned_array"]


class CopyQueue:
    """A second in-order queue on the runtime's context for copies. Every call enqueues without
    blocking; ``wait`` is a list of events (from :func:`work_done` or :meth:`marker`) to wait for."""

    def __init__(self, rt):
        self.queue = cl.CommandQueue(rt.context)

    def upload(self, dev, host: np.ndarray, wait=()):
        """Copy ``host`` into the device array ``dev`` (a view into a larger buffer is fine)."""
        cl.enqueue_copy(self.queue, dev.base_data, host, dst_offset=dev.offset, is_blocking=False,
                        wait_for=list(wait) or None)

    def download(self, host: np.ndarray, dev, wait=()):
        """Copy the device array ``dev`` into ``host`` (which must stay alive until :meth:`finish`)."""
        cl.enqueue_copy(self.queue, host, dev.base_data, src_offset=dev.offset, is_blocking=False,
                        wait_for=list(wait) or None)

    def marker(self, wait=()):
        """An event complete once ``wait`` and every copy enqueued so far are."""
        return cl.enqueue_marker(self.queue, wait_for=list(wait) or None)

    def finish(self):
        self.queue.finish()


def work_done(rt):
    """An event complete once everything enqueued so far on the runtime's work queue is."""
    return cl.enqueue_marker(rt.queue)


def wait_before_work(rt, events):
    """Make the runtime's work queue wait for ``events`` before anything enqueued after this."""
    events = [e for e in events if e is not None]
    if events:
        cl.enqueue_barrier(rt.queue, wait_for=events)


def pinned_array(rt, shape, dtype):
    """A zeroed host array mapped from a buffer the driver allocates in host memory (page-locked on
    GPUs, which lets the device copy while it computes), with the buffer that must be kept alive
    alongside it; ``(None, None)`` where the driver refuses."""
    nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    try:
        buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE | cl.mem_flags.ALLOC_HOST_PTR, nbytes)
        arr, _ = cl.enqueue_map_buffer(rt.queue, buf, cl.map_flags.READ | cl.map_flags.WRITE, 0,
                                       shape, dtype, is_blocking=True)
    except cl.Error:
        return None, None
    arr.fill(0)
    return arr, buf

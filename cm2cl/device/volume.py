"""Volumes on the device, stored per slab of depth planes.

No device buffer may exceed the device's largest single allocation, so a (nz, py, px) volume
is a list of slabs, each a contiguous pyopencl array of (planes, py, px).  Real volumes and
their spectra share the same slab bounds, chosen from the larger (complex) plane.

:func:`fill` and :func:`scale` work on any contiguous device array without pyopencl's elementwise
kernels, each of which is one more program for PoCL to compile on a cold start (docs/benchmarks.md,
"Measurements behind code choices").
"""

from __future__ import annotations

import numpy as np

from ..errors import DeviceError


def slab_bounds(nz: int, plane_bytes: int, max_alloc: int, max_planes: int | None = None):
    """Split nz planes into slabs of at most ``max_alloc`` bytes (and ``max_planes`` planes)."""
    if plane_bytes > max_alloc:
        raise DeviceError(
            f"one depth plane needs {plane_bytes / 2**20:.1f} MiB but the device's largest buffer "
            f"is {max_alloc / 2**20:.1f} MiB; bin the measurement or use lateral tiles"
        )
    per = max(1, max_alloc // plane_bytes)
    if max_planes:
        per = min(per, int(max_planes))
    return [(z, min(z + per, nz)) for z in range(0, nz, per)]


def upload(a, host: np.ndarray):
    """Copy ``host`` into device array ``a`` and keep no reference to it: pyopencl keeps each copy's event,
    which holds its host array, in the array's event list (up to 12 of them: 0.8 GiB of a full frame's
    padded PSF planes when they were uploaded one by one)."""
    a.set(host)
    a.finish()
    return a


def fill(rt, a, value=0):
    """Set every element of the contiguous device array ``a`` to ``value`` (clEnqueueFillBuffer,
    no kernel); returns ``a``."""
    import pyopencl as cl

    if not a.flags.forc:
        raise DeviceError(f"fill: the array {a.shape} is not contiguous")
    if a.size == 0:
        return a
    if rt.caps.platform.startswith("NVIDIA") and a.nbytes >= 2**31:
        return a.fill(value)   # NVIDIA's clEnqueueFillBuffer fails on 2 GiB and more (pyopencl issue 395)
    cl.enqueue_fill_buffer(rt.queue, a.base_data, a.dtype.type(value), a.offset, a.nbytes)
    return a


def copy_head(rt, dst, src):
    """Copy the first ``dst.nbytes`` bytes of device array ``src`` (any dtype) into ``dst``, on the device;
    returns ``dst``."""
    import pyopencl as cl

    if src.nbytes < dst.nbytes:
        raise DeviceError(f"copy_head: {src.nbytes} bytes in the source, {dst.nbytes} to copy")
    cl.enqueue_copy(rt.queue, dst.data, src.data, byte_count=dst.nbytes)
    return dst


def scale(rt, a, factor):
    """``a *= factor`` in place for the contiguous device array ``a`` (real or complex) and a real
    factor; returns ``a``."""
    from . import kernels

    if not a.flags.forc:
        raise DeviceError(f"scale: the array {a.shape} is not contiguous")
    real = np.finfo(a.dtype).dtype
    n = a.size * (2 if a.dtype.kind == "c" else 1)
    if n:
        kernels.launch(rt, kernels.kernel(rt, "layout.cl", "scale_real", real), (n,), a.data,
                       real.type(factor), np.uint64(n))
    return a


class Volume:
    """A (nz, *plane_shape) array on the device as a list of slabs with the given bounds."""

    def __init__(self, rt, bounds, plane_shape, dtype):
        import pyopencl as cl
        import pyopencl.array as cla

        self.rt = rt
        self.bounds = list(bounds)
        self.plane_shape = tuple(int(s) for s in plane_shape)
        self.dtype = np.dtype(dtype)
        plane = int(np.prod(self.plane_shape)) * self.dtype.itemsize
        total = self.bounds[-1][1] * plane
        align = max(int(rt.device.mem_base_addr_align) // 8, 1)
        self._whole = None
        if len(self.bounds) > 1 and total <= rt.caps.max_alloc and all(z0 * plane % align == 0 for z0, _ in self.bounds):
            # one allocation, a sub-buffer per slab: separately allocated slabs ran the stencil kernels
            # ~1.3-1.9x slower than one buffer on PoCL (the demo grid; docs/benchmarks.md, "The lean layout")
            self._whole = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, total)
            self.slabs = [cla.Array(rt.queue, (z1 - z0,) + self.plane_shape, self.dtype,
                                    data=self._whole.get_sub_region(z0 * plane, (z1 - z0) * plane))
                          for z0, z1 in self.bounds]
        else:
            self.slabs = [cla.empty(rt.queue, (z1 - z0,) + self.plane_shape, self.dtype)
                          for z0, z1 in self.bounds]

    @property
    def whole(self):
        """The whole volume as one device array where it is one allocation (one slab, or slabs that are
        sub-buffers of one buffer), else None."""
        if len(self.slabs) == 1:
            return self.slabs[0]
        if self._whole is None:
            return None
        import pyopencl.array as cla

        return cla.Array(self.rt.queue, self.shape, self.dtype, data=self._whole)

    @property
    def shape(self):
        return (self.bounds[-1][1],) + self.plane_shape

    @property
    def nbytes(self) -> int:
        return sum(s.nbytes for s in self.slabs)

    def __iter__(self):
        return iter(zip(self.bounds, self.slabs))

    def set(self, host: np.ndarray):
        host = np.ascontiguousarray(host, dtype=self.dtype)
        for (z0, z1), s in self:
            upload(s, host[z0:z1])
        return self

    def get(self, out=None) -> np.ndarray:
        """The volume on the host, into ``out`` (its shape, this dtype, C-contiguous) where given."""
        out = np.empty(self.shape, self.dtype) if out is None else out
        for (z0, z1), s in self:
            s.get(ary=out[z0:z1])
        return out

    def fill(self, value=0):
        for s in self.slabs:
            fill(self.rt, s, value)
        return self

    def scale(self, factor):
        for s in self.slabs:
            scale(self.rt, s, factor)
        return self

    def copy_from(self, other: "Volume"):
        import pyopencl as cl

        for a, b in zip(self.slabs, other.slabs):
            cl.enqueue_copy(self.rt.queue, a.data, b.data, byte_count=a.nbytes)
        return self

"""Grey opening (erosion, then dilation) with a flat, nearly round footprint on the device, at a cost
per pixel that does not grow with the footprint: the footprint is the Minkowski sum of four centred line
segments (horizontal and vertical of half-length a, both diagonals of half-length b: an octagon), and
each segment is one van Herk / Gil-Werman pass (kernels/morphology.cl). :func:`octagon` gives the exact
footprint realised, so the result equals ``scipy.ndimage.grey_opening(img, footprint=octagon(a, b),
mode='reflect')``: the image is padded by mirroring (2 x the reach, plus one) before the passes and
cropped after, and the octagon is symmetric under both axis mirrors."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from . import kernels
from .runtime import get_runtime


def octagon(a: int, b: int) -> np.ndarray:
    """The footprint realised by h and v segments of half-length a and both diagonals of half-length b:
    a boolean (2r+1, 2r+1) array, r = a + 2b (the reach). The h and v segments sum to the square
    max(|y|, |x|) <= a, the diagonals to the lattice points |y| + |x| <= 2b with y + x even; for a >= 1 the
    square fills the parity gaps, which leaves |y| + |x| <= 2a + 2b within the square of the reach."""
    r = a + 2 * b
    yy, xx = np.abs(np.mgrid[-r:r + 1, -r:r + 1])
    if a == 0:
        return (yy + xx <= 2 * b) & ((yy + xx) % 2 == 0)
    return yy + xx <= 2 * (a + b)


def disk_segments(radius_px: float) -> tuple[int, int]:
    """(a, b): the octagon closest to a disk of ``radius_px`` (fewest differing pixels; the smallest b of
    those tied). Rows of the disk and of an octagon with a >= 1 are centred runs, so the pixels that differ
    are twice the difference of the half-widths summed over rows: time linear in the radius per b."""
    r = float(radius_px)
    if not np.isfinite(r) or r < 1:
        raise InputError(f"background radius: {radius_px!r} px is smaller than a pixel (needs >= 1)")
    R = int(np.ceil(r))
    yy, xx = np.mgrid[0:R + 1, 0:R + 1]
    w = (yy ** 2 + xx ** 2 <= r * r).sum(1) - 1            # the disk's half-width in rows 0..R (-1: empty)
    disk_w = np.concatenate([w[:0:-1], w])                  # rows -R..R
    bs = np.arange(0, R // 2 + 1)
    a_s = R - 2 * bs                                        # >= 0; a = 0 only for the last b when R is even
    y = np.abs(np.arange(-R, R + 1))
    oct_w = np.minimum(R, 2 * (a_s + bs)[:, None] - y[None, :])
    errs = 2 * np.abs(disk_w[None, :] - oct_w).sum(1)
    if a_s[-1] == 0:             # the diamond |y| + |x| <= R with y + x even: every other pixel of a run
        q = R - y                                           # its half-width per row
        inside = _same_parity(np.minimum(disk_w, q), y)     # of the disk's run
        errs[-1] = np.sum(np.maximum(2 * disk_w + 1, 0) + _same_parity(q, y) - 2 * inside)
    b = int(np.argmin(errs))                                # the first of those tied, as before
    return R - 2 * b, b


def _same_parity(m, y):
    """How many x in [-m, m] have x + y even (0 where m < 0)."""
    return np.where(m < 0, 0, np.where(y % 2 == 0, 2 * (m // 2) + 1, 2 * ((m + 1) // 2)))


def grey_opening(image, a: int, b: int, device=None) -> np.ndarray:
    """Grey opening of a 2D image by :func:`octagon` (a, b) on the device, in the image's float dtype
    (float32 unless float64 is given and the device has it)."""
    import pyopencl.array as cla

    rt = get_runtime(device)
    img = np.asarray(image)
    dt = np.float64 if img.dtype == np.float64 and rt.caps.fp64 else np.float32
    if img.ndim != 2:
        raise InputError(f"background: expected a 2D image, got shape {img.shape}")
    reach = a + 2 * b
    pad = 2 * reach + 1
    p = np.pad(img.astype(dt), pad, mode="symmetric")
    ny, nx = p.shape
    k = kernels.kernel(rt, "morphology.cl", "line_minmax", dt)
    bufs = [cla.to_device(rt.queue, p), cla.empty(rt.queue, p.shape, dt)]
    g, h = cla.empty(rt.queue, p.shape, dt), cla.empty(rt.queue, p.shape, dt)
    cur = 0
    for is_max in (0, 1):
        for d, half in ((0, a), (1, a), (2, b), (3, b)):
            if half == 0:
                continue
            n = ny if d == 0 else (nx if d == 1 else ny + nx - 1)
            kernels.launch(rt, k, (n,), bufs[1 - cur].data, bufs[cur].data, g.data, h.data, np.int32(ny),
                           np.int32(nx), np.int32(d), np.int32(half), np.int32(is_max))
            cur = 1 - cur
    return bufs[cur].get()[pad:-pad, pad:-pad]

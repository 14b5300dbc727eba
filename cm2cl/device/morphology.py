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
    a boolean (2r+1, 2r+1) array, r = a + 2b (the reach)."""
    r = a + 2 * b
    pts = {(0, 0)}
    segs = [[(0, t) for t in range(-a, a + 1)], [(t, 0) for t in range(-a, a + 1)],
            [(t, t) for t in range(-b, b + 1)], [(t, -t) for t in range(-b, b + 1)]]
    for seg in segs:
        pts = {(p[0] + s[0], p[1] + s[1]) for p in pts for s in seg}
    fp = np.zeros((2 * r + 1, 2 * r + 1), bool)
    for y, x in pts:
        fp[y + r, x + r] = True
    return fp


def disk_segments(radius_px: float) -> tuple[int, int]:
    """(a, b): the octagon closest to a disk of ``radius_px`` (fewest differing pixels)."""
    r = float(radius_px)
    if not np.isfinite(r) or r < 1:
        raise InputError(f"background radius: {radius_px!r} px is smaller than a pixel (needs >= 1)")
    R = int(np.ceil(r))
    yy, xx = np.mgrid[-R:R + 1, -R:R + 1]
    disk = yy ** 2 + xx ** 2 <= r * r
    best = None
    for b in range(0, R // 2 + 1):
        a = R - 2 * b
        if a < 0:
            continue
        fp = octagon(a, b)
        pad = (disk.shape[0] - fp.shape[0]) // 2
        cmp = np.pad(fp, pad) if pad > 0 else fp
        err = int(np.sum(cmp != disk))
        if best is None or err < best[0]:
            best = (err, a, b)
    return best[1], best[2]


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

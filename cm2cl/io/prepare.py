"""Preparing measured images and PSF stacks: camera offset, binning, normalisation."""

from __future__ import annotations

import numpy as np

from ..errors import InputError


def bin_image(a, factor: int, name: str = "image") -> np.ndarray:
    """Sum-bin the last two axes by ``factor`` (trailing rows/columns that do not fill a bin
    are dropped). Returns float64."""
    f = int(factor)
    if f < 1:
        raise InputError(f"bin: factor must be an integer >= 1, got {factor!r}")
    a = np.asarray(a, np.float64)
    if f == 1:
        return a
    ny, nx = a.shape[-2] // f, a.shape[-1] // f
    if ny == 0 or nx == 0:
        raise InputError(f"{name}: shape {a.shape} is smaller than the bin factor {f}")
    a = a[..., : ny * f, : nx * f]
    return a.reshape(a.shape[:-2] + (ny, f, nx, f)).sum(axis=(-3, -1))


#: the dark corner ``offset='auto'`` averages: pixels [5:15, 5:15]
DARK_REGION = (slice(5, 15), slice(5, 15))


def estimate_offset(img, region=DARK_REGION, name: str = "image") -> float:
    """Camera offset (dark level) as the mean of a dark corner of the image (last two axes); an
    InputError when the image has no pixel there."""
    img = np.asarray(img, np.float64)
    corner = img[(Ellipsis,) + tuple(region)]
    if corner.size == 0:
        rows, cols = (f"{r.start}:{r.stop}" for r in region)
        raise InputError(f"{name}: offset 'auto' averages pixels [{rows}, {cols}], which an image of shape "
                         f"{img.shape} does not have; give the offset as a number")
    return float(corner.mean())


def check_image(img, name: str = "image") -> np.ndarray:
    """Camera data as read: a numeric dtype and finite values (InputError naming ``name`` otherwise)."""
    img = np.asarray(img)
    if img.dtype.kind not in "uif":
        raise InputError(f"{name}: dtype {img.dtype} is not numeric")
    if img.dtype.kind == "f" and not np.isfinite(img).all():
        raise InputError(f"{name}: contains NaN/Inf values")
    return img


def subtract_offset(img, offset: float, clip: bool = True) -> np.ndarray:
    out = np.asarray(img, np.float64) - float(offset)
    return np.maximum(out, 0.0) if clip else out


def prepare(img, *, offset="auto", bin_factor: int = 1, name: str = "image") -> np.ndarray:
    """Offset subtraction (``'auto'``: the mean of pixels [5:15, 5:15]; a number; or None)
    followed by binning. Returns float64 >= 0."""
    img = check_image(img, name)
    if offset == "auto":
        offset = estimate_offset(img, name=name)
    out = subtract_offset(img, offset) if offset is not None else np.asarray(img, np.float64)
    return bin_image(out, bin_factor, name)


def fit_lateral(a, shape, axis=None, name: str = "psf"):
    """The last two axes of ``a`` padded with zeros and/or cropped to ``shape`` (rows, cols), so that its
    optical axis, pixel ``axis`` (row, col; default its centre (H // 2, W // 2)), lands on the centre
    (rows // 2, cols // 2) of the result: the rule for a PSF whose lateral size differs from the sensor's
    (a cropped calibration scan, a larger stack). Whole pixels, nothing resampled.

    Returns (array float64, info): ``info`` has ``from``, ``to``, ``axis``, ``offset`` (rows, cols added
    before the first row / column; negative: cropped), ``light_cut`` (fraction of the total |a| cut off)
    and ``message`` (one line: what was done), or ``message`` None when the shapes already agree."""
    a = np.asarray(a, np.float64)
    src = tuple(int(n) for n in a.shape[-2:])
    dst = tuple(int(n) for n in shape)
    if len(dst) != 2 or min(dst) < 1:
        raise InputError(f"{name}: the target lateral shape must be two positive sizes, got {shape!r}")
    try:
        ax = (src[0] // 2, src[1] // 2) if axis is None else tuple(int(round(float(v))) for v in axis)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{name}: optical axis {axis!r} is not a (row, col) pair of finite numbers") from None
    if len(ax) != 2 or not (0 <= ax[0] < src[0] and 0 <= ax[1] < src[1]):
        raise InputError(f"{name}: optical axis {axis!r} (row, col) is outside its {src[0]} x {src[1]} pixels")
    off = (dst[0] // 2 - ax[0], dst[1] // 2 - ax[1])
    info = {"from": list(src), "to": list(dst), "axis": list(ax), "offset": list(off), "light_cut": 0.0,
            "message": None}
    if src == dst and off == (0, 0):
        return a, info
    out = np.zeros(a.shape[:-2] + dst)
    r0, r1 = max(0, off[0]), min(dst[0], src[0] + off[0])
    c0, c1 = max(0, off[1]), min(dst[1], src[1] + off[1])
    if r1 > r0 and c1 > c0:
        out[..., r0:r1, c0:c1] = a[..., r0 - off[0]:r1 - off[0], c0 - off[1]:c1 - off[1]]
    total = float(np.abs(a).sum())
    cut = 1.0 - float(np.abs(out).sum()) / total if total > 0 else 0.0
    kinds = []
    for what, n_src, n_dst, o in (("rows", src[0], dst[0], off[0]), ("columns", src[1], dst[1], off[1])):
        added, dropped = max(0, o) + max(0, n_dst - n_src - o), max(0, -o) + max(0, n_src + o - n_dst)
        if added:
            kinds.append(f"{added} {what} of zeros added")
        if dropped:
            kinds.append(f"{dropped} {what} cropped")
    info["light_cut"] = max(0.0, cut)
    info["message"] = (f"{name}: {src[0]} x {src[1]} pixels fitted to {dst[0]} x {dst[1]} ({', '.join(kinds)}), its "
                       f"optical axis pixel ({ax[0]}, {ax[1]}) on the centre ({dst[0] // 2}, {dst[1] // 2})"
                       + (f"; {info['light_cut']:.2%} of its light cut off" if info["light_cut"] > 0 else ""))
    return out, info


def prepare_psf(psf, sensor_shape, *, offset=None, bin_factor: int = 1, axis=None, name: str = "psf"):
    """A PSF stack on a measurement's grid: its offset subtracted (before any padding, so that 'auto'
    reads the PSF's own corner), fitted to ``sensor_shape`` (unbinned) by :func:`fit_lateral` when its
    lateral size differs, then binned. Returns (h float64, message: what the fit did, or None)."""
    h = prepare(psf, offset=offset, name=name)
    h, info = fit_lateral(h, sensor_shape, axis, name)
    return bin_image(h, bin_factor, name), info["message"]

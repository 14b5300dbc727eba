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


def fit_psf_to_sensor(psf, sensor_shape, name: str = "psf"):
    """(psf, note): a PSF stack (nz, Py, Px) brought to the sensor's (My, Mx), centred on the array's
    optical axis (the array centre): cropped where larger (a scan wider than the sensor), zero-padded where
    smaller (a cropped calibration scan: no light is assumed outside it). ``note`` says what was done
    (None when the sizes already match)."""
    h = np.asarray(psf)
    sensor = tuple(int(n) for n in sensor_shape)
    if h.shape[-2:] == sensor:
        return h, None
    out = h
    done = []
    for axis, (p, m) in enumerate(zip(h.shape[-2:], sensor)):
        ax = h.ndim - 2 + axis
        if p > m:
            start = (p - m) // 2
            out = np.take(out, np.arange(start, start + m), axis=ax)
            done.append(f"cropped {p} -> {m} {'rows' if axis == 0 else 'columns'}")
        elif p < m:
            before = (m - p) // 2
            pad = [(0, 0)] * out.ndim
            pad[ax] = (before, m - p - before)
            out = np.pad(out, pad)
            done.append(f"zero-padded {p} -> {m} {'rows' if axis == 0 else 'columns'}")
    return out, (f"{name}: lateral size {h.shape[-2:]} differs from the measurement's {sensor}: "
                 + ", ".join(done) + ", centred on the array centre")

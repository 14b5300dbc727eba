"""Input checks shared by the public functions: each failure is an InputError whose one-line
message names the argument and the problem."""

from __future__ import annotations

import numpy as np

from .errors import InputError


def real_array(a, name: str, ndims=(2, 3)) -> np.ndarray:
    """A finite floating-point numpy array with one of ``ndims`` dimensions."""
    if not isinstance(a, np.ndarray):
        try:
            a = np.asarray(a)
        except Exception as exc:  # noqa: BLE001 - anything numpy refuses
            raise InputError(f"{name}: not convertible to an array ({exc})") from exc
    if a.dtype.kind != "f":
        raise InputError(f"{name}: dtype {a.dtype} is not floating point (convert to float32/float64 "
                         "after subtracting the camera offset)")
    if a.ndim not in ndims:
        raise InputError(f"{name}: expected {' or '.join(f'{d}D' for d in ndims)} array, got shape {a.shape}")
    if a.size == 0:
        raise InputError(f"{name}: empty array of shape {a.shape}")
    bad = ~np.isfinite(a)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise InputError(f"{name}: contains {int(bad.sum())} NaN/Inf values (first at index {idx})")
    return a


def psf_stack(psf, name: str = "psf") -> np.ndarray:
    """PSF as (nz, My, Mx); 2D means one depth plane. Every plane must carry some light."""
    psf = real_array(psf, name)
    if psf.ndim == 2:
        psf = psf[None]
    energy = np.abs(psf).reshape(psf.shape[0], -1).sum(axis=1)
    zero = np.flatnonzero(energy == 0)
    if zero.size:
        raise InputError(f"{name}: depth plane(s) {zero.tolist()} are all zero")
    return psf


def positive(value, name: str, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: {value!r} is not a number") from exc
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        need = ">= 0" if allow_zero else "> 0"
        raise InputError(f"{name}: must be finite and {need}, got {value!r}")
    return v

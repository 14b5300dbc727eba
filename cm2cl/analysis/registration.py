"""Sub-pixel lateral registration of images by cross-correlation (the upsampled-DFT refinement of
Guizar-Sicairos, Thurman and Fienup, Opt. Lett. 33, 156 (2008)), the linear drift of a z scan fitted
from the shifts between consecutive planes, and Fourier shifting. Host numpy: a once-per-calibration
step."""

from __future__ import annotations

import numpy as np

from ..errors import InputError


def _upsampled_dft(data, region, factor, offsets):
    """The DFT of ``data`` (a spectrum) upsampled by ``factor`` on a ``region`` x ``region`` grid
    starting at ``offsets`` (in upsampled pixels)."""
    ny, nx = data.shape
    ky = np.fft.ifftshift(np.arange(ny)) - ny // 2
    kx = np.fft.ifftshift(np.arange(nx)) - nx // 2
    ry = np.arange(region) - offsets[0]
    rx = np.arange(region) - offsets[1]
    ey = np.exp(2j * np.pi * np.outer(ry, ky) / (ny * factor))
    ex = np.exp(2j * np.pi * np.outer(kx, rx) / (nx * factor))
    return ey @ data @ ex


def measure_shift(reference, moving, upsample: int = 100) -> np.ndarray:
    """(dy, dx) such that ``moving`` is ``reference`` shifted by (dy, dx) pixels, to 1/``upsample`` pixel:
    the peak of their cross-correlation, refined by an upsampled DFT around it."""
    a, b = np.asarray(reference, np.float64), np.asarray(moving, np.float64)
    if a.shape != b.shape or a.ndim != 2:
        raise InputError(f"registration: images of shapes {a.shape} and {b.shape}; expected two equal 2D shapes")
    A, B = np.fft.fft2(a), np.fft.fft2(b)
    cross = B * np.conj(A)
    corr = np.fft.ifft2(cross)
    peak = np.array(np.unravel_index(np.argmax(np.abs(corr)), corr.shape), float)
    shape = np.array(a.shape)
    peak[peak > shape // 2] -= shape[peak > shape // 2]
    region = int(np.ceil(1.5 * upsample))
    centre = np.fix(region / 2.0)
    offsets = centre - np.round(peak * upsample)
    up = _upsampled_dft(cross, region, upsample, offsets)   # the correlation near the peak
    fine = np.array(np.unravel_index(np.argmax(np.abs(up)), up.shape), float) - centre
    return (np.round(peak * upsample) + fine) / upsample


def scan_drift(planes, z_um) -> dict:
    """Lateral drift of a z scan: the shift of each plane against the previous one (cross-correlation of
    neighbours, whose PSFs differ little), accumulated, and a straight line fitted through it against z.
    Returns ``shifts`` (n, 2) accumulated (dy, dx) px, ``fit`` (n, 2) the line at each plane, and
    ``per_mm`` (dy, dx) px per mm of z."""
    planes = np.asarray(planes, np.float64)
    z = np.asarray(z_um, np.float64)
    if planes.ndim != 3 or len(z) != len(planes):
        raise InputError(f"scan: {planes.shape} planes for {len(z)} z positions")
    steps = [np.zeros(2)] + [measure_shift(planes[i - 1], planes[i]) for i in range(1, len(planes))]
    shifts = np.cumsum(steps, axis=0)
    if len(z) < 2:
        return {"shifts": shifts, "fit": shifts.copy(), "per_mm": np.zeros(2)}
    G = np.column_stack([np.ones_like(z), z])
    coef, *_ = np.linalg.lstsq(G, shifts, rcond=None)
    return {"shifts": shifts, "fit": G @ coef, "per_mm": coef[1] * 1000.0}


def fourier_shift(image, shift) -> np.ndarray:
    """``image`` shifted by (dy, dx) pixels (sub-pixel, periodic), real."""
    a = np.asarray(image, np.float64)
    ky = np.fft.fftfreq(a.shape[0])[:, None]
    kx = np.fft.fftfreq(a.shape[1])[None, :]
    phase = np.exp(-2j * np.pi * (ky * shift[0] + kx * shift[1]))
    return np.real(np.fft.ifft2(np.fft.fft2(a) * phase))

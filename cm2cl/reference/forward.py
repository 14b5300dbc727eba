"""Float64 numpy twin of the forward model (paper Eq. 3), written from the equations.

Conventions (stated here, not imported): PSF plane i sampled on the sensor grid M = (My, Mx) with
the optical axis at pixel (My//2, Mx//2); object on a padded grid P >= 2M - 1; circular
convolution on P; the sensor window is rows [(Py-My)//2, +My), cols [(Px-Mx)//2, +Mx).
"""

from __future__ import annotations

import numpy as np


def crop_offsets(sensor_shape, padded_shape):
    """(row, col) of the sensor window's first pixel on the padded grid: the window is centred."""
    return tuple((int(p) - int(m)) // 2 for m, p in zip(sensor_shape, padded_shape))


def centered_psf(psf, padded_shape) -> np.ndarray:
    """PSF planes (nz, My, Mx) as circular-convolution kernels on the padded grid: tap (r, c) of the
    sensor-grid PSF is the response at offset (r - My//2, c - Mx//2) from the source, stored at that
    offset modulo P."""
    psf = np.asarray(psf, np.float64)
    psf = psf[None] if psf.ndim == 2 else psf
    nz, my, mx = psf.shape
    py, px = (int(s) for s in padded_shape)
    rows = (np.arange(my) - my // 2) % py
    cols = (np.arange(mx) - mx // 2) % px
    out = np.zeros((nz, py, px))
    out[:, rows[:, None], cols[None, :]] = psf
    return out


def psf_spectra(psf, padded_shape) -> np.ndarray:
    psf = np.asarray(psf, np.float64)
    if psf.ndim == 2:
        psf = psf[None]
    return np.fft.fft2(centered_psf(psf, padded_shape))


def crop(a, sensor_shape):
    oy, ox = crop_offsets(sensor_shape, a.shape[-2:])
    return a[..., oy:oy + sensor_shape[0], ox:ox + sensor_shape[1]]


def embed(y, padded_shape):
    """C^T: zero padded grid with the sensor window filled."""
    out = np.zeros(y.shape[:-2] + tuple(padded_shape), np.float64)
    oy, ox = crop_offsets(y.shape[-2:], padded_shape)
    out[..., oy:oy + y.shape[-2], ox:ox + y.shape[-1]] = y
    return out


def convolve(psf, x, padded_shape) -> np.ndarray:
    """sum_i h_i (*) x_i on the padded grid."""
    Hs = psf_spectra(psf, padded_shape)
    return np.fft.ifft2((Hs * np.fft.fft2(np.asarray(x, np.float64))).sum(axis=0)).real


def forward(psf, x, padded_shape) -> np.ndarray:
    """y = C H x (paper Eq. 3)."""
    psf = np.asarray(psf)
    sensor = psf.shape[-2:]
    return crop(convolve(psf, x, padded_shape), sensor)


def adjoint(psf, y, padded_shape) -> np.ndarray:
    """H^T C^T y."""
    Hs = psf_spectra(psf, padded_shape)
    V = np.fft.fft2(embed(np.asarray(y, np.float64), padded_shape))
    return np.fft.ifft2(np.conj(Hs) * V).real


# ---- spatial-domain operators (no FFT), to check Fourier-domain formulas against ---------
def _psf_taps(psf):
    psf = np.asarray(psf, np.float64)
    psf = psf[None] if psf.ndim == 2 else psf
    cy, cx = psf.shape[1] // 2, psf.shape[2] // 2
    return psf, cy, cx


def convolve_spatial(psf, x, padded_shape=None) -> np.ndarray:
    """sum_i h_i (*) x_i by explicit circular shifts on the padded grid (small sizes only)."""
    psf, cy, cx = _psf_taps(psf)
    out = np.zeros(x.shape[1:])
    for i in range(psf.shape[0]):
        for a, b in zip(*np.nonzero(psf[i])):
            out += psf[i, a, b] * np.roll(x[i], (a - cy, b - cx), axis=(0, 1))
    return out


def correlate_spatial(psf, v) -> np.ndarray:
    """The adjoint of convolve_spatial: x_i = h_i correlated with the padded plane v."""
    psf, cy, cx = _psf_taps(psf)
    out = np.zeros((psf.shape[0],) + v.shape)
    for i in range(psf.shape[0]):
        for a, b in zip(*np.nonzero(psf[i])):
            out[i] += psf[i, a, b] * np.roll(v, (cy - a, cx - b), axis=(0, 1))
    return out

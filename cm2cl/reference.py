"""Float64 numpy twins of every device computation, for tests and tools only.

Same conventions as the device code (see cm2cl.forward): PSF centred at (My//2, Mx//2), object on
the padded grid P, circular convolution on P, crop window at ((Py-My)//2, (Px-Mx)//2).
"""

from __future__ import annotations

import numpy as np

from .forward import centered_psf, crop_offsets


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

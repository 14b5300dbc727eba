"""Loaders for the real data in ../shared/data/ (see its README), prepared as that README says.

Used by the accuracy study and by tests; nothing in the package depends on it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def available(name: str) -> bool:
    return (DATA / name).exists()


def _bin(a, f):
    if f == 1:
        return a
    ny, nx = a.shape[-2] // f, a.shape[-1] // f
    a = a[..., : ny * f, : nx * f]
    return a.reshape(a.shape[:-2] + (ny, f, nx, f)).sum(axis=(-3, -1))


def diffusercam_3d(bin_factor: int = 1, planes=None):
    """(psf (nz, My, Mx), y (My, Mx)) float64: the image minus its dark level (100) clipped at 0;
    each PSF plane minus the median of its four 20 x 20 corners, clipped at 0, unit sum."""
    import tifffile

    root = DATA / "diffusercam-3d"
    y = tifffile.imread(root / "image.tiff").astype(np.float64)
    y = np.maximum(y - 100.0, 0.0)
    files = sorted((root / "psf").glob("psf*.tiff"))
    if planes is not None:
        files = [files[i] for i in planes]
    psf = []
    for f in files:
        p = tifffile.imread(f).astype(np.float64)
        c = np.concatenate([p[:20, :20].ravel(), p[:20, -20:].ravel(), p[-20:, :20].ravel(), p[-20:, -20:].ravel()])
        p = np.maximum(p - np.median(c), 0.0)
        psf.append(p / p.sum())
    psf = np.stack(psf)
    return _bin(psf, bin_factor), _bin(y, bin_factor)


def diffusercam_2d(bin_factor: int = 4):
    """(psf (1, My, Mx), y (My, Mx)) float64 with the dark level (mean of PSF pixels [5:15, 5:15])
    removed and clipped at 0, binned (the tutorial's working size is 4x: 300 x 400)."""
    import tifffile

    root = DATA / "diffusercam-2d"
    psf = tifffile.imread(root / "psf_sample.tif").astype(np.float64)
    y = tifffile.imread(root / "rawdata_hand_sample.tif").astype(np.float64)
    bg = psf[5:15, 5:15].mean()
    psf = np.maximum(psf - bg, 0.0)
    y = np.maximum(y - bg, 0.0)
    return _bin(psf, bin_factor)[None], _bin(y, bin_factor)

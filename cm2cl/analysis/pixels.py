"""Measurement checks: saturated and hot pixels, counted and located, and the data-term weights that mask
them (issue 8 item 12, issue 12 item 3).

- **Saturated**: at the bit depth's maximum (integer images: the dtype's maximum, or ``level``), where the
  recorded value is a lower bound of the light, not a measurement.
- **Hot**: isolated outliers. A pixel is hot when it exceeds its 8 neighbours' largest value by more
  than the optics allow: ratio x that value plus 10 noise sigmas (sigma:
  :func:`cm2cl.solver.control.noise_sigma`), ratio = 2 x the sharpest peak-to-neighbour ratio of the PSF
  stack (at least 3). A real spot is a PSF, so it is never sharper than the PSF's sharpest peak; on a
  coarse (binned) sensor in-focus spots can be single pixels, which a fixed ratio would flag.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

MASKS = ("saturated", "hot")
#: how many positions a report lists
SHOW = 10


def saturated_pixels(img, level=None) -> np.ndarray:
    """(n, 2) row, column of pixels at the saturation level (the integer dtype's maximum by default;
    float images only with an explicit ``level``)."""
    a = np.asarray(img)
    if level is None:
        if a.dtype.kind not in "ui":
            return np.zeros((0, 2), int)
        level = np.iinfo(a.dtype).max
    return np.argwhere(a >= level)


def _neighbour_max(a: np.ndarray) -> np.ndarray:
    from scipy.ndimage import maximum_filter

    fp = np.ones((3, 3), bool)
    fp[1, 1] = False
    return maximum_filter(a, footprint=fp, mode="nearest")


def psf_sharpness(psf) -> float:
    """The largest peak-to-neighbour ratio the optics can produce: over the PSF stack's planes, the
    largest value / (max of its 8 neighbours) among pixels above 10% of their plane's maximum."""
    best = 1.0
    for plane in np.asarray(psf, np.float64).reshape((-1,) + np.shape(psf)[-2:]):
        if plane.max() <= 0 or min(plane.shape) < 3:
            continue
        nb = _neighbour_max(plane)
        sel = plane > 0.1 * plane.max()
        best = max(best, float(np.max(plane[sel] / np.maximum(nb[sel], 1e-300 * plane.max()))))
    return best


def hot_pixels(img, psf=None, ratio: float | None = None, sigmas: float = 10.0) -> np.ndarray:
    """(n, 2) row, column of isolated outliers: value > ratio x (max of the 8 neighbours) + sigmas x noise.
    ``ratio`` defaults to 2 x :func:`psf_sharpness` of ``psf`` (no light through these optics is that
    sharp), at least 3; without a PSF, 3."""
    from ..solver.control import noise_sigma

    a = np.asarray(img, np.float64)
    if a.ndim != 2 or min(a.shape) < 3:
        return np.zeros((0, 2), int)
    if ratio is None:
        ratio = max(3.0, 2.0 * psf_sharpness(psf)) if psf is not None else 3.0
    return np.argwhere(a > ratio * np.maximum(_neighbour_max(a), 0) + sigmas * noise_sigma(a))


def check_pixels(img, level=None, psf=None) -> dict:
    """{'saturated': {...}, 'hot': {...}}: count and the first positions (row, column) of each; the
    saturation level used (None: a float image without a given level is not checked)."""
    a = np.asarray(img)
    if level is None and a.dtype.kind in "ui":
        level = np.iinfo(a.dtype).max
    out = {}
    for name, idx in (("saturated", saturated_pixels(a, level)), ("hot", hot_pixels(a, psf))):
        out[name] = {"count": int(len(idx)), "first": [tuple(int(v) for v in p) for p in idx[:SHOW]]}
    out["saturated"]["level"] = None if level is None else float(level)
    return out


def mask_weights(img, names, level=None, psf=None) -> np.ndarray:
    """Data-term weights: 1 everywhere, 0 on the pixels of the named checks ('saturated', 'hot')."""
    unknown = [n for n in names if n not in MASKS]
    if unknown:
        raise InputError(f"mask: unknown {', '.join(map(repr, unknown))} (known: {', '.join(MASKS)})")
    a = np.asarray(img)
    w = np.ones(a.shape)
    for n in names:
        idx = saturated_pixels(a, level) if n == "saturated" else hot_pixels(a, psf)
        w[tuple(idx.T)] = 0.0
    return w

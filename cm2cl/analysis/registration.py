"""Sub-pixel lateral registration of the planes of a z scan (issue 12 item 1), host numpy/scipy: a
once-per-calibration step.

- :func:`measure_shift`: the shift between two images: the whole-pixel peak of their cross-correlation,
  refined by a least-squares fit of the phase ramp of their cross-spectrum at low frequencies (free of
  the pixel locking of interpolated correlation peaks for PSFs about a pixel wide).
- :func:`scan_drift`: the lateral drift of a scan whose stage axis is tilted, a straight line in z (px
  per mm) fitted to the shifts between pairs of planes up to a few hundred um apart.
- :func:`shift_image`: an image moved by a sub-pixel shift, zero filled (nothing wraps around), by a
  Fourier phase ramp or bilinear interpolation.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

from ..errors import InputError

#: shift methods of :func:`shift_image`
SHIFT_METHODS = ("fourier", "bilinear")


#: spatial frequencies (cycles per pixel, each axis) whose cross-spectrum phase gives the sub-pixel shift
K_MAX = 0.1


def _spectrum(image):
    """complex64: a scan keeps a few of these; the shift's precision does not need more"""
    return sfft.fft2(np.asarray(image, np.float32), workers=-1)


def _low_frequencies(shape, k_max):
    ky = sfft.fftfreq(shape[0])
    kx = sfft.fftfreq(shape[1])
    iy = np.flatnonzero(np.abs(ky) <= k_max)
    ix = np.flatnonzero(np.abs(kx) <= k_max)
    KY, KX = np.meshgrid(ky[iy], kx[ix], indexing="ij")
    return np.ix_(iy, ix), KY.ravel(), KX.ravel()


def _shift_of_spectra(A, B, k_max: float = K_MAX) -> np.ndarray:
    """(dy, dx) of the image with spectrum ``B`` against the one with spectrum ``A``: the whole-pixel peak
    of their cross-correlation, refined by a weighted least-squares fit of the cross-spectrum's phase ramp
    over the frequencies up to ``k_max`` cycles per pixel. Near zero frequency the pixel's sinc response
    cancels the aliases, so the phase there is free of the bias towards whole pixels ("pixel locking")
    that an interpolated correlation peak shows for PSFs about a pixel wide. The cross-spectrum is
    squared first: planes at different depths may differ in sign at some frequencies (a phase of pi),
    which squaring removes (it leaves shifts up to 1 / (4 k_max) pixels unambiguous)."""
    cross = B * np.conj(A)
    corr = sfft.ifft2(cross, workers=-1).real
    peak = np.array(np.unravel_index(int(np.argmax(corr)), corr.shape), float)
    shape = np.array(cross.shape)
    wrap = peak > shape // 2
    peak[wrap] -= shape[wrap]
    idx, KY, KX = _low_frequencies(cross.shape, k_max)
    C = cross[idx].ravel().astype(np.complex128)
    keep = (KY != 0) | (KX != 0)
    C, KY, KX = C[keep], KY[keep], KX[keep]
    if len(C) < 2:
        return peak
    s = peak.copy()
    for _ in range(3):              # the remaining phase shrinks each pass; three reach float precision
        R = (C * np.exp(2j * np.pi * (KY * s[0] + KX * s[1]))) ** 2
        w = np.sqrt(np.abs(R))
        if not w.any():
            return peak
        G = np.column_stack([-4 * np.pi * KY, -4 * np.pi * KX]) * w[:, None]
        s = s + np.linalg.lstsq(G, np.angle(R) * w, rcond=None)[0]
    return s


def measure_shift(reference, moving, k_max: float = K_MAX) -> np.ndarray:
    """(dy, dx) pixels such that ``moving`` is ``reference`` moved by (dy, dx) (row, column): the whole
    pixel from the peak of their circular cross-correlation, the fraction from the phase of their
    cross-spectrum at low frequencies (see :func:`_shift_of_spectra`)."""
    a, b = np.asarray(reference, np.float64), np.asarray(moving, np.float64)
    if a.shape != b.shape or a.ndim != 2:
        raise InputError(f"registration: images of shapes {a.shape} and {b.shape}; expected two equal 2D shapes")
    return _shift_of_spectra(_spectrum(a), _spectrum(b), k_max)


def _positions(pairs, shifts, n) -> np.ndarray:
    """Least-squares positions p (n, 2), p[0] = 0, from p[j] - p[i] = shift for each pair (i, j)."""
    G = np.zeros((len(pairs), n))
    G[np.arange(len(G)), pairs[:, 1]] = 1.0
    G[np.arange(len(G)), pairs[:, 0]] -= 1.0
    p = np.zeros((n, 2))
    p[1:] = np.linalg.lstsq(G[:, 1:], shifts, rcond=None)[0]
    return p


def scan_drift(planes, z_um, *, max_lag_um: float = 320.0,
               reference_um: float | None = None) -> dict:
    """Lateral drift of a z scan, fitted as a straight line in z.

    ``planes``: an iterable of 2D planes taken at ``z_um`` (read once, one at a time). Each plane is
    correlated with the two planes before it and with anchor planes (every ``stride``-th, at most 8 kept)
    up to ``max_lag_um`` before it: a sharp PSF on large pixels moves by whole pixels only (its sub-pixel
    shifts between neighbours lock to 0), so the slope comes from the long baselines, where the drift spans
    pixels, while the neighbours keep every plane linked. The slope (px per um) is the least-squares fit of
    the pair shifts to slope x dz; pairs more than 5 robust sigmas (and 0.2 px) off it are dropped once
    (false peaks of a periodic lenslet pattern); positions per plane are solved from the kept pairs.

    Returns ``per_mm`` (dy, dx) px per mm of z, ``fit`` (n, 2) the line at each plane relative to
    ``reference_um`` (default: the middle of the scan's z range), ``positions`` (n, 2) the measured ones
    (same origin), ``residual_px`` (RMS of the positions about the line), ``pairs`` used, ``pairs_dropped``."""
    z = np.asarray(z_um, np.float64).ravel()
    n = len(z)
    zr = (0.5 * (z.min() + z.max()) if n else 0.0) if reference_um is None else float(reference_um)
    if n < 2:
        return {"positions": np.zeros((n, 2)), "fit": np.zeros((n, 2)), "per_mm": np.zeros(2), "residual_px": 0.0,
                "pairs": 0, "pairs_dropped": 0, "reference_um": zr}
    step = float(np.median(np.abs(np.diff(z))))
    window = max(2, int(np.floor(float(max_lag_um) / step + 1e-9))) if step > 0 else 2
    stride = max(1, int(np.ceil(window / 8)))
    recent, anchors, pairs, shifts = [], [], [], []
    count = 0
    for j, plane in enumerate(planes):
        B = _spectrum(plane)
        if recent and recent[-1][1].shape != B.shape:
            raise InputError(f"registration: plane {j} has shape {B.shape}, plane {recent[-1][0]} {recent[-1][1].shape}")
        partners = {i: A for i, A in recent}
        partners.update({i: A for i, A in anchors if j - i <= window})
        for i, A in sorted(partners.items()):
            pairs.append((i, j))
            shifts.append(_shift_of_spectra(A, B))
        recent = (recent + [(j, B)])[-2:]
        anchors = [(i, A) for i, A in anchors if j + 1 - i <= window]
        if j % stride == 0:
            anchors.append((j, B))
        count += 1
    if count != n:
        raise InputError(f"registration: {count} planes for {n} z positions")
    pairs, shifts = np.array(pairs), np.array(shifts)
    dz = z[pairs[:, 1]] - z[pairs[:, 0]]

    def slope(k):
        return (shifts[k] * dz[k, None]).sum(axis=0) / (dz[k] ** 2).sum()

    keep = np.ones(len(pairs), bool)
    b = slope(keep)
    resid = np.linalg.norm(shifts - dz[:, None] * b, axis=1)
    bad = resid > max(5.0 * 1.4826 * np.median(resid), 0.2)
    if bad.any() and (~bad).sum() >= 1:
        keep = ~bad
        b = slope(keep)
    p = _positions(pairs[keep], shifts[keep], n)
    fit = np.outer(z - zr, b)
    off = np.mean(p - fit, axis=0)
    p = p - off
    return {"positions": p, "fit": fit, "per_mm": b * 1000.0,
            "residual_px": float(np.sqrt(np.mean(np.sum((p - fit) ** 2, axis=1)))),
            "pairs": int(keep.sum()), "pairs_dropped": int((~keep).sum()), "reference_um": zr}


def shift_image(image, shift, method: str = "fourier") -> np.ndarray:
    """``image`` moved by ``shift`` = (dy, dx) pixels (sub-pixel), zero filled: what leaves the frame is
    lost, what enters is 0. ``method``: 'fourier' (a phase ramp on the image padded with zeros; exact for
    band-limited content, rings around single-pixel spots) or 'bilinear' (no ringing, blurs by up to half
    a pixel). Returns float64."""
    a = np.asarray(image, np.float64)
    dy, dx = (float(s) for s in shift)
    if method not in SHIFT_METHODS:
        raise InputError(f"shift method: unknown {method!r} (known: {', '.join(SHIFT_METHODS)})")
    if dy == 0.0 and dx == 0.0:
        return a.copy()
    if method == "bilinear":
        from scipy.ndimage import shift as nd_shift

        return nd_shift(a, (dy, dx), order=1, mode="constant", cval=0.0, prefilter=False)
    py, px = int(np.ceil(abs(dy))) + 2, int(np.ceil(abs(dx))) + 2
    shape = (sfft.next_fast_len(a.shape[0] + 2 * py), sfft.next_fast_len(a.shape[1] + 2 * px))
    big = np.zeros(shape)
    big[py:py + a.shape[0], px:px + a.shape[1]] = a
    ky = sfft.fftfreq(shape[0])[:, None]
    kx = sfft.rfftfreq(shape[1])[None, :]
    F = sfft.rfft2(big, workers=-1) * np.exp(-2j * np.pi * (ky * dy + kx * dx))
    out = sfft.irfft2(F, shape, workers=-1)
    return out[py:py + a.shape[0], px:px + a.shape[1]]

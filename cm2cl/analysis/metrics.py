"""Figures of merit of the paper: PCC (Eq. 5), axial PCC width, FWHM, local SBR.

Coordinates of volumes are (z, y, x) with voxel sizes (dz, dy, dx) in um; positions returned in um
are index * voxel size (or the given depth of each plane for z).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import fft as sfft
from scipy import ndimage

from ..errors import InputError

__all__ = ["register_shift", "pcc", "axial_pcc", "width_at_level", "fwhm", "local_sbr", "signal_mask", "particle_mask", "raw_sbr", "PARTICLE_SIGMAS"]


def _as_image(a, name):
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.size == 0:
        raise InputError(f"{name}: expected a non-empty 2D image, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise InputError(f"{name}: contains NaN/Inf")
    return a


def _shift_zero(img, dy, dx):
    """img shifted by (dy, dx) whole pixels, zero filled (no wrap-around)."""
    out = np.zeros_like(img)
    ny, nx = img.shape
    ys, yd = (slice(0, ny - dy), slice(dy, ny)) if dy >= 0 else (slice(-dy, ny), slice(0, ny + dy))
    xs, xd = (slice(0, nx - dx), slice(dx, nx)) if dx >= 0 else (slice(-dx, nx), slice(0, nx + dx))
    out[yd, xd] = img[ys, xs]
    return out


def register_shift(ref, img, max_shift: int | None = None) -> tuple:
    """Integer shift (dy, dx) that best aligns ``img`` onto ``ref``: the location of the maximum of
    their (linear, zero-padded) 2D cross-correlation, as in the paper's Methods. ``max_shift``
    limits the search (and the padding) to +-max_shift pixels."""
    ref = _as_image(ref, "ref")
    img = _as_image(img, "img")
    if ref.shape != img.shape:
        raise InputError(f"register_shift: shapes differ, {ref.shape} vs {img.shape}")
    ny, nx = ref.shape
    pad = (ny, nx) if max_shift is None else (min(ny, max_shift), min(nx, max_shift))
    shape = tuple(sfft.next_fast_len(n + p, real=True) for n, p in zip(ref.shape, pad))
    a = sfft.rfft2(ref - ref.mean(), shape)
    b = sfft.rfft2(img - img.mean(), shape)
    cc = sfft.irfft2(a * np.conj(b), shape)            # cc[s] = sum ref[p] img[p - s]
    sy = np.arange(shape[0]); sy = np.where(sy > shape[0] // 2, sy - shape[0], sy)
    sx = np.arange(shape[1]); sx = np.where(sx > shape[1] // 2, sx - shape[1], sx)
    valid = (np.abs(sy)[:, None] <= pad[0]) & (np.abs(sx)[None, :] <= pad[1])
    cc = np.where(valid, cc, -np.inf)
    iy, ix = np.unravel_index(int(np.argmax(cc)), cc.shape)
    return int(sy[iy]), int(sx[ix])


def pcc(a, b, register: bool = True, max_shift: int | None = None) -> float:
    """Pearson correlation coefficient (paper Eq. 5) of two images, after registering ``b`` onto
    ``a`` by the cross-correlation peak when ``register``."""
    a = _as_image(a, "a")
    b = _as_image(b, "b")
    if a.shape != b.shape:
        raise InputError(f"pcc: shapes differ, {a.shape} vs {b.shape}")
    if register:
        b = _shift_zero(b, *register_shift(a, b, max_shift))
    da = a - a.mean()
    db = b - b.mean()
    den = math.sqrt(float((da * da).sum()) * float((db * db).sum()))
    if den == 0:
        raise InputError("pcc: an image is constant")
    return float((da * db).sum() / den)


def axial_pcc(stack, ref_index: int, register: bool = True, max_shift: int | None = None) -> np.ndarray:
    """PCC of each plane of a (nz, ny, nx) PSF stack with plane ``ref_index`` (the in-focus PSF)."""
    stack = np.asarray(stack)
    if stack.ndim != 3:
        raise InputError(f"axial_pcc: expected a (nz, ny, nx) stack, got shape {stack.shape}")
    if not -stack.shape[0] <= ref_index < stack.shape[0]:
        raise InputError(f"axial_pcc: ref_index {ref_index} outside 0..{stack.shape[0] - 1}")
    ref = stack[ref_index]
    return np.array([pcc(ref, p, register, max_shift) for p in stack])


def _crossing(x0, x1, v0, v1, level):
    return x0 + (level - v0) * (x1 - x0) / (v1 - v0)


def width_at_level(positions, values, level: float, peak_index: int | None = None) -> float:
    """Full width of the region around the peak where ``values`` >= ``level`` (linear
    interpolation between samples), in the units of ``positions`` (e.g. the full width at
    PCC = 0.8 of an axial PCC curve). Raises InputError if the curve does not drop below
    ``level`` on both sides."""
    x = np.asarray(positions, dtype=float)
    v = np.asarray(values, dtype=float)
    if x.shape != v.shape or x.ndim != 1 or x.size < 3:
        raise InputError(f"width_at_level: need two 1D arrays of equal length >= 3, got {x.shape}, {v.shape}")
    i = int(np.argmax(v)) if peak_index is None else int(peak_index)
    if v[i] < level:
        raise InputError(f"width_at_level: the peak {v[i]:.3g} is below the level {level}")
    j = i
    while j > 0 and v[j - 1] >= level:
        j -= 1
    k = i
    while k < v.size - 1 and v[k + 1] >= level:
        k += 1
    if j == 0 or k == v.size - 1:
        raise InputError(f"width_at_level: the curve does not fall below {level} on both sides of "
                         f"the peak within {x[0]:g}..{x[-1]:g}; extend the range")
    left = _crossing(x[j - 1], x[j], v[j - 1], v[j], level)
    right = _crossing(x[k], x[k + 1], v[k], v[k + 1], level)
    return float(right - left)


def fwhm(profile, spacing: float = 1.0, baseline: float | str = 0.0) -> float:
    """Full width at half maximum of a 1D profile (linear interpolation), in units of ``spacing``.
    ``baseline`` is subtracted first; ``'min'`` uses the profile's minimum."""
    p = np.asarray(profile, dtype=float)
    if p.ndim != 1 or p.size < 3:
        raise InputError(f"fwhm: need a 1D profile of >= 3 samples, got shape {p.shape}")
    b = float(p.min()) if baseline == "min" else float(baseline)
    p = p - b
    peak = float(p.max())
    if peak <= 0:
        raise InputError("fwhm: the profile has no peak above the baseline")
    return width_at_level(np.arange(p.size) * spacing, p, peak / 2.0)


def signal_mask(signal_image, rel_threshold: float = 0.2, patch_px: int | None = None) -> np.ndarray:
    """Pixels where a (noise-free, background-free) signal image exceeds ``rel_threshold`` of its
    maximum; with ``patch_px``, of the maximum within each patch (the local particle region)."""
    s = _as_image(signal_image, "signal_image")
    if patch_px is None:
        return s > rel_threshold * s.max()
    local = ndimage.maximum_filter(s, size=int(patch_px), mode="nearest")
    return (s > rel_threshold * local) & (local > 0)


#: particle pixels of a raw frame lie this many robust sigmas above their patch's median (background)
PARTICLE_SIGMAS = 5.0


def particle_mask(image, patch_px: int, sigmas: float = PARTICLE_SIGMAS) -> np.ndarray:
    """The particle pixels of a raw measurement, patch by patch (``patch_px`` square): those above the
    patch's median (its background, the particles being sparse) by more than ``sigmas`` x its robust noise
    (1.4826 x the median absolute deviation); at 5 sigmas pure noise leaves ~3e-7 of the pixels."""
    img = _as_image(image, "image")
    n = int(patch_px)
    if n < 2:
        raise InputError(f"particle_mask: patch_px must be >= 2, got {patch_px!r}")
    mask = np.zeros(img.shape, bool)
    for y0 in range(0, img.shape[0], n):
        for x0 in range(0, img.shape[1], n):
            v = img[y0:y0 + n, x0:x0 + n]
            med = float(np.median(v))
            sigma = 1.4826 * float(np.median(np.abs(v - med)))
            if sigma > 0:
                mask[y0:y0 + n, x0:x0 + n] = v > med + sigmas * sigma
    return mask


def local_sbr(image, mask, patch_px: int, min_pixels: int = 4):
    """Local signal-to-background ratio (Methods): in each ``patch_px`` x ``patch_px`` patch, the
    mean of ``image`` over the particle region ``mask`` divided by its mean over the rest. Patches
    with fewer than ``min_pixels`` of either kind are NaN.

    Returns (sbr_map (patches_y, patches_x), mean of the finite local values)."""
    img = _as_image(image, "image")
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != img.shape:
        raise InputError(f"local_sbr: mask shape {mask.shape} differs from image shape {img.shape}")
    n = int(patch_px)
    if n < 2:
        raise InputError(f"local_sbr: patch_px must be >= 2, got {patch_px!r}")
    ny, nx = img.shape[0] // n, img.shape[1] // n
    if ny == 0 or nx == 0:
        raise InputError(f"local_sbr: patch {n} px is larger than the image {img.shape}")
    out = np.full((ny, nx), np.nan)
    for i in range(ny):
        for j in range(nx):
            sl = (slice(i * n, (i + 1) * n), slice(j * n, (j + 1) * n))
            m = mask[sl]
            v = img[sl]
            if m.sum() >= min_pixels and (~m).sum() >= min_pixels:
                bg = v[~m].mean()
                if bg > 0:
                    out[i, j] = v[m].mean() / bg
    finite = out[np.isfinite(out)]
    return out, (float(finite.mean()) if finite.size else float("nan"))


def raw_sbr(image, patch_px: int, sigmas: float = PARTICLE_SIGMAS):
    """Fig. 5B's local SBR of a raw measurement with its automatic masks (``cm2cl analyze sbr``):
    :func:`particle_mask` then :func:`local_sbr` on ``patch_px`` patches. Returns (sbr_map, mean, mask)."""
    mask = particle_mask(image, patch_px, sigmas)
    sbr_map, mean = local_sbr(image, mask, patch_px)
    return sbr_map, mean, mask

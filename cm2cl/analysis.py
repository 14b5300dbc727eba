"""Figures of merit of the paper: PCC (Eq. 5), axial PCC width, FWHM, local SBR, MIP figures, and
emitter detection / matching for simulated ground truth.

Coordinates of volumes are (z, y, x) with voxel sizes (dz, dy, dx) in um; positions returned in um
are index * voxel size (or the given depth of each plane for z).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy import fft as sfft
from scipy import ndimage

from .errors import InputError

__all__ = [
    "register_shift", "pcc", "axial_pcc", "width_at_level", "fwhm", "local_sbr", "signal_mask",
    "content_region", "mip_png", "find_emitters", "match_emitters",
]


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


def content_region(volume, margin: int = 10, rel: float = 0.05) -> tuple:
    """(row slice, col slice) bounding the voxels of a (nz, ny, nx) volume above ``rel`` x its
    maximum, grown by ``margin`` pixels (the whole plane if it is empty)."""
    vol = np.asarray(volume)
    proj = vol.max(axis=0)
    top = float(proj.max()) if proj.size else 0.0
    if top <= 0:
        return slice(0, proj.shape[0]), slice(0, proj.shape[1])
    r, c = np.nonzero(proj > rel * top)
    return (slice(max(r.min() - margin, 0), min(r.max() + margin + 1, proj.shape[0])),
            slice(max(c.min() - margin, 0), min(c.max() + margin + 1, proj.shape[1])))


def mip_png(volume, path, voxel_size_um=(1.0, 1.0, 1.0), depths_um=None, title: str | None = None,
            cmap: str = "turbo", gamma: float = 1.0, dpi: int = 120, region=None) -> Path:
    """Save orthogonal maximum-intensity projections (XY, XZ, YZ) of a (nz, ny, nx) volume as a
    PNG with depth colour-coding (hue = depth of the maximum, brightness = its value ** gamma).
    ``region`` = (row slice, col slice) shows only part of the field (see :func:`content_region`);
    axes are in um from the volume's first pixel.

    matplotlib is imported here only (``pip install 'cm2cl[plot]'``)."""
    try:
        from matplotlib.figure import Figure
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib import colormaps
        from matplotlib.colors import Normalize
        from matplotlib.cm import ScalarMappable
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise InputError("mip_png: matplotlib is not installed (pip install 'cm2cl[plot]')") from exc
    vol = np.asarray(volume, dtype=np.float64)
    if vol.ndim != 3 or vol.size == 0:
        raise InputError(f"mip_png: expected a (nz, ny, nx) volume, got shape {vol.shape}")
    dz, dy, dx = (float(v) for v in voxel_size_um)
    y0 = x0 = 0.0
    if region is not None:
        rs, cs = region
        y0 = (rs.start or 0) * dy
        x0 = (cs.start or 0) * dx
        vol = vol[:, rs, cs]
        if vol.size == 0:
            raise InputError(f"mip_png: region {region} is empty")
    nz, ny, nx = vol.shape
    depths = np.arange(nz) * dz if depths_um is None else np.asarray(depths_um, dtype=float)
    if depths.shape != (nz,):
        raise InputError(f"mip_png: depths_um has {depths.size} entries for {nz} planes")
    vmax = float(vol.max())
    scale = 1.0 / vmax if vmax > 0 else 1.0
    colours = colormaps[cmap](np.linspace(0.0, 1.0, nz) if nz > 1 else np.array([0.5]))[:, :3]

    def coloured(values, index):
        v = np.clip(values * scale, 0.0, 1.0) ** gamma
        return colours[index] * v[..., None]

    xy = coloured(vol.max(axis=0), vol.argmax(axis=0))
    xz = coloured(vol.max(axis=1), np.broadcast_to(np.arange(nz)[:, None], (nz, nx)))
    yz = coloured(vol.max(axis=2).T, np.broadcast_to(np.arange(nz)[None, :], (ny, nz)))

    zlen = max(nz * dz, 1e-9)
    w_xy, h_xy, w_z = nx * dx, ny * dy, zlen
    zscale = max(1.0, 0.25 * max(w_xy, h_xy) / zlen)      # stretch thin stacks so they stay visible
    fig = Figure(figsize=(8, 8 * (h_xy + w_z * zscale) / (w_xy + w_z * zscale)), dpi=dpi)
    FigureCanvasAgg(fig)
    W = w_xy + w_z * zscale
    H = h_xy + w_z * zscale
    m = 0.1
    fx = (1 - 2 * m) / W
    fy = (1 - 2 * m) / H
    ax_xy = fig.add_axes([m, m + w_z * zscale * fy, w_xy * fx, h_xy * fy])
    ax_yz = fig.add_axes([m + w_xy * fx, m + w_z * zscale * fy, w_z * zscale * fx, h_xy * fy])
    ax_xz = fig.add_axes([m, m, w_xy * fx, w_z * zscale * fy])
    z0, z1 = depths[0] - dz / 2, depths[-1] + dz / 2
    ax_xy.imshow(xy, extent=(x0, x0 + w_xy, y0 + h_xy, y0), aspect="auto", interpolation="nearest")
    ax_yz.imshow(yz, extent=(z0, z1, y0 + h_xy, y0), aspect="auto", interpolation="nearest")
    ax_xz.imshow(xz, extent=(x0, x0 + w_xy, z1, z0), aspect="auto", interpolation="nearest")
    ax_xy.set_xticks([]); ax_xy.set_ylabel("y (um)")
    ax_yz.set_yticks([]); ax_yz.set_xlabel("z (um)"); ax_yz.xaxis.set_label_position("top")
    ax_yz.xaxis.tick_top()
    ax_xz.set_xlabel("x (um)"); ax_xz.set_ylabel("z (um)")
    for ax in (ax_xy, ax_yz, ax_xz):
        ax.set_facecolor("black")
    if nz > 1:
        cax = fig.add_axes([m + w_xy * fx + 0.01, m, 0.02, w_z * zscale * fy * 0.9])
        sm = ScalarMappable(norm=Normalize(depths[0], depths[-1]), cmap=cmap)
        fig.colorbar(sm, cax=cax, label="depth (um)")
    if title:
        fig.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, facecolor="white")
    return path


def find_emitters(volume, threshold: float = 0.2, min_distance_vox=(1, 2, 2),
                  voxel_size_um=(1.0, 1.0, 1.0), depths_um=None, method: str = "gaussian") -> dict:
    """Local maxima of a (nz, ny, nx) volume above ``threshold`` x its maximum, at least
    ``min_distance_vox`` (z, y, x) apart, with sub-voxel positions refined along each axis from the
    peak voxel and its two neighbours: ``method='gaussian'`` fits a parabola to the log values
    (exact for Gaussian-shaped peaks), ``'centroid'`` takes their intensity centroid.

    Returns a dict with ``index`` (n, 3) fractional voxel coordinates, ``position_um`` (n, 3)
    (z from ``depths_um`` if given, else index * dz), and ``amplitude`` (n,), brightest first."""
    vol = np.asarray(volume, dtype=np.float64)
    if vol.ndim != 3:
        raise InputError(f"find_emitters: expected a (nz, ny, nx) volume, got shape {vol.shape}")
    if method not in ("gaussian", "centroid"):
        raise InputError(f"find_emitters: unknown method {method!r} (known: gaussian, centroid)")
    vmax = float(vol.max()) if vol.size else 0.0
    empty = {"index": np.zeros((0, 3)), "position_um": np.zeros((0, 3)), "amplitude": np.zeros(0)}
    if vmax <= 0:
        return empty
    size = tuple(2 * int(d) + 1 for d in min_distance_vox)
    peaks = (vol == ndimage.maximum_filter(vol, size=size, mode="constant", cval=-np.inf)) & (vol > threshold * vmax)
    idx = np.argwhere(peaks)
    if idx.size == 0:
        return empty
    # plateaus: keep one maximum per connected flat region
    amp = vol[tuple(idx.T)]
    order = np.argsort(-amp, kind="stable")
    idx, amp = idx[order], amp[order]
    taken = np.zeros(len(idx), bool)
    keep = []
    md = np.asarray(min_distance_vox)
    for i in range(len(idx)):
        if taken[i]:
            continue
        keep.append(i)
        close = np.all(np.abs(idx - idx[i]) <= md, axis=1)
        taken |= close
    idx, amp = idx[keep], amp[keep]
    cent = idx.astype(float)
    for n, p in enumerate(idx):
        for ax in range(3):
            if not 0 < p[ax] < vol.shape[ax] - 1:
                continue                      # on the border: keep the voxel centre
            lo, hi = p.copy(), p.copy()
            lo[ax] -= 1
            hi[ax] += 1
            v0, vm, vp = vol[tuple(p)], vol[tuple(lo)], vol[tuple(hi)]
            if method == "gaussian" and vm > 0 and vp > 0:
                lm, l0, lp = math.log(vm), math.log(v0), math.log(vp)
                den = lm - 2.0 * l0 + lp
                off = 0.5 * (lm - lp) / den if den < 0 else 0.0
            else:
                wm, w0, wp = max(vm, 0.0), max(v0, 0.0), max(vp, 0.0)
                off = (wp - wm) / (wm + w0 + wp)
            cent[n, ax] += float(np.clip(off, -0.5, 0.5))
    dz, dy, dx = (float(v) for v in voxel_size_um)
    pos = cent * np.array([dz, dy, dx])
    if depths_um is not None:
        depths = np.asarray(depths_um, dtype=float)
        if depths.shape != (vol.shape[0],):
            raise InputError(f"find_emitters: depths_um has {depths.size} entries for {vol.shape[0]} planes")
        pos[:, 0] = np.interp(cent[:, 0], np.arange(depths.size), depths)
    return {"index": cent, "position_um": pos, "amplitude": amp}


def match_emitters(detected_um, true_um, max_lateral_um: float, max_axial_um: float) -> dict:
    """One-to-one matching of detected and true emitter positions (n, 3) (z, y, x) in um, minimising
    the total normalised distance; a pair matches only within ``max_lateral_um`` laterally and
    ``max_axial_um`` axially.

    Returns counts, recall/precision, matched index pairs, and the errors of the matched pairs:
    ``lateral_error_um`` (>= 0) and ``axial_error_um`` (detected - true, signed)."""
    from scipy.optimize import linear_sum_assignment

    d = np.asarray(detected_um, dtype=float).reshape(-1, 3)
    t = np.asarray(true_um, dtype=float).reshape(-1, 3)
    out = {"n_true": len(t), "n_detected": len(d), "n_matched": 0, "pairs": np.zeros((0, 2), int),
           "lateral_error_um": np.zeros(0), "axial_error_um": np.zeros(0)}
    if len(d) and len(t):
        lat = np.hypot(d[:, None, 1] - t[None, :, 1], d[:, None, 2] - t[None, :, 2])
        ax = d[:, None, 0] - t[None, :, 0]
        ok = (lat <= max_lateral_um) & (np.abs(ax) <= max_axial_um)
        cost = np.hypot(lat / max_lateral_um, ax / max_axial_um)
        cost = np.where(ok, cost, 1e6)
        r, c = linear_sum_assignment(cost)
        good = ok[r, c]
        r, c = r[good], c[good]
        out.update(n_matched=int(len(r)), pairs=np.stack([r, c], axis=1),
                   lateral_error_um=lat[r, c], axial_error_um=ax[r, c])
    out["recall"] = out["n_matched"] / out["n_true"] if out["n_true"] else float("nan")
    out["precision"] = out["n_matched"] / out["n_detected"] if out["n_detected"] else float("nan")
    for key in ("lateral_error_um", "axial_error_um"):
        e = out[key]
        out[key.replace("_error_um", "_rms_um")] = float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")
    return out

"""View configurations of a measured PSF stack and their axial PCC curves (paper Fig. 2A): the lenslets are
found in the stack itself (its footprint pieces, :func:`cm2cl.solver.psf_refine.lenslet_labels`), arranged
into their rows and columns, and each configuration (all R x C, (R-1) x C, (R-1) x (C-1), the one nearest
the axis: 3x3, 2x3, 2x2 and 1 for the CM2) keeps some of them, as the paper emulates the smaller arrays by
cropping the 3 x 3 PSF. A configuration's curve is the PCC of each plane with the reference plane on the
window of its lenslets, registered by the cross-correlation peak; its width at PCC = 0.8 is the depth range
over which a point's image stays alike (the paper: 155 / 179 / 206 um)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..errors import InputError
from .metrics import axial_pcc, width_at_level

#: the PCC level of the paper's widths
PCC_LEVEL = 0.8


def _groups(values) -> list[list[int]]:
    """Indices of ``values`` grouped into rows (or columns): split the sorted values where a gap exceeds
    half the largest gap (a single group when all are within a fifth of the spread of the others)."""
    order = np.argsort(values)
    v = np.asarray(values, float)[order]
    if v.size == 1:
        return [[int(order[0])]]
    gaps = np.diff(v)
    big = gaps > 0.5 * gaps.max() if gaps.max() > 0 else np.zeros_like(gaps, bool)
    out, cur = [], [int(order[0])]
    for k, g in enumerate(big):
        if g:
            out.append(cur)
            cur = []
        cur.append(int(order[k + 1]))
    out.append(cur)
    return out


def lenslet_grid(psf) -> dict:
    """The stack's lenslets: ``labels`` (My, Mx; 1..n, every pixel to its nearest footprint), ``centroids``
    (n, 2) in px, ``rows`` and ``cols`` (lists of lenslet indices, top to bottom, left to right) and
    ``axis`` (the index of the lenslet nearest the optical axis, pixel (My//2, Mx//2))."""
    from ..solver.psf_refine import lenslet_labels

    psf = np.asarray(psf, np.float64)
    if psf.ndim != 3:
        raise InputError(f"psf: expected a (nz, My, Mx) stack, got shape {psf.shape}")
    labels = lenslet_labels(psf)
    n = int(labels.max())
    peak = psf.reshape(psf.shape[0], -1).max(axis=1)
    foot = (psf / np.where(peak > 0, peak, 1.0)[:, None, None]).max(axis=0)
    cents = np.array(ndimage.center_of_mass(foot, labels, index=np.arange(1, n + 1))).reshape(n, 2)
    rows = [sorted(g, key=lambda j: cents[j, 1]) for g in _groups(cents[:, 0])]
    cols = [sorted(g, key=lambda j: cents[j, 0]) for g in _groups(cents[:, 1])]
    cy, cx = psf.shape[1] // 2, psf.shape[2] // 2
    axis = int(np.argmin(np.hypot(cents[:, 0] - cy, cents[:, 1] - cx)))
    return {"labels": labels, "centroids": cents, "rows": rows, "cols": cols, "axis": axis}


def view_configurations(grid: dict) -> dict:
    """{name: lenslet indices}: the whole R x C array, (R-1) x C (its last row dropped), (R-1) x (C-1) and
    the single lenslet nearest the axis, those that differ; one configuration for a PSF that is no array."""
    R, C = len(grid["rows"]), len(grid["cols"])
    n = grid["centroids"].shape[0]
    row_of = {j: r for r, g in enumerate(grid["rows"]) for j in g}
    col_of = {j: c for c, g in enumerate(grid["cols"]) for j in g}
    out = {f"{R}x{C}": list(range(n))}
    if R > 1:
        out[f"{R - 1}x{C}"] = [j for j in range(n) if row_of[j] < R - 1]
        if C > 1:
            out[f"{R - 1}x{C - 1}"] = [j for j in range(n) if row_of[j] < R - 1 and col_of[j] < C - 1]
    if n > 1:
        out["1"] = [grid["axis"]]
    return {k: v for k, v in out.items() if v}


def sharpest_plane(psf) -> int:
    """The plane whose light is most concentrated (largest peak / total): the in-focus reference."""
    psf = np.asarray(psf, np.float64)
    tot = psf.reshape(psf.shape[0], -1).sum(axis=1)
    pk = psf.reshape(psf.shape[0], -1).max(axis=1)
    return int(np.argmax(pk / np.where(tot > 0, tot, np.inf)))


def pcc_curves(psf, depths_um=None, ref_index: int | None = None, level: float = PCC_LEVEL,
               max_shift: int | None = None) -> dict:
    """Axial PCC curves of a PSF stack per view configuration: ``z_um`` (the depths, or plane indices),
    ``ref_index``, ``curves`` {name: PCC per plane}, ``widths_um`` {name: full width at PCC = ``level``, or
    None where the curve stays above it within the stack}, ``lenslets`` {name: indices}, ``windows`` {name:
    (y0, y1, x0, x1) of its crop} and the ``grid``."""
    psf = np.asarray(psf, np.float64)
    grid = lenslet_grid(psf)
    z = np.arange(psf.shape[0], dtype=float) if depths_um is None else np.asarray(depths_um, float)
    if z.shape != (psf.shape[0],):
        raise InputError(f"depths_um: {z.size} depths for {psf.shape[0]} planes")
    ref = sharpest_plane(psf) if ref_index is None else int(ref_index)
    if not 0 <= ref < psf.shape[0]:
        raise InputError(f"reference plane {ref} outside 0..{psf.shape[0] - 1}")
    out = {"z_um": z, "ref_index": ref, "curves": {}, "widths_um": {}, "lenslets": {}, "windows": {},
           "grid": grid, "level": level}
    for name, members in view_configurations(grid).items():
        mask = np.isin(grid["labels"], np.array(members) + 1)
        ys, xs = np.nonzero(mask)
        y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
        stack = (psf * mask)[:, y0:y1, x0:x1]
        curve = axial_pcc(stack, ref, register=True, max_shift=max_shift)
        try:
            width = width_at_level(z, curve, level, peak_index=ref)
        except InputError:
            width = None
        out["curves"][name], out["widths_um"][name] = curve, width
        out["lenslets"][name], out["windows"][name] = members, (y0, y1, x0, x1)
    return out


__all__ = ["PCC_LEVEL", "lenslet_grid", "view_configurations", "sharpest_plane", "pcc_curves"]

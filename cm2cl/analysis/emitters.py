"""Emitter detection (local maxima) and matching against a ground-truth table."""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from ..errors import InputError

__all__ = ["find_emitters", "match_emitters", "score_beads", "DETECT_THRESHOLD", "MATCH_LATERAL_VOXELS", "MATCH_AXIAL_PLANES"]

#: detection threshold (fraction of the brightest voxel) and matching tolerances (voxels / planes)
#: used to score a reconstruction of a simulated bead scene
DETECT_THRESHOLD = 0.25
MATCH_LATERAL_VOXELS = 3.0
MATCH_AXIAL_PLANES = 1.5


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


def score_beads(volume, sim) -> dict:
    """Score a reconstruction (nz, My, Mx) of a simulated bead scene (a SimulationResult): local maxima
    above DETECT_THRESHOLD of the peak, mapped to object space through the scene's optics, matched one
    to one with the true beads within MATCH_LATERAL_VOXELS voxels and MATCH_AXIAL_PLANES planes.
    Returns match_emitters' dict plus ``found_um`` and ``true_um`` ((n, 3) x, y, z) and the tolerances."""
    dz, dxy = sim.voxel_size_um[0], sim.voxel_size_um[1]
    det = find_emitters(np.asarray(volume), threshold=DETECT_THRESHOLD, min_distance_vox=(1, 3, 3))
    idx = det["index"]
    z = np.interp(idx[:, 0], np.arange(len(sim.depths_um)), sim.depths_um)
    x_mm, y_mm = sim.scene.optics.sensor_to_object_mm(idx[:, 1], idx[:, 2], z)
    found = np.column_stack([1000.0 * x_mm, 1000.0 * y_mm, z])
    e = sim.emitters
    true = np.column_stack([e["x_um"], e["y_um"], e["z_um"]])
    m = match_emitters(found[:, [2, 1, 0]], true[:, [2, 1, 0]], MATCH_LATERAL_VOXELS * dxy, MATCH_AXIAL_PLANES * dz)
    m.update(found_um=found, true_um=true, lateral_tolerance_um=MATCH_LATERAL_VOXELS * dxy,
             axial_tolerance_um=MATCH_AXIAL_PLANES * dz)
    return m

"""Particles in a reconstruction and their sizes (paper Fig. 2D and 3E): local maxima found by
:func:`~cm2cl.analysis.emitters.find_emitters`, each fitted with a 3D Gaussian (one lateral sigma, one
axial, a constant background) on a window around it, its lateral and axial FWHM (2 sqrt(2 ln 2) sigma) in
um; statistics over the particles, and by view region when the caller gives the regions."""

from __future__ import annotations

import math

import numpy as np
from scipy import optimize

from ..errors import InputError
from .emitters import find_emitters

#: FWHM of a Gaussian per sigma
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
#: the fit's narrowest Gaussian (voxels): a particle one voxel wide fits at this sigma, FWHM 0.71 voxel
SIGMA_MIN_VOX = 0.3
#: half window (z, y, x) in voxels of each particle's fit
HALF_WINDOW = (3, 5, 5)


def at_fit_floor(sigma_vox: float) -> bool:
    """Whether a fitted sigma (voxels) is at the fit's floor :data:`SIGMA_MIN_VOX` (within 1%): the particle
    fills one voxel along that axis, so its FWHM bounds the width from above and does not measure it."""
    return float(sigma_vox) <= 1.01 * SIGMA_MIN_VOX


def median_at_floor(rows, axis: str) -> bool:
    """Whether the median ``axis`` ('lateral' or 'axial') width of ``rows`` (particle rows, the well-fitted
    ones) is the fit's floor: more than half of them are at it (the floor is the smallest width a fit gives)."""
    return 2 * sum(1 for r in rows if r.get(f"{axis}_at_floor", False)) > len(rows)


def _gauss(p, zz, yy, xx):
    a, z0, y0, x0, sz, sr, b = p
    return a * np.exp(-0.5 * (((zz - z0) / sz) ** 2 + ((yy - y0) ** 2 + (xx - x0) ** 2) / sr ** 2)) + b


def fit_particle(volume, index, half_window=HALF_WINDOW) -> dict:
    """3D Gaussian fit of the particle at voxel ``index`` (z, y, x; fractional allowed) of ``volume``:
    centre (voxels), sigmas (voxels), amplitude, background, ``rel_residual`` (RMS misfit / amplitude),
    ``ok`` (the fit converged with its sigmas inside the window and its centre within a voxel of the start) and
    ``lateral_at_floor`` / ``axial_at_floor`` (:func:`at_fit_floor`)."""
    vol = np.asarray(volume, np.float64)
    c = [int(round(float(v))) for v in index]
    lo = [max(ci - h, 0) for ci, h in zip(c, half_window)]
    hi = [min(ci + h + 1, n) for ci, h, n in zip(c, half_window, vol.shape)]
    win = vol[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    zz, yy, xx = np.meshgrid(*(np.arange(a, b, dtype=float) for a, b in zip(lo, hi)), indexing="ij")
    peak = float(vol[tuple(c)])
    base = float(np.percentile(win, 10))
    p0 = [max(peak - base, 1e-12), *(float(v) for v in index), 1.0, 1.5, base]
    span = [max(b - a, 1) for a, b in zip(lo, hi)]
    lb = [0.0, lo[0] - 0.5, lo[1] - 0.5, lo[2] - 0.5, SIGMA_MIN_VOX, SIGMA_MIN_VOX, -abs(peak)]
    ub = [10 * abs(peak) + 1e-12, hi[0] - 0.5, hi[1] - 0.5, hi[2] - 0.5, 2.0 * span[0], 2.0 * max(span[1:]), abs(peak)]
    p0 = list(np.clip(p0, np.array(lb) + 1e-9, np.array(ub) - 1e-9))
    r = optimize.least_squares(lambda p: (_gauss(p, zz, yy, xx) - win).ravel(), p0, bounds=(lb, ub), x_scale="jac")
    a, z0, y0, x0, sz, sr, b = r.x
    resid = float(np.sqrt(np.mean(r.fun ** 2)) / a) if a > 0 else float("inf")
    moved = max(abs(z0 - index[0]), abs(y0 - index[1]), abs(x0 - index[2]))
    ok = bool(r.success and a > 0 and sz < span[0] and sr < max(span[1:]) and moved <= 1.0)
    return {"center_vox": (float(z0), float(y0), float(x0)), "sigma_axial_vox": float(sz),
            "sigma_lateral_vox": float(sr), "amplitude": float(a), "background": float(b),
            "rel_residual": resid, "ok": ok, "lateral_at_floor": at_fit_floor(sr), "axial_at_floor": at_fit_floor(sz)}


def noise_floor(volume) -> float:
    """The value a voxel of pure noise stays below: median + sqrt(2 ln N) x 1.4826 MAD (N voxels: the
    universal threshold, as the solver's l1 weight), plus one sigma of margin; the median alone for a
    volume whose MAD is 0 (a sparse reconstruction, mostly zeros)."""
    v = np.asarray(volume, np.float64).ravel()
    med = float(np.median(v))
    sigma = 1.4826 * float(np.median(np.abs(v - med)))
    return med + (math.sqrt(2.0 * math.log(max(v.size, 2))) + 1.0) * sigma


def particle_table(volume, voxel_size_um=(1.0, 1.0, 1.0), depths_um=None, threshold: float = 0.2,
                   min_distance_vox=(1, 2, 2), half_window=HALF_WINDOW) -> list[dict]:
    """One row per particle (brightest first; local maxima above ``threshold`` x the maximum and above the
    noise floor, :func:`noise_floor`): ``z_um, y_um, x_um`` (z from ``depths_um`` when given, else
    index x dz; y, x from the first pixel), ``fwhm_lateral_um``, ``fwhm_axial_um``, ``amplitude``,
    ``rel_residual``, ``ok``, ``lateral_at_floor``, ``axial_at_floor`` (a width at the fit's floor: one voxel)
    and the voxel centre ``z, y, x``."""
    vol = np.asarray(volume, np.float64)
    if vol.ndim != 3:
        raise InputError(f"volume: expected a (nz, ny, nx) volume, got shape {vol.shape}")
    dz, dy, dx = (float(v) for v in voxel_size_um)
    if abs(dy - dx) > 1e-6 * max(dy, dx):
        raise InputError(f"voxel_size_um: the lateral fit needs square pixels, got dy {dy} and dx {dx}")
    det = find_emitters(vol, threshold=threshold, min_distance_vox=min_distance_vox)
    floor = noise_floor(vol)
    return [measure_particle(vol, idx, (dz, dy, dx), depths_um, half_window)
            for idx, amp in zip(det["index"], det["amplitude"]) if amp > floor]   # else a noise maximum


def measure_particle(volume, index, voxel_size_um=(1.0, 1.0, 1.0), depths_um=None, half_window=HALF_WINDOW) -> dict:
    """The row of :func:`particle_table` for the particle at voxel ``index`` of ``volume``: its fitted centre
    in voxels and um, lateral and axial FWHM in um, amplitude, misfit and whether the fit is ``ok``."""
    vol = np.asarray(volume, np.float64)
    dz, dy, dx = (float(v) for v in voxel_size_um)
    f = fit_particle(vol, index, half_window)
    z0, y0, x0 = f["center_vox"]
    zu = float(np.interp(z0, np.arange(vol.shape[0]), depths_um)) if depths_um is not None else z0 * dz
    return {"z": z0, "y": y0, "x": x0, "z_um": zu, "y_um": y0 * dy, "x_um": x0 * dx,
            "fwhm_lateral_um": FWHM_PER_SIGMA * f["sigma_lateral_vox"] * dy,
            "fwhm_axial_um": FWHM_PER_SIGMA * f["sigma_axial_vox"] * dz,
            "amplitude": f["amplitude"], "rel_residual": f["rel_residual"], "ok": f["ok"],
            "lateral_at_floor": f["lateral_at_floor"], "axial_at_floor": f["axial_at_floor"]}


def summary(rows, key=None) -> dict:
    """Median and quartiles of the lateral and axial FWHM over the rows whose fit is ok (``n``, ``n_fit``), and
    how many of those widths are at the fit's floor (``n_lateral_at_floor``, ``n_axial_at_floor``: one voxel, a
    bound) and whether the median is (``lateral_median_at_floor``, ``axial_median_at_floor``); with ``key(row) -> region``, the same per region as well."""
    def stats(rs):
        good = [r for r in rs if r["ok"]]
        out = {"n": len(rs), "n_fit": len(good)}
        for axis in ("lateral", "axial"):
            out[f"n_{axis}_at_floor"] = sum(1 for r in good if r.get(f"{axis}_at_floor", False))
            out[f"{axis}_median_at_floor"] = median_at_floor(good, axis)
        for k in ("fwhm_lateral_um", "fwhm_axial_um"):
            v = np.array([r[k] for r in good])
            out[k] = ({"median": float(np.median(v)), "q1": float(np.percentile(v, 25)),
                       "q3": float(np.percentile(v, 75))} if v.size else None)
        return out

    res = {"all": stats(rows)}
    if key is not None:
        groups = {}
        for r in rows:
            groups.setdefault(str(key(r)), []).append(r)
        res["regions"] = {k: stats(v) for k, v in sorted(groups.items())}
    return res


def depth_range(rows, field_um, patch_um: float = 800.0, elongation_um: float | None = None,
                min_particles: int = 1) -> dict:
    """The reconstructed depth range (paper Fig. 5B, Methods): the field (``field_um`` = (height, width) from
    the first pixel, the frame of the rows' ``y_um``, ``x_um``) cut into ``patch_um`` square patches (whole
    ones only), and in each patch holding at least ``min_particles`` particles the local range
    max z - min z of their centres plus one particle's axial elongation (``elongation_um``; default the median
    axial FWHM of the well-fitted particles, as the paper adds the 372 um of its 25-um particles); the mean
    and standard deviation over those patches. Returns ``patches`` (one dict per patch with particles),
    ``mean_um``, ``std_um``, ``elongation_um``, where it came from, and ``elongation_at_floor``: the median
    particle fills one plane (its axial width is the fit's floor, :func:`at_fit_floor`), so the elongation
    added is a bound, not a measured length."""
    if not (math.isfinite(patch_um) and patch_um > 0):
        raise InputError(f"patch: {patch_um!r} um must be a positive number")
    ny, nx = (int(math.floor(float(f) / patch_um + 1e-9)) for f in field_um)
    if ny < 1 or nx < 1:
        raise InputError(f"patch: {patch_um:g} um is larger than the field {field_um[0]:g} x {field_um[1]:g} um")
    if int(min_particles) < 1:
        raise InputError(f"min_particles: {min_particles!r} must be at least 1")
    source, at_floor = "given", False
    if elongation_um is None:
        good = [r for r in rows if r["ok"]]
        if not good:
            raise InputError("depth range: no well-fitted particle to measure the axial elongation; give it")
        elongation_um, source = float(np.median([r["fwhm_axial_um"] for r in good])), \
            "median axial FWHM of the fitted particles"
        at_floor = median_at_floor(good, "axial")
    elif not (math.isfinite(elongation_um) and elongation_um >= 0):
        raise InputError(f"elongation: {elongation_um!r} um must be a number >= 0")
    cells = {}
    for r in rows:
        i, j = int(r["y_um"] // patch_um), int(r["x_um"] // patch_um)
        if 0 <= i < ny and 0 <= j < nx:
            cells.setdefault((i, j), []).append(r["z_um"])
    patches = []
    for (i, j), zs in sorted(cells.items()):
        if len(zs) < min_particles:
            continue
        patches.append({"patch_row": i, "patch_col": j, "y0_um": i * patch_um, "x0_um": j * patch_um,
                        "particles": len(zs), "z_min_um": float(min(zs)), "z_max_um": float(max(zs)),
                        "range_um": float(max(zs) - min(zs) + elongation_um)})
    v = np.array([p["range_um"] for p in patches])
    return {"patches": patches, "patch_um": float(patch_um), "patches_total": ny * nx,
            "mean_um": float(v.mean()) if v.size else None, "std_um": float(v.std(ddof=1)) if v.size > 1 else None,
            "elongation_um": float(elongation_um), "elongation_from": source, "elongation_at_floor": at_floor}


__all__ = ["FWHM_PER_SIGMA", "HALF_WINDOW", "SIGMA_MIN_VOX", "at_fit_floor", "depth_range", "fit_particle",
           "measure_particle", "median_at_floor", "noise_floor", "particle_table", "summary"]

"""The sample's scattering length estimated from a reconstruction: how the emitters' light falls with depth.

A reconstruction made with a clear-medium PSF holds each emitter dimmed by the ballistic fraction
exp(-d / l_s) of its depth d below the surface (cm2cl.solver.attenuation). Where the emitters' brightness does
not depend on depth (beads in a phantom, cells of one kind through a slab of tissue) the fall of their light with
depth measures l_s. The light of one emitter is its flux, the volume summed over a small box around its maximum:
the PSF's planes hold the same light, so a reconstructed point keeps its flux at every depth, while its peak
grows near focus and falls away from it (on the paper's fig5_scattering phantom without scattering the median
flux per plane stayed within 15% of the shallowest plane's, the median peak varied 1.8x).

The rule (:func:`estimate_scattering_length`):

1. local maxima above ``threshold`` of the volume's maximum (:func:`~cm2cl.analysis.emitters.find_emitters`);
   the first and last two planes are left out (light from beyond the stack's range collects there);
2. per plane with at least ``min_per_plane`` of them, the median log flux; a line through these medians against
   the depth below the surface (Theil-Sen, robust to a plane off the line) gives the decay rate k = 1 / l_s;
3. the volume is brightened by exp(k d) and 1-2 are repeated, so that deep emitters the threshold cut for being
   dim enter the medians (a median over only the brightest deep ones reads too little decay), until k moves by
   less than 1% of the stack's depth range;
4. a bootstrap over the maxima (resampled with replacement) gives k's 95% interval. The estimate is applied only
   where that interval says the light falls by at least 10% over the stack (exp(-k_low D) <= 0.9, D the
   deepest plane's depth below the surface): the flux of a point varies by about that much with depth without
   any scattering.

What it assumes, and cannot check: the emitters' brightness is the same in distribution at every depth. A
sample whose deep emitters are dimmer for another reason (fewer labels, a dimmer cell type) is brightened
as if it scattered.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage, stats

from ..errors import InputError
from .emitters import find_emitters

__all__ = ["estimate_scattering_length", "DETECT", "MIN_PER_PLANE", "MIN_FALL"]

#: maxima above this fraction of the volume's maximum are the emitters (below ~0.05 the end planes' faint
#: maxima outnumber the beads on fig5_scattering)
DETECT = 0.1
#: a plane's median flux needs at least this many emitters
MIN_PER_PLANE = 5
#: the estimate is applied where the light falls by at least this fraction over the stack (95% confidence)
MIN_FALL = 0.1
#: planes left out at each end of the stack: light from beyond the stack's range collects in the end planes,
#: and their neighbours share it (on the quality suite's array PSF a bead in the last two planes reconstructs
#: with 30-60% of its light missing, with or without attenuation)
END_PLANES = 2
#: the flux box's half sizes (planes, pixels, pixels)
HALF_BOX = (1, 2, 2)


def _fluxes(v, threshold):
    """(plane index, log flux) of the maxima of ``v`` above ``threshold`` x its maximum, inner planes only."""
    det = find_emitters(v, threshold=threshold, min_distance_vox=(1, 3, 3))
    idx = np.rint(det["index"]).astype(int)
    size = tuple(2 * h + 1 for h in HALF_BOX)
    box = ndimage.uniform_filter(v, size, mode="constant") * float(np.prod(size))
    # above each plane's floor (its median: 0 in a sparse volume, a noise floor where the volume has one)
    floor = ndimage.uniform_filter1d(np.median(v, axis=(1, 2)), size[0], mode="constant") * float(np.prod(size))
    flux = box[tuple(idx.T)] - floor[idx[:, 0]] if len(idx) else np.zeros(0)
    iz = idx[:, 0] if len(idx) else np.zeros(0, int)
    ok = (iz >= END_PLANES) & (iz < v.shape[0] - END_PLANES) & (flux > 0)
    return iz[ok], np.log(flux[ok])


def _rate(iz, lf, d, min_per_plane):
    """The decay rate of the per-plane median log flux with depth below the surface (Theil-Sen: the median of
    the slopes between pairs of planes, so that one plane off the line, a stack's end or a plane of few
    emitters, does not tilt it), or None with fewer than 3 planes of enough maxima."""
    planes = [i for i in np.unique(iz) if np.count_nonzero(iz == i) >= min_per_plane]
    if len(planes) < 3 or np.ptp(d[planes]) <= 0:
        return None
    m = np.array([np.median(lf[iz == i]) for i in planes])
    return -float(stats.theilslopes(m, d[planes])[0])


def estimate_scattering_length(volume, depths_um, surface_um: float | None = None, *, threshold: float = DETECT,
                               min_per_plane: int = MIN_PER_PLANE, min_fall: float = MIN_FALL, rounds: int = 8,
                               n_boot: int = 200, seed: int = 0) -> dict:
    """Estimate l_s from how the emitters' flux falls with depth in ``volume`` (nz, ny, nx), reconstructed
    with a clear-medium PSF (the module's doc has the rule and its assumption). ``depths_um``: the planes'
    depths (depth increases with them); ``surface_um`` None: the shallowest plane.

    Returns a dict: ``scattering_length_um`` (the estimate to apply, or None where none is: no decay, too
    little, or too few emitters), ``rate_per_um`` k and its bootstrap 95% interval ``rate_interval_per_um``,
    ``fall_over_stack`` (1 - exp(-k D)), ``surface_um``, ``emitters`` and ``planes`` used, ``per_plane`` (each
    used plane's depth, emitters and median log flux in the volume as given), ``rounds``, ``reason`` (why nothing
    is applied, else None) and the rule's constants."""
    v0 = np.asarray(volume, np.float64)
    z = np.asarray(depths_um, np.float64).ravel()
    if v0.ndim != 3:
        raise InputError(f"volume: expected (planes, y, x), got shape {v0.shape}")
    if z.size != v0.shape[0]:
        raise InputError(f"depths_um: {z.size} depths for {v0.shape[0]} planes")
    top = float(z.min()) if surface_um is None else float(surface_um)
    d = np.clip(z - top, 0.0, None)
    out = {"scattering_length_um": None, "rate_per_um": None, "rate_interval_per_um": None, "fall_over_stack": None,
           "surface_um": top, "emitters": 0, "planes": 0, "per_plane": [], "rounds": 0, "reason": None,
           "rule": {"threshold": threshold, "min_per_plane": min_per_plane, "min_fall": min_fall,
                    "half_box": list(HALF_BOX), "n_boot": n_boot}}
    short = (f"{v0.shape[0]} planes: it needs {2 * END_PLANES + 3} (the {END_PLANES} at each end are left out)"
             if v0.shape[0] < 2 * END_PLANES + 3 else "no plane below the surface" if d.max() <= 0
             else "an empty volume" if v0.max() <= 0 else None)
    if short:
        out["reason"] = short
        return out
    k, step = 0.0, None
    for r in range(rounds):
        iz, lf = _fluxes(v0 * np.exp(k * d)[:, None, None], threshold)
        step = _rate(iz, lf, d, min_per_plane)
        if step is None:
            out["reason"] = f"fewer than 3 inner planes with {min_per_plane} maxima above {threshold:g} of the peak"
            return {**out, "emitters": int(len(iz)), "rounds": r + 1}
        k += step
        if abs(step) * d.max() < 0.01:
            break
    base = k - step   # the bootstrap refits the last round's maxima
    rng = np.random.default_rng(seed)
    boot = [b for b in (_rate(iz[s], lf[s], d, min_per_plane) for s in
                        (rng.integers(0, len(iz), len(iz)) for _ in range(n_boot))) if b is not None]
    if len(boot) < n_boot // 2:   # most resamples leave fewer than 3 planes of enough maxima
        out["reason"] = f"too few maxima for a stable fit ({len(boot)} of {n_boot} resamples fit a line)"
        return {**out, "emitters": int(len(iz)), "rounds": r + 1}
    lo, hi = (float(base + q) for q in np.quantile(boot, [0.025, 0.975]))
    used = [int(i) for i in np.unique(iz) if np.count_nonzero(iz == i) >= min_per_plane]
    # each plane's median log flux in the volume as solved (the last round's brightening taken back out)
    per_plane = [{"plane": i, "depth_um": float(z[i]), "emitters": int(np.count_nonzero(iz == i)),
                  "median_log_flux": float(np.median(lf[iz == i]) - (k - step) * d[i])} for i in used]
    out.update(rate_per_um=float(k), rate_interval_per_um=[lo, hi], fall_over_stack=float(1 - np.exp(-k * d.max())),
               emitters=int(len(iz)), planes=len(used), rounds=r + 1, per_plane=per_plane)
    if k <= 0:
        out["reason"] = "the emitters' light does not fall with depth"
    elif 1.0 - np.exp(-lo * d.max()) < min_fall:
        out["reason"] = (f"the light falls by less than {min_fall:g} over the stack at 95% confidence "
                         f"(lower bound {1.0 - np.exp(-lo * d.max()):.3f})")
    else:
        out["scattering_length_um"] = float(1.0 / k)
    return out

"""From a raw calibration scan (a pinhole moved along z, paper Methods "PSF calibration") to the PSF stack
the solver takes: dark level off, lateral drift of the stage axis registered out, depth range and axial
binning, lateral binning, a noise floor, per-plane normalisation; every step and what it measured in a
record (issue 12 item 1)."""

from __future__ import annotations

import logging

import numpy as np

from ..analysis.registration import fourier_shift, scan_drift
from ..errors import InputError
from ..solver.control import noise_sigma
from .prepare import bin_image

log = logging.getLogger("cm2cl")

#: corner boxes (pixels) whose median is a plane's dark level
CORNER = 20


def corner_level(plane, box: int = CORNER) -> float:
    p = np.asarray(plane, np.float64)
    b = max(1, min(box, p.shape[0] // 4, p.shape[1] // 4))
    c = np.concatenate([p[:b, :b].ravel(), p[:b, -b:].ravel(), p[-b:, :b].ravel(), p[-b:, -b:].ravel()])
    return float(np.median(c))


def prepare_psf_stack(scan, z_um, *, dark="corners", register: bool = True, z_range=None, axial_bin: int = 1,
                      lateral_bin: int = 1, noise_floor: float = 3.0, name: str = "scan"):
    """(stack (nz, My, Mx) float64, depths_um (nz,), record) from ``scan`` (n, H, W) taken at ``z_um`` (n,).

    ``dark``: 'corners' (each plane's median of its four 20 x 20 corners), a number, a dark frame (H, W),
    or None. ``z_range``: (z_min, z_max) um of the planes to keep. ``axial_bin``: planes summed per output
    plane (depth = their mean z). ``noise_floor``: values under this many noise sigmas (measured in the
    corners, scaled for the binning) are set to 0. Each output plane is normalised to unit sum."""
    a = np.asarray(scan)
    if a.ndim != 3 or a.shape[0] < 1:
        raise InputError(f"{name}: expected a (planes, H, W) scan, got shape {a.shape}")
    if a.dtype.kind not in "uif":
        raise InputError(f"{name}: dtype {a.dtype} is not numeric")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name}: contains NaN/Inf values")
    z = np.asarray(z_um, np.float64).ravel()
    if len(z) != len(a):
        raise InputError(f"{name}: {len(a)} planes but {len(z)} z positions")
    if len(z) > 1 and not (np.all(np.diff(z) > 0) or np.all(np.diff(z) < 0)):
        raise InputError(f"{name}: z positions must increase (or decrease) monotonically")
    for k, v in (("axial_bin", axial_bin), ("lateral_bin", lateral_bin)):
        if int(v) != v or v < 1:
            raise InputError(f"{k}: must be an integer >= 1, got {v!r}")
    rec = {"planes_in": int(len(a)), "z_um": [float(z[0]), float(z[-1])], "steps": []}

    # 1. dark level
    sigma = float(np.median([noise_sigma(p) for p in a[:: max(1, len(a) // 8)]]))
    if isinstance(dark, str) and dark == "corners":
        levels = np.array([corner_level(p) for p in a])
        peaks = a.reshape(len(a), -1).max(axis=1)
        bright = levels > 0.05 * np.maximum(peaks - levels, 1e-300)
        if np.any(bright):
            msg = (f"{name}: the corners of {int(bright.sum())} plane(s) are not dark (median up to "
                   f"{float(levels.max()):.4g}, {float((levels / np.maximum(peaks, 1e-300)).max()):.1%} of the "
                   "peak); give a dark frame or a dark level")
            log.warning(msg)
            rec.setdefault("warnings", []).append(msg)
        a = a - levels[:, None, None]
        rec["steps"].append({"step": "dark level", "method": "median of the four 20 x 20 corners per plane",
                             "level_min": float(levels.min()), "level_max": float(levels.max())})
    elif dark is not None:
        d = np.asarray(dark, np.float64)
        if d.ndim == 2 and d.shape != a.shape[1:]:
            raise InputError(f"{name}: the dark frame's shape {d.shape} differs from the planes' {a.shape[1:]}")
        a = a - (d[None] if d.ndim == 2 else float(d))
        rec["steps"].append({"step": "dark level", "method": "dark frame" if d.ndim == 2 else "constant",
                             "level_mean": float(np.mean(d))})
    a = np.maximum(a, 0.0)

    # 2. lateral drift of the scan axis
    if register and len(a) > 1:
        drift = scan_drift(a, z)
        for i in range(len(a)):
            a[i] = np.maximum(fourier_shift(a[i], -drift["fit"][i]), 0.0)
        rec["steps"].append({"step": "registration", "method": "cross-correlation of neighbouring planes "
                             "(upsampled DFT, 1/100 px), straight line against z",
                             "drift_px_per_mm": [float(v) for v in drift["per_mm"]],
                             "residual_px": float(np.sqrt(np.mean((drift["shifts"] - drift["fit"]) ** 2)))})

    # 3. depth range
    if z_range is not None:
        lo, hi = sorted(float(v) for v in z_range)
        if lo < z.min() - 1e-9 or hi > z.max() + 1e-9:
            raise InputError(f"{name}: depth range [{lo:g}, {hi:g}] um is outside the scan [{z.min():g}, {z.max():g}] um")
        keep = (z >= lo - 1e-9) & (z <= hi + 1e-9)
        a, z = a[keep], z[keep]
        rec["steps"].append({"step": "depth range", "z_um": [lo, hi], "planes": int(keep.sum())})

    # 4. axial binning
    n = (len(a) // axial_bin) * axial_bin
    if n == 0:
        raise InputError(f"{name}: {len(a)} plane(s) cannot be binned by {axial_bin}")
    a = a[:n].reshape(n // axial_bin, axial_bin, *a.shape[1:]).sum(axis=1)
    depths = z[:n].reshape(-1, axial_bin).mean(axis=1)
    if axial_bin > 1:
        rec["steps"].append({"step": "axial binning", "planes_summed": int(axial_bin), "planes": int(len(a))})

    # 5. lateral binning, noise floor, normalisation
    a = bin_image(a, lateral_bin, name)
    floor = noise_floor * sigma * np.sqrt(axial_bin * lateral_bin ** 2)
    a[a < floor] = 0.0
    sums = a.reshape(len(a), -1).sum(axis=1)
    if np.any(sums <= 0):
        raise InputError(f"{name}: plane(s) {np.flatnonzero(sums <= 0).tolist()} hold no light above the noise floor")
    a /= sums[:, None, None]
    rec["steps"] += [{"step": "lateral binning", "factor": int(lateral_bin)},
                     {"step": "noise floor", "sigmas": float(noise_floor), "noise_sigma": sigma, "floor": float(floor)},
                     {"step": "normalisation", "method": "unit sum per plane"}]
    rec.update(planes_out=int(len(a)), depths_um=[float(d) for d in depths])
    return a, depths, rec

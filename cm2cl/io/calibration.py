"""From a raw calibration scan (a pinhole moved along z, paper Methods "PSF calibration") to the PSF stack
the solver takes (issue 12 items 1 and 4), in the order the data flows:

1. depth range: the planes whose z lies in the range (checked against the scan before any pixel is read);
2. dark level: each plane's median of its four corners (``'corners'``, 20 x 20), of a region, a number,
   or a dark frame; a "dark" level that is not dark (the region holds light, or much of the plane lies
   below it) is reported with the level measured;
3. registration: the lateral drift of the stage axis, measured by sub-pixel cross-correlation
   (:func:`cm2cl.analysis.registration.scan_drift`), fitted as a line in z, reported in px per mm, and
   taken out of every plane (Fourier or bilinear shift, zero filled);
4. sensor fit: a scan whose lateral size differs from the sensor is padded with zeros or cropped so that
   its optical axis lands on the sensor's centre (:func:`cm2cl.io.prepare.fit_lateral`);
5. axial binning (sums of neighbouring planes; a plane's depth is their mean z), lateral binning to the
   working pixel, values under a noise floor set to 0, normalisation (unit sum per plane).

The scan is read plane by plane, twice (measure, then apply): memory holds two planes, a few spectra and
the output. Every step, its parameters and what it measured go into the returned record.
"""

from __future__ import annotations

import numpy as np

from ..analysis.registration import SHIFT_METHODS, scan_drift, shift_image
from ..errors import InputError
from ..solver.control import noise_sigma
from .prepare import bin_image, fit_lateral

#: corner boxes (pixels) whose median is a plane's dark level by default (the DiffuserCam 3D recipe)
CORNER = 20
#: a dark level is "not dark" when more than this fraction of the plane lies over 3 noise sigmas below it
#: (it was measured on light), or when the dark region's spread exceeds 3 noise sigmas (it holds structure)
NOT_DARK_BELOW = 0.05
NORMALISATIONS = ("plane", "stack", "none")


def parse_dark(text: str):
    """The CLI's ``--dark``: 'corners', 'corners:N', 'region:R0:R1,C0:C1' (rows R0..R1-1, columns C0..C1-1),
    a number, 'none', or else the path of a dark-frame TIFF (returned as a str for the caller to read)."""
    t = str(text).strip()
    if t == "none":
        return None
    if t == "corners":
        return "corners"
    if t.startswith("corners:"):
        try:
            return ("corners", int(t.split(":", 1)[1]))
        except ValueError:
            raise InputError(f"dark: expected corners:N (a box size in pixels), got {text!r}") from None
    if t.startswith("region:"):
        try:
            rows, cols = t.split(":", 1)[1].split(",")
            r0, r1 = (int(v) for v in rows.split(":"))
            c0, c1 = (int(v) for v in cols.split(":"))
        except ValueError:
            raise InputError(f"dark: expected region:R0:R1,C0:C1 (rows R0..R1-1, columns C0..C1-1), "
                             f"got {text!r}") from None
        return ("region", (r0, r1, c0, c1))
    try:
        return float(t)
    except ValueError:
        return t


class _DarkModel:
    """A plane's dark level from the ``dark`` argument of :func:`prepare_psf_stack`, and the check that it
    is dark."""

    def __init__(self, dark, shape, name):
        self.name, self.frame, self.value, self.boxes = name, None, None, None
        H, W = shape
        if dark is None:
            self.kind, self.describe = "none", "none"
        elif isinstance(dark, str) or (isinstance(dark, tuple) and dark and dark[0] == "corners"):
            if isinstance(dark, str) and dark != "corners":
                raise InputError(f"{name}: dark {dark!r} is not 'corners', a region, a number or a frame")
            b = CORNER if isinstance(dark, str) else int(dark[1])
            if b < 1 or 2 * b > min(H, W):
                raise InputError(f"{name}: dark corners of {b} x {b} pixels do not fit twice in its {H} x {W} planes")
            self.kind, self.describe = "region", f"median of the four {b} x {b} corners of each plane"
            self.boxes = [(slice(0, b), slice(0, b)), (slice(0, b), slice(W - b, W)),
                          (slice(H - b, H), slice(0, b)), (slice(H - b, H), slice(W - b, W))]
        elif isinstance(dark, tuple) and dark and dark[0] == "region":
            r0, r1, c0, c1 = (int(v) for v in dark[1])
            if not (0 <= r0 < r1 <= H and 0 <= c0 < c1 <= W):
                raise InputError(f"{name}: dark region rows {r0}:{r1}, columns {c0}:{c1} is empty or outside "
                                 f"its {H} x {W} planes")
            self.kind, self.describe = "region", f"median of rows {r0}:{r1}, columns {c0}:{c1} of each plane"
            self.boxes = [(slice(r0, r1), slice(c0, c1))]
        elif np.ndim(dark) == 0:
            v = float(dark)
            if not np.isfinite(v):
                raise InputError(f"{name}: dark level must be finite, got {dark!r}")
            self.kind, self.value, self.describe = "constant", v, f"the constant {v:g}"
        else:
            d = np.asarray(dark, np.float64)
            d = d.mean(axis=0) if d.ndim == 3 else d
            if d.shape != tuple(shape):
                raise InputError(f"{name}: the dark frame's shape {d.shape} differs from the planes' {tuple(shape)}")
            if not np.isfinite(d).all():
                raise InputError(f"{name}: the dark frame holds NaN/Inf values")
            self.kind, self.frame = "frame", d
            self.describe = "a dark frame" + (f" (the mean of {np.shape(dark)[0]})" if np.ndim(dark) == 3 else "")

    def level(self, plane):
        """The dark level of ``plane`` (a number, or the frame)."""
        if self.kind == "region":
            return float(np.median(np.concatenate([plane[b].ravel() for b in self.boxes])))
        if self.kind == "constant":
            return self.value
        if self.kind == "frame":
            return self.frame
        return 0.0

    def not_dark(self, plane, level, sigma) -> bool:
        """True when the level was measured on light: much of the plane lies below it, or the region holds
        structure beyond the noise."""
        if self.kind == "none":
            return False
        below = float(np.mean(plane - level < -3.0 * sigma)) if sigma > 0 else 0.0
        if below > NOT_DARK_BELOW:
            return True
        if self.kind == "region":
            vals = np.concatenate([plane[b].ravel() for b in self.boxes])
            spread = 1.4826 * float(np.median(np.abs(vals - np.median(vals))))
            return spread > 3.0 * sigma
        return False


def _check_int(key, v):
    if isinstance(v, bool) or int(v) != v or v < 1:
        raise InputError(f"{key}: must be an integer >= 1, got {v!r}")
    return int(v)


def _select(z, z_range, name):
    """Indices of the planes in ``z_range``, by increasing z."""
    order = np.argsort(z, kind="stable")
    if z_range is None:
        return order
    lo, hi = sorted(float(v) for v in z_range)
    eps = 1e-6 * max(1.0, float(np.abs(z).max()))
    if lo < z.min() - eps or hi > z.max() + eps:
        raise InputError(f"{name}: depth range [{lo:g}, {hi:g}] um is outside the scan's [{z.min():g}, "
                         f"{z.max():g}] um")
    keep = order[(z[order] >= lo - eps) & (z[order] <= hi + eps)]
    if len(keep) == 0:
        raise InputError(f"{name}: no plane lies in the depth range [{lo:g}, {hi:g}] um")
    return keep


def prepare_psf_stack(scan, z_um, *, dark="corners", register: bool = True, shift_method: str = "fourier",
                      max_lag_um: float = 320.0, z_range=None, axial_bin: int | None = None, dz_um: float | None = None,
                      lateral_bin: int = 1, sensor_shape=None, axis=None, noise_floor: float = 3.0,
                      normalise: str = "plane", name: str = "scan"):
    """A prepared PSF stack from a raw z scan.

    Parameters
    ----------
    scan : the raw planes, (n, H, W) array (8/12/16-bit integers or float) or any sequence of n 2D planes
        (``len`` and ``scan[i]``; read one at a time, twice).
    z_um : (n,) z position of each plane, um (increasing or decreasing).
    dark : 'corners' (each plane's median of its four 20 x 20 corners), ('corners', N), ('region',
        (r0, r1, c0, c1)), a number, a dark frame (H, W) or frames (k, H, W) (averaged), or None.
    register : measure the lateral drift of the scan and take it out (shift_method 'fourier' or
        'bilinear'; planes up to ``max_lag_um`` apart are correlated, see
        :func:`cm2cl.analysis.registration.scan_drift`).
    z_range : (z_min, z_max) um of the planes to keep (inclusive); default all.
    axial_bin, dz_um : planes summed per output plane, or the output plane step in um (a multiple of the
        scan step); default 1. Planes left over are dropped evenly at both ends.
    lateral_bin : sum-binning of rows and columns to the working pixel.
    sensor_shape : (rows, cols) in scan pixels: pad with zeros / crop every plane to the sensor, its
        optical axis on the sensor's centre; ``axis`` (row, col) in scan pixels, 'centroid' (the light's
        centroid of the plane nearest the middle depth) or None (the scan's centre).
    noise_floor : values under this many noise sigmas (of the binned planes) become 0 (0: only negative
        values, as a clip at 0).
    normalise : 'plane' (each plane sums to 1), 'stack' (the brightest plane sums to 1, relative
        throughput kept) or 'none'.

    Returns (stack (nz, My, Mx) float64, depths_um (nz,), record dict)."""
    z = np.asarray(z_um, np.float64).ravel()
    n = len(scan)
    if n < 1:
        raise InputError(f"{name}: holds no plane")
    if len(z) != n:
        raise InputError(f"{name}: {n} planes but {len(z)} z positions")
    if not np.isfinite(z).all():
        raise InputError(f"{name}: z positions must be finite")
    if n > 1 and not (np.all(np.diff(z) > 0) or np.all(np.diff(z) < 0)):
        raise InputError(f"{name}: z positions must increase (or decrease) strictly")
    if shift_method not in SHIFT_METHODS:
        raise InputError(f"shift method: unknown {shift_method!r} (known: {', '.join(SHIFT_METHODS)})")
    if normalise not in NORMALISATIONS:
        raise InputError(f"normalise: unknown {normalise!r} (known: {', '.join(NORMALISATIONS)})")
    if not (np.isfinite(noise_floor) and noise_floor >= 0):
        raise InputError(f"noise floor: must be a number >= 0, got {noise_floor!r}")
    lateral_bin = _check_int("lateral bin", lateral_bin)
    if not (np.isfinite(max_lag_um) and max_lag_um > 0):
        raise InputError(f"max lag: must be a positive number of um, got {max_lag_um!r}")
    step = float(np.median(np.abs(np.diff(z)))) if n > 1 else None
    if dz_um is not None:
        if not (np.isfinite(float(dz_um)) and float(dz_um) > 0):
            raise InputError(f"dz: must be a positive number of um, got {float(dz_um):g}")
        if axial_bin is not None:
            raise InputError("axial binning: give the planes summed or dz_um, not both")
        if step is None:
            raise InputError(f"{name}: dz {dz_um} um needs a scan of more than one plane")
        ratio = float(dz_um) / step
        if not (np.isfinite(ratio) and ratio >= 1 - 1e-6 and abs(ratio - round(ratio)) < 1e-6):
            raise InputError(f"dz: {float(dz_um):g} um is not a whole multiple of the scan step {step:g} um")
        axial_bin = int(round(ratio))
    axial_bin = _check_int("axial bin", 1 if axial_bin is None else axial_bin)

    # 1. depth range, and the planes each output plane sums (from z alone: nothing read yet)
    sel = _select(z, z_range, name)
    nb = len(sel) // axial_bin
    if nb == 0:
        raise InputError(f"{name}: {len(sel)} plane(s) in the depth range cannot be binned by {axial_bin}")
    left = len(sel) - nb * axial_bin
    sel_used = sel[left // 2: left // 2 + nb * axial_bin]
    zs = z[sel_used]
    rec = {"scan": name, "planes_in": int(n), "z_um": [float(z[0]), float(z[-1])],
           "step_um": step, "steps": [], "warnings": []}
    rec["steps"].append({"step": "depth range", "z_um": None if z_range is None else sorted(map(float, z_range)),
                         "planes_kept": int(len(sel_used)), "planes_dropped_for_binning": int(left),
                         "kept_z_um": [float(zs[0]), float(zs[-1])]})

    first = np.asarray(scan[int(sel_used[0])])
    if first.ndim != 2:
        raise InputError(f"{name}: plane {int(sel_used[0])} has shape {first.shape}; expected 2D planes")
    shape = first.shape
    if min(shape) < 3:
        raise InputError(f"{name}: planes of {shape[0]} x {shape[1]} pixels are too small")
    darkm = _DarkModel(dark, shape, name)
    fit_shape = shape if sensor_shape is None else tuple(int(v) for v in sensor_shape)
    if len(fit_shape) != 2 or min(fit_shape) < lateral_bin:
        if sensor_shape is None:
            raise InputError(f"lateral bin: {lateral_bin} is larger than the {shape[0]} x {shape[1]} planes")
        raise InputError(f"sensor shape: {sensor_shape!r} must be (rows, cols) of at least the lateral bin "
                         f"{lateral_bin}")
    if isinstance(axis, str) and axis != "centroid":
        raise InputError(f"axis: expected (row, col), 'centroid' or None, got {axis!r}")

    # 2. pass 1: dark level, noise, saturation and the drift, plane by plane
    stats = {"level": [], "sigma": [], "peak": [], "not_dark": [], "saturated": 0}
    sat_planes, mid = [], int(np.argmin(np.abs(zs - 0.5 * (zs.min() + zs.max()))))
    centroid = None

    def read(k):
        i = int(sel_used[k])
        p = np.asarray(scan[i])
        if p.shape != shape:
            raise InputError(f"{name}: plane {i} has shape {p.shape}, plane {int(sel_used[0])} {shape}; all planes "
                             "of a scan must have one shape")
        if p.dtype.kind not in "uif":
            raise InputError(f"{name}: plane {i} has dtype {p.dtype}, not a number type")
        return p

    def measured():
        nonlocal centroid
        for k in range(len(sel_used)):
            raw = read(k)
            if raw.dtype.kind in "ui":
                s = int(np.count_nonzero(raw == np.iinfo(raw.dtype).max))
                if s:
                    stats["saturated"] += s
                    sat_planes.append(int(sel_used[k]))
            p = raw.astype(np.float64)
            if not np.isfinite(p).all():
                raise InputError(f"{name}: plane {int(sel_used[k])} holds NaN/Inf values")
            lev = darkm.level(p)
            sig = noise_sigma(p - lev) if darkm.kind == "frame" else noise_sigma(p)
            stats["not_dark"].append(darkm.not_dark(p, lev, sig))
            stats["level"].append(float(np.mean(lev)))    # a frame's mean (pass 2 subtracts the frame)
            stats["sigma"].append(sig)
            p = p - lev
            stats["peak"].append(float(p.max()))
            if k == mid and isinstance(axis, str):
                w = np.maximum(p, 0.0)
                if w.sum() <= 0:
                    raise InputError(f"{name}: plane {int(sel_used[k])} holds no light to find the axis from")
                rr, cc = np.indices(w.shape)
                centroid = (float((w * rr).sum() / w.sum()), float((w * cc).sum() / w.sum()))
            yield p

    drift = None
    if register and len(sel_used) > 1:
        drift = scan_drift(measured(), zs, max_lag_um=max_lag_um)
    else:
        for _ in measured():
            pass
    levels = np.array(stats["level"])
    sigma = float(np.median(stats["sigma"]))
    step_rec = {"step": "dark level", "method": darkm.describe}
    if darkm.kind != "none":
        step_rec.update(level_min=float(levels.min()), level_max=float(levels.max()),
                        level_median=float(np.median(levels)))
    rec["steps"].append(step_rec)
    bad = np.flatnonzero(stats["not_dark"])
    if bad.size:
        k = int(bad[np.argmax(levels[bad])])
        frac = levels[k] / max(levels[k] + stats["peak"][k], 1e-300)
        rec["warnings"].append(
            f"{name}: the dark level ({darkm.describe}) is not dark in {bad.size} of {len(levels)} planes: up to "
            f"{levels[k]:.4g} (plane {int(sel_used[k])}, z {zs[k]:g} um; {frac:.1%} of its peak; noise "
            f"{stats['sigma'][k]:.3g}); light is subtracted with it: give a dark frame or a region away from the PSF")
    if stats["saturated"]:
        rec["warnings"].append(f"{name}: {stats['saturated']} pixel(s) at the integer maximum (saturated) in "
                               f"{len(sat_planes)} plane(s), first {sat_planes[:5]}: those PSF peaks are clipped")
    rec["noise_sigma"] = sigma
    if drift is not None:
        rec["steps"].append({"step": "registration", "method": "cross-correlation of pairs of planes up to "
                             f"{max_lag_um:g} um apart (whole-pixel peak, sub-pixel from the cross-spectrum's "
                             "low-frequency phase), a line in z fitted to the pair shifts; "
                             f"{shift_method} shift, zero filled",
                             "drift_px_per_mm": [float(v) for v in drift["per_mm"]],
                             "reference_um": drift["reference_um"], "residual_px": drift["residual_px"],
                             "pairs": drift["pairs"], "pairs_dropped": drift["pairs_dropped"],
                             "shift_px_max": float(np.abs(drift["fit"]).max())})

    # 3. sensor fit (the axis in scan pixels, at the reference depth)
    ax = None
    if axis is not None:
        ax = centroid if isinstance(axis, str) else tuple(float(v) for v in axis)
    _, fit_info = fit_lateral(np.zeros((1,) + shape), fit_shape, ax, name)
    fit_step = None
    if sensor_shape is not None or axis is not None:
        fit_step = {"step": "sensor fit", "rule": "pad with zeros / crop, the optical axis on the centre",
                    "axis_source": "centroid" if isinstance(axis, str) else ("given" if axis else "centre"),
                    **{k: v for k, v in fit_info.items() if k not in ("message", "light_cut")}}
        rec["steps"].append(fit_step)

    # 4. pass 2: apply, bin axially and laterally
    out, acc = None, np.zeros(fit_shape)
    lost = total = 0.0
    for k in range(len(sel_used)):
        p = read(k).astype(np.float64) - (darkm.frame if darkm.kind == "frame" else levels[k])
        if drift is not None:
            p = shift_image(p, -drift["fit"][k], shift_method)
        q, info = fit_lateral(p, fit_shape, ax, name)
        light = float(np.abs(p).sum())
        total += light
        lost += info["light_cut"] * light
        acc += q
        if (k + 1) % axial_bin == 0:
            b = bin_image(acc, lateral_bin, name)
            if out is None:
                out = np.zeros((nb,) + b.shape)
            out[k // axial_bin] = b
            acc[:] = 0.0
    depths = zs.reshape(nb, axial_bin).mean(axis=1)
    if fit_step is not None:
        fit_step["light_cut"] = lost / total if total > 0 else 0.0
        if fit_info["message"]:
            rec["notes"] = [fit_info["message"].split("; ")[0]
                            + (f"; {fit_step['light_cut']:.2%} of the light cut off" if fit_step["light_cut"] else "")]
    if axial_bin > 1:
        rec["steps"].append({"step": "axial binning", "planes_summed": axial_bin, "planes": int(nb),
                             "dz_um": None if step is None else step * axial_bin})
    if lateral_bin > 1:
        rec["steps"].append({"step": "lateral binning", "factor": lateral_bin, "shape": list(out.shape[1:])})

    # 5. noise floor and normalisation
    floor = noise_floor * sigma * np.sqrt(axial_bin * lateral_bin ** 2)
    out[out < floor] = 0.0
    rec["steps"].append({"step": "noise floor", "sigmas": float(noise_floor), "noise_sigma_raw": sigma,
                         "floor": float(floor), "zeroed_fraction": float(np.mean(out == 0))})
    sums = out.reshape(nb, -1).sum(axis=1)
    if np.any(sums <= 0):
        dead = np.flatnonzero(sums <= 0)
        raise InputError(f"{name}: output plane(s) {dead.tolist()} (depth {depths[dead[0]]:g} um ...) hold no light "
                         "above the noise floor")
    if normalise == "plane":
        out /= sums[:, None, None]
    elif normalise == "stack":
        out /= sums.max()
    rec["steps"].append({"step": "normalisation", "method": {"plane": "unit sum per plane", "none": "none",
                                                             "stack": "the brightest plane sums to 1"}[normalise],
                         "plane_sums_before": [float(s) for s in sums]})
    rec.update(planes_out=int(nb), depths_um=[float(d) for d in depths], shape=list(out.shape),
               axis_pixel=[out.shape[1] // 2, out.shape[2] // 2])
    if not rec["warnings"]:
        del rec["warnings"]
    return out, depths, rec

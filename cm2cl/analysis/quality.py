"""The quality suite's scenes and scores (issue 24, item 5; run by ``tools/quality_suite.py``).

Scenes are rendered with a synthetic CM2-like array PSF of this module's own (:func:`array_psf`: a
3 x 3 lenslet array whose foci move radially and blur with depth), never with the PSF the
reconstruction is given: the reconstruction gets the nominal stack, the measurement is made with a
perturbed one (:class:`Mismatch`: blurrier, off in depth, aberrated, truncated), plus a background
(:func:`background_field`) and Poisson-Gaussian camera noise with an offset the user subtracts. The
true object lives on the reconstruction grid (the sensor's field of view, embedded centred in the
padded grid exactly as the solver's crop C), so scores compare voxel arrays with no optics mapping:

- bead scenes: :func:`score_beads` (recall, false maxima, axial and lateral error),
- every scene: :func:`nrmse` (after a least-squares scale) and :func:`energy_near` (the fraction of the
  reconstructed energy within 2 voxels of the true object).

Everything random takes a seed; the same spec renders the same scene bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage

from ..errors import InputError
from .emitters import find_emitters, match_emitters

__all__ = ["DETECT_REL", "LATERAL_TOL_VOX", "AXIAL_TOL_PLANES", "NEAR_RADIUS_VOX", "TARGETS",
           "score_beads", "bead_moments", "nrmse", "energy_near", "quality_value", "targets_met",
           "Mismatch", "array_psf", "background_field", "Camera", "SceneSpec", "Scene", "render_scene",
           "place_beads", "fibre_volume", "scene_specs", "calibration_spec", "CALIBRATION_SEED_OFFSET"]

#: a scene's calibration frame (:func:`calibration_spec`) is rendered with the scene's seed plus this
CALIBRATION_SEED_OFFSET = 100

#: detection threshold (fraction of the volume's maximum), matching tolerances and the "near" radius
DETECT_REL = 0.2
LATERAL_TOL_VOX = 2.0
AXIAL_TOL_PLANES = 1.0
NEAR_RADIUS_VOX = 2.0

#: the issue's targets: bead scenes (recall at +-1 plane, false maxima per 10 beads, mean |axial
#: error| in planes) and fibre scenes (energy within 2 voxels of the truth)
TARGETS = {"recall": 0.95, "false_per_10": 1.0, "axial_err": 0.5, "energy_near": 0.60}


# ---------------------------------------------------------------------------------------------- scores
def score_beads(volume, true_zyx, threshold: float = DETECT_REL, lateral_tol: float = LATERAL_TOL_VOX,
                axial_tol: float = AXIAL_TOL_PLANES, min_distance_vox=(1, 2, 2)) -> dict:
    """Bead scores of a (nz, ny, nx) volume against true bead positions ``true_zyx`` (n, 3) in voxel
    units (plane index, row, column; fractional allowed).

    Detections are :func:`~cm2cl.analysis.emitters.find_emitters`' local maxima above ``threshold`` x
    the volume's maximum, ``min_distance_vox`` apart, with sub-voxel refinement. They are matched one to
    one with the true beads by :func:`~cm2cl.analysis.emitters.match_emitters` (minimum total normalised
    distance); a pair matches only within ``lateral_tol`` voxels laterally (Euclidean in y, x) and
    ``axial_tol`` planes axially. Returns:

    - ``n_true``, ``n_detected``, ``n_matched``;
    - ``recall`` = n_matched / n_true;
    - ``false_maxima`` = n_detected - n_matched (detections matched to no bead), and
      ``false_per_10`` = 10 x false_maxima / n_true;
    - ``axial_err`` = mean |detected - true plane| over the matched pairs (planes; NaN if none matched),
      ``lateral_err`` = their mean lateral distance (voxels);
    - ``f1`` = 2 n_matched / (n_true + n_detected), the one number recall and false maxima make together;
    - ``matched``: the indices of the true beads that were matched (the rest were missed).
    """
    true = np.asarray(true_zyx, dtype=float).reshape(-1, 3)
    if len(true) == 0:
        raise InputError("score_beads: no true beads")
    det = find_emitters(volume, threshold=threshold, min_distance_vox=min_distance_vox)
    m = match_emitters(det["index"], true, lateral_tol, axial_tol)
    n_t, n_d, n_m = m["n_true"], m["n_detected"], m["n_matched"]
    false = n_d - n_m
    return {"n_true": n_t, "n_detected": n_d, "n_matched": n_m, "recall": n_m / n_t,
            "false_maxima": false, "false_per_10": 10.0 * false / n_t,
            "axial_err": float(np.mean(np.abs(m["axial_error_um"]))) if n_m else float("nan"),
            "lateral_err": float(np.mean(m["lateral_error_um"])) if n_m else float("nan"),
            "f1": 2.0 * n_m / (n_t + n_d), "matched": sorted(int(j) for _, j in m["pairs"])}


def bead_moments(volume, zyx, half=(3, 3, 3)) -> dict:
    """Where the light around each bead lies: for each position of ``zyx`` (n, 3; plane, row, column, rounded to
    the voxel) the volume's non-negative part in the window of +-``half`` (planes, rows, columns) around it,
    clipped to the volume, gives

    - ``peak``: its maximum, the detector's measure (:func:`score_beads` compares it with the volume's);
    - ``flux``: its sum, the bead's light wherever it went;
    - ``axial_sd``: the intensity-weighted standard deviation of the plane index (planes);
    - ``lateral_rms``: the intensity-weighted rms distance from the window's lateral centroid (px; sigma sqrt 2
      for a lateral Gaussian of sigma px).

    Arrays of n; a window with no light gives NaN moments. A bead spread over planes or pixels keeps its flux
    while its peak falls."""
    v = np.maximum(np.asarray(volume, dtype=np.float64), 0.0)
    if v.ndim != 3:
        raise InputError(f"bead_moments: volume must be (nz, ny, nx), got shape {v.shape}")
    h = tuple(int(a) for a in half)
    if len(h) != 3 or min(h) < 0:
        raise InputError(f"bead_moments: half must be three non-negative integers, got {half!r}")
    pts = np.rint(np.asarray(zyx, dtype=float).reshape(-1, 3)).astype(int)
    out = {k: np.full(len(pts), np.nan) for k in ("peak", "flux", "axial_sd", "lateral_rms")}
    for i, p in enumerate(pts):
        lo = [max(int(c) - a, 0) for c, a in zip(p, h)]
        hi = [min(int(c) + a + 1, n) for c, a, n in zip(p, h, v.shape)]
        if any(b <= a for a, b in zip(lo, hi)):
            continue
        w = v[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        out["peak"][i], out["flux"][i] = float(w.max()), float(w.sum())
        if out["flux"][i] <= 0:
            continue
        z, y, x = np.meshgrid(*(np.arange(a, b, dtype=float) for a, b in zip(lo, hi)), indexing="ij")
        f = out["flux"][i]
        mz, my, mx = ((w * c).sum() / f for c in (z, y, x))
        out["axial_sd"][i] = math.sqrt((w * (z - mz) ** 2).sum() / f)
        out["lateral_rms"][i] = math.sqrt((w * ((y - my) ** 2 + (x - mx) ** 2)).sum() / f)
    return out


def nrmse(volume, truth) -> float:
    """||s x - t|| / ||t|| for volume x and truth t (same shape), with s = <x, t> / <x, x> the
    least-squares scale (the reconstruction's units are free); 0 for x proportional to t, 1 for x
    orthogonal to t or zero."""
    x = np.asarray(volume, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if x.shape != t.shape:
        raise InputError(f"nrmse: volume shape {x.shape} != truth shape {t.shape}")
    tn = float(np.vdot(t, t))
    if tn == 0:
        raise InputError("nrmse: the truth is zero")
    xx = float(np.vdot(x, x))
    s = float(np.vdot(x, t)) / xx if xx > 0 else 0.0
    return float(np.linalg.norm(s * x - t) / math.sqrt(tn))


def near_mask(truth, radius: float = NEAR_RADIUS_VOX) -> np.ndarray:
    """Voxels within Euclidean distance ``radius`` (in voxels, one plane = one voxel) of a non-zero
    voxel of ``truth``: the truth dilated by a 3D ball."""
    t = np.asarray(truth) != 0
    if not t.any():
        raise InputError("near_mask: the truth has no non-zero voxel")
    return ndimage.distance_transform_edt(~t) <= radius


def energy_near(volume, truth, radius: float = NEAR_RADIUS_VOX) -> float:
    """Fraction of the reconstructed energy within ``radius`` voxels of the true object: sum of
    max(x, 0) over :func:`near_mask` (the truth's non-zero voxels dilated by a 3D ball of that radius,
    one plane counting as one voxel) over sum of max(x, 0) everywhere. 1 when everything lies near the
    truth, NaN for an all-zero volume."""
    x = np.maximum(np.asarray(volume, dtype=np.float64), 0.0)
    if x.shape != np.shape(truth):
        raise InputError(f"energy_near: volume shape {x.shape} != truth shape {np.shape(truth)}")
    total = float(x.sum())
    if total == 0:
        return float("nan")
    return float(x[near_mask(truth, radius)].sum() / total)


def quality_value(row: dict) -> float:
    """The one number by which runs of a scene are compared (higher is better): a bead scene's ``f1``
    (recall and false maxima together; a bead pushed more than a plane off counts as one lost and one
    false), a fibre scene's ``energy_near``; NaN for rows without scores (real data)."""
    if row.get("kind") == "beads":
        return row["f1"]
    if row.get("kind") == "fibres":
        return row["energy_near"]
    return float("nan")


def targets_met(row: dict) -> dict:
    """{target: True/False} for one scored row: bead scenes recall >= 0.95, false maxima <= 1 per 10
    beads, mean axial error <= 0.5 plane; fibre scenes energy near the truth >= 0.60 (:data:`TARGETS`)."""
    if row.get("kind") == "beads":
        ax = row["axial_err"]
        return {"recall": row["recall"] >= TARGETS["recall"], "false_per_10": row["false_per_10"] <= TARGETS["false_per_10"],
                "axial_err": bool(np.isfinite(ax) and ax <= TARGETS["axial_err"])}
    if row.get("kind") == "fibres":
        return {"energy_near": bool(row["energy_near"] >= TARGETS["energy_near"])}
    return {}


# ---------------------------------------------------------------------------------------------- PSF model
@dataclass(frozen=True)
class Mismatch:
    """How the PSF that makes the measurement differs from the nominal one given to the reconstruction.

    blur: extra Gaussian blur (px, added in quadrature to every spot); dz: the stack rendered at plane
    coordinate t + dz (planes); aberration: strength of per-lenslet asymmetric blur (radially elongated,
    with a coma-like tail thrown outward, growing with the lenslet's distance from the axis, each lenslet
    jittered by a fixed seed); vignette: the outer lenslets' light cut (corners lose ``vignette``, edges
    half of it) and, when > 0, a circular field stop that cuts what falls beyond 0.42 x the sensor's
    smaller side from the axis."""
    blur: float = 0.0
    dz: float = 0.0
    aberration: float = 0.0
    vignette: float = 0.0

    def __bool__(self):
        return any((self.blur, self.dz, self.aberration, self.vignette))


NOMINAL = Mismatch()


def array_psf(nz: int, shape=(128, 128), mismatch: Mismatch = NOMINAL, *, grid: int = 3, pitch_frac: float = 0.27,
              spread: float = 0.2, sigma0: float = 1.0, sigma_slope: float = 1.0, supersample: int = 2,
              seed: int = 7, planes=None) -> np.ndarray:
    """A (nz, My, Mx) CM2-like array PSF stack: ``grid`` x ``grid`` lenslet foci around the optical axis
    (pixel (My//2, Mx//2), the solver's convention) at pitch ``pitch_frac`` x min(My, Mx).

    Plane coordinate t = 0 .. nz-1 (plus ``mismatch.dz``), u = (t - c) / c with c = (nz - 1) / 2 in
    [-1, 1]: lenslet (i, j)'s focus sits at pitch (i, j) (1 + spread u) from the axis (a point's images
    spread apart or contract with depth, the array's depth cue) and is a Gaussian of sigma
    sigma0 + sigma_slope |u| px (in focus mid-stack); ``mismatch`` perturbs the spots (:class:`Mismatch`).
    Each spot is rendered on a ``supersample``-fold grid and binned. Every nominal plane sums to 1 (the
    spots lie within the sensor); a vignetted stack sums to less. ``planes``: the plane coordinates t to
    render (fractional allowed: an emitter between planes), one output plane each; default 0 .. nz-1."""
    if nz < 1:
        raise InputError(f"array_psf: nz must be >= 1, got {nz}")
    my, mx = (int(s) for s in shape)
    ss = int(supersample)
    cy, cx = my // 2, mx // 2
    # pixel centres of the supersampled grid, relative to the axis
    gy = (np.arange(my * ss) + 0.5) / ss - 0.5 - cy
    gx = (np.arange(mx * ss) + 0.5) / ss - 0.5 - cx
    Y, X = np.meshgrid(gy, gx, indexing="ij")
    pitch = pitch_frac * min(my, mx)
    half = (grid - 1) / 2
    rng = np.random.default_rng(seed)
    lenslets = []
    for i in range(grid):
        for j in range(grid):
            oy, ox = i - half, j - half
            r = math.hypot(oy, ox) / max(half, 1e-9)        # 0 centre, 1 edges, sqrt 2 corners (3 x 3)
            # per-lenslet jitter of the aberration (fixed seed: the same aberrated stack every time)
            lenslets.append((oy, ox, r, 1.0 + 0.3 * rng.standard_normal(), math.radians(20.0) * rng.uniform(-1, 1)))
    rmax = max(l[2] for l in lenslets) or 1.0
    c = (nz - 1) / 2 if nz > 1 else 1.0
    a, b = mismatch.aberration, mismatch.blur
    ts = np.arange(nz, dtype=float) if planes is None else np.asarray(planes, float).ravel()
    out = np.zeros((len(ts), my, mx))
    for z, t0 in enumerate(ts):
        t = t0 + mismatch.dz
        u = (t - c) / c if nz > 1 else 0.0
        s = 1.0 + spread * u
        sig = sigma0 + sigma_slope * abs(u)
        plane = np.zeros_like(Y)
        full = np.zeros_like(Y)      # the same spots unvignetted: the plane's light before truncation
        for oy, ox, r, jit, rot in lenslets:
            py, px = pitch * oy * s, pitch * ox * s
            ang = (math.atan2(oy, ox) + (rot if a else 0.0)) if r > 0 else rot
            ar = a * jit * (r if r > 0 else 0.3)
            sr = math.hypot(sig * (1 + 0.8 * ar), b)          # radial
            st = math.hypot(sig * (1 + 0.15 * ar), b)         # tangential
            spots = [(1.0, 0.0, sr, st)]
            if a and r > 0:                                   # coma-like tail, thrown outward
                tail = 0.35 * min(ar, 1.5) / 1.5
                spots = [(1.0 - tail, 0.0, sr, st),
                         (tail, 1.8 * ar, math.hypot(1.3 * sig * (1 + 0.8 * ar), b), math.hypot(1.3 * sig, b))]
            cs, sn = math.cos(ang), math.sin(ang)
            w_len = 1.0 - mismatch.vignette * (r / rmax) ** 2
            for w, shift, s_r, s_t in spots:
                dy, dx = Y - (py + shift * sn), X - (px + shift * cs)
                dr = dx * cs + dy * sn
                dt = -dx * sn + dy * cs
                g = (w / (2 * math.pi * s_r * s_t)) * np.exp(-0.5 * ((dr / s_r) ** 2 + (dt / s_t) ** 2))
                full += g
                plane += w_len * g
        if mismatch.vignette:
            plane[np.hypot(Y, X) > 0.42 * min(my, mx)] = 0.0
        # unit light per plane before truncation (the spots lie within the sensor); truncation removes light
        out[z] = plane.reshape(my, ss, mx, ss).sum(axis=(1, 3)) / full.sum()
    return out


# ---------------------------------------------------------------------------------------------- objects
def place_beads(n: int, nz: int, shape, seed: int, planes=None, margin: int = 12, min_lateral: float = 5.0,
                min_axial: int = 2) -> np.ndarray:
    """(n, 3) integer bead positions (plane, row, column) in the field of view, ``margin`` px from its
    edges, in ``planes`` (default all), no two within ``min_lateral`` px laterally and ``min_axial``
    planes axially of each other (so that the matching's 2 px / 1 plane windows never hold two beads)."""
    rng = np.random.default_rng(seed)
    planes = np.arange(nz) if planes is None else np.asarray(planes)
    my, mx = shape
    pts = []
    tries = 0
    while len(pts) < n:
        tries += 1
        if tries > 200000:
            raise InputError(f"place_beads: cannot place {n} beads with these separations")
        p = np.array([rng.choice(planes), rng.integers(margin, my - margin), rng.integers(margin, mx - margin)])
        if all(not (abs(p[0] - q[0]) <= min_axial and math.hypot(p[1] - q[1], p[2] - q[2]) < min_lateral) for q in pts):
            pts.append(p)
    return np.array(pts, dtype=int)


def bead_volume(beads, amplitudes, nz: int, shape, sigma: float = 0.8) -> np.ndarray:
    """A (nz, My, Mx) volume of beads at integer positions ``beads`` (n, 3): each a lateral Gaussian of
    ``sigma`` px with peak ``amplitude`` at its voxel, kept within 1.5 px of it (a 3 x 3 blob: centre 1,
    edges exp(-1 / (2 sigma^2)), corners its square), in its plane only (planes are wider apart than
    pixels); sigma 0 gives single voxels."""
    vol = np.zeros((nz,) + tuple(shape))
    for (z, y, x), a in zip(np.asarray(beads, int), amplitudes):
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if sigma == 0 and (dy or dx):
                    continue
                w = math.exp(-0.5 * (dy * dy + dx * dx) / sigma ** 2) if sigma else 1.0
                if 0 <= y + dy < shape[0] and 0 <= x + dx < shape[1]:
                    vol[z, y + dy, x + dx] = max(vol[z, y + dy, x + dx], a * w)
    return vol


def _blob_mask(y: int, x: int, shape) -> np.ndarray:
    """(My, Mx) ones on the 3 x 3 pixels of :func:`bead_volume`'s blob around (y, x)."""
    m = np.zeros(shape)
    m[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2] = 1.0
    return m


def fibre_volume(n: int, nz: int, shape, seed: int, margin: int = 10, length: float = 90.0) -> np.ndarray:
    """A (nz, My, Mx) volume of ``n`` fibres: smooth random curves (a random walk of the direction,
    step 0.25 px) that run ``length`` px laterally while crossing most of the depth (from a random plane
    near one end of the stack to one near the other), each voxel along the curve set to the fibre's
    brightness (0.6-1), its lateral neighbours (4-connected) to half of it: tubes about 2 px wide."""
    rng = np.random.default_rng(seed)
    my, mx = shape
    vol = np.zeros((nz, my, mx))
    for _ in range(n):
        amp = rng.uniform(0.6, 1.0)
        z0, z1 = rng.uniform(0, 0.3 * (nz - 1)), rng.uniform(0.7 * (nz - 1), nz - 1)
        if rng.random() < 0.5:
            z0, z1 = z1, z0
        y, x = rng.uniform(margin + 10, my - margin - 10), rng.uniform(margin + 10, mx - margin - 10)
        th = rng.uniform(0, 2 * math.pi)
        steps = int(length / 0.25)
        for k in range(steps):
            th += rng.normal(0, 0.02)
            ny, nx = y + 0.25 * math.sin(th), x + 0.25 * math.cos(th)
            if not (margin <= ny < my - margin and margin <= nx < mx - margin):
                th += math.pi / 2          # turn away from the edge
                continue
            y, x = ny, nx
            z = int(round(z0 + (z1 - z0) * k / (steps - 1)))
            iy, ix = int(round(y)), int(round(x))
            for dy, dx, w in ((0, 0, 1.0), (1, 0, 0.5), (-1, 0, 0.5), (0, 1, 0.5), (0, -1, 0.5)):
                vol[z, iy + dy, ix + dx] = max(vol[z, iy + dy, ix + dx], w * amp)
    return vol


# ---------------------------------------------------------------------------------------------- background
BACKGROUNDS = ("none", "haze", "ramp", "blob", "random")


def background_field(shape, kind: str, seed: int = 0) -> np.ndarray:
    """A smooth non-negative (My, Mx) field with maximum 1 (zeros for 'none'):

    - 'haze': a wide Gaussian (sigma 0.45 x the size) centred off the axis;
    - 'ramp': a linear ramp from 0.2 to 1 along a random direction;
    - 'blob': a large bright blob (Gaussian, sigma 0.12 x the size) at a random place, on nothing;
    - 'random': white noise low-passed by a Gaussian of sigma 0.08 x the size, shifted to minimum 0."""
    my, mx = shape
    rng = np.random.default_rng(seed)
    Y, X = np.mgrid[:my, :mx].astype(float)
    n = min(my, mx)
    if kind == "none":
        return np.zeros(shape)
    if kind == "haze":
        cy, cx = my / 2 + rng.uniform(-0.2, 0.2) * my, mx / 2 + rng.uniform(-0.2, 0.2) * mx
        f = np.exp(-0.5 * ((Y - cy) ** 2 + (X - cx) ** 2) / (0.45 * n) ** 2)
    elif kind == "ramp":
        th = rng.uniform(0, 2 * math.pi)
        p = (Y - my / 2) * math.sin(th) + (X - mx / 2) * math.cos(th)
        f = 0.2 + 0.8 * (p - p.min()) / (p.max() - p.min())
    elif kind == "blob":
        cy, cx = rng.uniform(0.25, 0.75) * my, rng.uniform(0.25, 0.75) * mx
        f = np.exp(-0.5 * ((Y - cy) ** 2 + (X - cx) ** 2) / (0.12 * n) ** 2)
    elif kind == "random":
        f = ndimage.gaussian_filter(rng.standard_normal(shape), 0.08 * n, mode="wrap")
        f -= f.min()
    else:
        raise InputError(f"background_field: unknown kind {kind!r} (known: {', '.join(BACKGROUNDS)})")
    return f / f.max()


# ---------------------------------------------------------------------------------------------- scenes
@dataclass(frozen=True)
class Camera:
    """Camera model: counts = gain x Poisson(photons) + Normal(0, read_noise) + offset (no clipping, no
    rounding: the offset keeps the frame positive)."""
    gain: float = 1.0
    offset: float = 100.0
    read_noise: float = 2.0

    def as_dict(self) -> dict:
        return {"gain": self.gain, "offset": self.offset, "read_noise": self.read_noise}


@dataclass(frozen=True)
class SceneSpec:
    """A scene of the suite. kind 'beads' (``n_beads`` beads of brightness 0.5-1 in ``bead_planes`` or all
    planes, each a 3 x 3 voxel blob in one plane, :func:`bead_volume`) or 'fibres' (``n_fibres`` tubes through depth); the measurement is
    made with the array PSF perturbed by ``mismatch``, plus ``background`` (a :func:`background_field`
    kind) at ``bg_level`` x the bead image's peak, scaled so that the noiseless object image's brightest
    pixel holds ``photons`` photons, then the camera's noise and offset. ``depth_jitter`` > 0 (beads): each
    bead's depth is drawn uniformly within +-depth_jitter plane of its plane (kept inside the stack) and its
    image rendered with the PSF of that depth (:func:`array_psf`'s ``planes``): emitters between the planes the
    reconstruction has; the scored positions are the true fractional ones."""
    name: str
    what: str
    kind: str = "beads"
    nz: int = 12
    shape: tuple = (128, 128)
    n_beads: int = 40
    bead_sigma: float = 0.8
    bead_planes: tuple | None = None
    n_fibres: int = 5
    depth_jitter: float = 0.0
    mismatch: Mismatch = NOMINAL
    background: str = "none"
    bg_level: float = 0.0
    photons: float = 1000.0
    camera: Camera = field(default_factory=Camera)
    seed: int = 1


@dataclass
class Scene:
    """A rendered scene: ``y`` the offset-subtracted frame (what the reconstruction gets), ``raw`` the
    camera frame, ``psf`` the nominal stack (given to the reconstruction), ``psf_true`` the one that made
    the data, ``truth`` (nz, My, Mx) the object on the reconstruction's field of view, ``beads`` (n, 3)
    positions in voxels (fractional planes with ``depth_jitter``) or None, ``expected`` the noiseless photons per pixel (object + background),
    ``signal`` the object's part of it, ``bg`` the background's."""
    spec: SceneSpec
    y: np.ndarray
    raw: np.ndarray
    psf: np.ndarray
    psf_true: np.ndarray
    truth: np.ndarray
    beads: np.ndarray | None
    expected: np.ndarray
    signal: np.ndarray
    bg: np.ndarray


def object_image(psf, truth) -> np.ndarray:
    """C H x in float64, written here from the solver's stated conventions (docs/design.md; the package
    does not use cm2cl.reference): the truth (nz, My, Mx) on the sensor's field of view embedded centred,
    at row (Py - My) // 2, in a padded grid P = 2M; PSF tap (r, c) the response at offset
    (r - My // 2, c - Mx // 2); circular convolution on P, summed over planes, cropped to the same window."""
    psf = np.asarray(psf, np.float64)
    truth = np.asarray(truth, np.float64)
    nz, my, mx = truth.shape
    py, px = 2 * my, 2 * mx
    oy, ox = (py - my) // 2, (px - mx) // 2
    x = np.zeros((nz, py, px))
    x[:, oy:oy + my, ox:ox + mx] = truth
    k = np.zeros((nz, py, px))
    rows = (np.arange(my) - my // 2) % py
    cols = (np.arange(mx) - mx // 2) % px
    k[:, rows[:, None], cols[None, :]] = psf
    full = np.fft.irfft2((np.fft.rfft2(k) * np.fft.rfft2(x)).sum(axis=0), s=(py, px))
    return full[oy:oy + my, ox:ox + mx]


def render_scene(spec: SceneSpec) -> Scene:
    """Render ``spec`` (:class:`SceneSpec`): object, measurement PSF, background, noise. Deterministic
    in ``spec.seed``."""
    nz, shape = spec.nz, tuple(spec.shape)
    if spec.kind == "beads":
        beads = place_beads(spec.n_beads, nz, shape, spec.seed, planes=spec.bead_planes)
        rng = np.random.default_rng(spec.seed + 1000)
        truth = bead_volume(beads, rng.uniform(0.5, 1.0, len(beads)), nz, shape, spec.bead_sigma)
    elif spec.kind == "fibres":
        beads = None
        truth = fibre_volume(spec.n_fibres, nz, shape, spec.seed)
    else:
        raise InputError(f"render_scene: unknown kind {spec.kind!r}")
    psf = array_psf(nz, shape)
    psf_true = array_psf(nz, shape, spec.mismatch) if spec.mismatch else psf
    if spec.kind == "beads" and spec.depth_jitter > 0:
        # each bead imaged by the PSF of its own depth: one rendered plane and one volume plane per bead (the
        # blobs of one plane do not overlap: beads are at least 5 px apart there)
        t = np.clip(beads[:, 0] + np.random.default_rng(spec.seed + 4000).uniform(
            -spec.depth_jitter, spec.depth_jitter, len(beads)), 0.0, nz - 1.0)
        own = np.stack([truth[z] * _blob_mask(y, x, shape) for z, y, x in beads])
        img = object_image(array_psf(nz, shape, spec.mismatch, planes=t), own)
        beads = np.column_stack([t, beads[:, 1:]])
    else:
        img = object_image(psf_true, truth)
    # FFT rounding (~1e-16 of the peak) set to exactly 0: numpy's Poisson draws no random number for a mean of
    # 0 and some for any other, so rounding noise there would shift every later draw between FFT libraries
    img[img < 1e-9 * img.max()] = 0.0
    signal = img * (spec.photons / img.max())
    bg = background_field(shape, spec.background, spec.seed + 2000) * (spec.bg_level * spec.photons)
    expected = signal + bg
    rng = np.random.default_rng(spec.seed + 3000)
    cam = spec.camera
    raw = cam.gain * rng.poisson(expected) + rng.normal(0.0, cam.read_noise, shape) + cam.offset
    return Scene(spec=spec, y=raw - cam.offset, raw=raw, psf=psf, psf_true=psf_true, truth=truth, beads=beads,
                 expected=expected, signal=signal, bg=bg)


def calibration_spec(spec: SceneSpec) -> SceneSpec:
    """The bead frame a lab would record through the same optics as ``spec`` to calibrate the PSF: 40 beads
    on the planes, with ``spec``'s PSF mismatch, background (kind and level), photon budget and camera, and a
    seed of its own (``spec.seed`` + :data:`CALIBRATION_SEED_OFFSET`), so neither its beads nor its noise are
    the scene's. Reconstructed with PSF refinement, it gives the refined stack (``rec.psf``, ``--save-psf``) a
    sample of the same optics is then reconstructed with (``tools/quality_suite.py``'s ``suite_psf``)."""
    return replace(spec, name=f"{spec.name}_calibration", what=f"40 beads through {spec.name}'s optics",
                   kind="beads", n_beads=40, bead_planes=None, depth_jitter=0.0,
                   seed=spec.seed + CALIBRATION_SEED_OFFSET)


def scene_specs(quick: bool = False) -> list[SceneSpec]:
    """The suite's synthetic scenes (12 planes on a 128 x 128 sensor; ``quick``: a few, 10 planes on
    96 x 96, fewer beads)."""
    allm = Mismatch(blur=1.0, dz=0.4, aberration=1.0, vignette=0.6)
    base = [
        SceneSpec("beads", "40 beads, nominal PSF, 1000 photons, no background (the control)"),
        SceneSpec("mm_blur", "blurrier PSF (+1 px Gaussian)", mismatch=Mismatch(blur=1.0)),
        SceneSpec("mm_depth", "PSF 0.4 plane off in depth (the floor of the axial error is 0.4)", mismatch=Mismatch(dz=0.4)),
        SceneSpec("mm_aberr", "aberrated PSF (elliptical + coma-like, per lenslet)", mismatch=Mismatch(aberration=1.0)),
        SceneSpec("mm_trunc", "truncated PSF (outer lenslets vignetted by up to 60%, field stop)",
                  mismatch=Mismatch(vignette=0.6)),
        SceneSpec("mm_all", "all four mismatches together", mismatch=allm),
        SceneSpec("mm_blur_aberr", "blurrier and aberrated PSF together (the blur hides the aberration's "
                  "spot shapes)", mismatch=Mismatch(blur=1.0, aberration=1.0)),
        SceneSpec("mm_issue", "30 beads, blurrier PSF 0.4 plane off in depth, haze 8%, 800 photons (the issue's "
                  "mismatch case)", n_beads=30, mismatch=Mismatch(blur=1.0, dz=0.4), background="haze",
                  bg_level=0.08, photons=800.0, seed=2),
        SceneSpec("bg_haze10", "smooth haze, 10% of the peak", background="haze", bg_level=0.10),
        SceneSpec("bg_ramp20", "linear ramp, 20% of the peak", background="ramp", bg_level=0.20),
        SceneSpec("bg_blob15", "large blob, 15% of the peak", background="blob", bg_level=0.15),
        SceneSpec("bg_random5", "low-frequency random field, 5% of the peak", background="random", bg_level=0.05),
        SceneSpec("photons200", "200 photons at the peak", photons=200.0),
        SceneSpec("photons5000", "5000 photons at the peak, haze 5%", photons=5000.0, background="haze", bg_level=0.05),
        SceneSpec("dense", "90 beads", n_beads=90),
        SceneSpec("edge_planes", "30 beads in the first and last two planes (far from focus)", n_beads=30,
                  bead_planes=(0, 1, 10, 11)),
        SceneSpec("between", "40 beads between the planes (each within +-0.5 plane of one)", depth_jitter=0.5),
        SceneSpec("held_out", "30 beads, all mismatches, haze 8%, 800 photons (the issue's case)", n_beads=30,
                  mismatch=allm, background="haze", bg_level=0.08, photons=800.0, seed=5),
        SceneSpec("fibres", "5 fibres through depth, haze 5%", kind="fibres", background="haze", bg_level=0.05),
        SceneSpec("fibres_blur", "5 fibres, blurrier PSF 0.4 plane off in depth, haze 5%, 800 photons", kind="fibres",
                  mismatch=Mismatch(blur=1.0, dz=0.4), background="haze", bg_level=0.05, photons=800.0, seed=4),
        SceneSpec("fibres_mm", "5 fibres, all mismatches, random background 10%, 800 photons", kind="fibres",
                  mismatch=allm, background="random", bg_level=0.10, photons=800.0, seed=3),
        SceneSpec("fibres_trunc", "5 fibres, truncated PSF (outer lenslets vignetted by up to 60%, field stop), "
                  "haze 5%, 800 photons", kind="fibres", mismatch=Mismatch(vignette=0.6), background="haze",
                  bg_level=0.05, photons=800.0, seed=6),
    ]
    if not quick:
        return base
    keep = {"beads", "mm_all", "bg_haze10", "fibres"}
    return [replace(s, nz=10, shape=(96, 96), n_beads=min(s.n_beads, 15), n_fibres=3,
                    bead_planes=None if s.bead_planes is None else (0, 1, 8, 9)) for s in base if s.name in keep]

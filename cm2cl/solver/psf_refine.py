"""Self-calibration of the PSF stack from the measurement: a small kernel per lenslet, fitted to the data.

A measured or modelled PSF stack never matches the sample's optics exactly (aberrations that vary over
the field, vignetted outer lenslets, a blur or a shift of focus), and the least-squares objective then
explains the misfit with spurious emitters. The model here is that the true PSF of lenslet j is the given
one convolved with an unknown small kernel k_j (a local blur, shift and gain):

    h_true = sum_j k_j (*) (h . m_j)

with m_j the lenslet's footprint on the sensor (:func:`lenslet_labels`). An aberration that scales with the
spot (the spot's width changes with depth) is no fixed convolution, so the kernel may vary with depth: it
is interpolated linearly between G depth nodes spread evenly over the stack's planes, k_j(i) = sum_g
w_g(i) k_jg with hat weights w_g (:func:`depth_weights`; G = 1: one kernel for every plane). Given a
reconstruction x and its background b, the kernels are the non-negative least-squares fit, weighted like
the data term, of

    y - b  =  C sum_jg k_jg (*) F_jg,     F_jg = sum_i w_g(i) (h_i . m_j) (*) x_i   (on the padded grid)

with a ridge towards the identity kernel (:func:`fit_kernels`); the PSF is updated
(:func:`apply_kernels`), the volume re-solved from the last one, and so on for a few rounds
(:func:`cm2cl.solver.api.reconstruct`, ``psf_refine``). The volume absorbs part of any mismatch, so a
fitted kernel under-corrects: each update is over-relaxed, k = max(delta + beta (k_fit - delta), 0).

A PSF whose footprint is not a few lenslets (a diffuser's caustic: more than ``MAX_LENSLETS`` pieces) gets
one kernel for the whole stack. All of it runs on the host in float64.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy import fft as sfft
from scipy import ndimage, optimize, signal
from scipy.linalg import cho_factor, solve_triangular

from .forward import centered_psf, crop_offsets

#: a pixel belongs to a lenslet's footprint where some plane's PSF, normalised to its peak, exceeds this
FOOTPRINT_LEVEL = 0.02
#: footprint pieces smaller than this (pixels) are noise, not lenslets
MIN_PIECE_PX = 4
#: more pieces than this: the PSF is not a lenslet array (a diffuser), and one kernel serves the stack
MAX_LENSLETS = 25
#: the ridge towards the identity kernel, relative to the mean diagonal of the normal equations
RIDGE = 1e-3
#: over-relaxation of each kernel update (measured on docs/quality.md's mismatch scenes: 1.7 converged in
#: 4-6 rounds where 1.0 needed more than 10)
OVERRELAX = 1.7
#: the rounds' penalties where the caller gave none: a round stops at psf_refine_iter (100) iterations, so its
#: penalty shapes the volume the kernels are fitted to. The schedule was set at these (the solver's defaults
#: before stop 50); with the final solve's 0.2 and x1.5 in the rounds too, mm_all lost 3 beads of 40
#: (docs/penalty.md, last section); they rebalance from the first iteration, as they were set with
ROUND_PENALTIES = {"mu_v": 1.0, "adapt_max_step": 3.0, "adapt_from": 1}
#: a footprint piece of n is a view in a plane where it holds more than VIEW_SHARE / n of the plane's light
VIEW_SHARE = 0.2
#: psf_refine='auto': the rounds (the common one included) when the views disagree (docs/psf_refine.md's schedule)
AUTO_ROUNDS = 12
#: rounds of one kernel common to every lenslet ('common', and 'auto' where the views agree or cannot be
#: compared): the first from the sparse solve (12x l1), the second from a solve at the final l1 weight, whose
#: volume holds the faint emitters too. One round left a blurrier PSF half-corrected: the quality suite's
#: mm_blur and mm_issue gained one or two ghosts from 50 iterations to convergence (F1 0.988 -> 0.976, 0.968 ->
#: 0.952); with the second 0.988 -> 0.988 and 0.984 -> 1.000 (docs/psf_refine.md, stop 56)
COMMON_ROUNDS = 2
#: psf_refine='auto': refine per lenslet when separate kernels per lenslet explain more than this fraction of
#: the misfit beyond one common kernel (:func:`view_disagreement`), measured on the volume of the first round
#: (a sparse solve, its PSF then refined by a kernel common to every lenslet). On docs/quality.md's rendered
#: bead scenes whose PSF matches or differs alike for every lenslet (their own seeds and 11-13: 52 frames) d was
#: 0.003-0.017 (90% below 0.013), on aberrated or vignetted ones at least 0.029, and on an aberrated PSF blurred
#: as well (mm_blur_aberr) 0.018-0.034. Kernels per lenslet forced on those 52 frames kept every one at the
#: bead targets (mean axial error 0.13 -> 0.06 plane) for 4.6x the time, while mm_blur_aberr left unrefined
#: keeps 16-25 false maxima per 10 beads (1.2 refined): a needless refinement costs time, a missed one ghosts,
#: so the threshold sits at the matched frames' upper edge (docs/psf_refine.md, stop 47). The demo's beads
#: between 250-um planes gave 0.005-0.011, a paper scene 0.005 (binned 8x).
VIEW_DISAGREEMENT = 0.015
#: F statistic that kernels per lenslet reach on white noise, beyond one common kernel: non-negative kernels use
#: fewer taps than they have (0.3 on pure noise; 0.09-0.23 on the common answer's residual with random signs,
#: stop 58)
KERNEL_NOISE_F = 0.3
#: ... and when the F statistic of that comparison exceeds this: twice what separate kernels reach on white
#: noise (KERNEL_NOISE_F; the 0.999 quantile of F(392, N) for the
#: default 9 lenslets x 49 taps is 1.25 on any sensor of 4000 pixels or more). On a small sensor (128 x 128:
#: F ~ 41 d) it binds with d; on a large one F grows with the pixels and d decides
VIEW_F = 0.6
#: the pair where the data term weights pixels unequally (camera=, weights=): there the kernel fits follow the
#: variance weights, and kernels per lenslet forced on matched frames made them worse (mm_issue 1.00 / 1.0 ->
#: 0.93 / 1.0, mm_blur 1.00 / 1.0 -> 0.97 / 1.5, dense 0.94 / 0.2 -> 0.91 / 1.4 recall / false maxima per 10
#: beads), while those frames' d reached 0.020-0.026 (docs/psf_refine.md, stop 47)
VIEW_DISAGREEMENT_WEIGHTED = 0.025
VIEW_F_WEIGHTED = 1.25
#: psf_refine='auto' refines per lenslet only where the check's volume is made of points: kernels per lenslet
#: trade shifts with extended objects (docs/psf_refine.md: fibres with every mismatch kept 0.26 / 0.16 / 0.12 of
#: their energy near the truth with them, 0.41 / 0.38 / 0.38 with one common kernel). The volume is extended
#: where more than EXTENDED_SHARE of its energy lies in pieces (26-connected voxels above EXTENDED_LEVEL of its
#: maximum) wider laterally than EXTENDED_SPOTS of the PSF's sharpest spots (:func:`extended_share`). On the
#: quality suite's scenes (their seeds and 11-13) the fibre scenes' volumes gave 0.60-0.90 and the bead scenes'
#: at most 0.32 (docs/psf_refine.md, stop 45)
EXTENDED_LEVEL = 0.1
EXTENDED_SPOTS = 3.0
EXTENDED_SHARE = 0.5
#: psf_refine='auto' where the views disagree but the volume is extended: after the common round, this many
#: rounds fit each lenslet's gain alone (kernels of radius 0: a gain has no shift to trade with an extended
#: object). Fibres whose lenslets' light differs from the PSF's (vignetting, each view's share) are otherwise
#: reconstructed with the wrong views' weights. Measured on the quality suite's fibres (docs/psf_refine.md,
#: stop 56; energy near the fibres, 'common' -> gains): vignetted outer lenslets 0.44-0.52 -> 0.78-0.84 on 4
#: seeds, with a blurrier PSF off in depth too 0.39-0.45 -> 0.72-0.79, every mismatch (fibres_mm) 0.31-0.40 ->
#: 0.38-0.71 on 6; an aberrated PSF alone -0.03 to +0.03, the wave-optics simulator's vessels (truncation and
#: field aberrations, no gain error) 0.927 -> 0.909. More rounds drifted (a lenslet's gain towards 0 on
#: fibres_mm: 4 rounds 0.26-0.69, 5 rounds 0.19-0.67)
AUTO_GAIN_ROUNDS = 3
#: eps (a fraction of the volume's maximum) of the reweighted l1 in psf_refine='auto''s final solve after kernels
#: per lenslet (ADMMParams.psf_refine_reweight): beads that rounds per lenslet left at 0.17-0.19 of the brightest
#: came back above a fifth of it; eps 0.1 (weights down to 0.1 on the brightest) let more false maxima through
#: on the all-mismatches scene's seeds than 0.3 (docs/psf_refine.md, stop 46)
REWEIGHT_EPS = 0.3
#: a round whose volume leaves at least this relative misfit (it explains 1% of the data or less: the sparse
#: start removed everything, as the camera model's weights did at 200 photons) keeps the PSF: no kernel to fit
EMPTY_MISFIT = 0.99
#: design-matrix entries per chunk of sensor rows (memory of the normal equations' accumulation)
CHUNK_ENTRIES = 1 << 23
#: psf_refine words that step aside where a refinement cannot run (padding='support', lateral tiles, too little
#: host memory: the PSF is used as given and the reason recorded) where a number of rounds is refused:
#: 'common' fits one kernel common to every lenslet (a blur or shift of focus of the whole PSF) in
#: COMMON_ROUNDS rounds; 'auto' does the first, checks the lenslets' views on its volume and refines them one by
#: one only where they disagree (the second common round where they agree)
OPTIONAL_MODES = ("auto", "common")


def explicit_rounds(value) -> bool:
    """Whether the psf_refine value ``value`` asks for a number of rounds (refused where it cannot run)."""
    return bool(value) and value not in OPTIONAL_MODES


def plan_rounds(value) -> int:
    """The refinement rounds the psf_refine value ``value`` runs at most: 'auto' the whole schedule
    (COMMON_ROUNDS when its check finds the views in agreement), 'common' COMMON_ROUNDS, a number that many,
    0 none."""
    return {"auto": AUTO_ROUNDS, "common": COMMON_ROUNDS}.get(value, value or 0)


def describe(value) -> str:
    """What the psf_refine value ``value`` fits, in words (a series' and a log's message)."""
    return {"common": "one kernel common to every lenslet",
            "auto": "one kernel common to every lenslet, then kernels per lenslet where their views disagree "
                    "(each lenslet's gain alone on an extended sample)"
            }.get(value, f"{value} rounds")


def lenslet_labels(psf: np.ndarray) -> np.ndarray:
    """(My, Mx) labels 1..n: each sensor pixel assigned to the nearest lenslet footprint of the stack
    (pieces of its peak-normalised maximum over depth above FOOTPRINT_LEVEL); all ones where the footprint
    has more than MAX_LENSLETS pieces or none."""
    psf = np.asarray(psf, np.float64)
    peak = psf.reshape(psf.shape[0], -1).max(axis=1)
    norm = psf / np.where(peak > 0, peak, 1.0)[:, None, None]
    lab, n = ndimage.label(norm.max(axis=0) > FOOTPRINT_LEVEL)
    if n:
        sizes = ndimage.sum_labels(np.ones_like(lab), lab, index=np.arange(1, n + 1))
        keep = np.flatnonzero(sizes >= MIN_PIECE_PX) + 1
        lab = np.where(np.isin(lab, keep), np.searchsorted(keep, lab) + 1, 0)
        n = keep.size
    if n == 0 or n > MAX_LENSLETS:
        return np.ones(psf.shape[1:], np.int32)
    # every pixel to its nearest piece, so that the pieces together are the whole sensor
    _, (iy, ix) = ndimage.distance_transform_edt(lab == 0, return_indices=True)
    return lab[iy, ix].astype(np.int32)


def views_through_depth(psf: np.ndarray, labels: np.ndarray) -> bool:
    """Whether the footprint pieces of ``labels`` (:func:`lenslet_labels`) are views of one array: at least
    two, each holding a share of its plane's light (more than ``VIEW_SHARE`` / n of n pieces) in at least
    half of the planes, as a lenslet's focus does wherever it moves with depth. Pieces that each hold light
    in a plane or two (spots scattered anew in every plane) are no views that could disagree."""
    n = int(labels.max())
    if n < 2:
        return False
    psf = np.asarray(psf, np.float64)
    total = psf.reshape(psf.shape[0], -1).sum(axis=1)
    share = np.stack([(psf * (labels == j + 1)).reshape(psf.shape[0], -1).sum(axis=1) for j in range(n)])
    share = share / np.where(total > 0, total, 1.0)[None, :]
    return bool(np.all((share > VIEW_SHARE / n).sum(axis=1) >= 0.5 * psf.shape[0]))


def check_skipped(psf: np.ndarray, labels: np.ndarray) -> str | None:
    """Why psf_refine='auto' cannot compare the lenslets' views of ``psf`` (its ``labels``,
    :func:`lenslet_labels`), or None: one view (a diffuser's caustic or a single lens) or pieces that are no
    views through its depth (:func:`views_through_depth`). Such a PSF gets the 'common' round alone."""
    if int(labels.max()) < 2:
        return "the PSF has one view"
    if not views_through_depth(psf, labels):
        return "the PSF's pieces are not views through its depth"
    return None


def spot_width_px(psf: np.ndarray) -> float:
    """The width (pixels) of the PSF stack's sharpest spot: the diameter of the disc with the area of the
    half-maximum piece around the brightest pixel of the plane with the highest peak."""
    h = np.asarray(psf, np.float64)
    plane = h[int(np.argmax(h.reshape(h.shape[0], -1).max(axis=1)))]
    if not plane.max() > 0:
        return 1.0
    lab, _ = ndimage.label(plane >= 0.5 * plane.max(), structure=np.ones((3, 3)))
    area = int(np.count_nonzero(lab == lab.flat[int(np.argmax(plane))]))
    return float(2.0 * np.sqrt(area / np.pi))


def extended_share(volume: np.ndarray, spot_px: float) -> float:
    """The share of a (nz, ny, nx) volume's energy (its positive part) in extended pieces: 26-connected sets of
    voxels above EXTENDED_LEVEL x its maximum whose lateral extent (the larger side of their bounding box in
    y and x) exceeds EXTENDED_SPOTS x ``spot_px``. Beads reconstruct into pieces a few spots wide, fibres and
    vessels into pieces many spots long. 0 for an empty volume."""
    v = np.maximum(np.asarray(volume), 0)
    top = float(v.max()) if v.size else 0.0
    if not top > 0:
        return 0.0
    lab, n = ndimage.label(v > EXTENDED_LEVEL * top, structure=np.ones((3, 3, 3)))
    if n == 0:
        return 0.0
    energy = ndimage.sum_labels(v, lab, index=np.arange(1, n + 1))
    wide = np.array([max(s[1].stop - s[1].start, s[2].stop - s[2].start) > EXTENDED_SPOTS * spot_px
                     for s in ndimage.find_objects(lab)])
    return float(energy[wide].sum() / energy.sum())


def final_reweight(params, per_lenslet: bool) -> dict | None:
    """``{'rounds', 'eps'}`` of the reweighted l1 of the final solve, or None: ``params.psf_refine_reweight``
    rounds at eps REWEIGHT_EPS where psf_refine='auto' fitted kernels per lenslet (``per_lenslet``), unless
    the rounds are 0 or ``params.l1_reweight`` (the user's reweighting, which applies everywhere) is set."""
    if not per_lenslet or not params.psf_refine_reweight or params.l1_reweight:
        return None
    return {"rounds": int(params.psf_refine_reweight), "eps": REWEIGHT_EPS}


def with_reweight(params, reweight: dict | None):
    """``params`` with the reweighted l1 of ``reweight`` (:func:`final_reweight`'s record; None: unchanged): the
    parameters of the final solve, and of every frame of a series that refined its PSF on frame 0."""
    if not reweight:
        return params
    return replace(params, l1_reweight=int(reweight["rounds"]), l1_reweight_eps=float(reweight["eps"]))


def depth_weights(nz: int, nodes: int) -> np.ndarray:
    """(G, nz) hat weights of G depth nodes spread evenly over the planes 0..nz-1 (each plane's weights sum
    to 1; node g sits at plane g (nz - 1) / (G - 1)); G = 1, or a single plane: ones."""
    G = max(1, min(int(nodes), nz))
    if G == 1:
        return np.ones((1, nz))
    t = np.arange(nz) / (nz - 1) * (G - 1)
    return np.maximum(0.0, 1.0 - np.abs(t[None, :] - np.arange(G)[:, None]))


def lenslet_images(psf: np.ndarray, labels: np.ndarray, volume_padded: np.ndarray, depth_w=None) -> np.ndarray:
    """(n G, Py, Px): F_jg = sum_i w_g(i) (h_i . m_j) (*) x_i on the padded grid (circular, optical axis at the
    sensor centre, as the solver's forward model), lenslet label j = 1..n, depth node g of ``depth_w``
    ((G, nz), :func:`depth_weights`; None: one node), index j G + g."""
    P = volume_padded.shape[1:]
    X = sfft.rfft2(np.asarray(volume_padded, np.float64), workers=-1)
    n = int(labels.max())
    W = np.ones((1, psf.shape[0])) if depth_w is None else np.asarray(depth_w, np.float64)
    out = np.empty((n * W.shape[0],) + tuple(P))
    for j in range(n):
        hj = centered_psf(np.asarray(psf, np.float64) * (labels == j + 1), P)
        HX = sfft.rfft2(hj, workers=-1) * X
        for g, wg in enumerate(W):
            out[j * W.shape[0] + g] = sfft.irfft2(np.tensordot(wg, HX, axes=(0, 0)), s=P, workers=-1)
    return out


def _taps(radius: int):
    r = np.arange(-radius, radius + 1)
    return [(dy, dx) for dy in r for dx in r]


def fit_kernels(images: np.ndarray, target: np.ndarray, sensor_shape, radius: int, weights=None,
                ridge: float = RIDGE) -> np.ndarray:
    """(n, 2r+1, 2r+1) non-negative kernels k_j minimising
    sum_p w_p (target_p - (C sum_j k_j (*) F_j)_p)^2 + lam sum_j ||k_j - delta||^2,
    lam = ridge x the mean diagonal of the normal equations; ``images`` are the F_j on the padded grid
    (:func:`lenslet_images`), ``target`` (My, Mx) the measurement less its background, ``weights`` the
    data term's (None: ones). Kernel index [r + dy, r + dx] is the weight of the shift (dy, dx)."""
    n = images.shape[0]
    My, Mx = sensor_shape
    oy, ox = crop_offsets(sensor_shape, images.shape[1:])
    taps = _taps(radius)
    if min(oy, ox) < radius:
        raise ValueError(f"psf_refine: the padded grid leaves {min(oy, ox)} px around the sensor, "
                         f"less than the kernel radius {radius}")
    ncol = n * len(taps)
    w = np.ones((My, Mx)) if weights is None else np.asarray(weights, np.float64)
    G = np.zeros((ncol, ncol))
    b = np.zeros(ncol)
    rows = max(1, CHUNK_ENTRIES // (ncol * Mx))
    for r0 in range(0, My, rows):
        r1 = min(My, r0 + rows)
        A = np.empty(((r1 - r0) * Mx, ncol))
        c = 0
        for j in range(n):
            for dy, dx in taps:   # (k (*) F)(p) = sum_s k(s) F(p - s)
                A[:, c] = images[j, oy + r0 - dy:oy + r1 - dy, ox - dx:ox + Mx - dx].ravel()
                c += 1
        sw = np.sqrt(w[r0:r1].ravel())
        A *= sw[:, None]
        G += A.T @ A
        b += A.T @ (sw * target[r0:r1].ravel())
    lam = ridge * max(np.trace(G) / ncol, 1e-300)
    delta = np.zeros((n, len(taps)))
    delta[:, len(taps) // 2] = 1.0
    G[np.diag_indices(ncol)] += lam
    b += lam * delta.ravel()
    # min_k>=0 k'Gk - 2b'k  =  min ||L'k - L^-1 b||^2 with G = L L'
    L, _ = cho_factor(G, lower=True)
    L = np.tril(L)
    k, _ = optimize.nnls(L.T, solve_triangular(L, b, lower=True), maxiter=50 * ncol)
    return k.reshape(n, 2 * radius + 1, 2 * radius + 1)


def round_params(params):
    """``params`` for a refinement round: :data:`ROUND_PENALTIES` where the caller left them unset (None)."""
    return replace(params, **{k: v for k, v in ROUND_PENALTIES.items() if getattr(params, k) is None})


def round_schedule(index: int, rounds: int, l1_start: float, depth_nodes: int) -> tuple[float, int]:
    """(l1 scale, depth nodes) of refinement round ``index`` of ``rounds``.

    The alternation of volume and kernels settles where the volume has absorbed the mismatch (ghosts next to
    the beads explain the misfit as well as a better PSF would), so it starts sparse: the first round's solve
    has ``l1_start`` x the final l1 weight, which comes down geometrically to 1 x in the last round. Only the
    brightest structure, which the nominal PSF already places right, then shapes the first kernels. The first
    third of the rounds fit one kernel per lenslet (gain, blur, shift: well determined), the rest
    ``depth_nodes`` of them (docs/psf_refine.md measured both choices)."""
    t = index / max(rounds - 1, 1)
    scale = float(l1_start) ** (1.0 - t)
    nodes = 1 if index < rounds // 3 else int(depth_nodes)
    return scale, nodes


def relax(kernels: np.ndarray, beta: float = OVERRELAX) -> np.ndarray:
    """The kernels scaled to mean sum 1 (the volume carries the overall scale), then over-relaxed away
    from the identity: max(delta + beta (k - delta), 0)."""
    k = kernels / max(kernels.sum(axis=(1, 2)).mean(), 1e-300)
    r = k.shape[1] // 2
    delta = np.zeros_like(k)
    delta[:, r, r] = 1.0
    return np.maximum(delta + beta * (k - delta), 0.0)


def apply_kernels(psf: np.ndarray, labels: np.ndarray, kernels: np.ndarray, depth_w=None) -> np.ndarray:
    """sum_j k_j(i) (*) (h_i . m_j) per plane i (zero outside the sensor), k_j(i) = sum_g w_g(i) k_jg
    (``kernels`` indexed j G + g, ``depth_w`` (G, nz); None: one kernel per lenslet), clipped at 0 and scaled to
    the given stack's total light."""
    psf = np.asarray(psf, np.float64)
    W = np.ones((1, psf.shape[0])) if depth_w is None else np.asarray(depth_w, np.float64)
    G = W.shape[0]
    if len(kernels) % G:
        raise ValueError(f"apply_kernels: {len(kernels)} kernels for {G} depth nodes")
    out = np.zeros_like(psf)
    for j in range(len(kernels) // G):
        hj = psf * (labels == j + 1)
        kj = np.asarray(kernels[j * G:(j + 1) * G])
        for i in range(psf.shape[0]):
            out[i] += signal.fftconvolve(hj[i], np.tensordot(W[:, i], kj, axes=(0, 0)), mode="same")
    out = np.maximum(out, 0.0)
    # a plane the kernels took all light from (every tap clipped) keeps the given one: the solver needs light
    # in every plane, and the data said nothing for it
    dark = out.reshape(out.shape[0], -1).max(axis=1) <= 0
    out[dark] = psf[dark]
    # each plane keeps the given plane's light: a plane's overall scale and its volume's brightness trade
    # one for the other in the data, so the kernels' gains are free there (they drifted, and a plane's
    # faint beads dimmed below a detection threshold); the lenslets' gains relative to each other stay
    have = out.reshape(out.shape[0], -1).sum(axis=1)
    want = psf.reshape(psf.shape[0], -1).sum(axis=1)
    return out * np.where(have > 0, want / np.where(have > 0, have, 1.0), 0.0)[:, None, None]


def kernel_summary(kernels: np.ndarray) -> list[dict]:
    """Per kernel: its sum (gain), its centroid shift (dy, dx) in px and RMS width in px, for the record."""
    r = kernels.shape[1] // 2
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    out = []
    for k in kernels:
        s = float(k.sum())
        cy, cx = (float((k * yy).sum() / s), float((k * xx).sum() / s)) if s > 0 else (0.0, 0.0)
        width = float(np.sqrt((k * ((yy - cy) ** 2 + (xx - cx) ** 2)).sum() / s)) if s > 0 else 0.0
        out.append({"gain": s, "shift_px": [cy, cx], "rms_width_px": width})
    return out


def refine_step(psf, labels, volume_padded, target, radius: int, weights=None, beta: float = OVERRELAX,
                depth_nodes: int = 1, check: bool = False):
    """One round: (the refined PSF stack, the kernels applied (indexed j G + g), the relative weighted misfit
    ||target - C H x|| / ||target|| before it) from a reconstruction's padded volume and the measurement
    less its background; ``depth_nodes`` G kernels per lenslet, interpolated over depth. ``check`` (one
    node): a fourth item, :func:`view_disagreement`'s record of the same fit."""
    # the fit is invariant to the data's scale (volume and target scale together; the ridge is relative): taken
    # out, so that squares of counts near the float64 range's end do not overflow
    scale = float(np.abs(target).max()) or 1.0
    target = np.asarray(target, np.float64) / scale
    volume_padded = np.asarray(volume_padded, np.float64) / scale
    W = depth_weights(psf.shape[0], depth_nodes)
    F = lenslet_images(psf, labels, volume_padded, W)
    M = psf.shape[1:]
    w = np.ones(M) if weights is None else np.asarray(weights, np.float64)
    model = sensor_model(F, None, M)
    misfit = float(np.sqrt(np.sum(w * (target - model) ** 2) / max(np.sum(w * target ** 2), 1e-300)))
    fitted = fit_kernels(F, target, M, radius, weights)
    k = relax(fitted, beta)
    out = (apply_kernels(psf, labels, k, W), k, misfit)
    if not check:
        return out
    if W.shape[0] != 1:
        raise ValueError("refine_step: the view check fits one kernel per lenslet (depth_nodes=1)")
    return out + (view_disagreement(F, fitted, target, M, radius, w),)


def sensor_model(images, kernels, sensor_shape) -> np.ndarray:
    """C sum_j k_j (*) F_j on the sensor: ``images`` (n, Py, Px) the F_j on the padded grid, ``kernels``
    (n, 2r+1, 2r+1) indexed as :func:`fit_kernels` returns them (None: identity kernels, C sum_j F_j)."""
    My, Mx = sensor_shape
    oy, ox = crop_offsets(sensor_shape, images.shape[1:])
    if kernels is None:
        return images.sum(axis=0)[oy:oy + My, ox:ox + Mx]
    r = kernels.shape[1] // 2
    out = np.zeros((My, Mx))
    for j in range(images.shape[0]):
        for (dy, dx), kv in zip(_taps(r), kernels[j].ravel()):
            if kv:
                out += kv * images[j, oy - dy:oy + My - dy, ox - dx:ox + Mx - dx]
    return out


def view_thresholds(weights=None) -> tuple[float, float]:
    """The view check's (disagreement, F) thresholds: (VIEW_DISAGREEMENT, VIEW_F) where every pixel the data
    term keeps counts alike (no weights, or a 0/1 mask), (VIEW_DISAGREEMENT_WEIGHTED, VIEW_F_WEIGHTED) where the
    weights vary between pixels (a camera model's variances, a user's weights)."""
    if weights is not None:
        kept = np.asarray(weights, np.float64)
        kept = kept[kept > 0]
        if kept.size and float(np.ptp(kept)) > 1e-9 * float(kept.max()):
            return VIEW_DISAGREEMENT_WEIGHTED, VIEW_F_WEIGHTED
    return VIEW_DISAGREEMENT, VIEW_F


def lenslets_fit_better(lenslets: dict, common: dict, check: dict) -> bool:
    """Whether psf_refine='auto''s answer with kernels per lenslet fits the data better than the common kernel's
    (``info['misfit']`` of the two final solves, :func:`cm2cl.solver.control.data_misfit`): its residual sum of
    squares, less what the extra kernels fit of noise, is the smaller. Kernels per lenslet fitted to white noise
    lower the sum of squares by KERNEL_NOISE_F x their extra taps ((lenslets - 1) x taps: ``check``'s) per
    degree of freedom left, so a frame whose mismatch is common to every lenslet keeps the common answer unless
    the separate kernels explain more than that."""
    taps = (int(check["lenslets"]) - 1) * int(check["taps"])
    dof = max(int(lenslets["pixels"]) - taps, 1)
    return lenslets["rms"] ** 2 * (1.0 + KERNEL_NOISE_F * taps / dof) < common["rms"] ** 2


def view_disagreement(images, kernels, target, sensor_shape, radius: int, weights=None) -> dict:
    """How much the lenslets' views disagree with the PSF, from one fit of a kernel per lenslet (``kernels``,
    :func:`fit_kernels` on ``images`` F_j, one depth node), against one kernel common to every lenslet:

        S = sum_p w_p (target_p - (C sum_j k_j (*) F_j)_p)^2   (S_sep: a kernel per lenslet, S_com: one for all)
        d = (S_com - S_sep) / S_com                            (the misfit the separate kernels explain)
        F = ((S_com - S_sep) / (p_sep - p_com)) / (S_sep / (N - p_sep))

    with p the kernels' taps and N the pixels of non-zero weight. A kernel common to all lenslets is a blur,
    shift or gain of the whole PSF, which the volume can absorb (a bead's own size, a global defocus blur): it
    leaves no ghosts. Lenslets that need different kernels (aberrations that differ between lenslets,
    vignetting, a field stop) disagree about where an emitter is, and a least-squares volume explains the
    disagreement with spurious emitters: what psf_refine corrects. F is the F statistic of the nested fits:
    below 1 where the extra kernels fit only white noise (non-negative kernels use fewer taps than they have),
    though they still remove a share of the misfit that on a small sensor is several per cent; d is the
    effect's size, which on a large sensor
    stays small for a mismatch too slight to make ghosts while F grows with N. Refine when both exceed their
    thresholds (:func:`view_thresholds`).
    Returns ``{'disagreement': d, 'f_statistic': F, 'refine', 'threshold', 'f_threshold', 'lenslets', 'gains'}``."""
    w = np.ones(sensor_shape) if weights is None else np.asarray(weights, np.float64)
    common = images.sum(axis=0, keepdims=True)
    kc = fit_kernels(common, target, sensor_shape, radius, w)
    s_sep = float(np.sum(w * (target - sensor_model(images, kernels, sensor_shape)) ** 2))
    s_com = float(np.sum(w * (target - sensor_model(common, kc, sensor_shape)) ** 2))
    taps = (2 * radius + 1) ** 2
    p_sep, p_com = images.shape[0] * taps, taps
    dof = int(np.count_nonzero(w > 0)) - p_sep
    d = (s_com - s_sep) / s_com if s_com > 0 else 0.0
    f = ((s_com - s_sep) / max(p_sep - p_com, 1)) / (s_sep / dof) if s_sep > 0 and dof > 0 else 0.0
    d0, f0 = view_thresholds(weights)
    return {"disagreement": d, "f_statistic": f, "refine": bool(d > d0 and f > f0),
            "threshold": d0, "f_threshold": f0, "lenslets": int(images.shape[0]), "taps": taps,
            "gains": [float(g) for g in kernels.sum(axis=(1, 2))]}


__all__ = ["lenslet_labels", "depth_weights", "round_schedule", "lenslet_images", "fit_kernels", "relax",
           "apply_kernels", "kernel_summary", "refine_step", "sensor_model", "view_disagreement", "view_thresholds",
           "views_through_depth", "AUTO_ROUNDS", "VIEW_DISAGREEMENT", "VIEW_F", "VIEW_DISAGREEMENT_WEIGHTED",
           "VIEW_F_WEIGHTED", "OPTIONAL_MODES", "spot_width_px", "extended_share", "EXTENDED_SHARE", "EXTENDED_SPOTS",
           "explicit_rounds", "plan_rounds",
           "lenslets_fit_better", "KERNEL_NOISE_F", "EMPTY_MISFIT", "check_skipped", "describe", "final_reweight",
           "with_reweight", "REWEIGHT_EPS", "COMMON_ROUNDS", "AUTO_GAIN_ROUNDS"]

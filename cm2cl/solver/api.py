"""The Python entry point: :func:`reconstruct`, one CM2 frame to a 3D volume on an OpenCL device."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from .. import validate
from ..device.fft import resolve_backend
from ..device.runtime import get_runtime
from ..errors import InputError
from .admm import ADMMSolver, _padded_arg, pixel_weights
from .control import ADAPT_FROM
from .attenuation import AUTO, attenuate, solve_estimated, unattenuate
from .params import check_keywords, with_parameters

log = logging.getLogger(__name__)


#: reconstruct()'s docstring; the solver parameters' entries are made from their declaration (ADMMParams)
_DOC = """Reconstruct a 3D volume from one CM2 measurement (paper Eq. 4) on an OpenCL device.

    Solves ``min_x 1/2 ||C H x - y||^2 + l1 ||x||_1 + tv TV_3D(x)`` subject to ``x >= 0`` by ADMM,
    on the normalised problem: y scaled to max 1 and the PSFs to ||H|| = 1 (in float64 on the host),
    so weights and penalties mean the same on every dataset; the volume is scaled back to the
    measurement's units.

    Parameters
    ----------
    measurement : (My, Mx) array
        The camera image, camera offset (dark level) removed. Float, or integer camera data
        (uint8, uint16, ...), which is converted to float64.
    psf : (nz, My, Mx) or (My, Mx) array
        One PSF per depth plane, on the measurement's sensor grid, offset removed; every plane
        must carry some light. Float or integer.
    {parameters}
    dtype : float32 (default) or float64 (devices with fp64 only).
    backend : {'auto', 'cl', 'vkfft', 'reikna'}
        FFT backend ('cl': cm2cl's own kernels; see :mod:`cm2cl.device.fft` for what 'auto' picks).
    device : int, str, pyopencl Device or Runtime, optional
        Device index or name fragment (default: ``CM2CL_DEVICE``, else the best device).
    padded_shape : (Py, Px), optional
        Object grid, >= 2M - 1 (default: the FFT backend's fast size).
    max_slab_planes : int, optional
        Cap on the depth planes per device buffer (and per streamed slab).
    devices : list of devices, optional
        Spread the depth planes over these devices (indices, names, pyopencl Devices or Runtimes), each
        holding a contiguous run of planes; the iterates equal the one-device solve's to float rounding.
    max_memory : int, optional
        Bytes each device may use (default 90% of its memory): the planner keeps the planes resident
        when they fit, else streams them (see ``stream``).
    stream : 'auto' (default), True or False
        Stream depth slabs through each device from host memory: when they do not fit ('auto'), always
        (True), or never (False: a problem too large is refused).
    overlap : 'auto' (default), True or False
        Double-buffer streamed slabs where two buffer sets fit, so that copies overlap work: on GPUs and
        accelerators ('auto'), always (True), or never (False: one set, larger slabs, copies and work in
        turn; 'auto' on CPUs, where double buffering measured no faster).
    lean : 'auto' (default), True or False
        Keep the planes resident with one slab of x spectra instead of a volume of them (7 real volumes,
        3 without TV, and the PSF spectra per plane, for one more forward FFT per iteration): where the whole state
        does not fit ('auto'), always (True), or never (False). The iterates are the same.
    camera : None, 'auto', dict or str, optional
        The camera's noise model, for a data term that weighs each pixel by the inverse of its photon and
        read-noise variance (:mod:`cm2cl.io.camera`): ``{'gain': ADU per photoelectron, 'offset': ADU,
        'read_noise': electrons}`` or ``'gain=2,offset=100,read-noise=1.5'`` (the measurement is then the
        raw frame: the offset is subtracted), or 'auto' (gain and read noise fitted to the frame's
        mean-variance relation, offset 0: a frame whose dark level was removed). None (default): every pixel
        weighs the same. Recorded in ``rec.info['camera']``.
    voxel_size_um : (dz, dy, dx) in um, optional
        Object-space voxel size, carried to ``rec.voxel_size_um``.
    depths_um : (nz,) in um, optional
        Depth of each PSF plane, carried to ``rec.depths_um``.
    weights : (My, Mx) array or None
        Weight of each pixel in the data term (finite, >= 0): 0 masks a pixel (saturated or hot pixels,
        see :func:`cm2cl.analysis.pixels.check_pixels`), None weighs all pixels 1.
    padding : 'full' or 'support'
        'full' (default): the padded grid is 2M - 1 (rounded up to a fast size), right for a PSF that may
        fill the sensor. 'support': M + K - 1 with K the PSF stack's measured support (99.9999% of its
        light; the tails beyond are dropped, ``rec.info['padding']`` says how much and the voxels saved).
    callback, callback_every : callable, int, optional
        ``callback(row)`` with each log row (a dict) every ``callback_every`` iterations; with ``psf_refine``,
        the rows of every round, ``row['iter']`` counting on across them.
    x0 : (nz, My, Mx) or (nz, Py, Px) array, optional
        A warm start in the volume's units (e.g. the previous frame's ``rec.volume``): x and its splits
        start there instead of at zero, the data split at H x0 and its dual at the data term's gradient
        there (the background, where modelled, at its fit to y - C H x0), so that a start at the answer
        stays near it.

    Returns
    -------
    Reconstruction
        ``.volume`` (nz, My, Mx) on the sensor field of view, ``.volume_padded`` (nz, Py, Px),
        ``.history`` (the log as arrays: objective, residuals, penalties, seconds), ``.info``
        (device, why it stopped, whether it converged, the weights and noise level used),
        ``.scaling``.

    Examples
    --------
    >>> import numpy as np, cm2cl
    >>> psf = np.zeros((2, 32, 40)); psf[0, 16, 20] = psf[1, 14, 20] = psf[1, 18, 20] = 1.0
    >>> x = np.zeros((2, 32, 40)); x[1, 10, 12] = 5.0
    >>> y = psf[1, 14, 20] * np.roll(x[1], -2, 0) + psf[1, 18, 20] * np.roll(x[1], 2, 0)
    >>> rec = cm2cl.reconstruct(y, psf, max_iter=300)
    >>> tuple(int(i) for i in np.unravel_index(rec.volume.argmax(), rec.volume.shape))
    (1, 10, 12)
    >>> rec.history["objective"].shape == (rec.iterations,)
    True
    """


@with_parameters(_DOC)
def reconstruct(measurement, psf, *, dtype=np.float32, backend: str = "auto", device=None, padded_shape=None,
                max_slab_planes: int | None = None, devices=None, max_memory=None, stream="auto",
                overlap="auto", lean="auto", voxel_size_um=None, depths_um=None,
                weights=None, padding: str = "full", callback=None, callback_every: int = 1,
                x0=None, camera=None, **params) -> Reconstruction:
    call = dict(locals())   # the arguments as given: scattering_length_um='auto' solves twice with them
    prm = check_keywords("reconstruct", params)
    psf = validate.psf_stack(validate.image_array(psf, "psf"), "psf")
    y = validate.real_array(validate.image_array(measurement, "measurement", ndims=(2,)), "measurement", ndims=(2,))
    if y.shape != psf.shape[1:]:
        raise InputError(f"measurement: shape {y.shape} does not match the PSF's sensor grid "
                         f"{psf.shape[1:]} (psf shape {psf.shape})")
    vs, d = check_scale(voxel_size_um, depths_um, psf.shape[0])
    psf, attenuation = attenuate(psf, d, prm)
    if prm.scattering_length_um == AUTO:   # the depths are checked: solved clear, l_s estimated, solved with it
        kw = {**{k: v for k, v in call.items() if k != "params"}, **call["params"]}
        rec, record = solve_estimated(reconstruct, lambda r: r.volume, d, prm, kw)
        rec.info["attenuation"] = record
        return rec
    y, weights, cam = _camera(y, weights, camera)
    pad_info = None
    if padding not in ("full", "support"):
        raise InputError(f"padding: expected 'full' or 'support', got {padding!r}")
    if padding == "support":
        if padded_shape is not None:
            raise InputError("padding: 'support' chooses the padded grid itself; give padded_shape or padding, not both")
        from .forward import support_padding

        psf, padded_shape, pad_info = support_padding(psf, fft_backend(backend, device))
    from .psf_refine import OPTIONAL_MODES, explicit_rounds

    optional = prm.psf_refine in OPTIONAL_MODES
    if explicit_rounds(prm.psf_refine) and pad_info is not None:
        raise InputError("psf_refine: not with padding='support' (the refined PSF reaches past the measured "
                         "support); use padding='full'")
    if explicit_rounds(prm.psf_refine) and padded_shape is not None:
        margin = _refine_margin(psf, padded_shape)
        if margin < prm.psf_refine_radius:
            raise InputError(f"psf_refine: the padded grid {tuple(_padded_arg(padded_shape))} leaves {margin} px around "
                             f"the sensor, less than the kernel radius {prm.psf_refine_radius}; give a larger "
                             "padded_shape or psf_refine=0")
    skipped = (refine_skipped(psf, padded_shape, pad_info is not None, prm.psf_refine, prm.psf_refine_radius)
               if optional else None)

    done = [0]   # iterations of the refinement's rounds before this solve: the callback's rows count on

    def solve(h, p, P, x_start):
        solver = ADMMSolver(h, p, dtype=dtype, backend=backend, device=device,
                            padded_shape=P, max_slab_planes=max_slab_planes, devices=devices,
                            max_memory=max_memory, stream=stream, overlap=overlap, lean=lean)
        cb = callback if callback is None or not done[0] else (lambda row: callback({**row, "iter": row["iter"] + done[0]}))
        rec = solver.solve(y, callback=cb, callback_every=callback_every, weights=weights, x0=x_start)
        done[0] += rec.iterations
        return solver, rec

    if explicit_rounds(prm.psf_refine) or (optional and skipped is None):
        P, rec = _refined(solve, y, psf, weights, prm, padded_shape, x0)
    else:
        solver, rec = solve(psf, replace(prm, psf_refine=0), padded_shape, x0)
        P = solver.P
        if optional:
            log.info("psf_refine %s: the PSF is used as given (%s)", prm.psf_refine, skipped)
            rec.info["psf_refine"] = {"mode": prm.psf_refine, "refined": False, "rounds": 0, "skipped": skipped}
    rec.voxel_size_um, rec.depths_um = vs, d
    rec.info["padding"] = pad_info or {"padded_shape": list(P), "support_px": None}
    rec.info["camera"] = cam
    if attenuation is not None:
        rec.info["attenuation"] = attenuation
        if rec.psf is not None:   # the refined stack in the given (clear-medium) PSF's units
            rec.psf = unattenuate(rec.psf, attenuation)
    return rec


def refine_runs(psf, value, padded_shape=None, support: bool = False, radius: int = 3) -> bool:
    """Whether psf_refine ``value`` refines here: a number of rounds always (it is refused where it cannot run),
    'auto' and 'common' unless :func:`refine_skipped` gives a reason, 0 never."""
    from .psf_refine import OPTIONAL_MODES, explicit_rounds

    if value in OPTIONAL_MODES:
        return refine_skipped(psf, padded_shape, support, value, radius) is None
    return explicit_rounds(value)


def _refine_margin(psf, padded_shape) -> int:
    """The pixels the padded grid leaves around the sensor on its narrowest side (the kernels' reach)."""
    from .forward import crop_offsets

    P = tuple(int(v) for v in _padded_arg(padded_shape))
    lo = crop_offsets(psf.shape[1:], P)
    return int(min(lo + tuple(p - m - o for p, m, o in zip(P, psf.shape[1:], lo))))


def refine_skipped(psf, padded_shape=None, support: bool = False, mode: str = "auto", radius: int = 3) -> str | None:
    """Why ``psf_refine=mode`` ('auto' or 'common', :data:`.psf_refine.OPTIONAL_MODES`) does not run here, or
    None: padding='support' (the refined PSF would reach past the measured support), a padded grid that
    leaves less than the kernel ``radius`` around the sensor, or a refinement that would need more than half
    the host's available memory (its float64 lenslet images on the padded grid). 'auto' on a PSF whose views
    cannot be compared runs as 'common' (:func:`.psf_refine.check_skipped`)."""
    from . import psf_refine as R
    from .forward import choose_padded_shape
    from .memory import host_available_bytes

    if support:
        return "padding='support'"
    P = _padded_arg(padded_shape) if padded_shape is not None else choose_padded_shape(psf.shape[1:], "cl")
    if _refine_margin(psf, P) < radius:
        return f"the padded grid leaves less than the kernel radius ({radius} px) around the sensor"
    n = int(R.lenslet_labels(psf).max()) if mode == "auto" else 1
    # 'auto' may hold the answer with kernels per lenslet (its stack and volumes) while the common one is solved
    stacks = 5 if mode == "auto" else 3
    need = 8 * int(P[0]) * int(P[1]) * (stacks * psf.shape[0] + n * R.depth_weights(psf.shape[0], 3).shape[0] + 4)
    if need > host_available_bytes() // 2:
        log.warning("psf_refine %s: the refinement needs %.1f GiB of host memory, more than half of what is "
                    "available; the PSF is used as given", mode, need / 2**30)
        return f"the refinement needs {need / 2**30:.1f} GiB of host memory"
    return None


def _refined(solve, y, psf, weights, prm, padded_shape, x0):
    """(the padded grid, reconstruction) with the PSF self-calibrated (:mod:`.psf_refine`): ``prm.psf_refine``
    rounds of a ``psf_refine_iter``-iteration solve and a kernel fit, each solve warm-started from the last, then
    the solve to the stopping rule with the refined PSF; the record in ``info['psf_refine']``.

    'common': ``COMMON_ROUNDS`` rounds, one kernel for every lenslet (over ``psf_refine_depth_nodes``). 'auto':
    the first, then the view check on the same volume (:func:`.psf_refine.view_disagreement`, kernels per
    lenslet fitted to images of the commonly refined stack). Where the lenslets' views disagree and the volume
    is made of points (:func:`.psf_refine.extended_share`) both answers are solved: the rest of ``AUTO_ROUNDS``
    rounds of kernels per lenslet from the check's kernels, and the second common round; the one whose final
    solve fits the data better keeps (:func:`.psf_refine.lenslets_fit_better`). Where they disagree and the
    volume is extended (kernels per lenslet trade shifts with extended objects) ``AUTO_GAIN_ROUNDS`` rounds fit
    each lenslet's gain alone; where they agree, or the PSF has no views to compare
    (:func:`.psf_refine.check_skipped`), the second common round follows ('common''s answer). A number: that
    many rounds of kernels per lenslet."""
    from . import psf_refine as R

    mode = prm.psf_refine
    staged = mode in R.OPTIONAL_MODES          # round 0 fits one kernel common to every lenslet
    common_labels = np.ones(psf.shape[1:], np.int32)
    labels = common_labels if mode == "common" else R.lenslet_labels(psf)
    w = pixel_weights(weights, y.shape)
    check_why = R.check_skipped(psf, labels) if mode == "auto" else None
    inner = R.round_params(replace(prm, psf_refine=R.plan_rounds(mode),
                                   max_iter=min(prm.psf_refine_iter, prm.max_iter)))

    def one_round(h, rnd, n, kind, P, x_start, rounds):
        """Round ``rnd`` of ``n``: kind 'common' (one kernel for every lenslet), 'lenslets' or 'gains' (each
        lenslet's gain alone: kernels of radius 0). Returns (the stack, P, the round's reconstruction, its
        background, whether its volume explained too little to fit kernels to)."""
        scale, nodes = R.round_schedule(rnd, n, prm.psf_refine_l1_start, prm.psf_refine_depth_nodes)
        lab, radius = labels, prm.psf_refine_radius
        if kind == "common":
            lab, nodes = common_labels, prm.psf_refine_depth_nodes
        elif kind == "gains":
            radius, nodes = 0, 1
        solver, rec = solve(h, replace(inner, l1_scale=prm.l1_scale * scale), P, x_start)
        P = solver.P
        del solver
        b = rec.background if rec.background is not None else 0.0
        h_new, k, misfit = R.refine_step(h, lab, rec.volume_padded, y - b, radius, w, depth_nodes=nodes)
        empty = misfit >= R.EMPTY_MISFIT
        if empty:   # the round's volume explains (almost) none of the data: there is nothing to fit kernels to
            k = np.zeros_like(k)
            k[:, k.shape[1] // 2, k.shape[2] // 2] = 1.0
            log.info("PSF refinement round %d: its volume explains %.1f%% of the data; the PSF is kept",
                     rnd + 1, 100 * (1 - misfit))
        else:
            h = h_new
        rounds.append({"iterations": rec.iterations, "residual": misfit, "l1_scale": scale, "depth_nodes": nodes,
                       "mu_v": rec.info["initial_penalties"]["mu_v"], "adapt_max_step": rec.info["adapt_max_step"],
                       "adapt_from": rec.info["adapt_from"], "kernels": R.kernel_summary(k), "kept": bool(empty)})
        gains = [q["gain"] for q in rounds[-1]["kernels"]]
        log.info("PSF refinement round %d of %d: %d iterations, misfit %.4f before it; %d kernels, gains %.2f-%.2f",
                 len(rounds), n, rec.iterations, misfit, len(gains), min(gains), max(gains))
        return h, P, rec, b, empty

    def finish(h, first, n, kind, P, x_start, rounds, reweight=None):
        """Rounds ``first``..``n``-1 of ``kind``, then the final solve: (P, its reconstruction, the stack)."""
        for rnd in range(first, n):
            h, P, rec, _, _ = one_round(h, rnd, n, kind, P, x_start, rounds)
            x_start = rec.volume_padded
        # the final solve starts from the last round's volume, solved at up to psf_refine_l1_start x the l1
        # weight: a sparse start far from the answer, unlike a user's x0 (an answer, a series' previous frame), so
        # it waits as a cold solve does. Measured both ways on the quality suite, its seeds and the held-out
        # family (docs/quality.md, docs/heldout_psf.md "stop 54": 12 of 15 seed frames against 11, 7 of 12
        # held-out frames against 8)
        final = replace(prm, psf_refine=n, adapt_from=prm.adapt_from if prm.adapt_from is not None else ADAPT_FROM)
        solver, rec = solve(h, R.with_reweight(final, reweight), P, x_start)
        return solver.P, rec, h

    h = np.asarray(psf, np.float64)
    rounds, check, compared = [], None, None
    kind = "common" if staged else "lenslets"
    n = R.plan_rounds(mode)
    h, P, rec0, b0, empty = one_round(h, 0, n, kind, padded_shape, x0, rounds)
    x_start = rec0.volume_padded
    if staged and empty:   # nothing to fit from the sparse start: the PSF as given
        n = 1
        if mode == "auto":
            check_why = check_why or "the round's volume explained too little of the data"
    elif mode == "auto" and check_why is not None:
        n = R.COMMON_ROUNDS
    elif mode == "auto":   # the check: kernels per lenslet on the same volume, imaged by the commonly refined stack
        h_sep, k_sep, _, rec_check = R.refine_step(h, labels, x_start, y - b0, prm.psf_refine_radius, w, check=True)
        spot = R.spot_width_px(psf)
        share = R.extended_share(x_start, spot)
        check = {**rec_check, "iterations": rec0.iterations, "l1_scale": rounds[0]["l1_scale"],
                 "views_disagree": rec_check["refine"], "extended_share": share, "spot_px": spot,
                 "extended_threshold": R.EXTENDED_SHARE, "refine": rec_check["refine"] and share <= R.EXTENDED_SHARE}
        log.info("psf_refine auto: the lenslets' kernels explain %.3f of the misfit beyond a common one "
                 "(threshold %.3f), %.2f of the volume's energy in extended pieces (threshold %.2f): %s",
                 check["disagreement"], check["threshold"], share, R.EXTENDED_SHARE,
                 "both answers solved" if check["refine"] else "one kernel common to every lenslet")
        if check["refine"]:
            kind, n = "lenslets", R.AUTO_ROUNDS
            if not prm.psf_refine_compare:
                h = h_sep
                rounds[-1]["lenslet_kernels"] = R.kernel_summary(k_sep)
        elif check["views_disagree"] and R.AUTO_GAIN_ROUNDS:
            kind, n = "gains", 1 + R.AUTO_GAIN_ROUNDS
        else:
            n = R.COMMON_ROUNDS
    if kind == "lenslets" and mode == "auto" and prm.psf_refine_compare:
        # both answers from the same first round: kernels per lenslet (from the check's) and the common kernel's
        lens_rounds = [{**rounds[0], "lenslet_kernels": R.kernel_summary(k_sep)}]
        reweight = R.final_reweight(prm, True)
        P_l, rec_l, h_l = finish(h_sep, 1, n, "lenslets", P, x_start, lens_rounds, reweight)
        com_rounds = [dict(rounds[0])]
        P_c, rec_c, h_c = finish(h, 1, R.COMMON_ROUNDS, "common", P, x_start, com_rounds)
        keep = R.lenslets_fit_better(rec_l.info["misfit"], rec_c.info["misfit"], check)
        compared = {"lenslets": {**rec_l.info["misfit"], "iterations": rec_l.iterations
                                 + sum(r["iterations"] for r in lens_rounds[1:])},
                    "common": {**rec_c.info["misfit"], "iterations": rec_c.iterations
                               + sum(r["iterations"] for r in com_rounds[1:])},
                    "kept": "lenslets" if keep else "common"}
        log.info("psf_refine auto: final misfit %.4g with kernels per lenslet, %.4g with the common kernel: %s kept",
                 rec_l.info["misfit"]["rms"], rec_c.info["misfit"]["rms"], compared["kept"])
        spent = compared["lenslets"]["iterations"] + compared["common"]["iterations"] + rounds[0]["iterations"]
        if keep:
            P, rec, h, rounds = P_l, rec_l, h_l, lens_rounds
        else:
            P, rec, h, rounds, n, kind, reweight = P_c, rec_c, h_c, com_rounds, R.COMMON_ROUNDS, "common", None
    else:
        reweight = R.final_reweight(prm, mode == "auto" and kind == "lenslets")
        P, rec, h = finish(h, 1, n, kind, P, x_start, rounds, reweight)
        spent = sum(r["iterations"] for r in rounds) + rec.iterations
    common_only = staged and kind == "common"
    rec.psf = h
    rec.info["psf_refine"] = {"mode": mode if staged else "given",
                              "refined": not all(r["kept"] for r in rounds), "check": check,
                              "rounds": n,
                              "lenslets": int(labels.max()) if not common_only and (n > 1 or mode != "auto") else 1,
                              "common_only": common_only, "lenslet_gains_only": kind == "gains",
                              "radius_px": prm.psf_refine_radius, "overrelax": R.OVERRELAX,
                              "depth_nodes": int(R.depth_weights(h.shape[0], prm.psf_refine_depth_nodes).shape[0]),
                              "l1_start": prm.psf_refine_l1_start, "per_round": rounds, "reweight": reweight,
                              "compared": compared, "iterations_total": spent}
    if check_why is not None:
        rec.info["psf_refine"]["check_skipped"] = check_why
    return P, rec


def _camera(y, weights, camera):
    """(the measurement less the camera's offset, the data term's weights, the camera's record) for
    ``camera`` (:func:`cm2cl.io.camera.camera_weights`), the given pixel weights (masks) kept."""
    if camera is None:
        return y, weights, None
    from ..io.camera import camera_weights

    y, w, cam = camera_weights(y, camera)
    if w is not None and weights is not None:
        w = w * pixel_weights(weights, y.shape)
    return y, w, cam


def check_scale(voxel_size_um, depths_um, nz: int):
    """(voxel size, depths) checked: 3 positive numbers, ``nz`` finite depths (either None)."""
    vs = d = None
    if voxel_size_um is not None:
        try:
            vs = tuple(float(v) for v in voxel_size_um)
        except (TypeError, ValueError):
            vs = ()
        if len(vs) != 3 or not all(np.isfinite(v) and v > 0 for v in vs):
            raise InputError(f"voxel_size_um: expected 3 positive numbers (dz, dy, dx), got {voxel_size_um!r}")
    if depths_um is not None:
        d = np.asarray(depths_um, float).ravel()
        if d.size != nz or not np.all(np.isfinite(d)):
            raise InputError(f"depths_um: expected {nz} finite depths, got {np.shape(depths_um)}")
    return vs, d


def fft_backend(backend, device) -> str:
    """The FFT backend ``backend`` resolves to on ``device``."""
    return resolve_backend(backend, get_runtime(device))


__all__ = ["reconstruct", "fft_backend", "check_scale", "refine_skipped", "refine_runs"]

"""One frame of ``cm2cl reconstruct`` (whole, spread over devices, or as lateral tiles): the inputs read
and checked, pixels masked and background removed, the solve with a progress bar, and the volume, its
log and its record published together (a failed run leaves nothing behind)."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..solver.params import ADMMParams
from ..solver.psf_refine import EXTENDED_SPOTS, OPTIONAL_MODES, explicit_rounds
from .inputs import (check_bin, devices_arg, layout_options, offsets, read_psf, single_frame_shape, solver_params,
                     working_psf)
from .plan import check_headers
from .progress import Progress

#: --save-background writes the removed background beside the output, as a member of its unit
BACKGROUND_SUFFIX = ".background.ome.tif"
#: --save-psf writes the self-calibrated PSF stack beside the output, as a member of its unit
PSF_SUFFIX = ".psf.ome.tif"


def command(args, params: ADMMParams) -> int:
    """Reconstruct one frame (``args.measurement`` a path) to ``args.output``; one summary on stdout."""
    from .. import io
    from ..io.prepare import prepare
    from ..io.publish import OutputSet

    out = Path(args.output)
    check_headers(args, params)   # shapes and sizes from the TIFF headers, before decoding anything
    off, psf_off = offsets(args)
    meas, mmeta = _read_measurement(args)
    psf, pmeta = read_psf(args)
    wp = working_psf(args, psf, pmeta, meas.shape, psf_off)
    pixels, names, weights = _pixels(args, meas, psf)
    psf = None   # the stack as read is not needed past here (a full frame's is gigabytes)
    meas, background = _remove_background(args, meas, mmeta)
    off = _camera_offset(args, meas, off)
    y = prepare(meas, offset=off, bin_factor=args.bin, name=f"measurement '{args.measurement}'")
    weights, camera = _camera_weights(args, y, weights)
    dt = np.dtype(args.dtype)
    if wp.h.dtype.itemsize > dt.itemsize:   # the solve reads each plane in its own dtype: a float32 solve
        wp = replace(wp, h=wp.h.astype(dt))  # keeps a float32 working stack (half of a full frame's 2.6 GiB)
    planes, ny, nx = wp.h.shape   # the output is checked (writable, room, sidecars, no other run) and locked
    vol_bytes = planes * (2 * ny * 2 * nx if args.padded else ny * nx) * dt.itemsize
    outset = OutputSet(out, expected_bytes=vol_bytes, inputs=(args.measurement, args.psf), extras=extras(args))
    with outset:   # an OSError while writing becomes one line; nothing is left behind
        rec = _solve(args, y, wp, weights, params, dt)
        rec.info.update(pixels={**pixels, "masked": names}, background=args.background, psf_fit=wp.note,
                        camera=camera)
        px = mmeta.get("voxel_size_um") if mmeta.get("unit") == "um" else None
        if background is None and rec.background is not None:   # the model's b, on the (binned) working grid
            background, what = rec.background, "background of the model y = C H x + b (working grid)"
            px = None if px is None else tuple(float(v) * args.bin for v in px)
        else:
            what = "background removed from the measurement"
        if background is not None and args.save_background:   # a member of the published unit
            io.write_tiff(outset.staged("background"), background.astype(np.float32), voxel_size_um=px,
                          extra={"what": what, "method": args.background, "measurement": str(args.measurement)})
        if args.save_psf:   # 'auto' and 'common' step aside where they cannot run (host memory): the stack as used
            used = rec.psf if rec.psf is not None else wp.h
            what = ("PSF stack self-calibrated on the measurement (--psf-refine), working grid" if rec.psf is not None
                    else f"PSF stack used as given (--psf-refine {params.psf_refine} did not run: "
                         f"{rec.info['psf_refine'].get('skipped')}), working grid")
            io.write_tiff(outset.staged("psf"), np.asarray(used, np.float32), voxel_size_um=wp.voxel_size_um,
                          extra={"what": what, "psf": str(args.psf), "measurement": str(args.measurement),
                                 "psf_refine": rec.info["psf_refine"]["rounds"]})
        vol = _write(args, outset, rec, dt, wp.scale)
    _report(out, outset, rec, wp.scale, vol)
    return 0


def check_options(args) -> None:
    """The frame's options and output, checked before any work; creates nothing."""
    from ..io.publish import check_output_file

    out = Path(args.output)
    if out.suffix.lower() not in (".tif", ".tiff"):
        raise InputError(f"--output '{out}': must end in .ome.tif, .tif or .tiff (or .ome.zarr for a series)")
    check_output_file(out, 0, (args.measurement, args.psf), extras=extras(args))
    offsets(args)
    check_bin(args.bin)
    if args.camera is not None:
        from ..io.camera import parse_camera

        cam = parse_camera(args.camera)
        if cam not in (None, "auto") and cam.offset > 0 and args.offset != "none":
            raise InputError("--camera: the dark level is given twice (offset= and --offset); give it once")
    if args.background not in (None, "model", "none"):
        from ..io.background import check_background_spec

        check_background_spec(args.background)
    mode = solver_params(args).psf_refine   # the default, a --preset's or the option's
    if args.save_psf and (not mode or (not explicit_rounds(mode) and (args.tile or args.padding == "support"))):
        raise InputError("--save-psf: writes the self-calibrated PSF; needs --psf-refine ROUNDS, auto or common (not "
                         "0), on the whole frame's full padded grid (not with --tile or --padding support)")
    if explicit_rounds(args.psf_refine) and (args.tile or args.padding == "support"):
        raise InputError(f"--psf-refine: not with {'--tile' if args.tile else '--padding support'} (the PSF is "
                         "refined on the whole frame's full padded grid)")
    if args.mask:
        from ..analysis.pixels import MASKS

        bad = [n for n in args.mask.split(",") if n.strip() and n.strip() not in MASKS]
        if bad:
            raise InputError(f"--mask: unknown {', '.join(map(repr, bad))} (known: {', '.join(MASKS)})")


def extras(args):
    """The output's extra members (the background with --save-background, the PSF with --save-psf)."""
    out = {**({"background": BACKGROUND_SUFFIX} if args.save_background else {}),
           **({"psf": PSF_SUFFIX} if args.save_psf else {})}
    return out or None


def _read_measurement(args):
    from .. import io
    from ..io.prepare import check_image

    meas, mmeta = io.read_tiff(args.measurement)
    meas = meas.reshape(single_frame_shape(meas.shape))
    if meas.ndim != 2:
        raise InputError(f"measurement '{args.measurement}': expected a 2D image, got shape {meas.shape}"
                         + ("; several frames: give an .ome.zarr output for a series" if len(meas.shape) > 2 else ""))
    check_image(meas, f"measurement '{args.measurement}'")    # numeric and finite before anything reads them
    return meas, mmeta


def _pixels(args, meas, psf):
    """(the saturated / hot pixel report, the masks asked for, the data term's weights or None)."""
    from ..analysis.pixels import check_pixels, mask_weights
    from ..io.prepare import bin_image

    pixels = check_pixels(meas, args.saturation, psf)
    names = [n.strip() for n in args.mask.split(",") if n.strip()] if args.mask else []
    weights = None
    if names:                      # a binned pixel is masked when any of its sensor pixels is
        weights = (bin_image(1.0 - mask_weights(meas, names, args.saturation, psf), args.bin) == 0).astype(float)
    return pixels, names, weights


def _remove_background(args, meas, mmeta):
    """(the measurement, the background removed or None) for --background."""
    if args.background in (None, "model", "none"):
        return meas, None
    from ..io.background import parse_background, remove_background

    px_um = (mmeta.get("voxel_size_um") or (None,))[-1] if mmeta.get("unit") == "um" else None
    return remove_background(meas, parse_background(args.background, px_um), args.device)


def _camera_offset(args, meas, off):
    """The dark level to subtract: --offset, or the camera's offset (checked against the frame)."""
    from ..io.camera import check_camera, parse_camera

    cam = parse_camera(args.camera)
    if cam in (None, "auto"):
        return off
    check_camera(cam, meas)
    return cam.offset if cam.offset > 0 else off


def _camera_weights(args, y, weights):
    """(the data term's weights, the camera's record) for --camera on the prepared frame ``y`` (dark level
    removed, sum-binned: each binned pixel's variance is gain x its counts + bin^2 (gain read noise)^2)."""
    from ..io.camera import Camera, estimate_camera, parse_camera, variance_weights

    cam = parse_camera(args.camera)
    if cam is None:
        return weights, None
    if cam == "auto":
        cam = estimate_camera(y)
    else:
        cam = Camera(cam.gain, 0.0, cam.read_noise * args.bin, cam.source)
    w = variance_weights(y, cam)
    return (w if weights is None else w * weights), {**cam.as_dict(), "bin": args.bin}


def _solve(args, y, wp, weights, params: ADMMParams, dt):
    from ..solver import reconstruct

    devs = devices_arg(args.device)
    if args.tile:
        return _tiled(args, y, wp, dt, devs, weights, params)
    # auto and common: the common round where it runs (auto's rounds per lenslet, if any, run past the bar's estimate)
    from ..solver.api import refine_runs

    n = params.psf_refine
    if n in OPTIONAL_MODES:
        n = int(refine_runs(wp.h, n, None, args.padding == "support", params.psf_refine_radius))
    rounds = n * min(params.psf_refine_iter, params.max_iter)
    progress = Progress(params.max_iter + rounds, args.quiet, every=args.progress_every)
    try:
        return reconstruct(y, wp.h, dtype=dt, backend=args.backend, device=devs[0],
                           devices=devs if len(devs) > 1 else None, **layout_options(args), weights=weights,
                           padding=args.padding, callback=progress, voxel_size_um=wp.voxel_size_um,
                           depths_um=wp.depths_um, **params.as_dict())
    finally:
        progress.close()


def _tiled(args, y, wp, dt, devs, weights, params: ADMMParams):
    """A single frame as lateral tiles (cm2cl.jobs.tiles), wrapped as a Reconstruction for the writer."""
    from ..jobs.tiles import reconstruct_tiled
    from ..solver.result import Reconstruction

    if len(devs) > 1 or weights is not None or args.padding != "full" or args.padded:
        raise InputError("--tile: not with several devices, --mask, --padding support or --padded")
    last = {}

    def progress(k, n, rec):
        last.update(rec=rec)
        if not args.quiet:
            print(f"cm2cl: tile {k}/{n}: {rec.iterations} iterations, {rec.info['stop']}", file=sys.stderr)

    kw = {k: v for k, v in params.as_dict().items() if k != "normalize"}   # the tiles normalise as one frame
    vol, info = reconstruct_tiled(y, wp.h, tuple(args.tile), args.halo, dtype=dt, backend=args.backend,
                                  device=devs[0], progress=progress, **kw)
    rec = last["rec"]
    out = Reconstruction(volume_padded=vol, crop=(slice(0, vol.shape[1]), slice(0, vol.shape[2])), log=rec.log,
                         scaling={"psf_scale": 1.0, "y_scale": 1.0}, params=rec.params,
                         info={**rec.info, "tiles": info, "l1": info["l1"], "tv": info["tv"],
                               "noise_x": info["noise_x"], "noise_sigma": info["noise_sigma"],
                               "misfit": worst_misfit(info["misfit"]), "tile_misfits": info["misfit"],
                               "converged": all(info["converged"]),
                               "stop": f"{sum(info['converged'])} of {info['tiles']} tiles converged",
                               **({"attenuation": info["attenuation"]} if "attenuation" in info else {})})
    out.voxel_size_um, out.depths_um = wp.voxel_size_um, wp.depths_um
    return out


def _write(args, outset, rec, dt, how):
    from .. import io

    # the volume in the dtype of the solve (the solver's rescaling may promote it to float64)
    vol = (rec.volume_padded if args.padded else rec.volume).astype(dt, copy=False)
    extra = {"what": "cm2cl reconstruction", "measurement": str(args.measurement), "psf": str(args.psf),
             "params": rec.params, "scaling": rec.scaling, "info": rec.info, "padded": bool(args.padded),
             "voxel_space": io.OBJECT_SPACE if rec.voxel_size_um else None, "scale": how}
    io.write_tiff(outset.staged("volume"), vol, voxel_size_um=rec.voxel_size_um, depths_um=rec.depths_um,
                  extra=extra, name=f"{io.tiff_stem(args.output).name} (cm2cl reconstruction of "
                                    f"{Path(args.measurement).name})",
                  channel=args.channel, emission_nm=args.emission_nm)
    rec.write_log(outset.staged("log"), fmt="csv")
    rec.write_log(outset.staged("record"), fmt="json", extra=outset.record_fields())
    outset.publish()   # committed, then the old sidecars, the volume, the new sidecars: never two runs mixed
    return vol


def refine_line(record) -> str:
    """One line on what --psf-refine did (``info['psf_refine']``), or '' without it."""
    if not record:
        return ""
    check = record.get("check")
    test = (f"the lenslets' views {'disagree' if check['refine'] else 'agree'} with the PSF: separate kernels "
            f"explain {check['disagreement']:.3f} of the misfit (threshold {check['threshold']:g}), F "
            f"{check['f_statistic']:.2f} (threshold {check['f_threshold']:g})") if check else ""
    if check and check.get("views_disagree") and not check["refine"]:
        test = (f"the lenslets' views disagree with the PSF (separate kernels explain {check['disagreement']:.3f} "
                f"of the misfit), but the volume is extended ({check['extended_share']:.2f} of its energy in "
                f"pieces wider than {EXTENDED_SPOTS:g} spots, threshold {check['extended_threshold']:g}): kernels "
                "per lenslet would trade shifts with it" + ("; each lenslet's gain fitted alone"
                                                            if record.get("lenslet_gains_only") else ""))
    cmp = record.get("compared")
    if cmp:
        kept = cmp["kept"] == "lenslets"
        test += (f"; both answers solved: kernels per lenslet reach a misfit of {cmp['lenslets']['rms']:.4g} (rms), "
                 f"the common kernel {cmp['common']['rms']:.4g}, so "
                 + ("kernels per lenslet are kept" if kept else "the common kernel's answer is kept"))
    if record.get("check_skipped") and record.get("refined"):
        test = f"the lenslets' views not compared ({record['check_skipped']})"
    if record.get("refined"):
        if record.get("common_only"):
            n = record["rounds"]
            what = f"{n} round{'s' if n > 1 else ''}, one kernel common to every lenslet"
        elif record["rounds"] > 1:
            then = "each lenslet's gain" if record.get("lenslet_gains_only") else "kernels per lenslet"
            what = f"{record['rounds']} rounds" + (f" (one kernel common to every lenslet, then {then})"
                                                   if record.get("mode") == "auto" else "")
            rw = record.get("reweight")
            if rw:
                what += f", then l1 reweighted {rw['rounds']}x (eps {rw['eps']:g} of the maximum)"
        else:
            what = "1 round" + (", one kernel common to every lenslet" if record.get("mode") in OPTIONAL_MODES else "")
        head = f"PSF refined in {what} ({record['iterations_total']} iterations in all)"
        return head + (f"; --psf-refine auto: {test}" if test else "")
    if record.get("per_round") and all(r.get("kept") for r in record["per_round"]):
        return ("PSF used as given: the refinement's sparse volume explained too little of the data to fit a kernel "
                f"({record['iterations_total']} iterations in all)")
    return f"PSF used as given: --psf-refine {record.get('mode', 'auto')} does not run here ({record.get('skipped')})"


def attenuation_line(record) -> str:
    """One line on the scattering attenuation of ``--scattering-length-um auto`` (its estimate), or ''."""
    est = (record or {}).get("estimate")
    if not est:
        return ""
    k = est["rate_interval_per_um"]
    found = (f"{est['emitters']} emitters in {est['planes']} planes, their light falls "
             f"{100 * est['fall_over_stack']:.0f}% over the stack" if k else f"{est['emitters']} emitters")
    if record["scattering_length_um"] is None:
        return f"scattering length not estimated: {est['reason']} ({found}); the clear-medium answer stands"
    lo, hi = (1.0 / v if v > 0 else float("inf") for v in k[::-1])
    a = record.get("ballistic_fraction")
    return (f"scattering length estimated {record['scattering_length_um']:.0f} um (95%: {lo:.0f}-{hi:.0f}) from "
            f"{found}; solved with it" + (f" (the deepest plane keeps {min(a):.3f} of its light)" if a else ""))


def worst_misfit(misfits: list) -> dict:
    """The misfit record of the tile whose residual lies farthest above its white noise (the first where none has
    a ratio)."""
    rated = [m for m in misfits if m.get("ratio") is not None]
    return max(rated, key=lambda m: m["ratio"]) if rated else misfits[0]


def misfit_words(misfit) -> str:
    """The data misfit a solve reached, in words (:func:`cm2cl.solver.control.data_misfit`'s record)."""
    if not misfit or misfit.get("relative") is None:
        return "data misfit not measured"
    txt = f"data misfit {misfit['relative']:.4f} of the measurement"
    if misfit.get("ratio") is not None:
        txt += f", {misfit['ratio']:.2f}x the residual's white noise"
    return txt


def _report(out, outset, rec, how, vol):
    last, info = rec.log[-1], rec.info
    scale = "voxel {:g} x {:g} x {:g} um (z, y, x; {})".format(*rec.voxel_size_um, how) if rec.voxel_size_um else how
    how_stop = ("converged" if info["converged"] else
                f"NOT converged: stopped at --max-iter, relative residuals {last['primal_rel']:.1e} / "
                f"{last['dual_rel']:.1e} against tol {info['tol']:g}")
    print(f"{out}: {vol.shape} {vol.dtype} volume, {scale}; {rec.iterations} iterations, {how_stop}; "
          f"{misfit_words(info.get('misfit'))}; "
          f"l1 {info['l1']:.3g}, tv {info['tv']:.3g} (volume-domain noise level {info['noise_x']:.3g}; "
          f"measurement noise {info['noise_sigma']:.3g} of max y); "
          f"objective {last['objective']:.4e}, {last['seconds']:.1f} s on {info['device']}; "
          f"log: {outset.sidecars['log'].name}, {outset.sidecars['record'].name}")
    lay = info.get("layout") or []
    if len(lay) > 1 or any(p["streamed"] or p.get("lean") for p in lay):
        from ..solver.memory import peak_rss_bytes

        rss = peak_rss_bytes()
        print("  planes: " + "; ".join(
            f"{p['planes'][0]}..{p['planes'][1] - 1} on {p['device']}"
            + (f" streamed in slabs of {p['slab_planes']}{' (double-buffered)' if p.get('overlap') else ''}"
               if p["streamed"] else f" resident, lean (x spectra in slabs of {p['slab_planes']})" if p.get("lean")
               else " resident") for p in lay)
            + f"; {info['moved_bytes'] / 1e9:.2f} GB moved between host and devices, "
              f"{info['device_bytes'] / 2**30:.2f} GiB on the devices, peak host RSS {rss / 2**30:.2f} GiB")
    line = refine_line(info.get("psf_refine"))
    if line:
        print("  " + line)
    line = attenuation_line(info.get("attenuation"))
    if line:
        print("  " + line)
    px = info.get("pixels") or {}
    for name in ("saturated", "hot"):
        c = px.get(name, {}).get("count", 0)
        if c:
            print(f"  {c} {name} pixel(s) in the measurement, first at (row, column) "
                  f"{', '.join(map(str, px[name]['first'][:5]))}; "
                  + ("masked in the data term" if name in px.get("masked", []) else f"not masked (--mask {name})"))

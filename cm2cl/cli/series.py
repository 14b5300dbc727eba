"""``cm2cl reconstruct FRAMES... --psf PSF -o OUT.ome.zarr``: many frames (a multi-page TIFF, folders, globs)
into one OME-Zarr store, in order with a warm start, on the local devices (``--device all|0,2``) or a Dask
cluster (``--scheduler``); re-running the same command resumes a killed job. Called by
:mod:`cm2cl.cli.reconstruct` when the output is a ``.zarr`` store; the options are reconstruct's."""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..solver.params import ADMMParams
from ..solver.psf_refine import explicit_rounds, with_reweight
from .inputs import check_bin, devices_arg, layout_options, offsets, read_psf, working_psf
from .progress import FrameProgress


def executor(args):
    """The job's executor from --warm-start, --scheduler and --device; what cannot run is refused here."""
    from ..jobs import executor_for

    ex = executor_for([None] if args.scheduler else devices_arg(args.device), args.scheduler, args.warm_start)
    ex.check(np.dtype(args.dtype))
    return ex


def command(args, params: ADMMParams) -> int:
    """Run the job described by reconstruct's arguments; one summary line on stdout."""
    from ..io.prepare import prepare
    from ..jobs import FrameSeries, FrameStore, run_series
    from ..jobs.run import fingerprint

    out = Path(args.output)
    if args.save_psf and not params.psf_refine:
        raise InputError("--save-psf: writes the self-calibrated PSF; give --psf-refine ROUNDS as well")
    if explicit_rounds(params.psf_refine) and args.padding == "support":
        raise InputError("--psf-refine: not with --padding support (the PSF is refined on the first frame's full "
                         "padded grid)")
    check_bin(args.bin)
    series = FrameSeries(args.measurement)                      # headers only: shapes checked first
    psf, pmeta = read_psf(args)
    off, psf_off = offsets(args)
    check_bin(args.bin, series.shape, "measurement (frames)")
    wp = working_psf(args, psf, pmeta, series.shape, psf_off)
    ex = executor(args)
    h, solver_kw, prep = _grid(args, wp.h, off, psf_off, ex.devices[0])
    dt = np.dtype(args.dtype)
    from ..solver import attenuation
    from ..solver.attenuation import AUTO

    attenuation.check(params, wp.depths_um, h.shape[0])   # before the store exists
    key = fingerprint(h, params, series, dt, args.backend, prep)
    shape = (h.shape[0],) + tuple(n // args.bin for n in series.shape)
    if not args.scheduler:   # a frame that cannot fit (--stream never, --max-memory) is refused before the store
        from .plan import backend_of, layout

        layout(args, shape[0], shape[1:], dt, backend_of(args)[0], params, solver_kw.get("padded_shape"))
    record = {"what": "cm2cl reconstruction series", "psf": str(args.psf), "params": params.as_dict(),
              "frames": [f"{f.path}[{f.index}]" for f in series.frames[:1000]], "scale": wp.scale, "prep": prep}
    from ..solver.api import refine_runs

    # N rounds, or 'auto' / 'common' where they can run: frame 0 decides, once for every frame
    refine = refine_runs(h, params.psf_refine, solver_kw.get("padded_shape"), args.padding == "support",
                         params.psf_refine_radius)
    if refine:
        from ..jobs.refine import refined_psf_path

        record["psf_refined"] = str(refined_psf_path(out))
    t0 = time.perf_counter()
    frame_prep = lambda a: prepare(a, offset=off, bin_factor=args.bin, name="measurement")  # noqa: E731
    if params.scattering_length_um == AUTO:   # frame 0's estimate for every frame (read back on a resume)
        from ..jobs.refine import series_attenuation
        from .frame import attenuation_line

        params, record["attenuation"] = series_attenuation(
            out, key, series, h, frame_prep, params, voxel_size_um=wp.voxel_size_um, depths_um=wp.depths_um,
            solve_kw={"dtype": dt, "backend": args.backend, "device": devices_arg(args.device)[0], **solver_kw})
        if not args.quiet:
            print("cm2cl: frame 0: " + attenuation_line(record["attenuation"]), file=sys.stderr)
    with FrameStore.open(out, fingerprint=key, n_frames=len(series), volume_shape=shape, dtype=dt,
                         voxel_size_um=wp.voxel_size_um, depths_um=wp.depths_um, record=record,
                         channel=args.channel, frame_interval_s=args.frame_interval, levels=args.pyramid,
                         ngff=args.ngff) as store:
        reweight = None
        if refine:
            h, reweight = _refined(args, params, series, h, store, key, frame_prep, solver_kw, dt, wp)
        params = with_reweight(replace(params, psf_refine=0), reweight)
        from ..solver.attenuation import attenuate

        h, _ = attenuate(h, wp.depths_um, params)   # every frame's model (the refinement attenuated its own)
        progress = FrameProgress(len(store.missing()), args.quiet, every=args.progress_every)
        try:
            s = run_series(series, h, store, params=params, key=key, executor=ex, dtype=dt, backend=args.backend,
                           prepare=frame_prep, progress=progress, solver_kw=solver_kw)
        finally:
            progress.close()
    from ..solver.memory import peak_rss_bytes

    where = ex.where or ", ".join(s.devices) or "-"
    rss = peak_rss_bytes() / 2**30
    print(f"{out}: {s.frames} frames of {shape} {dt.name} volumes; {s.computed} computed "
          f"({s.converged} converged, {s.iterations} iterations), {s.skipped} already done; "
          + (f"{len(store.recomputed)} whose chunk failed its checksum computed again; " if store.recomputed else "")
          + f"{time.perf_counter() - t0:.1f} s on {where}; {s.moved_bytes / 1e9:.2f} GB streamed between host and "
          f"devices, peak host RSS {rss:.2f} GiB")
    return 0


def _refined(args, params, series, h, store, key, frame_prep, solver_kw, dt, wp):
    """(the PSF stack every frame is solved with under --psf-refine, the reweighted l1 they take from frame 0's
    final solve: :func:`cm2cl.jobs.refine.series_psf`)."""
    from ..jobs.refine import refined_psf_path, series_psf

    if not args.quiet:
        from ..solver.psf_refine import describe

        how = describe(params.psf_refine)
        print(f"cm2cl: the PSF is refined on frame 0 ({how}) unless '{refined_psf_path(args.output)}' "
              "holds this job's", file=sys.stderr)
    solve_kw = {"dtype": dt, "backend": args.backend, "device": devices_arg(args.device)[0], **solver_kw}
    h, read_back, reweight = series_psf(args.output, key, series, h, store, frame_prep, params, solve_kw=solve_kw,
                                        voxel_size_um=wp.voxel_size_um, depths_um=wp.depths_um,
                                        psf_name=str(args.psf))
    if read_back:
        print(f"cm2cl: note: the PSF refined on frame 0 is read back from '{refined_psf_path(args.output)}'",
              file=sys.stderr)
    return h, reweight


def _grid(args, h, off, psf_off, device):
    """(the PSF stack, the solvers' layout options, what the job's fingerprint records of the preparation):
    with --padding support one grid for every frame, from the PSF stack's measured support."""
    solver_kw = layout_options(args)
    prep = {"offset": off, "psf_offset": psf_off, "bin": args.bin, "padding": args.padding,
            "warm_start": bool(args.warm_start)}
    if args.padding == "support":
        from ..device import get_runtime
        from ..device.fft import resolve_backend
        from ..solver.forward import support_padding

        h, solver_kw["padded_shape"], _ = support_padding(h, resolve_backend(args.backend, get_runtime(device)))
        prep["padded_shape"] = list(solver_kw["padded_shape"])
    return h, solver_kw, prep


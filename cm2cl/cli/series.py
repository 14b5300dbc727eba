"""``cm2cl reconstruct FRAMES... --psf PSF -o OUT.ome.zarr``: many frames (a multi-page TIFF, folders, globs)
into one OME-Zarr store, on the local devices (``--device all|0,2``) or a Dask cluster (``--scheduler``);
re-running the same command resumes a killed job. Called by :mod:`cm2cl.cli.reconstruct` when the
output is a ``.zarr`` store; the options are reconstruct's."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from ..errors import InputError


def devices_arg(text):
    """``--device``: None (the automatic choice), 'all' (every device that compiles), or 'i,j,...'/a name."""
    from ..device import compiler_report

    if text is None:
        return [None]
    if text == "all":
        devs = [i for i, (ok, _) in sorted(compiler_report().items()) if ok]
        if not devs:
            raise InputError("--device all: no OpenCL device that compiles kernels")
        return devs
    parts = [p.strip() for p in str(text).split(",") if p.strip()]
    out = [int(p) if p.isdigit() else p for p in parts]
    if len(set(map(str, out))) != len(out):
        raise InputError(f"--device '{text}': a device is listed twice")
    return out


def check_scheduler(address: str) -> None:
    try:
        from distributed import Client
    except ImportError as exc:
        raise InputError("--scheduler: needs Dask distributed (pip install 'cm2cl[dask]')") from exc
    try:
        Client(address, timeout="5s").close()
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(f"--scheduler '{address}': no Dask scheduler answers there ({exc})") from exc


def command(args) -> int:
    """Run the job described by reconstruct's arguments; one summary line on stdout."""
    from .. import io
    from ..device import get_runtime
    from ..io.prepare import prepare
    from ..jobs import FrameSeries, FrameStore, run_series
    from ..jobs.run import fingerprint
    from ..solver.params import PRESETS, PRIORS, ADMMParams
    from .reconstruct import _offset, _volume_geometry, psf_binning, psf_on_working_grid

    out = Path(args.output)
    if args.bin < 1:
        raise InputError(f"--bin: must be an integer >= 1, got {args.bin}")
    series = FrameSeries(args.measurement)                      # headers only: shapes checked first
    psf, pmeta = io.read_tiff(args.psf)
    if psf.ndim not in (2, 3):
        raise InputError(f"psf '{args.psf}': expected a (nz, My, Mx) stack, got shape {psf.shape}")
    off, psf_off = _offset(args.offset), _offset(args.psf_offset, "--psf-offset")
    if min(series.shape) < args.bin:
        raise InputError(f"measurement: frames of shape {series.shape} are smaller than the bin factor {args.bin}")
    sensor = tuple(n // args.bin for n in series.shape)
    psf_bin = psf_binning(args, psf.shape, series.shape)
    h, _ = psf_on_working_grid(args, psf, psf_off, psf_bin, series.shape, pmeta["extra"].get("axis_pixel"))
    vs, depths, how = _volume_geometry(args, pmeta, psf_bin)
    devices = devices_arg(args.device) if not args.scheduler else [None]
    if args.warm_start and (args.scheduler or len(devices) != 1):
        raise InputError("--warm-start: frame t starts from frame t - 1, so the frames run in order on one device "
                         "(no --scheduler, one --device)")
    if args.scheduler:
        check_scheduler(args.scheduler)
    else:
        for d in devices:
            get_runtime(d)                                      # an unknown device fails here, before output
    given = {k: v for k, v in (("max_iter", args.max_iter), ("tol", args.tol), ("tol_change", args.tol_change))
             if v is not None}
    params = ADMMParams.from_kwargs(**{
        **dict(l1=args.l1, tv=args.tv, tv_axial_weight=args.tv_axial_weight, tv_isotropic=not args.anisotropic,
               tv_iters=args.tv_iters, patience=args.patience, penalty=args.penalty),
        **PRIORS[args.prior], **PRESETS[args.preset or "balanced"], **given})
    dt = np.dtype(args.dtype)
    if dt == np.float64 and not args.scheduler:
        for d in devices:
            get_runtime(d).check_dtype(dt)
    from .reconstruct import _STREAM

    solver_kw = {"max_memory": args.max_memory, "stream": _STREAM[args.stream], "lean": _STREAM[args.lean]}
    prep = {"offset": off, "psf_offset": psf_off, "bin": args.bin, "padding": args.padding,
            "warm_start": bool(args.warm_start)}
    if args.padding == "support":   # one grid for every frame, from the PSF stack's measured support
        from ..device.fft import resolve_backend
        from ..solver.forward import support_padding

        h, solver_kw["padded_shape"], _ = support_padding(h, resolve_backend(args.backend, get_runtime(devices[0])))
        prep["padded_shape"] = list(solver_kw["padded_shape"])
    key = fingerprint(h, params, series, dt, args.backend, prep)
    shape = (h.shape[0],) + sensor
    record = {"what": "cm2cl reconstruction series", "psf": str(args.psf), "params": params.as_dict(),
              "frames": [f"{f.path}[{f.index}]" for f in series.frames[:1000]], "scale": how, "prep": prep}
    t0 = time.perf_counter()
    with FrameStore.open(out, fingerprint=key, n_frames=len(series), volume_shape=shape, dtype=dt,
                         voxel_size_um=vs, depths_um=depths, record=record) as store:
        todo = len(store.missing())
        bar = None
        if not args.quiet and sys.stderr.isatty() and todo:
            from tqdm import tqdm

            bar = tqdm(total=todo, file=sys.stderr, desc="frames", unit="frame", dynamic_ncols=True)

        def progress(i, info):
            if bar is not None:
                bar.set_postfix(frame=i, it=info["iterations"], refresh=False)
                bar.update(1)

        try:
            s = run_series(series, h, store, params=params, key=key,
                           prepare=lambda a: prepare(a, offset=off, bin_factor=args.bin, name="measurement"),
                           dtype=dt, backend=args.backend, devices=devices, scheduler=args.scheduler,
                           progress=progress, solver_kw=solver_kw, warm_start=args.warm_start)
        finally:
            if bar is not None:
                bar.close()
    import resource

    where = args.scheduler or ", ".join(s.devices) or "-"
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20    # Linux: KiB -> GiB
    print(f"{out}: {s.frames} frames of {shape} {dt.name} volumes; {s.computed} computed "
          f"({s.converged} converged, {s.iterations} iterations), {s.skipped} already done; "
          f"{time.perf_counter() - t0:.1f} s on {where}; {s.moved_bytes / 1e9:.2f} GB streamed between host and "
          f"devices, peak host RSS {rss:.2f} GiB")
    return 0

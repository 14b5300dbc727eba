"""``cm2cl reconstruct MEAS.tif --psf PSF.ome.tif -o OUT.ome.tif``: one frame, with a progress bar and
the iteration log written next to the output (OUT.cm2cl.log.csv and the record OUT.cm2cl.json).

The volume is OME-TIFF in the dtype of the solve (float32, or float64 with ``--dtype float64``). Its
physical scale comes from the PSF stack when the PSF says its voxel size is object-space (the
simulator's psf.ome.tif does), times ``--bin`` laterally, or from ``--voxel-size DZ DY DX``; without
either the volume is labelled in pixels (a PSF measured on a camera gives no object-space scale).
Depths come from the PSF's plane positions (OME ``Plane PositionZ``) when it has them."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..solver.params import PENALTY_POLICIES, PRESETS, PRIORS, ADMMParams
from .series import devices_arg

_DEFAULTS = ADMMParams()
#: --save-background writes the removed background beside the output, as a member of its unit
BACKGROUND_SUFFIX = ".background.ome.tif"


def register(sub):
    r = sub.add_parser("reconstruct", help="reconstruct a 3D volume from one CM2 measurement",
                       description=__doc__)
    r.add_argument("measurement", nargs="+",
                   help="2D TIFF of the measurement; or, with an OME-Zarr output (-o OUT.ome.zarr), the frames of a "
                        "series: multi-page TIFFs, folders of TIFFs, globs (quoted)")
    r.add_argument("--psf", required=True, help="3D TIFF of the PSF stack (nz, My, Mx), same sensor grid")
    r.add_argument("-o", "--output", required=True,
                   help="output OME-TIFF of the volume (name it *.ome.tif so that Fiji opens it with Bio-Formats)")
    g = r.add_argument_group("problem")
    g.add_argument("--l1", type=float, default=None,
                   help="l1 weight on the normalised problem (default: %g x the volume-domain noise level: the "
                        "measurement's estimated noise times the RMS PSF plane norm, reported in the log)"
                        % _DEFAULTS.l1_noise_ratio)
    g.add_argument("--tv", type=float, default=None,
                   help="3D TV weight on the normalised problem, 0 disables TV (default: %g x the volume-domain noise level)"
                        % _DEFAULTS.tv_noise_ratio)
    g.add_argument("--prior", choices=list(PRIORS), default="default",
                   help="what the sample looks like: 'points' (beads, sparse cells): TV off, which spreads points "
                        "into plateaus where the PSF blurs them; 'points-weighted': TV off and each plane's l1 "
                        "weight ~ ||h_i||^2, which keeps emitters in planes whose PSF spreads their light "
                        "(docs/paper_scenes.md); 'default': l1 and TV for extended structure. --l1/--tv win")
    g.add_argument("--tv-axial-weight", type=float, default=_DEFAULTS.tv_axial_weight,
                   help="weight of axial differences in TV (non-cubic voxels: e.g. dx/dz)")
    g.add_argument("--anisotropic", action="store_true", help="anisotropic TV (default isotropic)")
    g.add_argument("--tv-iters", type=int, default=_DEFAULTS.tv_iters, help="TV dual iterations per outer iteration")
    g = r.add_argument_group("solver")
    g.add_argument("--preset", choices=list(PRESETS), default=None,
                   help="accuracy against time, measured in docs/accuracy_vs_time.md: " + "; ".join(
                       f"{k}: {', '.join(f'{n}={v:g}' for n, v in o.items()) or 'the defaults'}"
                       for k, o in PRESETS.items()) + ". Explicit --max-iter/--tol/--tol-change win")
    g.add_argument("--max-iter", type=int, default=None, help=f"iteration cap (default {_DEFAULTS.max_iter})")
    g.add_argument("--tol", type=float, default=None,
                   help="converged when every split's relative primal and dual residuals are below this "
                        "(Boyd et al. 2011, sec. 3.3), with --tol-change and --patience (default %g; 0 runs to --max-iter)" % _DEFAULTS.tol)
    g.add_argument("--tol-change", type=float, default=None,
                   help="the relative change of x must also be below this (default %g)" % _DEFAULTS.tol_change)
    g.add_argument("--patience", type=int, default=_DEFAULTS.patience,
                   help="consecutive iterations the stopping test must hold (default %(default)d)")
    g.add_argument("--penalty", choices=PENALTY_POLICIES, default=_DEFAULTS.penalty,
                   help="penalty policy: adaptive (from the problem's scale, rebalanced on large imbalances), "
                        "balance (the CM2 authors' x1.1 steps), fixed (default %(default)s)")
    g.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    g.add_argument("--padding", choices=["full", "support"], default="full",
                   help="padded grid: 'full' = 2M - 1; 'support' = M + K - 1 with K the PSF stack's measured "
                        "support (fewer voxels for a compact PSF; its faint tails beyond 1e-6 of the light are "
                        "dropped)")
    g.add_argument("--backend", default="auto", help="FFT backend: auto, cl, vkfft, reikna")
    g.add_argument("--device", default=None,
                   help="device index or name fragment (see cm2cl devices), or 'all' / '0,2': a single frame "
                        "spreads its depth planes over those devices, a series runs one worker per device")
    g.add_argument("--max-memory", type=_size, default=None, metavar="SIZE",
                   help="device memory each device may use, e.g. 4G or 512M (default 90%% of its memory); "
                        "planes that do not fit are streamed in slabs from host memory")
    g.add_argument("--host-memory", type=_size, default=None, metavar="SIZE",
                   help="host memory the job may use (default: what the host has available)")
    g.add_argument("--stream", choices=["auto", "always", "never"], default="auto",
                   help="stream depth slabs through the device from host memory: when the planes do not fit "
                        "(auto, default), always, or never (refuse a problem that does not fit)")
    g.add_argument("--lean", choices=["auto", "always", "never"], default="auto",
                   help="keep the planes on the device with one slab of x spectra instead of a volume of them "
                        "(about 9%% less memory, one more FFT per iteration): when the whole state does not fit "
                        "(auto, default), always, or never")
    g.add_argument("--tile", type=int, nargs=2, metavar=("TY", "TX"), default=None,
                   help="single frame: solve lateral tiles of about TY x TX pixels, each with a halo of measurement "
                        "around it, and blend them (approximate; for a PSF small against the field)")
    g.add_argument("--halo", type=int, default=None,
                   help="with --tile: the halo in pixels (default: the PSF's reach from its axis; smaller is refused)")
    g.add_argument("--warm-start", action="store_true",
                   help="series: start frame t from frame t - 1's volume (frames in order, one device)")
    g.add_argument("--scheduler", default=None,
                   help="series: run the frames on this Dask distributed scheduler (tcp://host:port) instead of "
                        "the local devices; pin each worker to a device with CM2CL_DEVICE")
    g = r.add_argument_group("input preparation")
    g.add_argument("--offset", default="none",
                   help="camera offset (dark level) of the measurement to subtract: 'none', 'auto' (mean of "
                        "pixels [5:15, 5:15]) or a number")
    g.add_argument("--psf-offset", default="none",
                   help="offset of the PSF stack, separately (a calibration has its own dark level): 'none', "
                        "'auto' or a number")
    g.add_argument("--bin", type=int, default=1, help="bin measurement and PSF laterally by this factor")
    g.add_argument("--mask", default=None,
                   help="comma-separated pixels to leave out of the data term: 'saturated' (at the bit depth's "
                        "maximum, or --saturation), 'hot' (isolated outliers); they are always counted and reported")
    g.add_argument("--background", default=None,
                   help="remove the slowly varying background before the solve (paper Fig. 5A): "
                        "'opening:RADIUS_UM' or 'opening:RADIUSpx', a grey opening with a disk larger than the "
                        "targets, on the device")
    g.add_argument("--save-background", action="store_true",
                   help="also write the removed background next to the output (OUT.background.ome.tif)")
    g.add_argument("--saturation", type=float, default=None,
                   help="saturation level of the measurement (default: the integer dtype's maximum)")
    g = r.add_argument_group("output")
    g.add_argument("--padded", action="store_true",
                   help="write the whole padded grid (emitters outside the field of view) instead of the FOV")
    g.add_argument("--voxel-size", type=float, nargs=3, metavar=("DZ", "DY", "DX"), default=None,
                   help="object-space voxel size in um of the PSF stack's grid (before --bin); overrides the "
                        "PSF's own; without it and without an object-space PSF the volume is in pixels")
    g.add_argument("--dry-run", action="store_true",
                   help="print the plan (grid, device and host memory, whether it fits) from the TIFF headers, "
                        "solve and write nothing")
    g.add_argument("--quiet", action="store_true",
                   help="no progress bar (there is none either when stderr is not a terminal)")
    r.set_defaults(func=command)


def _size(text: str) -> int:
    """A byte count: a number with an optional binary unit K, M, G or T (4G = 4 * 2**30)."""
    t = str(text).strip().upper().removesuffix("B").removesuffix("I")
    mult = {"K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}.get(t[-1:], 1)
    try:
        value = float(t[:-1] if mult > 1 else t) * mult
    except ValueError:
        value = float("nan")
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a size such as 4G, 512M or 1000000, got {text!r}")
    return int(value)


_STREAM = {"auto": "auto", "always": True, "never": False}


def _layout(args, nz, sensor, dt, backend):
    """The planner's layout for a single frame (DeviceError when nothing fits) and the runtimes."""
    from ..device import get_runtime
    from ..solver.forward import choose_padded_shape
    from ..solver.memory import plan_layout
    rts = [get_runtime(d) for d in devices_arg(args.device)]
    P = choose_padded_shape(sensor, backend)
    return P, plan_layout(nz, P, dt, backend, rts, max_memory=args.max_memory, stream=_STREAM[args.stream],
                          lean=_STREAM[args.lean])


def _offset(text: str, option: str = "--offset"):
    if text == "none":
        return None
    if text == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError as exc:
        raise InputError(f"{option}: expected 'none', 'auto' or a number, got {text!r}") from exc
    if not np.isfinite(value):
        raise InputError(f"{option}: expected a finite number, got {text!r}")
    return value


class Progress:
    """One tqdm bar on ``stream`` (stderr): iterations, with objective and primal / dual residuals as
    its postfix. Off with ``--quiet`` and when the stream is not a terminal (logs, pipes, batch jobs):
    the summary line and OUT.cm2cl.log.csv say how the run went."""

    def __init__(self, total: int, quiet: bool, stream=None):
        stream = sys.stderr if stream is None else stream
        self.bar = None
        if not quiet and stream.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=total, file=stream, desc="ADMM", unit="it", dynamic_ncols=True)

    def __call__(self, row):
        if self.bar is None:
            return
        self.bar.set_postfix(obj=f"{row['objective']:.4e}", primal=f"{row['primal']:.2e}",
                             dual=f"{row['dual']:.2e}", refresh=False)
        self.bar.update(int(row["iter"]) - self.bar.n)

    def close(self):
        if self.bar is not None:
            self.bar.close()


def _volume_geometry(args, pmeta, bin_factor: int):
    """(voxel_size_um or None, depths_um or None, how): the volume's object-space scale."""
    from ..io import OBJECT_SPACE

    depths = pmeta.get("depths_um")
    if args.voxel_size is not None:
        vs, how = tuple(args.voxel_size), "from --voxel-size"
        if not all(np.isfinite(v) and v > 0 for v in vs):
            raise InputError(f"--voxel-size: expected 3 positive finite numbers DZ DY DX in um, "
                             f"got {args.voxel_size}")
    elif pmeta.get("voxel_size_um") and pmeta["extra"].get("voxel_space") == OBJECT_SPACE:
        vs, how = tuple(pmeta["voxel_size_um"]), f"object-space scale of the PSF '{args.psf}'"
        if len(vs) == 2:
            return None, depths, "unit pixel: the PSF is a single plane without a z spacing; give --voxel-size"
    else:
        return None, depths, ("unit pixel: the PSF has no object-space voxel size; give --voxel-size DZ DY DX "
                              "(um) to label the volume")
    return (vs[0], vs[1] * bin_factor, vs[2] * bin_factor), depths, how


def command(args) -> int:
    from .. import io
    from ..io.prepare import check_image, prepare
    from ..solver import reconstruct

    if args.lean == "always" and args.stream == "always":   # before any work, series too
        raise InputError("--lean always and --stream always: the lean layout keeps every plane on the device, "
                         "streaming keeps them in host memory; ask for one of them")
    out = Path(args.output)
    if out.suffix.lower() == ".zarr":
        from . import series

        return series.command(args)
    if len(args.measurement) != 1:
        raise InputError(f"measurement: {len(args.measurement)} inputs given; a series needs an OME-Zarr output "
                         "(-o OUT.ome.zarr)")
    if args.scheduler:
        raise InputError("--scheduler: only for a series written to an OME-Zarr output (-o OUT.ome.zarr)")
    if args.warm_start:
        raise InputError("--warm-start: only for a series written to an OME-Zarr output (-o OUT.ome.zarr)")
    args.measurement = args.measurement[0]
    if out.suffix.lower() not in (".tif", ".tiff"):
        raise InputError(f"--output '{out}': must end in .ome.tif, .tif or .tiff (or .ome.zarr for a series)")
    from ..io.publish import OutputSet, check_output_file

    extras = {"background": BACKGROUND_SUFFIX} if args.save_background else None
    check_output_file(out, 0, (args.measurement, args.psf), extras=extras)   # before any work; creates nothing
    off, psf_off = _offset(args.offset), _offset(args.psf_offset, "--psf-offset")
    if args.bin < 1:
        raise InputError(f"--bin: must be an integer >= 1, got {args.bin}")
    if args.background:
        from ..io.background import check_background_spec

        check_background_spec(args.background)
    if args.mask:
        from ..analysis.pixels import MASKS

        bad = [n for n in args.mask.split(",") if n.strip() and n.strip() not in MASKS]
        if bad:
            raise InputError(f"--mask: unknown {', '.join(map(repr, bad))} (known: {', '.join(MASKS)})")
    if args.dry_run:
        return _plan(args)
    _check_headers(args)      # shapes and sizes from the TIFF headers, before decoding anything
    meas, mmeta = io.read_tiff(args.measurement)
    psf, pmeta = io.read_tiff(args.psf)
    if meas.ndim != 2:
        raise InputError(f"measurement '{args.measurement}': expected a 2D image, got shape {meas.shape}")
    if psf.ndim not in (2, 3):
        raise InputError(f"psf '{args.psf}': expected a (nz, My, Mx) stack, got shape {psf.shape}")
    check_image(meas, f"measurement '{args.measurement}'")    # numeric and finite before anything reads them
    check_image(psf, f"psf '{args.psf}'")
    psf_bin = psf_binning(args, psf.shape, meas.shape)
    vs, depths, how = _volume_geometry(args, pmeta, psf_bin)
    from ..analysis.pixels import check_pixels, mask_weights
    from ..io.prepare import bin_image

    pixels = check_pixels(meas, args.saturation, psf)
    names = [n.strip() for n in args.mask.split(",") if n.strip()] if args.mask else []
    weights = None
    if names:                      # a binned pixel is masked when any of its sensor pixels is
        weights = (bin_image(1.0 - mask_weights(meas, names, args.saturation, psf), args.bin) == 0).astype(float)
    background = None
    if args.background:
        from ..io.background import parse_background, remove_background

        px_um = (mmeta.get("voxel_size_um") or (None,))[-1] if mmeta.get("unit") == "um" else None
        corrected, background = remove_background(meas, parse_background(args.background, px_um), args.device)
        meas = corrected
    y = prepare(meas, offset=off, bin_factor=args.bin, name=f"measurement '{args.measurement}'")
    h, fit_note = psf_on_working_grid(args, psf, psf_off, psf_bin, meas.shape, pmeta["extra"].get("axis_pixel"))
    if depths is not None and len(depths) != h.shape[0]:
        raise InputError(f"psf '{args.psf}': {len(depths)} plane positions for {h.shape[0]} planes")
    dt = np.dtype(args.dtype)
    params = dict(l1=args.l1, tv=args.tv, tv_axial_weight=args.tv_axial_weight,
                  tv_isotropic=not args.anisotropic, tv_iters=args.tv_iters, patience=args.patience,
                  penalty=args.penalty)
    given = {k: v for k, v in (("max_iter", args.max_iter), ("tol", args.tol), ("tol_change", args.tol_change))
             if v is not None}
    params.update({**PRIORS[args.prior], **PRESETS[args.preset or "balanced"], **given})
    # the output is checked (writable, room, sidecars, no other run on it) and locked before the solve
    planes, ny, nx = h.shape
    vol_bytes = planes * (2 * ny * 2 * nx if args.padded else ny * nx) * dt.itemsize
    outset = OutputSet(out, expected_bytes=vol_bytes, inputs=(args.measurement, args.psf), extras=extras)
    progress = Progress(params.get("max_iter", _DEFAULTS.max_iter), args.quiet)
    with outset:   # an OSError while writing becomes one line; nothing is left behind
        try:
            devs = devices_arg(args.device)
            if args.tile:
                rec = _tiled(y, h, args, dt, devs, weights, vs, depths, params)
            else:
                rec = reconstruct(y, h, dtype=dt, backend=args.backend, device=devs[0],
                                  devices=devs if len(devs) > 1 else None, max_memory=args.max_memory,
                                  stream=_STREAM[args.stream], lean=_STREAM[args.lean], weights=weights,
                                  padding=args.padding,
                                  callback=progress, voxel_size_um=vs, depths_um=depths, **params)
        finally:
            progress.close()
        rec.info["pixels"] = {**pixels, "masked": names}
        rec.info["background"] = args.background
        rec.info["psf_fit"] = fit_note
        if background is not None and args.save_background:   # a member of the published unit
            io.write_tiff(outset.staged("background"), background.astype(np.float32),
                          voxel_size_um=mmeta.get("voxel_size_um") if mmeta.get("unit") == "um" else None,
                          extra={"what": "background removed from the measurement", "method": args.background,
                                 "measurement": str(args.measurement)})
        vol = _write(args, out, outset, rec, dt, how)
    _report(out, outset, rec, how, vol)
    return 0


def psf_binning(args, psf_shape, meas_shape) -> int:
    """The binning the PSF needs: ``--bin``, or 1 for a PSF already on the binned grid (prepare-psf --bin N)."""
    working = tuple(n // args.bin for n in meas_shape)
    if args.bin > 1 and tuple(psf_shape[-2:]) == working:
        print(f"cm2cl: note: psf '{args.psf}' is already on the {args.bin}x binned grid {working}: only the "
              "measurement is binned", file=sys.stderr)
        return 1
    return args.bin


def psf_on_working_grid(args, psf, psf_off, psf_bin, sensor, axis=None):
    """(h (nz, My, Mx) float64, note): the PSF offset, fitted (zero-padded or cropped, its optical axis
    ``axis`` on the centre: :func:`cm2cl.io.prepare.fit_lateral`) to the measurement's grid at its own
    pixel (the unbinned ``sensor``, or the binned one for a PSF already binned), then binned; the note
    is said on stderr."""
    from ..io.prepare import prepare_psf

    target = sensor if psf_bin == args.bin else tuple(n // args.bin for n in sensor)
    h, note = prepare_psf(psf, target, offset=psf_off, bin_factor=psf_bin, axis=axis, name=f"psf '{args.psf}'")
    h = h[None] if h.ndim == 2 else h
    if note:
        print(f"cm2cl: note: {note}", file=sys.stderr)
    return h, note


def _tiled(y, h, args, dt, devs, weights, vs, depths, params):
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

    vol, info = reconstruct_tiled(y, h, tuple(args.tile), args.halo, dtype=dt, backend=args.backend,
                                  device=devs[0], progress=progress, **params)
    rec = last["rec"]
    out = Reconstruction(volume_padded=vol, crop=(slice(0, vol.shape[1]), slice(0, vol.shape[2])), log=rec.log,
                         scaling={"psf_scale": 1.0, "y_scale": 1.0}, params=rec.params,
                         info={**rec.info, "tiles": info, "l1": info["l1"], "tv": info["tv"],
                               "noise_x": info["noise_x"], "noise_sigma": info["noise_sigma"],
                               "converged": all(info["converged"]),
                               "stop": f"{sum(info['converged'])} of {info['tiles']} tiles converged"})
    out.voxel_size_um, out.depths_um = vs, depths
    return out


def _plan(args) -> int:
    """``--dry-run``: the plan from the headers only (layout of the planes over the devices, device and
    host memory, bytes moved per iteration); exit 0 when it fits, 2 when not."""
    from .. import io
    from ..device import get_runtime
    from ..device.fft import resolve_backend
    from ..errors import DeviceError
    from ..solver.memory import host_available_bytes, streamed_bytes_per_iteration

    (ms, mdt), (ps, pdt) = io.peek_tiff(args.measurement), io.peek_tiff(args.psf)
    dt = np.dtype(args.dtype)
    backend = resolve_backend(args.backend, get_runtime(devices_arg(args.device)[0]))
    sensor = tuple(n // args.bin for n in ms)
    nz = ps[0] if len(ps) == 3 else 1
    decode = 8 * 2 * (int(np.prod(ms)) + int(np.prod(ps)))
    host_cap = args.host_memory or host_available_bytes()
    try:
        P, layout = _layout(args, nz, sensor, dt, backend)
        problem = None
    except DeviceError as exc:
        P, layout, problem = None, [], str(exc)
    if args.tile:   # the memory plan is a tile's: its largest window (the PSF's reach needs its pixels)
        from ..io.prepare import bin_image
        from ..jobs.tiles import plan_tiles

        h = np.asarray(io.read_tiff(args.psf)[0], np.float64)
        h = h[None] if h.ndim == 2 else h
        if args.bin > 1 and h.shape[1:] == tuple(ms):
            h = np.stack([bin_image(p, args.bin) for p in h])
        tp = plan_tiles(sensor, h, tuple(args.tile), args.halo)
        print("tiles: " + tp.describe())
        sensor = (max(b - a for (a, b), _ in tp.windows), max(d - c for _, (c, d) in tp.windows))
    print(f"plan: {nz} planes x {sensor[0]} x {sensor[1]} sensor ({ms[0]} x {ms[1]} binned {args.bin}x)"
          + (f", padded {P[0]} x {P[1]} (2M - 1; --padding support may shrink it)" if P else "")
          + f", {dt.name}, FFT {backend}")
    moved = 0
    for lp in layout:
        how = (f"streamed in slabs of {lp.slab_planes} planes{' (double-buffered)' if lp.overlap else ''} from "
               f"{lp.host_bytes / 2**30:.2f} GiB of host memory" if lp.streamed else
               f"resident, lean (x spectra in slabs of {lp.slab_planes} planes)" if lp.lean else "resident")
        if lp.streamed:
            moved += streamed_bytes_per_iteration(lp.z1 - lp.z0, P, dt, backend, args.tv_iters)
        print(f"  device {lp.rt.caps.name} (#{lp.rt.caps.index}): planes {lp.z0}..{lp.z1 - 1}, {how}; "
              f"{lp.device_bytes / 2**30:.2f} GiB on the device")
    host = decode + sum(lp.host_bytes for lp in layout)
    fits = problem is None and host <= host_cap
    print(f"  host: {host / 2**30:.2f} GiB (inputs decoded and prepared"
          + (", streamed volumes" if moved else "") + f"), {host_cap / 2**30:.1f} GiB "
          + ("allowed (--host-memory)" if args.host_memory else "available"))
    if layout:
        from ..device.rates import copy_rate, transfer_rate
        from ..solver.memory import KERNEL_FLOOR_RATIO, expected_seconds

        rts = {id(lp.rt): lp.rt for lp in layout}
        copy = {k: copy_rate(rt) for k, rt in rts.items()}
        xfer = {k: transfer_rate(rt) for k, rt in rts.items()} if moved else {k: 1.0 for k in rts}
        t = expected_seconds(layout, P, dt, backend, args.tv_iters, copy, xfer)
        iters = args.max_iter or _DEFAULTS.max_iter
        print(f"  moved between host and devices per iteration: {moved / 2**30:.2f} GiB")
        print(f"  expected: about {t:.2g} s per iteration, {t * iters / 60:.2g} min for {iters} iterations (rates "
              f"measured now: copy {min(copy.values()) / 1e9:.1f} GB/s"
              + (f", host <-> device {min(xfer.values()) / 1e9:.1f} GB/s" if moved else "")
              + f"; kernels at {KERNEL_FLOOR_RATIO}x the bandwidth floor, as measured on PoCL)")
    if problem:
        print(f"  does NOT fit: {problem}")
    elif not fits:
        print("  does NOT fit: the host memory is too small; bin the measurement or use fewer planes")
    else:
        print(f"  output: {nz * int(np.prod(sensor)) * dt.itemsize / 2**20:.1f} MiB; fits: run without --dry-run")
    return 0 if fits else 2


def _check_headers(args) -> None:
    """Refuse, from the headers alone, inputs of the wrong shape and problems that cannot fit: the
    host memory to decode them (float64) and to hold streamed slabs, and the devices' memory."""
    from .. import io
    from ..device import get_runtime
    from ..device.fft import resolve_backend
    from ..solver.memory import host_available_bytes
    (ms, mdt), (ps, pdt) = io.peek_tiff(args.measurement), io.peek_tiff(args.psf)
    if len(ms) != 2:
        raise InputError(f"measurement '{args.measurement}': expected a 2D image, got shape {ms}")
    if len(ps) not in (2, 3):
        raise InputError(f"psf '{args.psf}': expected a (nz, My, Mx) stack, got shape {ps}")
    if min(ms) < args.bin:
        raise InputError(f"measurement '{args.measurement}': shape {ms} is smaller than the bin factor {args.bin}")
    rt = get_runtime(devices_arg(args.device)[0])
    dt = rt.check_dtype(np.dtype(args.dtype))
    backend = resolve_backend(args.backend, rt)
    sensor = tuple(n // args.bin for n in ms)
    nz = ps[0] if len(ps) == 3 else 1
    _, layout = _layout(args, nz, sensor, dt, backend)
    need = 8 * (int(np.prod(ms)) + int(np.prod(ps))) * 2      # decoded as float64, plus a prepared copy
    streamed = sum(lp.host_bytes for lp in layout)
    have = args.host_memory or host_available_bytes()
    if have and need + streamed > have:
        raise InputError(f"measurement '{args.measurement}' and psf '{args.psf}': decoding them"
                         + (" and holding the streamed slabs" if streamed else "")
                         + f" needs {(need + streamed) / 2**20:.1f} MiB of host memory, {have / 2**20:.1f} MiB "
                         + ("allowed (--host-memory)" if args.host_memory else "available"))


def _write(args, out, outset, rec, dt, how):
    from .. import io

    # the volume in the dtype of the solve (the solver's rescaling may promote it to float64)
    vol = (rec.volume_padded if args.padded else rec.volume).astype(dt, copy=False)
    extra = {"what": "cm2cl reconstruction", "measurement": str(args.measurement), "psf": str(args.psf),
             "params": rec.params, "scaling": rec.scaling, "info": rec.info, "padded": bool(args.padded),
             "voxel_space": io.OBJECT_SPACE if rec.voxel_size_um else None, "scale": how}
    io.write_tiff(outset.staged("volume"), vol, voxel_size_um=rec.voxel_size_um, depths_um=rec.depths_um,
                  extra=extra)
    rec.write_log(outset.staged("log"), fmt="csv")
    rec.write_log(outset.staged("record"), fmt="json", extra=outset.record_fields())
    outset.publish()   # committed, then the old sidecars, the volume, the new sidecars: never two runs mixed
    return vol


def _report(out, outset, rec, how, vol):
    last = rec.log[-1]
    if rec.voxel_size_um:
        scale = "voxel {:g} x {:g} x {:g} um (z, y, x; {})".format(*rec.voxel_size_um, how)
    else:
        scale = how
    info = rec.info
    how_stop = ("converged" if info["converged"] else
                f"NOT converged: stopped at --max-iter, relative residuals {last['primal_rel']:.1e} / "
                f"{last['dual_rel']:.1e} against tol {info['tol']:g}")
    print(f"{out}: {vol.shape} {vol.dtype} volume, {scale}; {rec.iterations} iterations, {how_stop}; "
          f"l1 {info['l1']:.3g}, tv {info['tv']:.3g} (volume-domain noise level {info['noise_x']:.3g}; "
          f"measurement noise {info['noise_sigma']:.3g} of max y); "
          f"objective {last['objective']:.4e}, {last['seconds']:.1f} s on {info['device']}; "
          f"log: {outset.sidecars['log'].name}, {outset.sidecars['record'].name}")
    lay = info.get("layout") or []
    if len(lay) > 1 or any(p["streamed"] or p.get("lean") for p in lay):
        import resource

        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024   # Linux: KiB
        print("  planes: " + "; ".join(
            f"{p['planes'][0]}..{p['planes'][1] - 1} on {p['device']}"
            + (f" streamed in slabs of {p['slab_planes']}{' (double-buffered)' if p.get('overlap') else ''}"
               if p["streamed"] else f" resident, lean (x spectra in slabs of {p['slab_planes']})" if p.get("lean")
               else " resident") for p in lay)
            + f"; {info['moved_bytes'] / 1e9:.2f} GB moved between host and devices, "
              f"{info['device_bytes'] / 2**30:.2f} GiB on the devices, peak host RSS {rss / 2**30:.2f} GiB")
    px = info.get("pixels") or {}
    for name in ("saturated", "hot"):
        c = px.get(name, {}).get("count", 0)
        if c:
            print(f"  {c} {name} pixel(s) in the measurement, first at (row, column) "
                  f"{', '.join(map(str, px[name]['first'][:5]))}; "
                  + ("masked in the data term" if name in px.get("masked", []) else f"not masked (--mask {name})"))

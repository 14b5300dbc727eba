"""A single frame's plan from the TIFF headers alone: the refusal of inputs of the wrong shape and of
problems that cannot fit (:func:`check_headers`, before anything is decoded), and ``--dry-run``'s report
(:func:`dry_run`: the planes over the devices, device and host memory, bytes moved, time expected)."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..solver.params import ADMMParams
from .inputs import STREAM, check_bin, check_psf_shape, devices_arg, single_frame_shape


def layout(args, nz, sensor, dt, backend, params: ADMMParams, padded_shape=None):
    """(padded grid, the planner's layout) for a single frame solved with ``params`` (its terms' state:
    without TV 3 real volumes per voxel, with 7; DeviceError when nothing fits); the grid is
    ``padded_shape`` when given (support padding), else the full one."""
    from ..device import get_runtime
    from ..solver.forward import choose_padded_shape
    from ..solver.memory import plan_layout
    from ..solver.terms import state_counts, terms_for

    rts = [get_runtime(d) for d in devices_arg(args.device)]
    P = tuple(padded_shape) if padded_shape is not None else choose_padded_shape(sensor, backend)
    terms = terms_for(params)
    return P, plan_layout(nz, P, dt, backend, rts, max_memory=args.max_memory, stream=STREAM[args.stream],
                          lean=STREAM[args.lean] if terms.fused else False, **state_counts(terms))


def _headers(args):
    """(measurement shape, PSF shape) from the TIFF headers."""
    from .. import io

    (ms, _), (ps, _) = io.peek_tiff(args.measurement), io.peek_tiff(args.psf)
    return ms, ps


def backend_of(args):
    """(the FFT backend, the first device's runtime)."""
    from ..device import get_runtime
    from ..device.fft import resolve_backend

    rt = get_runtime(devices_arg(args.device)[0])
    return resolve_backend(args.backend, rt), rt


def _decoded_bytes(ms, ps) -> int:
    return 8 * 2 * (int(np.prod(ms)) + int(np.prod(ps)))   # decoded as float64, plus a prepared copy


def _host_words(args) -> str:
    return "allowed (--host-memory)" if args.host_memory else "available"


def check_headers(args, params: ADMMParams) -> None:
    """Refuse, from the headers alone, inputs of the wrong shape and problems that cannot fit: the
    host memory to decode them (float64) and to hold streamed slabs, and the devices' memory."""
    from ..solver.memory import host_available_bytes

    ms, ps = _headers(args)
    ms = single_frame_shape(ms)
    if len(ms) != 2:
        raise InputError(f"measurement '{args.measurement}': expected a 2D image, got shape {ms}"
                         + ("; several frames: give an .ome.zarr output for a series" if len(ms) > 2 else ""))
    check_psf_shape(ps, args.psf)
    check_bin(args.bin, ms, f"measurement '{args.measurement}'")
    backend, rt = backend_of(args)
    dt = rt.check_dtype(np.dtype(args.dtype))
    nz = ps[0] if len(ps) == 3 else 1
    sensor = tuple(n // args.bin for n in ms)
    # --padding support pads to the PSF's support, known once it is decoded: here the grid is bounded from
    # below by the sensor, so only what fits on no grid is refused; the solver plans the real grid (and
    # refuses what does not fit) after the support is measured, before the solve
    lower = sensor if getattr(args, "padding", "full") == "support" else None
    _, lay = layout(args, nz, sensor, dt, backend, params, padded_shape=lower)
    need, streamed = _decoded_bytes(ms, ps), sum(lp.host_bytes for lp in lay)
    have = args.host_memory or host_available_bytes()
    if have and need + streamed > have:
        raise InputError(f"measurement '{args.measurement}' and psf '{args.psf}': decoding them"
                         + (" and holding the streamed slabs" if streamed else "")
                         + f" needs {(need + streamed) / 2**20:.1f} MiB of host memory, {have / 2**20:.1f} MiB "
                         + _host_words(args))


def dry_run(args, params: ADMMParams) -> int:
    """``--dry-run``: the plan from the headers only (layout of the planes over the devices, device and
    host memory, bytes moved per iteration); exit 0 when it fits, 2 when not."""
    from ..errors import DeviceError
    from ..solver.memory import host_available_bytes, streamed_bytes_per_iteration

    ms, ps = _headers(args)
    backend, _ = backend_of(args)
    dt = np.dtype(args.dtype)
    sensor = tuple(n // args.bin for n in ms)
    nz = ps[0] if len(ps) == 3 else 1
    host_cap = args.host_memory or host_available_bytes()
    try:
        P, lay = layout(args, nz, sensor, dt, backend, params)
        problem = None
    except DeviceError as exc:
        P, lay, problem = None, [], str(exc)
    if args.tile:   # the memory plan is a tile's: its largest window (the PSF's reach needs its pixels)
        sensor = _tile_window(args, ms, sensor)
    print(f"plan: {nz} planes x {sensor[0]} x {sensor[1]} sensor ({ms[0]} x {ms[1]} binned {args.bin}x)"
          + (f", padded {P[0]} x {P[1]} (2M - 1; --padding support may shrink it)" if P else "")
          + f", {dt.name}, FFT {backend}")
    moved = 0
    for lp in lay:
        how = (f"streamed in slabs of {lp.slab_planes} planes{' (double-buffered)' if lp.overlap else ''} from "
               f"{lp.host_bytes / 2**30:.2f} GiB of host memory" if lp.streamed else
               f"resident, lean (x spectra in slabs of {lp.slab_planes} planes)" if lp.lean else "resident")
        if lp.streamed:
            moved += streamed_bytes_per_iteration(lp.z1 - lp.z0, P, dt, backend, _tv_iters(params),
                                                  relaxed=params.relaxation != 1)
        print(f"  device {lp.rt.caps.name} (#{lp.rt.caps.index}): planes {lp.z0}..{lp.z1 - 1}, {how}; "
              f"{lp.device_bytes / 2**30:.2f} GiB on the device")
    host = _decoded_bytes(ms, ps) + sum(lp.host_bytes for lp in lay)
    print(f"  host: {host / 2**30:.2f} GiB (inputs decoded and prepared"
          + (", streamed volumes" if moved else "") + f"), {host_cap / 2**30:.1f} GiB " + _host_words(args))
    if lay:
        _expected(lay, P, dt, backend, params, moved)
    if problem:
        print(f"  does NOT fit: {problem}")
    elif host > host_cap:
        print("  does NOT fit: the host memory is too small; bin the measurement or use fewer planes")
    else:
        print(f"  output: {nz * int(np.prod(sensor)) * dt.itemsize / 2**20:.1f} MiB; fits: run without --dry-run")
    return 0 if problem is None and host <= host_cap else 2


def _tile_window(args, ms, sensor):
    """The largest measurement window of the tiles (said on stdout): what one solve holds."""
    from .. import io
    from ..io.prepare import bin_image
    from ..jobs.tiles import plan_tiles

    h = np.asarray(io.read_tiff(args.psf)[0], np.float64)
    h = h[None] if h.ndim == 2 else h
    if args.bin > 1 and h.shape[1:] == tuple(ms):
        h = np.stack([bin_image(p, args.bin) for p in h])
    tp = plan_tiles(sensor, h, tuple(args.tile), args.halo)
    print("tiles: " + tp.describe())
    return max(b - a for (a, b), _ in tp.windows), max(d - c for _, (c, d) in tp.windows)


def _tv_iters(params: ADMMParams):
    """TV's inner iterations for the traffic model, None for a solve without TV (its weight 0)."""
    from ..solver.terms import has_tv

    return params.tv_iters if has_tv(params) else None


def _expected(lay, P, dt, backend, params: ADMMParams, moved: int) -> None:
    """The bytes moved and the time expected per iteration, from rates measured now."""
    from ..device.rates import copy_rate, transfer_rate
    from ..solver.memory import KERNEL_FLOOR_RATIO, expected_seconds

    rts = {id(lp.rt): lp.rt for lp in lay}
    copy = {k: copy_rate(rt) for k, rt in rts.items()}
    xfer = {k: transfer_rate(rt) for k, rt in rts.items()} if moved else {k: 1.0 for k in rts}
    t = expected_seconds(lay, P, dt, backend, _tv_iters(params), copy, xfer)
    iters = params.max_iter
    print(f"  moved between host and devices per iteration: {moved / 2**30:.2f} GiB")
    print(f"  expected: about {t:.2g} s per iteration, {t * iters / 60:.2g} min for {iters} iterations (rates "
          f"measured now: copy {min(copy.values()) / 1e9:.1f} GB/s"
          + (f", host <-> device {min(xfer.values()) / 1e9:.1f} GB/s" if moved else "")
          + f"; kernels at {KERNEL_FLOOR_RATIO}x the bandwidth floor, as measured on PoCL)")
    if params.scattering_length_um == "auto":
        print("  --scattering-length-um auto: up to twice that (a clear-medium solve for the estimate, then the solve "
              "with it where it applies)")

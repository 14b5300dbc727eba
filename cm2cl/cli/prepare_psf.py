"""``cm2cl prepare-psf SCAN -o PSF.ome.tif [--z-start UM --z-step UM]``: a raw calibration scan (a multi-page
TIFF, folders or globs of planes in z order; 8/12/16-bit integers or float) to the PSF stack ``cm2cl
reconstruct`` takes: dark level off, the stage's lateral drift registered out, depth range, axial and
lateral binning, padding or cropping to the sensor, noise floor, normalisation. The stack is OME-TIFF with
its depths (and its object-space voxel size with ``--object-pixel-um``); the record of every step and what
it measured (dark level, drift per mm, planes kept) is ``PSF.cm2cl.json``. Warnings go to stderr."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from ..errors import InputError


def register(sub):
    r = sub.add_parser("prepare-psf", help="a raw PSF calibration scan to a prepared PSF stack", description=__doc__)
    r.add_argument("scan", nargs="+", help="the scan's planes: a multi-page TIFF, folders, globs (in z order)")
    r.add_argument("-o", "--output", required=True, help="the prepared stack (OME-TIFF, *.ome.tif)")
    g = r.add_argument_group("depths")
    g.add_argument("--z-start", type=float, default=None,
                   help="z of the first plane (um); with --z-step. Default: the scan's OME plane positions")
    g.add_argument("--z-step", type=float, default=None, help="z step between planes (um, e.g. 10; negative: "
                   "a scan towards the lens)")
    g.add_argument("--z-range", type=float, nargs=2, metavar=("ZMIN", "ZMAX"), default=None,
                   help="keep the planes in this depth range (um, inclusive; e.g. -1250 1250 for the central 2.5 mm)")
    b = g.add_mutually_exclusive_group()
    b.add_argument("--axial-bin", type=int, default=None, help="sum groups of this many planes (default 1)")
    b.add_argument("--dz", type=float, default=None, help="output plane step in um (a multiple of the scan step)")
    g = r.add_argument_group("pixels")
    g.add_argument("--dark", default="corners",
                   help="dark level: 'corners' (each plane's median of its four 20 x 20 corners), 'corners:N', "
                        "'region:R0:R1,C0:C1' (rows R0..R1-1, columns C0..C1-1 of each plane), a number, a "
                        "dark-frame TIFF (several frames are averaged), or 'none' (default corners)")
    g.add_argument("--no-register", action="store_true", help="do not measure and remove the lateral drift")
    g.add_argument("--shift", choices=("fourier", "bilinear"), default="fourier",
                   help="how planes are shifted by the fitted drift, zero filled (default fourier)")
    g.add_argument("--sensor-shape", type=int, nargs=2, metavar=("ROWS", "COLS"), default=None,
                   help="the sensor's size in scan pixels: a cropped scan is padded with zeros (a larger one "
                        "cropped) so that its optical axis lands on the sensor's centre")
    g.add_argument("--axis", default=None,
                   help="the optical axis in scan pixels: 'ROW,COL', or 'centroid' (of the middle plane's light); "
                        "default the scan's centre")
    g.add_argument("--bin", type=int, default=1, help="lateral binning to the working pixel (default 1)")
    g.add_argument("--noise-floor", type=float, default=3.0,
                   help="zero values under this many noise sigmas (default 3; 0 clips at 0)")
    g.add_argument("--normalise", choices=("plane", "stack", "none"), default="plane",
                   help="plane: unit sum per plane (default); stack: the brightest plane sums to 1; none")
    g.add_argument("--object-pixel-um", type=float, default=None,
                   help="object-space size of one scan pixel (sensor pixel / magnification, um): labels the stack "
                        "so that reconstructions carry a physical scale")
    r.set_defaults(func=command)


class _Planes:
    """The planes of a FrameSeries as a sequence (read on access)."""

    def __init__(self, series):
        self.series = series

    def __len__(self):
        return len(self.series)

    def __getitem__(self, i):
        return self.series.read(int(i))


def _z_positions(args, series) -> np.ndarray:
    if (args.z_start is None) != (args.z_step is None):
        raise InputError("--z-start/--z-step: give both, or neither to take the scan's OME plane positions")
    if args.z_start is not None:
        if not (np.isfinite(args.z_start) and np.isfinite(args.z_step) and args.z_step != 0):
            raise InputError(f"--z-step: must be a finite non-zero number of um, got {args.z_step}")
        return args.z_start + args.z_step * np.arange(len(series))
    from ..io.tiff import tiff_depths

    files = sorted({f.path for f in series.frames})
    depths = tiff_depths(files[0]) if len(files) == 1 else None
    if depths is None or len(depths) != len(series):
        raise InputError(f"scan '{args.scan[0]}': its files carry no z position per plane (OME Plane PositionZ); "
                         "give --z-start and --z-step (um)")
    return np.asarray(depths, float)


def _ignored_files(sources) -> list[str]:
    """Files in the scan's folders that are not TIFFs (not read)."""
    out = []
    for s in sources:
        p = Path(s)
        if p.is_dir():
            out += [f.name for f in sorted(p.iterdir())
                    if f.is_file() and not f.name.startswith(".") and f.suffix.lower() not in (".tif", ".tiff")]
    return out


def command(args) -> int:
    from .. import io
    from ..io.calibration import parse_dark, prepare_psf_stack
    from ..io.publish import OutputSet
    from ..jobs import FrameSeries

    out = Path(args.output)
    if out.suffix.lower() not in (".tif", ".tiff"):
        raise InputError(f"--output '{out}': must end in .ome.tif, .tif or .tiff")
    if args.object_pixel_um is not None and not (np.isfinite(args.object_pixel_um) and args.object_pixel_um > 0):
        raise InputError(f"--object-pixel-um: must be a positive number, got {args.object_pixel_um}")
    if args.bin < 1:
        raise InputError(f"--bin: must be an integer >= 1, got {args.bin}")
    if args.axial_bin is not None and args.axial_bin < 1:
        raise InputError(f"--axial-bin: must be an integer >= 1, got {args.axial_bin}")
    if args.sensor_shape is not None and min(args.sensor_shape) < 1:
        raise InputError(f"--sensor-shape: must be two positive sizes, got {args.sensor_shape}")
    axis = None
    if args.axis is not None:
        if args.axis == "centroid":
            axis = "centroid"
        else:
            try:
                axis = tuple(float(v) for v in args.axis.split(","))
            except ValueError:
                axis = ()
            if len(axis) != 2:
                raise InputError(f"--axis: expected ROW,COL or 'centroid', got {args.axis!r}")
    series = FrameSeries(args.scan, what="scan")          # plane shapes from the headers, checked first
    name = f"scan '{args.scan[0]}'" + (f" (+{len(args.scan) - 1} more)" if len(args.scan) > 1 else "")
    z = _z_positions(args, series)
    dark = parse_dark(args.dark)
    if isinstance(dark, str) and dark != "corners":        # a dark-frame file: its shape from the header first
        shape, _ = io.peek_tiff(dark)
        if tuple(shape[-2:]) != tuple(series.shape):
            raise InputError(f"--dark '{dark}': shape {shape} differs from the scan's planes {series.shape}")
        dark, _ = io.read_tiff(dark)
    out_shape = tuple(args.sensor_shape or series.shape)
    nz_max = len(series) // (args.axial_bin or 1)
    with OutputSet(out, expected_bytes=4 * nz_max * int(np.prod(out_shape)) // args.bin ** 2,
                   inputs=tuple(f.path for f in series.frames)) as outset:
        stack, depths, rec = prepare_psf_stack(
            _Planes(series), z, dark=dark, register=not args.no_register, shift_method=args.shift,
            z_range=args.z_range, axial_bin=args.axial_bin, dz_um=args.dz, lateral_bin=args.bin,
            sensor_shape=args.sensor_shape, axis=axis, noise_floor=args.noise_floor, normalise=args.normalise,
            name=name)
        ignored = _ignored_files(args.scan)
        if ignored:
            rec.setdefault("warnings", []).append(
                f"{name}: {len(ignored)} file(s) that are not TIFFs were not read: {', '.join(ignored[:5])}")
        vs = None
        if args.object_pixel_um:
            summed = rec["steps"][0]["planes_kept"] // rec["planes_out"]
            dz = float(np.median(np.diff(depths))) if len(depths) > 1 else (rec["step_um"] or 1.0) * summed
            vs = (dz, args.object_pixel_um * args.bin, args.object_pixel_um * args.bin)
        rec["object_pixel_um"] = args.object_pixel_um
        extra = {"what": "cm2cl prepared PSF stack", "kind": "psf", "scan": [str(s) for s in args.scan],
                 "voxel_space": io.OBJECT_SPACE if vs else None, "axis_pixel": rec["axis_pixel"], "record": rec}
        io.write_tiff(outset.staged("volume"), stack.astype(np.float32), voxel_size_um=vs, depths_um=depths,
                      extra=extra)
        outset.staged("record").write_text(json.dumps({"output": out.name, **rec}, indent=1))
        outset.publish()
    for w in rec.get("warnings", []):
        print(f"cm2cl: warning: {w}", file=sys.stderr)
    reg = next((s for s in rec["steps"] if s["step"] == "registration"), None)
    dark_step = rec["steps"][1]
    print(f"{out}: {stack.shape[0]} planes of {stack.shape[1]} x {stack.shape[2]}, depths {depths[0]:g} .. "
          f"{depths[-1]:g} um from {rec['steps'][0]['planes_kept']} of {rec['planes_in']} scan planes"
          + (f"; dark level {dark_step['level_median']:.4g}" if "level_median" in dark_step else "")
          + (f"; drift {reg['drift_px_per_mm'][0]:.3g}, {reg['drift_px_per_mm'][1]:.3g} px/mm (rows, columns) "
             f"registered out" if reg else "; not registered")
          + "".join(f"; {n}" for n in rec.get("notes", []))
          + (f"; voxel {vs[0]:g} x {vs[1]:g} x {vs[2]:g} um" if vs else "; no object-space scale (--object-pixel-um)")
          + f"; record: {outset.sidecars['record'].name}")
    return 0

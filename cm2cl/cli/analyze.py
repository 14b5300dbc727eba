"""``cm2cl analyze``: the paper's characterisation of a measured PSF stack and of a reconstruction, each
writing a table, a record and a figure into one output folder (published whole).

- ``cm2cl analyze pcc PSF.ome.tif -o OUT/``: axial PCC curves per view configuration (3x3, 2x3, 2x2, 1 for
  the CM2's array; the lenslets are found in the stack), registered by the cross-correlation peak, and each
  configuration's full width at PCC = 0.8 (paper Fig. 2A): ``pcc.csv``, ``pcc.png``, ``analysis.json``.
- ``cm2cl analyze particles VOL.ome.tif -o OUT/``: the particles of a reconstruction, each fitted with a 3D
  Gaussian, their lateral and axial FWHM in um, and the statistics over them (Fig. 2D, 3E):
  ``particles.csv``, ``particles.png``, ``analysis.json``.
- ``cm2cl analyze mtf PSF.ome.tif -o OUT/``: the 3D MTF of an axial PSF stack (Fig. 2B): its support above
  a floor, the lateral cutoff and bandwidth B_x, the axial bandwidth B_z at the cutoff, and the 3D SBP
  FOV x DOF x B_z B_x^2 / 2 from these measured bandwidths (Methods): ``mtf.csv`` (B_z along f_x),
  ``mtf.png`` (the f_x-f_z section, log scale), ``analysis.json``.
- ``cm2cl analyze depth-range VOL.ome.tif -o OUT/``: the reconstructed depth range (Fig. 5B): the particles'
  centres in each 800 x 800 um patch, max z - min z plus one particle's axial elongation, mean and standard
  deviation over the patches: ``depth_range.csv``, ``depth_range.png`` (the map), ``analysis.json``.
- ``cm2cl analyze pcc-map GRID.tif -o OUT/ --step-mm 0.2``: the lateral shift variance (Fig. 2C, S4C): a
  PSF per position of a lateral scan at one depth, each registered onto the on-axis one and compared by the
  PCC, over the whole sensor and over the central lenslet's focus; the foci each PSF holds give the regions
  (central 3x3, outer 2x3 / 3x2, corner 2x2): ``pcc_map.csv``, ``pcc_map.png`` (both maps with the regions'
  boundaries), ``analysis.json`` (mean PCC per region, the diameter where the central lenslet's PCC > 0.7).
- ``cm2cl analyze scattering VOL.ome.tif -o OUT/``: the sample's scattering length l_s from how the light of a
  reconstruction's emitters falls with depth (:mod:`cm2cl.analysis.attenuation`; the volume reconstructed with a
  clear-medium PSF, the emitters as bright at every depth): ``scattering.csv`` (each plane's emitters and
  median log flux beside the fitted line), ``scattering.png``, ``analysis.json``; the number to give
  ``--scattering-length-um``.
- ``cm2cl analyze sbr MEAS.tif -o OUT/``: the local signal-to-background ratio of a raw measurement on
  500 x 500 um patches (Fig. 5B), particle pixels found per patch (5 robust sigmas above its median):
  ``sbr.csv``, ``sbr.png`` (the map), ``analysis.json``."""

from __future__ import annotations

import csv
import json
import math

import numpy as np

from ..errors import InputError

__all__ = ["register", "command"]

RECORD = "analysis.json"


def register(sub):
    a = sub.add_parser("analyze", help="characterise a PSF stack (pcc, mtf), a lateral PSF scan (pcc-map), a reconstruction (particles, depth-range, scattering) or a raw "
                                       "frame (sbr)",
                       description=__doc__)
    kinds = a.add_subparsers(dest="kind", metavar="KIND", required=True)
    p = kinds.add_parser("pcc", help="axial PCC curves of a PSF stack per view configuration, widths at PCC 0.8")
    p.add_argument("psf", help="the PSF stack (OME-TIFF with its depths, or any (nz, My, Mx) TIFF)")
    p.add_argument("-o", "--output", required=True, help="output folder (made; replaced whole when it is a "
                                                          "previous analysis)")
    p.add_argument("--ref-z", type=float, default=None, metavar="UM",
                   help="depth of the reference plane (default: the sharpest plane)")
    p.add_argument("--level", type=float, default=0.8, help="PCC level of the widths (default 0.8, the paper's)")
    m = kinds.add_parser("pcc-map", help="lateral PCC map of a lateral PSF scan (Fig. 2C) and of its central "
                                         "lenslet's focus (Fig. S4C), by view region")
    m.add_argument("grid", help="the scan: a (ny, nx, My, Mx) TIFF, or (n, My, Mx) pages in row-major grid order "
                                "with --grid (read from disk as needed, not into memory)")
    m.add_argument("-o", "--output", required=True, help="output folder")
    m.add_argument("--grid", dest="grid_shape", default=None, metavar="NY,NX",
                   help="the scan's rows and columns of positions (default: the file's own 4D shape or record)")
    m.add_argument("--step-mm", default=None, metavar="S[,SX]",
                   help="the scan's step in mm (one value, or the y and x steps); positions are centred on the "
                        "grid's middle (default: the positions the file records, else grid indices)")
    m.add_argument("--ref", default=None, metavar="I,J",
                   help="grid row and column of the on-axis PSF (default: the position nearest 0, 0)")
    m.add_argument("--no-central", action="store_true", help="skip the central lenslet's map")
    t = kinds.add_parser("mtf", help="3D MTF of an axial PSF stack: lateral and axial bandwidths and the 3D SBP")
    t.add_argument("psf", help="the axial PSF stack (OME-TIFF with its depths and object-space voxel size)")
    t.add_argument("-o", "--output", required=True, help="output folder")
    t.add_argument("--floor", type=float, default=0.01,
                   help="the support is where the MTF exceeds this fraction of its zero-frequency value, or twice "
                        "the noise floor if higher (default 0.01)")
    c = t.add_mutually_exclusive_group()
    c.add_argument("--lateral-cutoff", type=float, default=None, metavar="PER_UM",
                   help="lateral cutoff frequency in cycles / um (default: measured from the MTF's support)")
    c.add_argument("--lateral-fwhm", type=float, default=None, metavar="UM",
                   help="a measured lateral resolution (FWHM, um): cutoff 1 / (2 FWHM), as the paper takes it")
    t.add_argument("--pixel-um", type=float, default=None,
                   help="object-space pixel of the stack in um (default: from its metadata)")
    t.add_argument("--fov-mm", default=None, metavar="H,W",
                   help="measured field of view for the SBP, mm (default: the stack's field in object space)")
    t.add_argument("--dof-mm", type=float, default=None,
                   help="measured depth of field for the SBP, mm (default: the stack's depth range)")
    q = kinds.add_parser("particles", help="3D Gaussian fits of the particles of a reconstruction: FWHM in um")
    q.add_argument("volume", help="a reconstruction (OME-TIFF with its voxel size)")
    q.add_argument("-o", "--output", required=True, help="output folder")
    q.add_argument("--threshold", type=float, default=0.2,
                   help="particles are local maxima above this fraction of the volume's maximum (default 0.2)")
    d = kinds.add_parser("depth-range", help="reconstructed depth range per lateral patch (Fig. 5B)")
    d.add_argument("volume", help="a reconstruction (OME-TIFF with its voxel size)")
    d.add_argument("-o", "--output", required=True, help="output folder")
    d.add_argument("--patch-um", type=float, default=800.0, help="patch side in um (default 800, the paper's)")
    d.add_argument("--elongation-um", type=float, default=None,
                   help="axial elongation of one particle added to each range (default: the median axial FWHM "
                        "of the fitted particles; the paper adds 372 um for its 25-um particles)")
    d.add_argument("--threshold", type=float, default=0.2,
                   help="particles are local maxima above this fraction of the volume's maximum (default 0.2)")
    d.add_argument("--min-particles", type=int, default=1, help="patches with fewer particles are left out "
                                                                 "(default 1)")
    r = kinds.add_parser("sbr", help="local signal-to-background ratio of a raw measurement, patch by patch (Fig. 5B)")
    r.add_argument("measurement", help="a raw measurement (TIFF; its pixel size in um for --patch-um)")
    r.add_argument("-o", "--output", required=True, help="output folder")
    g = r.add_mutually_exclusive_group()
    g.add_argument("--patch-um", type=float, default=500.0,
                   help="patch side in um (default 500, the paper's), in the file's pixel size (object space for "
                        "cm2cl's simulated measurements, which record it)")
    g.add_argument("--patch-px", type=int, default=None, help="patch side in pixels instead")
    r.add_argument("--sigmas", type=float, default=5.0,
                   help="particle pixels lie this many robust sigmas above their patch's median (default 5)")
    c = kinds.add_parser("scattering", help="the sample's scattering length from how a reconstruction's emitters' "
                                            "light falls with depth")
    c.add_argument("volume", help="a reconstruction made with a clear-medium PSF (OME-TIFF with its depths)")
    c.add_argument("-o", "--output", required=True, help="output folder")
    c.add_argument("--surface-um", type=float, default=None, help="depth of the sample's surface (default: the "
                                                                   "shallowest plane)")
    for s in (p, m, t, q, d, r, c):
        s.set_defaults(func=command)
    return a


def command(args) -> int:
    from .. import io
    from ..io.staging import StagedOutput

    src = {"pcc": "psf", "pcc-map": "grid", "mtf": "psf", "particles": "volume", "depth-range": "volume",
           "scattering": "volume", "sbr": "measurement"}[args.kind]
    data, meta = io.read_tiff(getattr(args, src), memmap=args.kind == "pcc-map")
    want = {"sbr": (2,), "pcc-map": (3, 4)}.get(args.kind, (3,))
    if data.ndim not in want:
        raise InputError(f"'{getattr(args, src)}': expected a {' or '.join(f'{n}D' for n in want)} "
                         f"{'image' if want == (2,) else 'stack'}, got shape {data.shape}")
    if args.kind == "pcc-map":
        grid, xs, ys, ref, unit = _lateral_grid(args, data, meta)
        with StagedOutput(args.output, RECORD, what="--output") as stage:
            _publish(stage, _pcc_map(args, grid, xs, ys, ref, unit))
        return 0
    if args.kind == "sbr":
        result = _sbr(args, data, meta)
    elif args.kind == "pcc":
        if not 0 < args.level < 1:
            raise InputError(f"--level: {args.level} is not between 0 and 1")
        result = _pcc(args, data, meta)
    elif args.kind == "mtf":
        result = _mtf(args, data, meta)
    elif args.kind == "scattering":
        result = _scattering(args, data, meta)
    else:
        if not 0 < args.threshold < 1:
            raise InputError(f"--threshold: {args.threshold} is not between 0 and 1")
        result = _particles(args, data, meta) if args.kind == "particles" else _depth_range(args, data, meta)
    with StagedOutput(args.output, RECORD, what="--output") as stage:
        _publish(stage, result)
    return 0


def _publish(stage, result: dict) -> None:
    """The table, the figure and the record (last) into the staged folder, swapped in; then the summary."""
    png = result.pop("png")
    say = result.pop("say")
    _write_csv(stage.dir / result["table"], result.pop("rows"), result.pop("columns"))
    result["figure"] = figure(png, stage.dir / result["figure"])
    stage.publish(RECORD, json.dumps(result, indent=2, default=_plain))
    print(say)


def _plain(v):
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating,)):
        return float(v)
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)


def _depths(meta, nz):
    d = meta.get("depths_um")
    if d is not None and len(d) == nz:
        return np.asarray(d, float), "um"
    vs = meta.get("voxel_size_um")
    if meta.get("unit") == "um" and vs and len(vs) == 3:
        return np.arange(nz) * float(vs[0]), "um"
    return np.arange(nz, dtype=float), "plane"


def _pcc(args, psf, meta) -> dict:
    from ..analysis.views import pcc_curves

    z, unit = _depths(meta, psf.shape[0])
    ref = None
    if args.ref_z is not None:
        if unit != "um":
            raise InputError("--ref-z: the PSF stack has no depths in um; its planes are indices")
        ref = int(np.argmin(np.abs(z - args.ref_z)))
    r = pcc_curves(psf, z, ref_index=ref, level=args.level)
    names = list(r["curves"])
    rows = [[float(z[k])] + [float(r["curves"][n][k]) for n in names] for k in range(z.size)]
    widths = r["widths_um"]
    say = f"{args.output}: PCC widths at {args.level:g} ({unit}, reference plane at {z[r['ref_index']]:g}): " + \
        ", ".join(f"{n} {'-' if widths[n] is None else f'{widths[n]:.1f}'}" for n in names)
    return {"what": "cm2cl analyze pcc", "psf": str(args.psf), "depth_unit": unit, "level": args.level,
            "reference_plane": r["ref_index"], "reference_depth": float(z[r["ref_index"]]),
            "widths": widths, "lenslets": r["lenslets"], "windows": r["windows"],
            "lenslet_centroids_px": r["grid"]["centroids"].tolist(), "table": "pcc.csv", "figure": "pcc.png",
            "columns": [f"z_{unit}"] + [f"pcc_{n}" for n in names], "rows": rows,
            "png": ("pcc", z, unit, r, args.level), "say": say}


def _numbers(text, flag, n, kind=float, repeat: bool = True):
    """``n`` comma-separated numbers of ``kind`` from an option's text (with ``repeat``, one value stands for
    all)."""
    try:
        v = [kind(t) for t in str(text).split(",")]
    except ValueError:
        v = []
    if repeat and len(v) == 1 and n > 1:
        v = v * n
    if len(v) != n or not all(math.isfinite(x) for x in v):
        raise InputError(f"{flag}: expected {n} comma-separated {'integers' if kind is int else 'numbers'}, got {text!r}")
    return v


class _Grid:
    """A lateral scan read as needed: ``grid[i, j]`` is the PSF at row i, column j (a copy in float64)."""

    def __init__(self, data, ny, nx):
        self.data = data
        self.shape = (ny, nx) + tuple(data.shape[-2:])

    def __getitem__(self, ij):
        i, j = ij
        if self.data.ndim == 4:
            return np.array(self.data[i, j], np.float64)
        return np.array(self.data[i * self.shape[1] + j], np.float64)


def _lateral_grid(args, data, meta):
    """The scan as a (ny, nx, My, Mx) grid, its x and y positions (mm or indices), the reference and the unit;
    every option checked before any PSF is read."""
    extra = meta.get("extra") or {}
    if args.grid_shape is not None:
        ny, nx = _numbers(args.grid_shape, "--grid", 2, int)
    elif data.ndim == 4:
        ny, nx = data.shape[:2]
    elif isinstance(extra.get("grid_shape"), list) and len(extra["grid_shape"]) == 2:
        ny, nx = (int(v) for v in extra["grid_shape"])
    else:
        raise InputError(f"'{args.grid}': a {data.shape[0]}-plane stack; give the scan's rows and columns with --grid NY,NX")
    if ny < 1 or nx < 1:
        raise InputError(f"--grid: {ny},{nx} must be positive")
    n = data.shape[0] * (data.shape[1] if data.ndim == 4 else 1)
    if ny * nx != n:
        raise InputError(f"--grid: {ny} x {nx} = {ny * nx} positions, but '{args.grid}' holds {n} PSFs")
    if ny * nx < 2:
        raise InputError(f"'{args.grid}': one PSF; a PCC map needs a scan of several positions")
    unit = "position"
    xs, ys = np.arange(nx, dtype=float) - (nx - 1) / 2, np.arange(ny, dtype=float) - (ny - 1) / 2
    if args.step_mm is not None:
        sy, sx = _numbers(args.step_mm, "--step-mm", 2)
        if sy <= 0 or sx <= 0:
            raise InputError(f"--step-mm: {args.step_mm} must be positive")
        xs, ys, unit = xs * sx, ys * sy, "mm"
    elif isinstance(extra.get("x_mm"), list) and isinstance(extra.get("y_mm"), list):
        try:
            xr, yr = np.asarray(extra["x_mm"], float), np.asarray(extra["y_mm"], float)
        except (TypeError, ValueError):
            raise InputError(f"'{args.grid}': its record's x_mm / y_mm are not numbers") from None
        if xr.shape != (nx,) or yr.shape != (ny,) or not (np.isfinite(xr).all() and np.isfinite(yr).all()):
            raise InputError(f"'{args.grid}': its record's x_mm / y_mm do not give {nx} and {ny} finite positions")
        xs, ys, unit = xr, yr, "mm"
    ref = None
    if args.ref is not None:
        ref = tuple(_numbers(args.ref, "--ref", 2, int))
        if not (0 <= ref[0] < ny and 0 <= ref[1] < nx):
            raise InputError(f"--ref: {args.ref} is outside the {ny} x {nx} grid")
    return _Grid(data, ny, nx), xs, ys, ref, unit


def _pcc_map(args, grid, xs, ys, ref, unit) -> dict:
    from ..analysis.lateral import CENTRAL_PCC_LEVEL, high_pcc_diameter_mm, lateral_pcc_map, region_summary

    r = lateral_pcc_map(grid, xs, ys, ref=ref, central=not args.no_central)
    ny, nx = r["pcc"].shape

    def num(v):
        return None if not np.isfinite(v) else float(v)

    cols = ["grid_row", "grid_col", f"y_{unit}", f"x_{unit}", "views", "region", "pcc", "pcc_central",
            "shift_y_px", "shift_x_px"]
    central = r["pcc_central"]
    rows = [[i, j, float(ys[i]), float(xs[j]), int(r["views"][i, j]), r["regions"][i, j], num(r["pcc"][i, j]),
             None if central is None else num(central[i, j]), int(r["shifts"][i, j, 0]), int(r["shifts"][i, j, 1])]
            for i in range(ny) for j in range(nx)]
    regions = region_summary(r)
    diameter = high_pcc_diameter_mm(r)
    R, C = r["array"]
    say = (f"{args.output}: lateral PCC over {ny} x {nx} positions ({R} x {C} foci on axis): " +
           ", ".join(f"{k} {v['pcc_mean']:.2f}" for k, v in regions.items() if v["pcc_mean"] is not None) +
           ("" if diameter is None else f"; central lenslet PCC > {CENTRAL_PCC_LEVEL:g} over a {diameter:.3g}-"
                                         f"{unit} diameter"))
    return {"what": "cm2cl analyze pcc-map", "grid": str(args.grid), "grid_shape": [ny, nx], "unit": unit,
            "reference": list(r["ref"]), "array": [R, C], "regions": regions,
            "central_window_px": r["window"], "central_pcc_level": CENTRAL_PCC_LEVEL,
            f"central_high_pcc_diameter_{unit}": diameter, "table": "pcc_map.csv", "figure": "pcc_map.png",
            "columns": cols, "rows": rows, "png": ("pcc-map", r, unit), "say": say}


def _positive(value, flag):
    if value is not None and not (math.isfinite(value) and value > 0):
        raise InputError(f"{flag}: must be a positive number, got {value:g}")
    return value


def _mtf(args, psf, meta) -> dict:
    from ..analysis.mtf import mtf_analysis

    for flag in ("floor", "lateral_cutoff", "lateral_fwhm", "pixel_um", "dof_mm"):
        _positive(getattr(args, flag), "--" + flag.replace("_", "-"))
    fov = None
    if args.fov_mm is not None:
        fov = tuple(_numbers(args.fov_mm, "--fov-mm", 2, repeat=False))
        if not all(v > 0 for v in fov):
            raise InputError(f"--fov-mm: expected two positive numbers H,W in mm, got {args.fov_mm!r}")
    z, unit = _depths(meta, psf.shape[0])
    if unit != "um":
        raise InputError(f"PSF stack '{args.psf}': no depths in um in its metadata; the MTF needs the plane spacing")
    dzs = np.diff(z)
    if dzs.size == 0 or np.any(dzs <= 0) or np.ptp(dzs) > 1e-3 * abs(float(np.mean(dzs))):
        raise InputError(f"PSF stack '{args.psf}': its depths are not evenly spaced; the 3D MTF needs even steps")
    px = args.pixel_um
    if px is None:
        vs, space = meta.get("voxel_size_um"), (meta.get("extra") or {}).get("voxel_space")
        if meta.get("unit") == "um" and vs and len(vs) == 3 and space != "sensor":
            px = float(vs[-1])
        else:
            raise InputError(f"PSF stack '{args.psf}': no object-space pixel size in its metadata; give --pixel-um")
    cutoff = args.lateral_cutoff if args.lateral_fwhm is None else 1.0 / (2.0 * args.lateral_fwhm)
    r = mtf_analysis(psf, float(np.mean(dzs)), px, px, floor=args.floor, lateral_cutoff_um=cutoff, fov_mm=fov,
                     dof_mm=args.dof_mm)
    say = (f"{args.output}: lateral cutoff {r['lateral_cutoff_per_um']:.4g} / um (B_x {r['lateral_bandwidth_per_um']:.4g}"
           f" / um), axial bandwidth at it B_z {r['axial_bandwidth_per_um']:.4g} / um, 3D SBP {r['sbp'] / 1e6:.3g} M "
           f"({r['fov_mm'][0]:.3g} x {r['fov_mm'][1]:.3g} mm x {r['dof_mm']:.3g} mm)")
    keys = ("floor", "lateral_cutoff_measured_per_um", "lateral_cutoff_per_um", "lateral_bandwidth_per_um",
            "axial_bandwidth_per_um", "bandwidth_per_um3", "sbp", "fov_mm", "dof_mm", "fov_given", "dof_given")
    return {"what": "cm2cl analyze mtf", "psf": str(args.psf), "pixel_um": px, "dz_um": float(np.mean(dzs)),
            "cutoff_from": "measured" if cutoff is None else ("--lateral-fwhm" if args.lateral_fwhm else
                                                              "--lateral-cutoff"),
            **{k: r[k] for k in keys}, "table": "mtf.csv", "figure": "mtf.png",
            "columns": ["fx_per_um", "axial_extent_per_um"], "rows": [list(p) for p in r["profile"]],
            "png": ("mtf", r), "say": say}


def _particle_rows(args, vol, meta):
    """The volume's voxel size (um, checked) and its particles (:func:`particle_table`), at least one."""
    from ..analysis.particles import particle_table

    vs = meta.get("voxel_size_um")
    if meta.get("unit") != "um" or not vs or len(vs) != 3:
        raise InputError(f"volume '{args.volume}': no voxel size in um in its metadata; the FWHM would be in voxels "
                         "(write the reconstruction with a PSF that has an object-space scale, or --voxel-size)")
    rows = particle_table(vol, vs, meta.get("depths_um"), threshold=args.threshold)
    if not rows:
        raise InputError(f"volume '{args.volume}': no particle above {args.threshold:g} of its maximum")
    return vs, rows


def _depth_range(args, vol, meta) -> dict:
    from ..analysis.particles import depth_range

    _positive(args.patch_um, "--patch-um")
    if args.elongation_um is not None and not (math.isfinite(args.elongation_um) and args.elongation_um >= 0):
        raise InputError(f"--elongation-um: must be a number >= 0, got {args.elongation_um:g}")
    if args.min_particles < 1:
        raise InputError(f"--min-particles: must be at least 1, got {args.min_particles}")
    vs = meta.get("voxel_size_um")
    field = (vol.shape[1] * float(vs[1]), vol.shape[2] * float(vs[2])) if vs and len(vs) == 3 else None
    if field is not None and args.patch_um > min(field):
        raise InputError(f"--patch-um: {args.patch_um:g} um is larger than the volume's field "
                         f"{field[0]:g} x {field[1]:g} um")
    vs, rows = _particle_rows(args, vol, meta)
    r = depth_range(rows, field, args.patch_um, args.elongation_um, args.min_particles)
    if not r["patches"]:
        raise InputError(f"volume '{args.volume}': no {args.patch_um:g}-um patch holds {args.min_particles} particle(s)")
    cols = ["patch_row", "patch_col", "y0_um", "x0_um", "particles", "z_min_um", "z_max_um", "range_um"]
    std = "-" if r["std_um"] is None else f"{r['std_um']:.0f}"
    say = (f"{args.output}: depth range {r['mean_um']:.0f} +- {std} um over {len(r['patches'])} of "
           f"{r['patches_total']} patches of {args.patch_um:g} um ({len(rows)} particles, elongation "
           f"{r['elongation_um']:.0f} um" + (": the fit's floor, the median particle one plane deep, a bound"
                                             if r["elongation_at_floor"] else "") + ")")
    return {"what": "cm2cl analyze depth-range", "volume": str(args.volume), "threshold": args.threshold,
            "voxel_size_um": list(vs), "particles": len(rows), **{k: v for k, v in r.items() if k != "patches"},
            "min_particles": args.min_particles, "table": "depth_range.csv", "figure": "depth_range.png",
            "columns": cols, "rows": [[p[c] for c in cols] for p in r["patches"]],
            "png": ("depth-range", r, vol.shape[1:], vs), "say": say}


def _particles(args, vol, meta) -> dict:
    from ..analysis.particles import FWHM_PER_SIGMA, SIGMA_MIN_VOX, summary

    vs, rows = _particle_rows(args, vol, meta)
    s = summary(rows)
    cols = ["z_um", "y_um", "x_um", "fwhm_lateral_um", "fwhm_axial_um", "amplitude", "rel_residual", "ok",
            "lateral_at_floor", "axial_at_floor"]
    a = s["all"]

    def med(k):
        return "-" if a[k] is None else f"{a[k]['median']:.1f} um"

    say = (f"{args.output}: {a['n']} particles, {a['n_fit']} fitted; median FWHM lateral {med('fwhm_lateral_um')}, "
           f"axial {med('fwhm_axial_um')}")
    floor = [f"{a[f'n_{axis}_at_floor']} {axis}" for axis in ("lateral", "axial") if a[f"n_{axis}_at_floor"]]
    if floor:   # a width at the fit's narrowest Gaussian is a particle in one voxel: a bound, not a measurement
        say += (f"; at the fit's floor ({FWHM_PER_SIGMA * SIGMA_MIN_VOX:.2f} voxel, the particle in one voxel: "
                f"a bound, not a width): {' and '.join(floor)} of {a['n_fit']}")
    return {"what": "cm2cl analyze particles", "volume": str(args.volume), "threshold": args.threshold,
            "voxel_size_um": list(vs), "summary": s, "table": "particles.csv", "figure": "particles.png",
            "columns": cols, "rows": [[r[c] for c in cols] for r in rows], "png": ("particles", rows), "say": say}


def _scattering(args, vol, meta) -> dict:
    from ..analysis.attenuation import estimate_scattering_length

    z, unit = _depths(meta, vol.shape[0])
    if unit != "um":
        raise InputError(f"volume '{args.volume}': no depths in um (a cm2cl reconstruction records them), so no "
                         "depth below the surface")
    if args.surface_um is not None and not math.isfinite(args.surface_um):
        raise InputError(f"--surface-um: must be a number, got {args.surface_um}")
    e = estimate_scattering_length(vol, z, args.surface_um)
    k = e["rate_per_um"]
    cols = ["plane", "depth_um", "emitters", "median_log_flux", "fitted_log_flux"]
    rows = []
    if e["per_plane"]:   # the fitted line through the planes' median
        mid = float(np.median([p["median_log_flux"] + k * (p["depth_um"] - e["surface_um"]) for p in e["per_plane"]]))
        rows = [[p["plane"], p["depth_um"], p["emitters"], p["median_log_flux"],
                 mid - k * (p["depth_um"] - e["surface_um"])] for p in e["per_plane"]]
    ls = e["scattering_length_um"]
    if ls is not None:
        lo, hi = (1.0 / v for v in e["rate_interval_per_um"][::-1])
        say = (f"{args.output}: scattering length {ls:.0f} um (95%: {lo:.0f}-{hi:.0f} um) from {e['emitters']} "
               f"emitters in {e['planes']} planes; their light falls {100 * e['fall_over_stack']:.0f}% over the stack")
    else:
        say = f"{args.output}: no scattering length: {e['reason']} ({e['emitters']} emitters)"
    # a cm2cl reconstruction records the attenuation it was solved with: then this is the decay left over
    solved = ((meta.get("extra") or {}).get("info") or {}).get("attenuation") or {}
    before = solved.get("scattering_length_um")
    if before:
        say += (f"; note: the volume was solved with a scattering length of {before:.0f} um already, so this is "
                "the fall left in it, not the sample's")
    return {"what": "cm2cl analyze scattering", "volume": str(args.volume), **e, "solved_with_scattering_length_um":
            before, "table": "scattering.csv",
            "figure": "scattering.png", "columns": cols, "rows": rows, "png": ("scattering", rows, e), "say": say}


def _sbr(args, img, meta) -> dict:
    from ..analysis.metrics import raw_sbr

    if args.sigmas <= 0:
        raise InputError(f"--sigmas: {args.sigmas} must be positive")
    if args.patch_px is not None:
        n, how, flag = int(args.patch_px), f"{args.patch_px} px", "--patch-px"
    else:
        _positive(args.patch_um, "--patch-um")
        flag = "--patch-um"
        extra = meta.get("extra") or {}
        px = extra.get("object_pixel_um") or ((meta.get("voxel_size_um") or [None])[-1]
                                              if meta.get("unit") == "um" else None)
        if not px:
            raise InputError(f"measurement '{args.measurement}': no pixel size in um in its metadata; give "
                             "--patch-px")
        n, how = int(round(args.patch_um / float(px))), f"{args.patch_um:g} um ({px:g} um pixels)"
    if n < 2 or n > min(img.shape):
        raise InputError(f"{flag}: a patch of {how} is {n} px; it must be 2 px to the image's {min(img.shape)} px")
    img = np.asarray(img, np.float64)
    sbr_map, mean, mask = raw_sbr(img, n, args.sigmas)
    rows = [[i, j, i * n, j * n, None if not np.isfinite(v) else float(v)]
            for i in range(sbr_map.shape[0]) for j in range(sbr_map.shape[1]) for v in [sbr_map[i, j]]]
    finite = sbr_map[np.isfinite(sbr_map)]
    say = (f"{args.output}: local SBR over {finite.size} of {sbr_map.size} patches of {how}: mean "
           f"{mean:.3f}" + (f", {finite.min():.3f} .. {finite.max():.3f}" if finite.size else ""))
    return {"what": "cm2cl analyze sbr", "measurement": str(args.measurement), "patch_px": n, "patch": how,
            "sigmas": args.sigmas, "mean_sbr": None if not np.isfinite(mean) else mean,
            "particle_fraction": float(mask.mean()), "table": "sbr.csv", "figure": "sbr.png",
            "columns": ["patch_row", "patch_col", "y0_px", "x0_px", "sbr"], "rows": rows,
            "png": ("sbr", sbr_map, n), "say": say}


def _write_csv(path, rows, columns):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        w.writerows(rows)


def _draw_pcc_map(fig, r, unit):
    """The lateral PCC maps (whole array, central lenslet) with the view regions' boundaries."""
    xs, ys = r["x_mm"], r["y_mm"]
    dx = float(np.mean(np.diff(xs))) if xs.size > 1 else 1.0
    dy = float(np.mean(np.diff(ys))) if ys.size > 1 else 1.0
    ext = (xs[0] - dx / 2, xs[-1] + dx / 2, ys[-1] + dy / 2, ys[0] - dy / 2)
    maps = [("PCC with the on-axis PSF", r["pcc"])]
    if r["pcc_central"] is not None:
        maps.append(("central lenslet only", r["pcc_central"]))
    for k, (title, v) in enumerate(maps):
        ax = fig.add_subplot(1, len(maps), k + 1)
        im = ax.imshow(v, cmap="viridis", vmin=0, vmax=1, extent=ext)
        if xs.size > 1 and ys.size > 1 and np.unique(r["views"]).size > 1:
            f = 8      # the regions' boundaries run between positions: contour a finely repeated map
            fx = xs[0] - dx / 2 + (np.arange(xs.size * f) + 0.5) * dx / f
            fy = ys[0] - dy / 2 + (np.arange(ys.size * f) + 0.5) * dy / f
            ax.contour(fx, fy, np.repeat(np.repeat(r["views"].astype(float), f, 0), f, 1),
                       levels=np.unique(r["views"])[:-1] + 0.5, colors="w", linewidths=0.8)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(f"x ({unit})")
        ax.set_ylabel(f"y ({unit})")
        fig.colorbar(im, ax=ax, shrink=0.8, label="PCC (white: view-region boundaries)" if k == len(maps) - 1
                     else None)


def _draw_scattering(fig, rows, e):
    """Each plane's median log flux against depth (marker size: its emitters) and the fitted line."""
    ax = fig.add_subplot(1, 1, 1)
    if rows:
        r = np.asarray([row[1:] for row in rows], float)
        ax.scatter(r[:, 0], r[:, 2], s=10 + 2 * r[:, 1], label="median per plane (size: emitters)")
        ax.plot(r[:, 0], r[:, 3], "k-", lw=1, label="fit" + (f": l_s {e['scattering_length_um']:.0f} um"
                                                             if e["scattering_length_um"] else " (not applied)"))
        ax.legend()
    ax.set_xlabel("depth (um)")
    ax.set_ylabel("log flux of an emitter")
    if e["reason"]:
        ax.set_title(e["reason"], fontsize=8)


def figure(spec, path):
    """The PNG of the analysis, or None (with why in the record) without matplotlib."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return None
    fig = Figure(figsize=(6.4, 4.0), dpi=120)
    FigureCanvasAgg(fig)
    if spec[0] == "pcc":
        _, z, unit, r, level = spec
        ax = fig.add_subplot(1, 1, 1)
        for n, c in r["curves"].items():
            w = r["widths_um"][n]
            ax.plot(z, c, label=f"{n} ({'-' if w is None else f'{w:.0f}'} {unit})")
        ax.axhline(level, color="0.5", lw=0.8, ls="--")
        ax.set_xlabel(f"depth ({unit})")
        ax.set_ylabel("PCC with the reference plane")
        ax.set_ylim(min(0.0, min(float(np.min(c)) for c in r["curves"].values())), 1.02)
        ax.legend(title=f"width at PCC {level:g}")
    elif spec[0] == "pcc-map":
        _draw_pcc_map(fig, *spec[1:])
    elif spec[0] == "mtf":
        r = spec[1]
        m = r["mtf"]
        sec = m["mtf"][:, m["mtf"].shape[1] // 2, :]
        ax = fig.add_subplot(1, 1, 1)
        ext = (m["fx"][0], m["fx"][-1], m["fz"][0], m["fz"][-1])
        im = ax.imshow(np.log10(np.maximum(sec, 1e-6)), origin="lower", extent=ext, aspect="auto", cmap="magma",
                       vmin=-4, vmax=0)
        ax.contour(m["fx"], m["fz"], sec, levels=[r["floor"]["used"]], colors="c", linewidths=0.8)
        fc = r["lateral_cutoff_per_um"]
        for s in (-fc, fc):
            ax.axvline(s, color="w", lw=0.8, ls="--")
        ax.set_xlabel("f_x (1/um)")
        ax.set_ylabel("f_z (1/um)")
        ax.set_title(f"B_x {r['lateral_bandwidth_per_um']:.3g} / um, B_z {r['axial_bandwidth_per_um']:.3g} / um at f_c")
        fig.colorbar(im, ax=ax, label="log10 MTF (support: cyan)")
    elif spec[0] == "depth-range":
        _, r, (ny, nx), vs = spec
        n = r["patch_um"]
        grid = np.full((int(ny * vs[1] // n), int(nx * vs[2] // n)), np.nan)
        for p in r["patches"]:
            grid[p["patch_row"], p["patch_col"]] = p["range_um"]
        ax = fig.add_subplot(1, 1, 1)
        im = ax.imshow(grid, cmap="viridis", extent=(0, grid.shape[1] * n / 1000, grid.shape[0] * n / 1000, 0))
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        fig.colorbar(im, ax=ax, label=f"depth range (um, {n:g}-um patches)")
    elif spec[0] == "scattering":
        _draw_scattering(fig, *spec[1:])
    elif spec[0] == "sbr":
        _, m, n = spec
        ax = fig.add_subplot(1, 1, 1)
        im = ax.imshow(m, cmap="viridis", extent=(0, m.shape[1] * n, m.shape[0] * n, 0))
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
        fig.colorbar(im, ax=ax, label=f"local SBR ({n} px patches)")
    else:
        rows = [r for r in spec[1] if r["ok"]]
        for k, (key, lab) in enumerate((("fwhm_lateral_um", "lateral FWHM (um)"), ("fwhm_axial_um", "axial FWHM (um)"))):
            ax = fig.add_subplot(1, 2, k + 1)
            v = [r[key] for r in rows]
            if v:
                ax.hist(v, bins=max(5, int(math.sqrt(len(v))) + 1))
                ax.axvline(float(np.median(v)), color="k", lw=1)
            ax.set_xlabel(lab)
            ax.set_ylabel("particles")
    fig.tight_layout()
    fig.savefig(path)
    return path.name

"""``cm2cl prepare-psf SCAN --z-start UM --z-step UM -o PSF.ome.tif``: a raw calibration scan (a multi-page
TIFF, a folder or a glob of planes, 8/12/16-bit or float) to the PSF stack ``cm2cl reconstruct`` takes,
with its object-space voxel size and depths, and the record of every step (``PSF.cm2cl.json``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError


def register(sub):
    r = sub.add_parser("prepare-psf", help="a raw PSF calibration scan to a prepared PSF stack", description=__doc__)
    r.add_argument("scan", nargs="+", help="the scan's planes: a multi-page TIFF, folders, globs (in z order)")
    r.add_argument("-o", "--output", required=True, help="the prepared stack (OME-TIFF, *.ome.tif)")
    r.add_argument("--z-start", type=float, required=True, help="z of the first plane (um)")
    r.add_argument("--z-step", type=float, required=True, help="z step between planes (um, e.g. 10)")
    r.add_argument("--dark", default="corners",
                   help="'corners' (median of each plane's 20 x 20 corners), a number, a dark-frame TIFF, or 'none'")
    r.add_argument("--z-range", type=float, nargs=2, metavar=("ZMIN", "ZMAX"), default=None,
                   help="keep the planes in this depth range (um)")
    r.add_argument("--axial-bin", type=int, default=1, help="sum groups of this many planes")
    r.add_argument("--bin", type=int, default=1, help="lateral binning to the working pixel")
    r.add_argument("--noise-floor", type=float, default=3.0, help="zero values under this many noise sigmas")
    r.add_argument("--no-register", action="store_true", help="do not register the planes laterally")
    r.add_argument("--object-pixel-um", type=float, default=None,
                   help="object-space size of one raw scan pixel (sensor pixel / magnification, um); labels the "
                        "stack so reconstructions carry a physical scale")
    r.set_defaults(func=command)


def command(args) -> int:
    from .. import io
    from ..io.calibration import prepare_psf_stack
    from ..io.publish import OutputSet
    from ..jobs import FrameSeries

    out = Path(args.output)
    if out.suffix.lower() not in (".tif", ".tiff"):
        raise InputError(f"--output '{out}': must end in .ome.tif, .tif or .tiff")
    if not (np.isfinite(args.z_step) and args.z_step != 0 and np.isfinite(args.z_start)):
        raise InputError(f"--z-step: must be a finite non-zero number, got {args.z_step}")
    if args.object_pixel_um is not None and not (np.isfinite(args.object_pixel_um) and args.object_pixel_um > 0):
        raise InputError(f"--object-pixel-um: must be a positive number, got {args.object_pixel_um}")
    series = FrameSeries(args.scan)                        # plane shapes from the headers, checked first
    with OutputSet(out, expected_bytes=8 * len(series) * int(np.prod(series.shape)),
                   inputs=tuple(f.path for f in series.frames)) as outset:
        if args.dark == "corners":
            dark = "corners"
        elif args.dark == "none":
            dark = None
        else:
            try:
                dark = float(args.dark)
            except ValueError:
                dark, _ = io.read_tiff(args.dark)
        scan = np.stack([series.read(i) for i in range(len(series))])
        z = args.z_start + args.z_step * np.arange(len(series))
        stack, depths, rec = prepare_psf_stack(scan, z, dark=dark, register=not args.no_register,
                                               z_range=args.z_range, axial_bin=args.axial_bin,
                                               lateral_bin=args.bin, noise_floor=args.noise_floor,
                                               name=f"scan '{args.scan[0]}'")
        vs = None
        if args.object_pixel_um:
            dz = abs(args.z_step) * args.axial_bin
            vs = (dz, args.object_pixel_um * args.bin, args.object_pixel_um * args.bin)
        extra = {"what": "cm2cl prepared PSF stack", "scan": [str(s) for s in args.scan], "record": rec,
                 "voxel_space": io.OBJECT_SPACE if vs else None}
        io.write_tiff(outset.staged("volume"), stack.astype(np.float32), voxel_size_um=vs, depths_um=depths,
                      extra=extra)
        outset.staged("record").write_text(json.dumps({"output": out.name, **rec}, indent=1))
        outset.publish()
    reg = next((s for s in rec["steps"] if s["step"] == "registration"), None)
    print(f"{out}: {stack.shape[0]} planes of {stack.shape[1]} x {stack.shape[2]}, depths {depths[0]:g} .. "
          f"{depths[-1]:g} um" + (f"; drift {reg['drift_px_per_mm'][0]:.3g}, {reg['drift_px_per_mm'][1]:.3g} px/mm "
                                  "(y, x) registered out" if reg else "")
          + ("; WARNING: " + "; ".join(rec["warnings"]) if rec.get("warnings") else "")
          + f"; record: {outset.sidecars['record'].name}")
    return 0

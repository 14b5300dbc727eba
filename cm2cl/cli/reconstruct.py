"""``cm2cl reconstruct MEAS.tif --psf PSF.ome.tif -o OUT.ome.tif``: one frame, with a progress bar and
the iteration log written next to the output (OUT.cm2cl.log.csv and the record OUT.cm2cl.json); with
``-o OUT.ome.zarr`` a series of frames, resumable.

The volume is OME-TIFF in the dtype of the solve (float32, or float64 with ``--dtype float64``). Its
physical scale comes from the PSF stack when the PSF says its voxel size is object-space (the
simulator's psf.ome.tif does), times ``--bin`` laterally, or from ``--voxel-size DZ DY DX``; without
either the volume is labelled in pixels (a PSF measured on a camera gives no object-space scale).
Depths come from the PSF's plane positions (OME ``Plane PositionZ``) when it has them."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import InputError
from . import options
from .inputs import solver_params
from .progress import Progress  # noqa: F401 - where callers found it

_size = options.size   # tools/bench_schedule.py parses sizes with it

EPILOG = """examples:
  one frame, weights from the noise level:
    cm2cl reconstruct meas.tif --psf psf.ome.tif -o vol.ome.tif --offset auto
  point-like sample, quicker and coarser, the plan first:
    cm2cl reconstruct meas.tif --psf psf.ome.tif -o vol.ome.tif --prior points --preset fast --dry-run
  a large problem: 2x binned, at most 4 GiB per device, planes over two devices:
    cm2cl reconstruct meas.tif --psf psf.ome.tif -o vol.ome.tif --bin 2 --max-memory 4G --device 0,1
  a series into one OME-Zarr store, each frame starting from the previous one (rerun to resume):
    cm2cl reconstruct 'frames/*.tif' --psf psf.ome.tif -o series.ome.zarr --warm-start
  a series on a Dask cluster:
    cm2cl reconstruct frames/ --psf psf.ome.tif -o series.ome.zarr --scheduler tcp://host:8786"""

#: options of a series only: (option, whether it was given)
_SERIES_ONLY = (("--scheduler", lambda a: a.scheduler), ("--warm-start", lambda a: a.warm_start),
                ("--frame-interval", lambda a: a.frame_interval is not None), ("--pyramid", lambda a: a.pyramid != 1),
                ("--ngff", lambda a: a.ngff != "0.4"))
#: options of a single frame that a series does not honour yet: (option, whether it was given); a series
#: refuses them before any work rather than running without them
_FRAME_ONLY = (("--dry-run", lambda a: a.dry_run), ("--mask", lambda a: a.mask),
               ("--saturation", lambda a: a.saturation is not None), ("--tile", lambda a: a.tile),
               ("--halo", lambda a: a.halo is not None), ("--padded", lambda a: a.padded),
               ("--save-background", lambda a: a.save_background), ("--host-memory", lambda a: a.host_memory),
               ("--camera", lambda a: a.camera not in (None, "none")),
               ("--background opening:R", lambda a: a.background not in (None, "model", "none")),
               ("--emission-nm", lambda a: a.emission_nm))


def register(sub):
    r = sub.add_parser("reconstruct", help="reconstruct a 3D volume from one CM2 measurement, or a series",
                       description=__doc__, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    options.add_inputs(r)
    options.add_solver(r)
    options.add_memory(r)
    options.add_series(r)
    options.add_output(r)
    r.set_defaults(func=command)


def command(args) -> int:
    """One frame, its tiles, its plan (--dry-run) or a series (an OME-Zarr output), after the checks
    that need no input read."""
    if args.lean == "always" and args.stream == "always":   # before any work, series too
        raise InputError("--lean always and --stream always: the lean layout keeps every plane on the device, "
                         "streaming keeps them in host memory; ask for one of them")
    params = solver_params(args)
    if Path(args.output).suffix.lower() == ".zarr":
        from . import series

        if args.background not in (None, "model", "none"):   # its syntax first: 'garbage' is not an opening
            from ..io.background import check_background_spec

            check_background_spec(args.background)
        for flag, given in _FRAME_ONLY:
            if given(args):
                raise InputError(f"{flag}: not for a series (.ome.zarr output) yet; reconstruct the frames one by "
                                 "one (-o FRAME.ome.tif) to use it")

        return series.command(args, params)
    if len(args.measurement) != 1:
        raise InputError(f"measurement: {len(args.measurement)} inputs given; a series needs an OME-Zarr output "
                         "(-o OUT.ome.zarr)")
    for flag, given in _SERIES_ONLY:
        if given(args):
            raise InputError(f"{flag}: only for a series written to an OME-Zarr output (-o OUT.ome.zarr)")
    args.measurement = args.measurement[0]
    from . import frame, plan

    frame.check_options(args)
    if args.dry_run:
        return plan.dry_run(args, params)
    return frame.command(args, params)

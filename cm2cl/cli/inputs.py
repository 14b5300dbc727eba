"""Input preparation shared by ``cm2cl reconstruct``'s frame and series jobs: the devices, the solver's
parameters and layout options, the camera offsets, binning, the PSF stack on the working grid and the
volume's physical scale, all from the parsed options and checked before any long work."""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..solver.params import ADMMParams, layered, parameters

#: --stream / --lean to the solver's 'auto' / True / False
STREAM = {"auto": "auto", "always": True, "never": False}



def single_frame_shape(shape) -> tuple:
    """A measurement's shape with leading axes of length 1 dropped (a 5-D TIFF of one frame, TCZYX = 1, 1,
    1, My, Mx, is one 2D image, as a series reads it)."""
    shape = tuple(int(n) for n in shape)
    while len(shape) > 2 and shape[0] == 1:
        shape = shape[1:]
    return shape

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
    if not parts:
        raise InputError(f"--device {text!r}: names no device (give an index, a name fragment or 'all'; see cm2cl devices)")
    out = [int(p) if p.isdigit() else p for p in parts]
    if len(set(map(str, out))) != len(out):
        raise InputError(f"--device '{text}': a device is listed twice")
    return out


def solver_params(args) -> ADMMParams:
    """The parameters: --prior, then --preset, then the options given (--background 'opening:R' is the
    paper's pre-step instead of the background in the model)."""
    given = {p.name: getattr(args, p.name) for p in parameters() if p.flag}
    bg = getattr(args, "background", None)
    if bg is not None:
        given["background"] = bg if bg in ("model", "none") else "none"
    return layered(args.prior, args.preset, **given)


def layout_options(args) -> dict:
    """The solver's memory layout options (device memory cap, streaming, lean state)."""
    return {"max_memory": args.max_memory, "stream": STREAM[args.stream], "lean": STREAM[args.lean]}


def parse_offset(text: str, option: str = "--offset"):
    """An offset option: None ('none'), 'auto' or a finite number >= 0 (a dark level in ADU)."""
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
    if value < 0:   # subtracting it would add light to every pixel: a sign slip, not a camera's black level
        raise InputError(f"{option}: a dark level is >= 0 ADU, got {text!r}")
    return value


def offsets(args):
    """(measurement offset, PSF offset) from --offset and --psf-offset."""
    return parse_offset(args.offset), parse_offset(args.psf_offset, "--psf-offset")


def check_bin(bin_factor: int, shape=None, what: str = "measurement") -> None:
    """--bin is a whole number >= 1 and, given the measurement's ``shape``, no larger than it."""
    if bin_factor < 1:
        raise InputError(f"--bin: must be an integer >= 1, got {bin_factor}")
    if shape is not None and min(shape) < bin_factor:
        raise InputError(f"{what}: shape {tuple(shape)} is smaller than the bin factor {bin_factor}")


def check_psf_shape(shape, path) -> None:
    if len(shape) not in (2, 3):
        raise InputError(f"psf '{path}': expected a (nz, My, Mx) stack, got shape {tuple(shape)}")


def read_psf(args):
    """(psf, metadata) of --psf, a (nz, My, Mx) or (My, Mx) numeric, finite stack."""
    from .. import io
    from ..io.prepare import check_image

    psf, pmeta = io.read_tiff(args.psf)
    check_psf_shape(psf.shape, args.psf)
    check_image(psf, f"psf '{args.psf}'")
    return psf, pmeta


@dataclass(frozen=True)
class WorkingPSF:
    """The PSF stack on the working grid and the volume's physical scale."""
    h: np.ndarray               #: (nz, My, Mx) float64: offset removed, fitted to the sensor, binned
    note: str | None            #: how it was fitted to the sensor (said on stderr)
    voxel_size_um: tuple | None
    depths_um: object
    scale: str                  #: where the scale comes from, for the summary


def working_psf(args, psf, pmeta, sensor, psf_offset) -> WorkingPSF:
    """The PSF of ``psf`` (as read, with its metadata) for a measurement of ``sensor`` (unbinned) pixels."""
    psf_bin = psf_binning(args, psf.shape, sensor)
    vs, depths, how = volume_geometry(args, pmeta, psf_bin)
    h, note = psf_on_working_grid(args, psf, psf_offset, psf_bin, sensor, pmeta["extra"].get("axis_pixel"))
    if depths is not None and len(depths) != h.shape[0]:
        raise InputError(f"psf '{args.psf}': {len(depths)} plane positions for {h.shape[0]} planes")
    return WorkingPSF(h, note, vs, depths, how)


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


def volume_geometry(args, pmeta, bin_factor: int):
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

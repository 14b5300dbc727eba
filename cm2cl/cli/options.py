"""The option groups of ``cm2cl reconstruct``, by what a user does (inputs, solver, memory and devices,
series, output), shared by its frame, tile, series and dry-run modes. The solver's options are made from
the parameters' declaration (:mod:`cm2cl.solver.params`); library errors name parameters, which
:func:`with_flags` turns into the options a user typed."""

from __future__ import annotations

import argparse
import re

import numpy as np

from ..solver.params import PRESETS, PRIORS, parameters

_TYPES = {"float": float, "int": int, "str": str}


def _with_words(convert, words):
    """A converter that takes ``words`` as themselves (e.g. --psf-refine auto), else ``convert``."""
    def parse(text: str):
        t = str(text).strip().lower()
        return t if t in words else convert(text)
    parse.__name__ = convert.__name__   # argparse names the type in its error message
    return parse


def size(text: str) -> int:
    """A byte count: a number with an optional binary unit K, M, G or T (4G = 4 * 2**30)."""
    t = str(text).strip().upper().removesuffix("B").removesuffix("I")
    mult = {"K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}.get(t[-1:], 1)
    try:
        value = float(t[:-1] if mult > 1 else t) * mult
    except ValueError:
        value = float("nan")
    if not np.isfinite(value) or value < 1:   # (0.5 would round to 0 bytes, which reads as "no limit")
        raise argparse.ArgumentTypeError(f"expected a size of at least 1 byte such as 4G, 512M or 1000000, got {text!r}")
    return int(value)


def add_inputs(r) -> None:
    g = r.add_argument_group("inputs")
    g.add_argument("measurement", nargs="+",
                   help="2D TIFF of the measurement; or, with an OME-Zarr output (-o OUT.ome.zarr), the frames of a "
                        "series: multi-page TIFFs, folders of TIFFs, globs (quoted)")
    g.add_argument("--psf", required=True, help="3D TIFF of the PSF stack (nz, My, Mx), same sensor grid")
    g.add_argument("--offset", default="none",
                   help="camera offset (dark level) of the measurement to subtract: 'none', 'auto' (mean of "
                        "pixels [5:15, 5:15]) or a number")
    g.add_argument("--camera", default=None,
                   help="the camera's noise model, for a data term that weighs each pixel by the inverse of its "
                        "photon and read-noise variance: 'gain=G,read-noise=R' (ADU per photoelectron, electrons "
                        "rms; ',offset=O' gives the dark level in ADU instead of --offset) or 'auto' (fitted to "
                        "the frame's mean-variance relation); default: every pixel weighs the same")
    g.add_argument("--psf-offset", default="none",
                   help="offset of the PSF stack, separately (a calibration has its own dark level): 'none', "
                        "'auto' or a number")
    g.add_argument("--bin", type=int, default=1, help="bin measurement and PSF laterally by this factor")
    g.add_argument("--mask", default=None,
                   help="comma-separated pixels to leave out of the data term: 'saturated' (at the bit depth's "
                        "maximum, or --saturation), 'hot' (isolated outliers); they are always counted and reported")
    g.add_argument("--saturation", type=float, default=None,
                   help="saturation level of the measurement (default: the integer dtype's maximum)")
    g.add_argument("--background", default="model",
                   help="the slowly varying background: 'model' (default: y = C H x + b, b smooth and >= 0, "
                        "estimated with the volume), 'none', or removed before the solve as in the paper (Fig. "
                        "5A): 'opening:RADIUS_UM' or 'opening:RADIUSpx', a grey opening with a disk larger than "
                        "the targets, on the device")


def add_solver(r) -> None:
    g = r.add_argument_group("solver")
    g.add_argument("--prior", choices=list(PRIORS), default="default",
                   help="what the sample looks like: 'default' (l1 at the universal threshold of the noise, each "
                        "plane's weight ~ (||h_i|| sum h_i)^(1/2), TV off: best for beads and fibres alike on "
                        "docs/quality.md's suite); 'points': each plane's l1 ~ its light (alike for planes of equal "
                        "light), TV off; 'points-weighted': each plane's l1 weight ~ ||h_i||^2 / sum h_i; 'extended': "
                        "TV at 5 x the noise level too, and the PSF refined by one kernel common to every lenslet "
                        "(--psf-refine common), for smooth extended structure. --l1/--tv/--psf-refine win")
    tuned = sorted({k for o in PRESETS.values() for k in o})
    g.add_argument("--preset", choices=list(PRESETS), default=None,
                   help="accuracy against time, measured in docs/accuracy_vs_time.md: " + "; ".join(
                       f"{k}: {', '.join(f'{n}={v:g}' for n, v in o.items()) or 'the defaults'}"
                       for k, o in PRESETS.items()) + ". Explicit " + "/".join(_flag(n) for n in tuned) + " win")
    add_parameters(g)
    g.add_argument("--dtype", choices=["float32", "float64"], default="float32",
                   help="precision of the solve and the volume (float64 on devices with fp64 only)")
    g.add_argument("--padding", choices=["full", "support"], default="full",
                   help="padded grid: 'full' = 2M - 1; 'support' = M + K - 1 with K the PSF stack's measured "
                        "support (fewer voxels for a compact PSF; its faint tails beyond 1e-6 of the light are "
                        "dropped)")
    g.add_argument("--backend", default="auto", help="FFT backend: auto, cl, vkfft, reikna")


def add_parameters(g) -> None:
    """One option per declared parameter that has a flag; its default is None (not given), so that a
    --prior and a --preset can fill what the user did not give."""
    flags = {p.name: p.flag for p in parameters() if p.flag}
    for p in parameters():
        if not p.flag:
            continue
        if p.spec["type"] == "bool":   # a switch to the other value
            g.add_argument(p.flag, dest=p.name, action="store_const", const=not p.default, default=None,
                           help=_escape(p.flag_help or p.help))
            continue
        text = re.sub(r"\b(" + "|".join(n for n in flags if n != p.name) + r")\b", lambda m: flags[m[1]], p.help)
        shown = p.auto or (p.default if isinstance(p.default, str) else f"{p.default:g}")
        convert = _TYPES[p.spec["type"]]
        words = p.spec.get("words")
        g.add_argument(p.flag, dest=p.name, type=_with_words(convert, words) if words else convert, default=None,
                       choices=p.spec.get("choices"), help=_escape(f"{text.rstrip('.')} (default: {shown})"))


def add_memory(r) -> None:
    g = r.add_argument_group("memory and devices")
    g.add_argument("--device", default=None,
                   help="device index or name fragment (see cm2cl devices), or 'all' / '0,2': a single frame "
                        "spreads its depth planes over those devices, a series runs one worker per device")
    g.add_argument("--max-memory", type=size, default=None, metavar="SIZE",
                   help="device memory each device may use, e.g. 4G or 512M (default 90%% of its memory); "
                        "planes that do not fit are streamed in slabs from host memory")
    g.add_argument("--host-memory", type=size, default=None, metavar="SIZE",
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


def add_series(r) -> None:
    g = r.add_argument_group("series (an OME-Zarr output)")
    g.add_argument("--warm-start", action="store_true",
                   help="start frame t from frame t - 1's volume (frames in order, one device)")
    g.add_argument("--scheduler", default=None,
                   help="run the frames on this Dask distributed scheduler (tcp://host:port) instead of the local "
                        "devices; pin each worker to a device with CM2CL_DEVICE")
    g.add_argument("--pyramid", type=int, default=1, metavar="LEVELS",
                   help="resolution levels of the store (default 1; e.g. 3: also 2x and 4x coarser laterally, "
                        "for viewers of large frames)")
    g.add_argument("--ngff", choices=("0.4", "0.5"), default="0.4",
                   help="OME-Zarr version of the store: 0.4 (Zarr format 2, default, what most readers read) or "
                        "0.5 (Zarr format 3)")
    g.add_argument("--frame-interval", type=_positive, default=None, metavar="SECONDS",
                   help="time between frames: the store's t axis in seconds (default: in frames)")


def _number(positive: bool, what: str):
    """An argparse type: a finite number, > 0 (``positive``) or >= 0, else one line saying it is not ``what``."""
    import argparse
    import math

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            v = float("nan")
        if not math.isfinite(v) or v < 0 or (positive and v == 0):
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}")
        return v
    return parse


_seconds = _number(False, "a number of seconds >= 0")
_positive = _number(True, "a positive number")


def add_output(r) -> None:
    g = r.add_argument_group("output")
    g.add_argument("-o", "--output", required=True,
                   help="output OME-TIFF of the volume (name it *.ome.tif so that Fiji opens it with Bio-Formats), "
                        "or OME-Zarr store (*.ome.zarr) of a series")
    g.add_argument("--padded", action="store_true",
                   help="write the whole padded grid (emitters outside the field of view) instead of the FOV")
    g.add_argument("--voxel-size", type=float, nargs=3, metavar=("DZ", "DY", "DX"), default=None,
                   help="object-space voxel size in um of the PSF stack's grid (before --bin); overrides the "
                        "PSF's own; without it and without an object-space PSF the volume is in pixels")
    g.add_argument("--save-background", action="store_true",
                   help="also write the background (the model's b, or the one removed) next to the output "
                        "(OUT.background.ome.tif)")
    g.add_argument("--save-psf", action="store_true",
                   help="with --psf-refine: also write the self-calibrated PSF stack the final solve used, on the "
                        "working grid (after --bin), next to the output (OUT.psf.ome.tif); give it as --psf of a "
                        "series of the same sample. A series with --psf-refine refines on its first frame and "
                        "always keeps that stack as OUT.psf.ome.tif (a resumed job reads it back)")
    g.add_argument("--dry-run", action="store_true",
                   help="print the plan (grid, device and host memory, whether it fits) from the TIFF headers, "
                        "solve and write nothing")
    g.add_argument("--channel", default="fluorescence", metavar="NAME",
                   help="the channel's name in the OME metadata (default 'fluorescence'; e.g. GCaMP, GFP)")
    g.add_argument("--emission-nm", type=_positive, default=None, metavar="NM",
                   help="the channel's emission wavelength in nm, written to the OME metadata")
    g.add_argument("--progress-every", type=_seconds, default=30.0, metavar="SECONDS",
                   help="when stderr is not a terminal (batch logs, pipes): a progress line every SECONDS "
                        "(iteration or frame, objective, time left; default 30, 0: none)")
    g.add_argument("--quiet", action="store_true",
                   help="no progress bar (there is none either when stderr is not a terminal)")


def flag_names(parser) -> dict:
    """{dest: the option's long name} of ``parser``'s options (positional arguments have none)."""
    out = {}
    for a in parser._actions:   # argparse keeps its actions there, and offers no public view of them
        long = [s for s in a.option_strings if s.startswith("--")]
        if long and a.dest not in (argparse.SUPPRESS, "help"):
            out.setdefault(a.dest, long[0])
    return out


def with_flags(message: str, flags: dict) -> str:
    """A library message that begins with a parameter's name (``tv: ...``, ``output 'x': ...``) with that
    name as the option the user typed (``--tv: ...``)."""
    m = re.match(r"([a-z][a-z0-9_]*)(?=:| ')", message)
    if m and m[1] in flags:
        return flags[m[1]] + message[m.end():]
    return message


def _flag(name: str) -> str:
    return next((p.flag for p in parameters() if p.name == name and p.flag), name)


def _escape(text: str) -> str:
    return text.replace("%", "%%")   # argparse formats help with %

"""``cm2cl reconstruct MEAS.tif --psf PSF.tif -o OUT.tif``: one frame, with a progress line and the
iteration log written next to the output (OUT.log.csv and OUT.json)."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..solver.params import ADMMParams

_DEFAULTS = ADMMParams()


def register(sub):
    r = sub.add_parser("reconstruct", help="reconstruct a 3D volume from one CM2 measurement",
                       description=__doc__)
    r.add_argument("measurement", help="2D TIFF of the measurement")
    r.add_argument("--psf", required=True, help="3D TIFF of the PSF stack (nz, My, Mx), same sensor grid")
    r.add_argument("-o", "--output", required=True, help="output TIFF of the volume")
    g = r.add_argument_group("problem")
    g.add_argument("--l1", type=float, default=_DEFAULTS.l1, help="l1 weight (normalised problem)")
    g.add_argument("--tv", type=float, default=_DEFAULTS.tv, help="3D TV weight (normalised problem)")
    g.add_argument("--tv-axial-weight", type=float, default=_DEFAULTS.tv_axial_weight,
                   help="weight of axial differences in TV (non-cubic voxels: e.g. dx/dz)")
    g.add_argument("--anisotropic", action="store_true", help="anisotropic TV (default isotropic)")
    g.add_argument("--tv-iters", type=int, default=_DEFAULTS.tv_iters, help="TV dual iterations per outer iteration")
    g = r.add_argument_group("solver")
    g.add_argument("--max-iter", type=int, default=_DEFAULTS.max_iter)
    g.add_argument("--tol", type=float, default=_DEFAULTS.tol,
                   help="stop when the relative change of x stays below this for --patience iterations")
    g.add_argument("--patience", type=int, default=_DEFAULTS.patience)
    g.add_argument("--no-balance", action="store_true", help="keep the penalties fixed")
    g.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    g.add_argument("--backend", default="auto", help="FFT backend: auto, cl, vkfft, reikna")
    g.add_argument("--device", default=None, help="device index or name fragment (see cm2cl devices)")
    g = r.add_argument_group("input preparation")
    g.add_argument("--offset", default="none",
                   help="camera offset to subtract: 'none', 'auto' (mean of pixels [5:15, 5:15]) or a number")
    g.add_argument("--bin", type=int, default=1, help="bin measurement and PSF laterally by this factor")
    g = r.add_argument_group("output")
    g.add_argument("--padded", action="store_true",
                   help="write the whole padded grid (emitters outside the field of view) instead of the FOV")
    g.add_argument("--quiet", action="store_true", help="no progress line")
    r.set_defaults(func=command)


def _offset(text: str):
    if text == "none":
        return None
    if text == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError as exc:
        raise InputError(f"--offset: expected 'none', 'auto' or a number, got {text!r}") from exc


class Progress:
    """One status line on stderr: iteration, objective, residuals, time."""

    def __init__(self, total: int, enabled: bool):
        self.total, self.enabled = total, enabled
        self.tty = sys.stderr.isatty()
        self.last = 0.0

    def __call__(self, row):
        if not self.enabled:
            return
        it = row["iter"]
        frac = it / self.total
        bar = "#" * int(20 * frac) + "." * (20 - int(20 * frac))
        line = (f"[{bar}] {it}/{self.total}  obj {row['objective']:.4e}  primal {row['primal']:.2e}  "
                f"dual {row['dual']:.2e}  change {row['rel_change']:.1e}  {row['seconds']:.1f} s")
        now = time.monotonic()
        if self.tty:
            sys.stderr.write("\r" + line)
            sys.stderr.flush()
        elif now - self.last > 2.0 or it == self.total:
            print(line, file=sys.stderr)
            self.last = now

    def close(self):
        if self.enabled and self.tty:
            sys.stderr.write("\n")


def command(args) -> int:
    from .. import io
    from ..io.prepare import prepare
    from ..solver import reconstruct

    out = Path(args.output)
    if out.suffix.lower() not in (".tif", ".tiff"):
        raise InputError(f"--output '{out}': must end in .tif or .tiff")
    if not out.parent.exists():
        raise InputError(f"--output '{out}': folder '{out.parent}' does not exist")
    for src in (args.measurement, args.psf):
        if Path(src).exists() and out.resolve() == Path(src).resolve():
            raise InputError(f"--output '{out}': would overwrite the input '{src}'")
    meas, _ = io.read_tiff(args.measurement)
    psf, pmeta = io.read_tiff(args.psf)
    if meas.ndim != 2:
        raise InputError(f"measurement '{args.measurement}': expected a 2D image, got shape {meas.shape}")
    if psf.ndim not in (2, 3):
        raise InputError(f"psf '{args.psf}': expected a (nz, My, Mx) stack, got shape {psf.shape}")
    off = _offset(args.offset)
    y = prepare(meas, offset=off, bin_factor=args.bin, name=f"measurement '{args.measurement}'")
    h = prepare(psf, offset=off, bin_factor=args.bin, name=f"psf '{args.psf}'")
    h = h[None] if h.ndim == 2 else h
    if y.shape != h.shape[1:]:
        raise InputError(f"measurement '{args.measurement}': shape {y.shape} does not match the PSF "
                         f"'{args.psf}' sensor grid {h.shape[1:]}")
    dt = np.dtype(args.dtype)
    params = dict(l1=args.l1, tv=args.tv, tv_axial_weight=args.tv_axial_weight,
                  tv_isotropic=not args.anisotropic, tv_iters=args.tv_iters, max_iter=args.max_iter,
                  tol=args.tol, patience=args.patience)
    if args.no_balance:
        params["balance_factor"] = 0.0
    progress = Progress(args.max_iter, not args.quiet)
    try:
        rec = reconstruct(y.astype(dt), h.astype(dt), dtype=dt, backend=args.backend, device=args.device,
                          callback=progress, **params)
    finally:
        progress.close()
    vol = (rec.volume_padded if args.padded else rec.volume).astype(np.float32)
    vs = tuple(pmeta.get("voxel_size_um") or (1.0, 1.0, 1.0))
    vs = (1.0,) + vs if len(vs) == 2 else vs
    vs = (vs[0], vs[1] * args.bin, vs[2] * args.bin)
    extra = {"what": "cm2cl reconstruction", "measurement": str(args.measurement), "psf": str(args.psf),
             "params": rec.params, "scaling": rec.scaling, "info": rec.info, "padded": bool(args.padded)}
    stem = out.with_suffix("")
    tmp = out.with_name(out.name + ".partial")
    io.write_tiff(tmp, vol, voxel_size_um=vs, depths_um=pmeta.get("depths_um"), extra=extra)
    rec.write_log(Path(f"{stem}.log.csv"))
    rec.write_log(Path(f"{stem}.json"))
    os.replace(tmp, out)  # the volume appears only when complete
    last = rec.log[-1]
    print(f"{out}: {vol.shape} float32 volume, {rec.iterations} iterations ({rec.info['stop']}), "
          f"objective {last['objective']:.4e}, {last['seconds']:.1f} s on {rec.info['device']}; "
          f"log: {stem}.log.csv, {stem}.json")
    return 0

"""Fit the optics model's one aberration parameter (``CM2Optics.spherical_waves``) to the paper, and
write the fit to docs/optics_fit.md.

    python tools/fit_optics.py [--values 0,0.25,...] [--step 10] [--out docs/optics_fit.md]

For each value of W040 (every lenslet refocused to its best focus at z = 0, ``CM2Optics.focus_waves``)
it measures, on the simulated full-resolution PSF (1400 x 1400 sensor window around the axis):
the sharpest plane, the in-focus spot's FWHM in object space, and the axial PCC widths at 0.8 of the
3 x 3 / 2 x 3 / 2 x 2 configurations (paper Fig. 2A: 155 / 179 / 206 um).

The rule: W040 is set by the lateral resolution, the one target the model can meet: the paper measures
~7 um against its 6.4 um diffraction limit, so the model's spot FWHM is set to 7 / 6.4 times its own
diffraction-limited FWHM (found by bisection on the cheap spot computation). The PCC widths are reported
beside it: no W040 that keeps the spot near the diffraction limit reaches them (the table shows how
slowly they grow), so they are not fitted.

``--blur`` adds a second scan: the fitted model's stack with every plane convolved by a Gaussian of sigma
pixels on the sensor (the pinhole's image, crosstalk, anything that blurs the measured spots alike), and the
same with only a fraction of the light blurred (a sharp core on a halo). For each: the PCC widths and the 3D
MTF's lateral support and axial bandwidth at f_x = 0.0715 / um (paper: 0.1 and 0.0143 / um), to see whether
one blur meets the paper's PCC widths and its MTF together."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchlib import with_hand_written  # noqa: E402
from cm2cl.analysis.mtf import mtf_analysis  # noqa: E402
from cm2cl.analysis.views import pcc_curves  # noqa: E402
from cm2cl.optics import CM2Optics, depth_planes  # noqa: E402
from cm2cl.optics.psf import axial_psf_stack  # noqa: E402
from cm2cl.optics.characterise import PAPER_PCC_WIDTHS_UM, pcc_widths, sharpest_z_um, spot_fwhm_um  # noqa: E402

PAPER_LATERAL_UM, PAPER_DIFFRACTION_UM = 7.0, 6.4
#: the paper's 3D MTF (Fig. 2B): lateral support and the axial bandwidth at the lateral frequency 0.0715 / um
PAPER_MTF_SUPPORT, PAPER_CUTOFF, PAPER_BZ = 0.1, 0.0715, 0.0143


def fit_lateral(target_um: float, lo: float = 0.0, hi: float = 4.0, tol: float = 0.005) -> float:
    """W040 at which the in-focus spot's object-space FWHM equals ``target_um`` (it grows with W040)."""
    f = lambda w: spot_fwhm_um(CM2Optics(spherical_waves=w)) - target_um   # noqa: E731
    if f(lo) >= 0:
        return lo
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) < 0 else (lo, mid)
    return round(0.5 * (lo + hi), 2)


def measure(w040: float, step_um: float) -> dict:
    o = CM2Optics(sensor_shape=(1400, 1400), spherical_waves=w040)
    t = time.perf_counter()
    widths = pcc_widths(o, depth_planes(-300.0, 300.0, step_um))
    return dict(w040=w040, focus=o.focus_waves, sharpest=sharpest_z_um(o, depth_planes(-300.0, 300.0, 25.0)),
                fwhm=spot_fwhm_um(o), **widths, seconds=time.perf_counter() - t)


def blur_scan(w040: float, step_um: float, blurs, log=print) -> list[dict]:
    """PCC widths and MTF figures of the W040 model's stack with a fraction ``f`` of every plane's light
    convolved by a Gaussian of ``sigma`` sensor pixels, for each (sigma, f) of ``blurs``."""
    from scipy.ndimage import gaussian_filter

    o = CM2Optics(sensor_shape=(1400, 1400), spherical_waves=w040)
    z = depth_planes(-300.0, 300.0, step_um)
    stack = axial_psf_stack(o, z, dtype=np.float64)
    px = float(o.object_pixel_um(0.0))
    ref = int(np.argmin(np.abs(z)))
    rows = []
    for sigma, f in blurs:
        st = stack if sigma == 0 or f == 0 else \
            (1 - f) * stack + f * np.stack([gaussian_filter(p, sigma) for p in stack])
        w = pcc_curves(st, z, ref_index=ref)["widths_um"]
        m = mtf_analysis(st, step_um, px, px, lateral_cutoff_um=PAPER_CUTOFF)
        rows.append({"sigma": sigma, "fraction": f, **{k: w.get(k) for k in PAPER_PCC_WIDTHS_UM},
                     "support": m["lateral_cutoff_measured_per_um"], "bz": m["axial_bandwidth_per_um"]})
        r = rows[-1]
        log(f"blur sigma {sigma:g} px on {f:.0%} of the light: PCC widths "
            + " / ".join("-" if r[k] is None else f"{r[k]:.0f}" for k in PAPER_PCC_WIDTHS_UM)
            + f" um, MTF support {r['support']:.4f} / um, B_z {r['bz']:.4f} / um", flush=True)
    return rows


def _parse_blurs(text: str) -> list[tuple[float, float]]:
    """'SIGMA[:FRACTION],...' -> [(sigma, fraction)] (fraction 1 when left out)."""
    out = []
    for item in filter(None, (t.strip() for t in text.split(","))):
        sig, _, frac = item.partition(":")
        try:
            sigma, f = float(sig), float(frac) if frac else 1.0
        except ValueError:
            raise ValueError(f"--blur: {item!r} is not SIGMA[:FRACTION] (numbers)") from None
        if not (np.isfinite(sigma) and sigma >= 0) or not 0 <= f <= 1:
            raise ValueError(f"--blur: {item!r} needs a finite sigma >= 0 and a fraction in 0..1")
        out.append((sigma, f))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--values", default="0,0.25,0.5,1,2,3", help="W040 values to tabulate (waves)")
    ap.add_argument("--step", type=float, default=10.0, help="axial step of the PCC curves (um)")
    ap.add_argument("--blur", default="",
                    help="also scan blurs of the fitted model's spots: SIGMA[:FRACTION],... (sensor pixels; the "
                         "fraction of the light blurred, 1 when left out), e.g. 0,0.5,1,1.5:0.84")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "optics_fit.md")
    a = ap.parse_args(argv)
    try:
        blurs = _parse_blurs(a.blur)
    except ValueError as e:
        ap.error(str(e))
    t0 = time.perf_counter()
    dl = spot_fwhm_um(CM2Optics(spherical_waves=0.0))
    target = dl * PAPER_LATERAL_UM / PAPER_DIFFRACTION_UM
    fitted = fit_lateral(target)
    values = sorted({float(v) for v in a.values.split(",")} | {fitted})
    rows = []
    for w in values:
        rows.append(measure(w, a.step))
        r = rows[-1]
        print(f"W040 {w:5.2f}: sharpest z {r['sharpest']:+.0f} um, spot FWHM {r['fwhm']:.2f} um, PCC widths "
              + " / ".join(f"{r[k]:.0f}" for k in PAPER_PCC_WIDTHS_UM) + f" um ({r['seconds']:.0f} s)", flush=True)
    brows = blur_scan(fitted, a.step, blurs) if blurs else []
    paper = " / ".join(f"{v:.0f}" for v in PAPER_PCC_WIDTHS_UM.values())
    lines = [
        "# The optics model fitted to the paper", "",
        f"Made by `python tools/fit_optics.py` in {time.perf_counter() - t0:.0f} s. Model: `cm2cl.optics.CM2Optics`, "
        "full resolution (2.2 um pixels), a 1400 x 1400 window around the axis; each lenslet carries spherical "
        "aberration W040 rho^4 and the defocus W020 rho^2 (`focus_waves`) that maximises its Strehl ratio, so that "
        "its best focus is at z = 0 (l = 12 mm) as in the paper's PSF scan. PCC curves: "
        f"{a.step:g}-um steps over +-300 um, registered by the cross-correlation peak, widths at PCC = 0.8.", "",
        "## Fit", "",
        f"- Rule: the lateral resolution, the one target the model can meet. The paper measures ~{PAPER_LATERAL_UM:g} um "
        f"against its {PAPER_DIFFRACTION_UM:g} um diffraction limit (ratio {PAPER_LATERAL_UM / PAPER_DIFFRACTION_UM:.3f}); the "
        f"model's diffraction-limited spot is {dl:.2f} um FWHM in object space, so the target is {target:.2f} um.",
        f"- Fitted: **W040 = {fitted:g} waves** (the default of `CM2Optics.spherical_waves`), refocus W020 = "
        f"{CM2Optics(spherical_waves=fitted).focus_waves:.3f} waves.",
        f"- Not met: the axial PCC widths. The paper's are {paper} um; the model's stay below 100 um for any W040 "
        "whose spot is within 1.5x the diffraction limit (table). Spherical aberration widens the spots, and with them the "
        "PCC curves, too slowly; what widens the measured curves (the pinhole, sensor crosstalk, aberrations "
        "that grow with the field, the measurement's sampling) is not in the model, and fitting the widths "
        "with W040 alone would give spots far blurrier than the paper's 7 um.", "",
        "## Scan", "",
        "| W040 (waves) | refocus W020 | sharpest plane (um) | spot FWHM, object (um) | PCC width 3x3 | 2x3 | 2x2 (um) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        mark = " (fitted)" if r["w040"] == fitted else ""
        lines.append(f"| {r['w040']:g}{mark} | {r['focus']:.3f} | {r['sharpest']:+.0f} | {r['fwhm']:.2f} | "
                     + " | ".join(f"{r[k]:.0f}" for k in PAPER_PCC_WIDTHS_UM) + " |")
    lines.append(f"| paper | | 0 | ~{PAPER_LATERAL_UM:g} (resolution) | " + " | ".join(f"{v:.0f}" for v in PAPER_PCC_WIDTHS_UM.values()) + " |")
    if blurs:
        lines += blur_section(brows, fitted, a.step)
    lines[2] = lines[2].replace("`python tools/fit_optics.py`", "`python tools/fit_optics.py"
                                + (f" --blur {a.blur}" if blurs else "") + "`")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(with_hand_written("\n".join(lines) + "\n", a.out))   # hand-written sections stay
    print(f"wrote {a.out}")
    return 0


def blur_section(rows: list[dict], w040: float, step_um: float) -> list[str]:
    """The blur scan's table and what it shows, as markdown lines."""
    def ok(v, ref):
        return v is not None and abs(v / ref - 1) <= 0.15

    meets_pcc = [r for r in rows if all(ok(r[k], v) for k, v in PAPER_PCC_WIDTHS_UM.items())]
    meets_both = [r for r in meets_pcc if ok(r["support"], PAPER_MTF_SUPPORT) and ok(r["bz"], PAPER_BZ)]
    out = ["", "## Blurred spots: the PCC widths against the MTF", "",
           f"The fitted model (W040 = {w040:g}) with a fraction of every plane's light convolved by a Gaussian of "
           f"sigma sensor pixels (2.2 um; 1 px is 5.3 um in object space), {step_um:g}-um planes over +-300 um. "
           "The MTF's support is where it stays above 1% of its value at zero frequency (`cm2cl analyze mtf`). "
           "Within 15% of the paper: **bold**.", "",
           "| sigma (px) | light blurred | PCC width 3x3 | 2x3 | 2x2 (um) | MTF lateral support (1/um) | "
           "B_z at f_x = 0.0715 (1/um) |", "|---|---|---|---|---|---|---|"]

    def cell(v, ref, fmt):
        if v is None:
            return "-"
        return f"**{v:{fmt}}**" if ok(v, ref) else f"{v:{fmt}}"
    for r in rows:
        out.append(f"| {r['sigma']:g} | {r['fraction']:.0%} | "
                   + " | ".join(cell(r[k], v, ".0f") for k, v in PAPER_PCC_WIDTHS_UM.items())
                   + f" | {cell(r['support'], PAPER_MTF_SUPPORT, '.4f')} | {cell(r['bz'], PAPER_BZ, '.4f')} |")
    out.append("| paper | | " + " | ".join(f"{v:.0f}" for v in PAPER_PCC_WIDTHS_UM.values())
               + f" | {PAPER_MTF_SUPPORT:g} | {PAPER_BZ:g} |")
    out.append("")
    if meets_both:
        out.append(f"{len(meets_both)} of the blurs meet the paper's PCC widths and its MTF together.")
    elif meets_pcc:
        bz = ", ".join(f"{r['bz']:.4f}" for r in meets_pcc)
        out.append(f"{len(meets_pcc)} of the blurs bring all three PCC widths within 15% of the paper's, and none of "
                   f"them keeps the paper's MTF with it: their axial bandwidth at f_x = 0.0715 / um is {bz} / um "
                   f"against the paper's {PAPER_BZ:g} (the blur takes the side views' tilted bands, which carry the "
                   "depth information at that lateral frequency, below the MTF's floor). So none of these blurs (a "
                   "Gaussian, or a sharp core on a Gaussian halo) reproduces both of the paper's measurements, and the optics defaults stay fitted to the "
                   "lateral resolution (above) with no blur.")
    else:
        out.append("None of the blurs brings all three PCC widths within 15% of the paper's.")
    return out


if __name__ == "__main__":
    raise SystemExit(main())

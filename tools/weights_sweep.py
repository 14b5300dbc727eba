"""The sweep behind the default weights and the adaptation threshold: l1 = tv = c x noise_x (the
volume-domain noise level, `cm2cl.solver.control.ProblemScale.noise_x`) for several c, and the former
rule (1 x the measurement's noise sigma), on
- `demo`: the demo's bead scene (the project's own simulator, no mismatch);
- `beads`: 24 beads rendered with per-bead aberration (shift-variant), sub-plane depths and sensor noise,
  reconstructed with the shift-invariant PSF stack (tools/accuracy_vs_time.py's bead case);
- `dc3d`: the real DiffuserCam 3D data (44 planes, 270 x 320), judged by its data residual
  ||C H x - y|| / ||y|| and its MIP (docs/img/weights_dc3d_c*.png);
then the adaptation threshold (adapt_ratio 100 against 1000) at the chosen weights.
Writes docs/weights.md.

    python tools/weights_sweep.py [--ratios 1,3,10,30,100]
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import accuracy_vs_time as av  # noqa: E402
import datasets  # noqa: E402
import cm2cl  # noqa: E402
from cm2cl import analysis, reference, simulate  # noqa: E402

DOCS = Path(__file__).resolve().parents[1] / "docs"


def cases():
    sim = simulate.simulate_scene("demo_beads")
    yield {"name": "demo", "psf": sim.psf.astype(np.float64), "y": sim.measurement.astype(np.float64), "sim": sim}
    yield av.bead_case(False)
    psf, y = datasets.diffusercam_3d(1)
    yield {"name": "dc3d", "psf": psf, "y": y, "sim": None}


def run(case, label, **kw) -> dict:
    psf, y = case["psf"], case["y"]
    t = time.perf_counter()
    rec = cm2cl.reconstruct(y, psf, **kw, psf_refine=0)
    sec = time.perf_counter() - t
    yh = reference.forward(psf, rec.volume_padded, rec.volume_padded.shape[1:])
    row = {"case": case["name"], "config": label, "weight": rec.info["l1"], "iterations": rec.iterations,
           "converged": rec.info["converged"], "objective": rec.log[-1]["objective"],
           "residual": float(np.linalg.norm(yh - y) / np.linalg.norm(y)), "seconds": sec}
    if case["sim"] is not None:
        m = analysis.score_beads(rec.volume, case["sim"])
        row.update(recall=m["recall"], precision=m["precision"], lateral_rms_um=m["lateral_rms_um"])
    else:
        png = f"weights_{case['name']}_{re.sub(r'[^A-Za-z0-9.]+', '_', label.replace('=', '')).strip('_')}.png"
        analysis.mip_png(rec.volume, DOCS / "img" / png, title=f"DiffuserCam 3D, {label}, weight {rec.info['l1']:.2g}",
                         gamma=0.6)
        row["mip"] = png
    print(row, flush=True)
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ratios", default="1,3,10,30,100")
    args = ap.parse_args(argv)
    ratios = [float(c) for c in args.ratios.split(",")]
    (DOCS / "img").mkdir(parents=True, exist_ok=True)
    rows, scales = [], {}
    for case in cases():
        d = cm2cl.reconstruct(case["y"], case["psf"], max_iter=1, psf_refine=0)
        scales[case["name"]] = (d.info["noise_sigma"], d.info["noise_x"], case["psf"].shape)
        rows.append(run(case, "former: 1 x sigma", l1=d.info["noise_sigma"], tv=d.info["noise_sigma"],
                        adapt_ratio=1000))
        for c in ratios:
            rows.append(run(case, f"c={c:g}", l1_noise_ratio=c, tv_noise_ratio=c, adapt_ratio=1000))
        rows.append(run(case, "defaults, adapt_ratio=100", adapt_ratio=100))
    from cm2cl.device import get_runtime

    lines = ["# Default weights and the adaptation threshold", "",
             f"Made by `python tools/weights_sweep.py --ratios {args.ratios}` on {get_runtime().caps.implementation}; "
             "defaults otherwise (200 iterations at most, float32). Seconds are indicative only (other jobs "
             "shared the 2 cores).", "",
             "noise_x = sigma x sqrt(sum_i ||h_i||^2 / nz) is the standard deviation of the back-projected sensor "
             "noise at one voxel on the normalised problem (max y = 1, ||H|| = 1). A weight above |h_i^T y| keeps "
             "voxel i at zero, so weights meant to hold noise back scale with it.", "",
             "| case | planes x sensor | sigma | noise_x | sigma / noise_x |", "|---|---|---|---|---|"]
    for k, (s, nx, shape) in scales.items():
        lines.append(f"| {k} | {shape[0]} x {shape[1]} x {shape[2]} | {s:.3g} | {nx:.3g} | {s / nx:.0f} |")
    lines += ["", "| case | config | weight | iterations | converged | objective | data residual | recall | "
              "precision | lateral RMS um | s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        g = lambda k, f: (f % r[k]) if k in r and r[k] == r[k] else ""  # noqa: E731
        lines.append(f"| {r['case']} | {r['config']} | {r['weight']:.3g} | {r['iterations']} | {r['converged']} | "
                     f"{r['objective']:.5g} | {r['residual']:.4f} | {g('recall', '%.2f')} | {g('precision', '%.2f')} | "
                     f"{g('lateral_rms_um', '%.1f')} | {r['seconds']:.0f} |")
    lines += ["", "Reading: on the bead scenes the weights at c = 30 are about the former ones (noise_x is sigma / 14 "
              "there) and give all beads of the demo and recall 0.83 at precision 1.00 with model mismatch, "
              "converged within 200 iterations; lower c finds as many or more beads but false maxima multiply "
              "(precision 0.36-0.63 at c = 1). On the real DiffuserCam 3D data (noise_x = sigma / 781) the former "
              "weights leave a blob (residual 0.074); every c <= 100 fits the data to 0.060-0.063 and shows the "
              "bar groups. c = 30 is the default: the largest that keeps the lensless data's structure, and the "
              "bead scenes' precision. The adaptation threshold 1000 against 100: same on the beads, a 12% lower "
              "objective after 200 iterations on DiffuserCam 3D.", "", "DiffuserCam 3D MIPs (depth colour-coded; the scene is a resolution target tilted in depth):", ""]
    lines += [f"![{r['config']}](img/{r['mip']})" for r in rows if "mip" in r]
    (DOCS / "weights.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()

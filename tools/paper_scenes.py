"""The paper's bead scenes (`fig3_beads`, `fig5_scattering`: 972 x 1296 sensor, 2x binned, 21 planes) simulated
and reconstructed at cm2cl's defaults, as a user would; recall and precision overall and by depth third
(emitters and detections split by their depth), lateral and axial error. Writes docs/paper_scenes.md and
the MIPs in docs/img/paper_<scene>_mip.png.

    python tools/paper_scenes.py [--scenes fig3_beads,fig5_scattering] [--max-iter N]

Slow on a CPU (about 20 min per scene on 2 cores): a benchmark, not a test.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import cm2cl
from cm2cl import analysis, simulate

DOCS = Path(__file__).resolve().parents[1] / "docs"


def by_thirds(m: dict, depths_um) -> list[tuple[float, float, int]]:
    """(recall, precision, true count) per depth third of the volume."""
    lo, hi = float(np.min(depths_um)), float(np.max(depths_um))
    edges = lo + (hi - lo) * np.array([0, 1 / 3, 2 / 3, 1 + 1e-9])
    tz, fz = m["true_um"][:, 2], m["found_um"][:, 2]
    pairs = m["pairs"]
    out = []
    for a, b in zip(edges[:-1], edges[1:]):
        ti = np.flatnonzero((tz >= a) & (tz < b))
        fi = np.flatnonzero((fz >= a) & (fz < b))
        mt = np.isin(pairs[:, 1], ti).sum() if len(pairs) else 0
        mf = np.isin(pairs[:, 0], fi).sum() if len(pairs) else 0
        out.append((mt / len(ti) if len(ti) else float("nan"), mf / len(fi) if len(fi) else float("nan"), len(ti)))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="fig3_beads,fig5_scattering")
    ap.add_argument("--max-iter", type=int, default=None, help="default: the solver's default")
    args = ap.parse_args(argv)
    rows = []
    (DOCS / "img").mkdir(parents=True, exist_ok=True)
    for name in args.scenes.split(","):
        t = time.perf_counter()
        sim = simulate.simulate_scene(name)
        ts = time.perf_counter() - t
        kw = {} if args.max_iter is None else {"max_iter": args.max_iter}
        t = time.perf_counter()
        rec = cm2cl.reconstruct(sim.measurement, sim.psf, voxel_size_um=sim.voxel_size_um, depths_um=sim.depths_um, **kw)
        tr = time.perf_counter() - t
        m = analysis.score_beads(rec.volume, sim)
        thirds = by_thirds(m, sim.depths_um)
        analysis.mip_png(rec.volume, DOCS / "img" / f"paper_{name}_mip.png", title=f"{name}: cm2cl defaults",
                         gamma=0.6)
        rows.append(dict(scene=name, shape=f"{sim.psf.shape[0]} x {sim.psf.shape[1]} x {sim.psf.shape[2]}",
                         sim_s=ts, rec_s=tr, iterations=rec.iterations, converged=rec.info["converged"],
                         stop=rec.info["stop"], recall=m["recall"], precision=m["precision"], n_true=m["n_true"],
                         thirds=thirds, lat=m.get("lateral_rms_um", float("nan")),
                         ax=m.get("axial_rms_um", float("nan")), l1=rec.info["l1"],
                         mib=rec.info["device_bytes"] / 2**20))
        print(rows[-1], flush=True)
    from cm2cl.device import get_runtime

    lines = ["# The paper's bead scenes at the defaults", "",
             f"Made by `python tools/paper_scenes.py --scenes {args.scenes}` on {get_runtime().caps.implementation}. "
             "Each scene is simulated with its effects (see `cm2cl simulate --list`) and reconstructed with "
             "`cm2cl.reconstruct` at the defaults. Depth thirds split the true beads and the detections by depth.", "",
             "| scene | planes x sensor | iterations | stop | recall | precision | recall / precision by depth "
             "third (near, middle, far) | beads per third | lateral RMS um | axial RMS um | device MiB | s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        th = ", ".join(f"{a:.2f} / {b:.2f}" for a, b, _ in r["thirds"])
        n = ", ".join(str(c) for _, _, c in r["thirds"])
        lines.append(f"| {r['scene']} | {r['shape']} | {r['iterations']} | {r['stop']} | {r['recall']:.2f} | "
                     f"{r['precision']:.2f} | {th} | {n} | {r['lat']:.1f} | {r['ax']:.1f} | {r['mib']:.0f} | "
                     f"{r['rec_s']:.0f} |")
    lines += [""] + [f"![{r['scene']}](img/paper_{r['scene']}_mip.png)" for r in rows] + [""]
    (DOCS / "paper_scenes.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()

"""psf_refine='common' against the PSF as given, over several seeds of the quality suite's scenes.

For each scene (cm2cl.analysis.quality.scene_specs) and seed, the scene is rendered with that seed and
reconstructed at the defaults with psf_refine=0 (the PSF as given) and psf_refine='common' (one round, one
kernel for every lenslet); each run is scored as the suite scores it (beads: recall at +-1 plane, false maxima
per 10 beads, mean |axial error|; fibres: energy within 2 voxels of the truth) and timed. Prints a markdown
table and writes it to --out (default docs/psf_common_seeds.md).

    python tools/psf_common_seeds.py --seeds 1,11,12,13 --scenes beads,mm_issue,fibres
"""

from __future__ import annotations

import argparse
import platform
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import cm2cl
from cm2cl.analysis import quality as Q

DOCS = Path(__file__).resolve().parents[1] / "docs"
SCENES = "beads,photons200,bg_haze10,bg_ramp20,dense,edge_planes,between,mm_blur,mm_depth,mm_issue,fibres,fibres_blur"
MODES = (("given", 0), ("common", "common"))


def score(sc, rec) -> dict:
    vol = np.asarray(rec.volume, np.float64)
    if sc.beads is None:
        return {"near": Q.energy_near(vol, sc.truth)}
    s = Q.score_beads(vol, sc.beads)
    return {k: s[k] for k in ("recall", "false_per_10", "axial_err")}


def passes(s: dict) -> bool:
    return bool(all(Q.targets_met({"kind": "fibres" if "near" in s else "beads",
                                   **({"energy_near": s["near"]} if "near" in s else s)}).values()))


def cell(s: dict, secs: float, its: int) -> str:
    head = (f"near {s['near']:.3f}" if "near" in s else
            f"{s['recall']:.2f} / {s['false_per_10']:.1f} / {s['axial_err']:.2f}")
    return f"{head}{'' if passes(s) else ' (fail)'}, {its} it, {secs:.1f} s"


def run(scenes, seeds, log=print) -> list[dict]:
    specs = {s.name: s for s in Q.scene_specs()}
    rows = []
    for name in scenes:
        for seed in seeds:
            sc = Q.render_scene(replace(specs[name], seed=seed))
            row = {"scene": name, "seed": seed}
            for label, mode in MODES:
                t = time.perf_counter()
                rec = cm2cl.reconstruct(sc.y, sc.psf, psf_refine=mode)
                secs = time.perf_counter() - t
                info = rec.info.get("psf_refine") or {}
                its = int(info.get("iterations_total", rec.iterations))
                row[label] = (score(sc, rec), secs, its)
            rows.append(row)
            log(f"{name} seed {seed}: " + " | ".join(f"{lab} {cell(*row[lab])}" for lab, _ in MODES))
    return rows


def markdown(rows, seconds: float, argv: str) -> str:
    from cm2cl.device import get_runtime

    where = f"{get_runtime().caps.implementation} ({platform.processor() or platform.machine()})"
    lines = [f"# psf_refine='common' over seeds\n",
             f"Made by `python tools/psf_common_seeds.py {argv}` in {seconds / 60:.1f} min on {where}; one run. Each cell: recall / false maxima per 10 beads / mean |axial error| "
             "(planes), or the fibres' energy within 2 voxels of the truth; '(fail)' where a target of "
             "docs/quality.md is missed; iterations in all (the round's included) and seconds of the call.\n",
             "| scene | seed | PSF as given (psf_refine=0) | psf_refine='common' |", "|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['seed']} | {cell(*r['given'])} | {cell(*r['common'])} |")
    n = len(rows)
    ok = {lab: sum(passes(r[lab][0]) for r in rows) for lab, _ in MODES}
    t = {lab: sum(r[lab][1] for r in rows) for lab, _ in MODES}
    lines += ["", f"Passed: given {ok['given']} of {n}, common {ok['common']} of {n}. Seconds in all: given "
              f"{t['given']:.0f}, common {t['common']:.0f} (ratio {t['common'] / max(t['given'], 1e-9):.2f})."]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=SCENES, help=f"comma list of quality scenes (default {SCENES})")
    ap.add_argument("--seeds", default="1,11,12,13", help="comma list of seeds (default 1,11,12,13)")
    ap.add_argument("--out", default=str(DOCS / "psf_common_seeds.md"))
    a = ap.parse_args(argv)
    known = {s.name for s in Q.scene_specs()}
    scenes = [s.strip() for s in a.scenes.split(",") if s.strip()]
    bad = [s for s in scenes if s not in known]
    if bad:
        ap.error(f"--scenes: unknown scene(s) {', '.join(bad)} (known: {', '.join(sorted(known))})")
    try:
        seeds = [int(s) for s in a.seeds.split(",") if s.strip()]
    except ValueError:
        ap.error(f"--seeds: expected a comma list of integers, got {a.seeds!r}")
    t = time.perf_counter()
    rows = run(scenes, seeds)
    text = markdown(rows, time.perf_counter() - t, " ".join(argv if argv is not None else __import__("sys").argv[1:]))
    Path(a.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()

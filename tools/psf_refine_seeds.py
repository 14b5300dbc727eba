"""The PSF self-calibration modes side by side, over several seeds of the quality suite's scenes.

For each scene (cm2cl.analysis.quality.scene_specs) and seed, the scene is rendered with that seed and
reconstructed at the defaults with each psf_refine mode of --modes (default: 0, the PSF as given; 'common',
one round of one kernel for every lenslet; 'auto', that round and kernels per lenslet where the view check
finds the views in disagreement); each run is scored as the suite scores it (beads: recall at +-1 plane,
false maxima per 10 beads, mean |axial error|; fibres: energy within 2 voxels of the truth) and timed. Prints
a markdown table and writes it to --out (default docs/psf_refine_seeds.md).

    python tools/psf_refine_seeds.py --seeds 1,11,12,13 --scenes beads,mm_issue,fibres
    python tools/psf_refine_seeds.py --modes common,auto --scenes mm_trunc,mm_aberr --out /tmp/t.md
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
from cm2cl.solver.psf_refine import EXTENDED_SHARE, VIEW_DISAGREEMENT

DOCS = Path(__file__).resolve().parents[1] / "docs"
SCENES = "beads,photons200,bg_haze10,bg_ramp20,dense,edge_planes,between,mm_blur,mm_depth,mm_issue,fibres,fibres_blur"
MODES = "given=0,common,auto"


def parse_modes(text: str):
    """[(label, psf_refine value)] from 'label=value' or 'value' items ('given=0,common,auto')."""
    out = []
    for item in (t.strip() for t in text.split(",") if t.strip()):
        label, _, value = item.rpartition("=")
        value = value.strip()
        v = int(value) if value.isdigit() else value
        if not (isinstance(v, int) or v in ("auto", "common")):
            raise ValueError(f"--modes: {item!r} is neither a number of rounds nor 'auto' or 'common'")
        out.append((label.strip() or value, v))
    return out


def score(sc, rec) -> dict:
    vol = np.asarray(rec.volume, np.float64)
    if sc.beads is None:
        return {"near": Q.energy_near(vol, sc.truth)}
    s = Q.score_beads(vol, sc.beads)
    return {k: s[k] for k in ("recall", "false_per_10", "axial_err")}


def passes(s: dict) -> bool:
    return bool(all(Q.targets_met({"kind": "fibres" if "near" in s else "beads",
                                   **({"energy_near": s["near"]} if "near" in s else s)}).values()))


def cell(s: dict, secs: float, its: int, rounds: int = 0, d=None, share=None) -> str:
    head = (f"near {s['near']:.3f}" if "near" in s else
            f"{s['recall']:.2f} / {s['false_per_10']:.1f} / {s['axial_err']:.2f}")
    check = (f", d {d:.3f}" if d is not None else "") + (f", ext {share:.2f}" if share is not None else "")
    return f"{head}{'' if passes(s) else ' (fail)'}, {rounds} rnd{check}, {its} it, {secs:.1f} s"


def run(scenes, seeds, modes, log=print) -> list[dict]:
    specs = {s.name: s for s in Q.scene_specs()}
    rows = []
    for name in scenes:
        for seed in seeds:
            sc = Q.render_scene(replace(specs[name], seed=seed))
            row = {"scene": name, "seed": seed}
            for label, mode in modes:
                t = time.perf_counter()
                rec = cm2cl.reconstruct(sc.y, sc.psf, psf_refine=mode)
                secs = time.perf_counter() - t
                info = rec.info.get("psf_refine") or {}
                its = int(info.get("iterations_total", rec.iterations))
                check = info.get("check") or {}
                row[label] = (score(sc, rec), secs, its, info.get("rounds", 0), check.get("disagreement"),
                              check.get("extended_share"))
            rows.append(row)
            log(f"{name} seed {seed}: " + " | ".join(f"{lab} {cell(*row[lab])}" for lab, _ in modes))
    return rows


def markdown(rows, modes, seconds: float, argv: str) -> str:
    from cm2cl.device import get_runtime

    where = f"{get_runtime().caps.implementation} ({platform.processor() or platform.machine()})"
    labels = [lab for lab, _ in modes]
    lines = ["# psf_refine modes over seeds\n",
             f"Made by `python tools/psf_refine_seeds.py {argv}` in {seconds / 60:.1f} min on {where}; one run. Each "
             "cell: recall / false maxima per 10 beads / mean |axial error| (planes), or the fibres' energy within 2 "
             "voxels of the truth; '(fail)' where a target of docs/quality.md is missed; refinement rounds run, "
             "'auto''s view check d (the misfit share kernels per lenslet explain beyond a common one; they "
             f"refine above {VIEW_DISAGREEMENT:g}) and the share of its volume's energy in extended pieces, 'ext' "
             f"(they refine only at or below {EXTENDED_SHARE:g}), iterations in all (the rounds' included) and "
             "seconds of the call.\n",
             "| scene | seed | " + " | ".join(f"psf_refine={v!r} ({lab})" for lab, v in modes) + " |",
             "|---|---|" + "---|" * len(modes)]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['seed']} | " + " | ".join(cell(*r[lab]) for lab in labels) + " |")
    n = len(rows)
    ok = {lab: sum(passes(r[lab][0]) for r in rows) for lab in labels}
    t = {lab: sum(r[lab][1] for r in rows) for lab in labels}
    lines += ["", "Passed: " + ", ".join(f"{lab} {ok[lab]} of {n}" for lab in labels) + ". Seconds in all: "
              + ", ".join(f"{lab} {t[lab]:.0f}" for lab in labels)
              + f" (ratios to {labels[0]}: " + ", ".join(f"{t[lab] / max(t[labels[0]], 1e-9):.2f}" for lab in labels[1:])
              + ")."]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=SCENES, help=f"comma list of quality scenes (default {SCENES})")
    ap.add_argument("--seeds", default="1,11,12,13", help="comma list of seeds (default 1,11,12,13)")
    ap.add_argument("--modes", default=MODES, help=f"comma list of psf_refine values, each 'label=value' or "
                    f"'value' (default {MODES})")
    ap.add_argument("--out", default=str(DOCS / "psf_refine_seeds.md"))
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
    try:
        modes = parse_modes(a.modes)
    except ValueError as exc:
        ap.error(str(exc))
    if not modes:
        ap.error("--modes: give at least one psf_refine value")
    t = time.perf_counter()
    rows = run(scenes, seeds, modes)
    text = markdown(rows, modes, time.perf_counter() - t, " ".join(argv if argv is not None else __import__("sys").argv[1:]))
    Path(a.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()

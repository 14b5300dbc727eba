"""Bead frames drawn at random from the quality suite's ranges: a check that the defaults hold between its scenes.

    python tools/random_scenes.py [--seed 57] [--frames 24] [--out docs/random_scenes.md]

The quality suite (docs/quality.md) varies one thing per scene; a user's frame varies several at once. Each frame
here draws all of them (from ``--seed``, so the set is reproducible): a background of each kind the suite has
(haze, ramp, blob, low-frequency random field) at 0-20% of the peak; 200-5000 photons at the peak (log-uniform);
the PSF that makes the frame blurred by 0, 0.5 or 1 px and 0, 0.2 or 0.4 plane off in depth against the stack the
reconstruction is given (the mismatches common to every lenslet, which the suite's mm_blur, mm_depth and mm_issue
take one or two at a time); 20, 40 or 60 beads. Each frame is reconstructed by ``cm2cl.reconstruct(y, psf)`` at
the defaults and scored as the suite scores beads (:func:`cm2cl.analysis.quality.score_beads`, issue 24's
targets), with what the PSF refinement decided (its rounds; the view check's disagreement d and F statistic) and
the data misfit reached (``rec.info['misfit']['ratio']``). A frame whose PSF differs from the stack alike in every
lenslet should keep the common kernel (2 rounds); 12 rounds mean the view check judged the views to disagree and
kernels per lenslet fitted the data better than the common kernel's answer solved beside them.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cm2cl  # noqa: E402
from benchlib import made_by, refine_words, with_hand_written  # noqa: E402
from cm2cl.analysis import quality as Q  # noqa: E402

BACKGROUNDS = ("haze", "ramp", "blob", "random")
BLURS, DEPTHS, BEADS = (0.0, 0.5, 1.0), (0.0, 0.2, 0.4), (20, 40, 60)
BG_RANGE, PHOTON_RANGE = (0.0, 0.2), (200.0, 5000.0)


def draw(seed: int, n: int) -> list:
    """``n`` :class:`cm2cl.analysis.quality.SceneSpec` drawn from the ranges above with generator ``seed``."""
    rng = np.random.default_rng(seed)
    specs = []
    for k in range(n):
        bg = str(rng.choice(BACKGROUNDS))
        level = float(rng.uniform(*BG_RANGE))
        photons = float(np.exp(rng.uniform(*np.log(PHOTON_RANGE))))
        mm = Q.Mismatch(blur=float(rng.choice(BLURS)), dz=float(rng.choice(DEPTHS)))
        beads = int(rng.choice(BEADS))
        scene_seed = int(rng.integers(100, 10000))
        what = (f"{beads} beads, {bg} {100 * level:.0f}%, {photons:.0f} photons, blur {mm.blur:g} px, "
                f"{mm.dz:g} plane off")
        specs.append(Q.SceneSpec(f"random{k}", what, n_beads=beads, mismatch=mm, background=bg, bg_level=level,
                                 photons=photons, seed=scene_seed))
    return specs


def run(specs, log=print) -> list[dict]:
    rows = []
    for spec in specs:
        sc = Q.render_scene(spec)
        t = time.perf_counter()
        rec = cm2cl.reconstruct(sc.y, sc.psf)
        s = Q.score_beads(rec.volume, sc.beads)
        pr = rec.info.get("psf_refine") or {}
        check = pr.get("check") or {}
        row = {"frame": spec.what, "seed": spec.seed, **s, "iterations": rec.iterations,
               "pass": all(Q.targets_met({"kind": "beads", **s}).values()), "rounds": refine_words(pr),
               "d": check.get("disagreement"), "F": check.get("f_statistic"),
               "misfit": rec.info["misfit"]["ratio"], "seconds": time.perf_counter() - t}
        rows.append(row)
        log(f"{spec.what} (seed {spec.seed}): recall {s['recall']:.2f}, false/10 {s['false_per_10']:.1f}, axial "
            f"{s['axial_err']:.2f}, {'pass' if row['pass'] else 'FAIL'}; {row['rounds']}; "
            f"{row['seconds']:.0f} s")
    return rows


def _f(v, fmt="{:.3f}") -> str:
    return "-" if v is None else fmt.format(v)


def write_md(rows, path: Path, argv, seconds: float) -> None:
    lines = ["# Bead frames drawn at random from the quality suite's ranges", "",
             made_by("random_scenes.py", argv, seconds, __doc__),
             "", "| frame | scene seed | recall | false / 10 | axial err | PSF refinement | d | F | misfit / "
             "white noise | iterations | s | targets |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['frame']} | {r['seed']} | {r['recall']:.2f} | {r['false_per_10']:.1f} | "
                     f"{r['axial_err']:.2f} | {r['rounds']} | {_f(r['d'])} | {_f(r['F'], '{:.2f}')} | "
                     f"{_f(r['misfit'], '{:.2f}')} | {r['iterations']} | {r['seconds']:.0f} | "
                     f"{'pass' if r['pass'] else 'fail'} |")
    lines += ["", f"{sum(r['pass'] for r in rows)} of {len(rows)} frames meet issue 24's bead targets (recall >= "
              "0.95 at +-1 plane, at most 1 false maximum per 10 beads, mean axial error <= 0.5 plane)."]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(with_hand_written("\n".join(lines) + "\n", path))   # the hand-written reading stays


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=57, help="the generator's seed (default 57)")
    ap.add_argument("--frames", type=int, default=24, help="frames to draw (default 24)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "random_scenes.md")
    args = ap.parse_args(argv)
    if args.frames < 1:
        ap.error(f"--frames: at least 1, got {args.frames}")
    t = time.perf_counter()
    rows = run(draw(args.seed, args.frames))
    argv_out = [f"--seed {args.seed}"] * (args.seed != 57) + [f"--frames {args.frames}"] * (args.frames != 24)
    write_md(rows, args.out, argv_out, time.perf_counter() - t)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

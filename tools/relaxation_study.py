"""How a solver parameter changes the iterations to an answer (issue 28): over-relaxation (``relaxation``,
alpha; the default) or the initial data penalty (``mu_v``, which scales every initial penalty: the
identity splits' start at spectral_mean x mu_v). For each case and value, one long solve with no stopping
rule (tol 0) gives the objective's history, and a solve at the defaults (the stopping rule) the
iterations, the objective gap and the quality where the rule stops.

    python tools/relaxation_study.py [--alphas 1,1.5,1.6,1.8] [--iters 2000] [--cases beads,mm_aberr,...]
        [--out docs/relaxation.md]
    python tools/relaxation_study.py --param mu_v --values 0.1,0.2,0.3,0.5,1 --out docs/penalty.md
    python tools/relaxation_study.py --variants "issue=relaxation:1,mu_v:1;defaults=" --out docs/iterations.md

``--variants``: named sets of keywords instead of one parameter's values (an empty set: the defaults); the
first is the one the others are compared with.

Cases: the quality suite's scenes (cm2cl/analysis/quality.py: rendered with a PSF the reconstruction is not
given), ``cm2cl demo``'s scene, and the real DiffuserCam 2D (binned 4x) and 3D (binned 4x) data. The reference objective of a case is
the lowest final objective of its solves (every alpha reaches the same minimiser); "to 1%" is the
iteration after which the objective stays within 1% of it (0.1% likewise), '-' where it never does.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import cm2cl  # noqa: E402
from benchlib import with_hand_written  # noqa: E402
from cm2cl.analysis import quality as Q  # noqa: E402

GAPS = (0.01, 0.001)


def load_case(name: str):
    """(psf, y, beads or None) of a case."""
    import datasets

    if name == "demo":          # cm2cl demo's scene, reconstructed as the demo does (its measurement as given)
        from cm2cl.simulate import simulate_scene

        sim = simulate_scene("demo_beads", seed=7)
        return sim.psf, sim.measurement.astype(np.float64), None
    if name == "dc2d":
        psf, y = datasets.diffusercam_2d(4)
        return psf, y, None
    if name == "dc3d":
        psf, y = datasets.diffusercam_3d(4)
        return psf, y, None
    if name == "dc3d_bin2":     # the issue's DiffuserCam 3D case (binned 2x)
        psf, y = datasets.diffusercam_3d(2)
        return psf, y, None
    specs = {s.name: s for s in Q.scene_specs()}
    sc = Q.render_scene(specs[name])
    return sc.psf, sc.y, sc.beads


def iterations_to(objective, ref: float, gap: float):
    """The first iteration after which ``objective`` stays within ``gap`` of ``ref`` on both sides (None: never).
    Both: the x iterate's objective can lie below the optimum while x is not yet non-negative (DiffuserCam 3D
    binned 2x when its penalties are not rebalanced in the first iterations: within 1% above from iteration 4)."""
    bad = np.flatnonzero(np.abs(np.asarray(objective, np.float64) / ref - 1.0) > gap)
    if bad.size and bad[-1] == len(objective) - 1:
        return None
    return int(bad[-1] + 2) if bad.size else 1


def parse_variants(text: str) -> dict:
    """"name=k:v,k:v;name2=" -> {name: {k: float(v)}} (in order)."""
    out = {}
    for item in filter(None, (s.strip() for s in text.split(";"))):
        name, _, kws = item.partition("=")
        out[name.strip()] = {k.strip(): float(v) for k, v in (kv.split(":") for kv in filter(None, kws.split(",")))}
    return out


def run_case(name: str, alphas, iters: int, log=print, param: str = "relaxation", variants=None) -> list[dict]:
    """``alphas``: the values of ``param``; or ``variants`` ({label: keywords}), whose labels key the rows."""
    psf, y, beads = load_case(name)
    variants = variants or {a: {param: a} for a in alphas}
    alphas = list(variants)
    long, stop = {}, {}
    for a, kw in variants.items():
        t = time.perf_counter()
        rec = cm2cl.reconstruct(y, psf, **kw, max_iter=iters, tol=0.0, psf_refine=0)
        long[a] = (np.asarray(rec.history["objective"]), time.perf_counter() - t)
        t = time.perf_counter()
        stop[a] = (cm2cl.reconstruct(y, psf, **kw, psf_refine=0), time.perf_counter() - t)
        log(f"{name} {param} {a}: {iters} iterations {long[a][1]:.1f} s; default stop {len(stop[a][0].log)} it")
    ref = min([float(o[-1]) for o, _ in long.values()] + [float(r.log[-1]["objective"]) for r, _ in stop.values()])
    rows = []
    for a in alphas:
        obj, secs = long[a]
        rec, ssecs = stop[a]
        row = {"case": name, "value": a, "s_per_iter": secs / iters}
        for g in GAPS:
            row[f"to_{g:g}"] = iterations_to(obj, ref, g)
        row["stop_iter"] = len(rec.log)
        row["stop_rule"] = rec.info["stop"]
        row["stop_gap"] = float(rec.log[-1]["objective"]) / ref - 1
        row["stop_s"] = ssecs
        row["residual"] = float(rec.log[-1].get("data", np.nan))
        if beads is not None:
            s = Q.score_beads(rec.volume, beads)
            row.update(recall=s["recall"], false_per_10=s["false_per_10"], axial_err=s["axial_err"])
        rows.append(row)
        log(f"  {param} {a}: to 1% {row['to_0.01']}, to 0.1% {row['to_0.001']}, stop {row['stop_iter']} it "
            f"(gap {row['stop_gap']:.2e})" + (f", recall {row['recall']:.2f}" if beads is not None else ""))
    return rows


def fmt(v, spec=""):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    return format(v, spec)


TITLES = {"relaxation": "Over-relaxation: iterations to an answer",
          "mu_v": "The initial penalty: iterations to an answer",
          "variants": "Iterations to an answer: settings compared"}
LABELS = {"relaxation": "alpha", "variants": "settings"}


def write_md(rows, path: Path, args, seconds: float) -> None:
    from cm2cl.device.runtime import get_runtime

    rt = get_runtime(None)
    param = args.param
    lab = LABELS.get(param, param)
    flag = {"relaxation": "--alphas", "variants": "--variants"}.get(param, f"--param {param} --values")
    values = f'"{args.variants}"' if param == "variants" else args.values
    lines = [
        f"# {TITLES.get(param, param + ': iterations to an answer')}",
        "",
        f"Made by `python tools/relaxation_study.py {flag} {values} --iters {args.iters} --cases {args.cases}` "
        f"in {seconds / 60:.1f} min on {rt.caps.platform} ({rt.caps.name}), {platform.machine()}, one run. "
        "Every other parameter at its default (background in the model, l1 at the universal threshold, TV off). "
        "For each case the reference is the lowest final objective of the long solves; 'to 1%' is the iteration "
        "after which the objective stays within 1% of it. 'stop' is the default stopping rule's solve: its "
        "iterations, its objective's gap to the reference, and for bead scenes the quality there.",
        "",
        f"| case | {lab} | to 1% | to 0.1% | stop: iterations | stop: gap | stop: s | recall | false / 10 | axial err |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['case']} | {r['value'] if isinstance(r['value'], str) else format(r['value'], 'g')} | {fmt(r['to_0.01'])} | {fmt(r['to_0.001'])} | "
                     f"{r['stop_iter']} ({r['stop_rule']}) | {r['stop_gap']:.2e} | {r['stop_s']:.1f} | "
                     f"{fmt(r.get('recall'), '.2f')} | {fmt(r.get('false_per_10'), '.1f')} | "
                     f"{fmt(r.get('axial_err'), '.2f')} |")
    lines.append("")
    first = rows[0]["value"] if param == "variants" and rows else 1.0
    base = {r["case"]: r for r in rows if r["value"] == first}
    values = list(dict.fromkeys(r["value"] for r in rows if r["value"] != first))
    if param != "variants":
        values = sorted(values)
    if base:
        name = lambda a: a if isinstance(a, str) else f"{lab} {a:g}"  # noqa: E731
        lines += [f"## Ratios to {name(first)} (iterations to 1%)", "", "| case | " + " | ".join(
            name(a) for a in values) + " |", "|---|" + "---|" * len(values)]
        for case, b in base.items():
            cells = []
            for a in values:
                r = next((r for r in rows if r["case"] == case and r["value"] == a), None)
                ok = r is not None and b["to_0.01"] and r["to_0.01"]
                cells.append(f"{b['to_0.01'] / r['to_0.01']:.2f}x" if ok else "-")
            lines.append(f"| {case} | " + " | ".join(cells) + " |")
        lines.append("")
    path.write_text(with_hand_written("\n".join(lines), path))   # hand-written readings stay


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--param", default="relaxation", choices=sorted(set(TITLES) - {"variants"}),
                    help="the parameter varied")
    ap.add_argument("--variants", default=None, help='named keyword sets instead, e.g. "issue=relaxation:1,mu_v:1;defaults="')
    ap.add_argument("--values", "--alphas", dest="values", default="1,1.5,1.6,1.8", help="its values, comma-separated")
    ap.add_argument("--iters", type=int, default=2000)
    ap.add_argument("--cases", default="beads,mm_aberr,photons200,bg_haze10,fibres,demo,dc2d,dc3d")
    ap.add_argument("--out", type=Path, default=None, help="default docs/relaxation.md (relaxation), docs/penalty.md (mu_v)")
    args = ap.parse_args(argv)
    variants = parse_variants(args.variants) if args.variants else None
    if variants:
        args.param = "variants"
    out = args.out or ROOT / "docs" / {"relaxation": "relaxation.md", "mu_v": "penalty.md"}.get(args.param, "iterations.md")
    values = [float(a) for a in args.values.split(",")]
    t0 = time.perf_counter()
    rows = []
    for c in args.cases.split(","):
        rows += run_case(c, values, args.iters, param=args.param, variants=variants)
    write_md(rows, out, args, time.perf_counter() - t0)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

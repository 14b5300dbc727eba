"""The paper's bead scenes (`fig3_beads`, `fig5_scattering`: 972 x 1296 sensor, 2x binned, 21 planes) simulated
and reconstructed at cm2cl's defaults, as a user would; recall and precision overall and by depth third
(emitters and detections split by their depth), lateral and axial error. Writes docs/paper_scenes.md and
the MIPs in docs/img/paper_<scene>_mip.png.

    python tools/paper_scenes.py [--scenes fig3_beads,fig5_scattering] [--max-iter N] [--binning B]
        [--trace 50,100,200] [--variants default,tv0] [--doc docs/paper_scenes.md]

``--binning`` simulates the scenes on a more (or less) binned sensor than their files say (4: a quarter
of the pixels, a few minutes per scene); the MIPs go to an ``img`` folder beside ``--doc``.

Every run goes through ``cm2cl.reconstruct``, the path a user's command takes (the defaults' PSF refinement
included; the table says what it did). ``--trace`` scores the iterate at those iterations too (what more
iterations buy; counted over the refinement's rounds and the final solve); ``--variants`` adds
runs with other weights: ``tv0`` = TV off (l1 only), ``dtype64`` = the default in float64, ``points`` =
TV off with each plane's l1 weight ~ ||h_i||^2 (``--prior points-weighted``; ``--prior points`` is TV off
alone, the ``tv0`` row).

Slow on a CPU (about 20 min per scene on 2 cores): a benchmark, not a test.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

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


def scene_at(name: str, binning: int | None):
    """The built-in scene ``name`` as a dict, its optics' binning replaced when ``binning`` is given."""
    import tomllib
    from cm2cl.simulate.scene import resolve_scene

    data = tomllib.loads(resolve_scene(name).read_text(encoding="utf-8"))
    if binning is not None:
        data.setdefault("optics", {})["binning"] = int(binning)
    return data


class _Recording:
    """Wraps the solver class ``cm2cl.reconstruct`` builds, keeping the last instance (the solve running now: a
    round of the PSF refinement or the final solve), so that ``--trace`` can score its iterate."""

    def __init__(self, cls):
        self.cls, self.last = cls, None

    def __call__(self, *args, **kwargs):
        self.last = self.cls(*args, **kwargs)
        return self.last


def run_variant(name, sim, label, var, kw, marks, ts, img_dir) -> dict:
    """One reconstruction of a simulated scene through ``cm2cl.reconstruct`` (the user's path: the PSF
    refinement of the defaults included), scored at the end and (``marks``: iterations counted over the
    refinement's rounds and the final solve, as the callback counts them) along the way."""
    from unittest import mock

    import cm2cl
    from cm2cl.solver import api

    trace = []
    rec_cls = _Recording(api.ADMMSolver)

    def score(x):
        m = analysis.score_beads(x, sim)
        return m, by_thirds(m, sim.depths_um)

    def cb(row):
        if row["iter"] in marks:
            s = rec_cls.last
            m, th = score(np.maximum(s.get_volume("x"), 0)[:, s.crop[0], s.crop[1]])
            trace.append((row["iter"], m["recall"], m["precision"], th))

    t = time.perf_counter()
    with mock.patch.object(api, "ADMMSolver", rec_cls):
        rec = cm2cl.reconstruct(np.asarray(sim.measurement, np.float64), sim.psf, voxel_size_um=sim.voxel_size_um,
                                depths_um=sim.depths_um, callback=cb if marks else None, **kw)
    tr = time.perf_counter() - t
    m, thirds = score(rec.volume)
    if var == "default":
        analysis.mip_png(rec.volume, img_dir / f"paper_{name}_mip.png", sim.voxel_size_um, sim.depths_um,
                         title=f"{name}: cm2cl defaults", gamma=0.6)
    pr = rec.info.get("psf_refine") or {}
    check = pr.get("check") or {}
    refine = (f"{pr.get('mode', 'given')}: {pr.get('rounds', 0)} round(s)"
              + (f", d {check['disagreement']:.3f}, F {check['f_statistic']:.2f}" if check else "")
              + (f" ({pr['skipped']})" if pr.get("skipped") else ""))
    est = (rec.info.get("attenuation") or {}).get("estimate")
    if est:   # --scattering-length-um auto: what it estimated, after a clear-medium solve of so many iterations
        refine += (f"; l_s estimated {est['scattering_length_um']:.0f} um" if est["scattering_length_um"]
                   else f"; l_s not applied ({est['reason']})") + f" after {est['first_solve_iterations']} iterations"
    return dict(scene=name, variant=label, shape=f"{sim.psf.shape[0]} x {sim.psf.shape[1]} x {sim.psf.shape[2]}",
                sim_s=ts, rec_s=tr, iterations=pr.get("iterations_total", rec.iterations),
                converged=rec.info["converged"], stop=rec.info["stop"], recall=m["recall"],
                precision=m["precision"], n_true=m["n_true"], thirds=thirds,
                lat=m.get("lateral_rms_um", float("nan")), ax=m.get("axial_rms_um", float("nan")),
                l1=rec.info["l1"], mib=rec.info["device_bytes"] / 2**20, trace=trace,
                dtype=np.dtype(kw.get("dtype", np.float32)).name, refine=refine)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="fig3_beads,fig5_scattering")
    ap.add_argument("--max-iter", type=int, default=None, help="default: the solver's default")
    ap.add_argument("--trace", default="", help="comma list of iterations at which the iterate is scored too")
    ap.add_argument("--variants", default="default", help="comma list of: default, tv0, dtype64, points, scattering, scattering_auto")
    ap.add_argument("--binning", type=int, default=None, help="sensor binning (default: the scene's own)")
    ap.add_argument("--doc", default=str(DOCS / "paper_scenes.md"))
    args = ap.parse_args(argv)
    rows = []
    img_dir = Path(args.doc).parent / "img"
    img_dir.mkdir(parents=True, exist_ok=True)
    marks = {int(v) for v in args.trace.split(",") if v.strip()}
    variants = {"default": ("defaults", {}), "tv0": ("TV off (tv 0, l1 default; = --prior points)", {"tv": 0.0}),
                "dtype64": ("defaults, float64", {"dtype": np.float64}),
                "points": ("TV off, l1 per plane ~ ||h_i||^2 (= --prior points-weighted)", {"tv_noise_ratio": 0.0, "l1_plane_power": 2.0}),
                "scattering": ("defaults, --scattering-length-um the scene's l_s", {"scattering_length_um": "scene"}),
                "scattering_auto": ("defaults, --scattering-length-um auto", {"scattering_length_um": "auto"})}
    unknown = [v for v in args.variants.split(",") if v not in variants]
    if unknown:
        raise SystemExit(f"--variants: unknown {', '.join(unknown)} (known: {', '.join(variants)})")
    lengths = {}   # the l_s (and surface) each scene was simulated with: the 'scattering' variant's model
    for name in args.scenes.split(","):
        eff = [e for e in scene_at(name, args.binning).get("effects", []) if e.get("name") == "scattering"]
        if eff:
            lengths[name] = {"scattering_length_um": float(eff[0]["ls_um"]),
                             **({"surface_um": float(eff[0]["surface_z_um"])}
                                if eff[0].get("surface_z_um") is not None else {})}
        elif "scattering" in args.variants.split(","):   # before any scene is simulated, not after the first
            raise SystemExit(f"--variants scattering: scene {name} has no scattering effect")
    for name in args.scenes.split(","):
        t = time.perf_counter()
        sim = simulate.simulate_scene(scene_at(name, args.binning))
        ts = time.perf_counter() - t
        for var in args.variants.split(","):
            label, extra = variants[var]
            label += f", sensor binned {args.binning}x" if args.binning else ""
            kw = dict(extra) if args.max_iter is None else {"max_iter": args.max_iter, **extra}
            if kw.get("scattering_length_um") == "scene":   # the l_s (and surface) the scene was simulated with
                kw.update(lengths[name])
                label = label.replace("the scene's l_s", f"{kw['scattering_length_um']:g}")
            rows.append(run_variant(name, sim, label, var, kw, marks, ts, img_dir))
            print(rows[-1], flush=True)
    from cm2cl.device import get_runtime

    cmd = " ".join(["python tools/paper_scenes.py", f"--scenes {args.scenes}", f"--variants {args.variants}"]
                   + ([f"--trace {args.trace}"] if args.trace else [])
                   + ([f"--max-iter {args.max_iter}"] if args.max_iter else [])
                   + ([f"--binning {args.binning}"] if args.binning else []))
    # rows of earlier runs (other scenes or variants) are kept: the doc shows every (scene, variant) measured
    store = Path(args.doc).with_suffix(".json")
    old = json.loads(store.read_text()) if store.exists() else []
    for r in rows:
        r["cmd"] = cmd
        r["thirds"] = [list(t) for t in r["thirds"]]
    keys = {(r["scene"], r["variant"]) for r in rows}
    rows = [r for r in old if (r["scene"], r["variant"]) not in keys] + rows
    store.write_text(json.dumps(rows, indent=1, default=float))
    cmd = "; ".join(dict.fromkeys(r["cmd"] for r in rows))
    lines = ["# The paper's bead scenes", "",
             f"Made by `{cmd}` on {get_runtime().caps.implementation}. "
             "Each scene is simulated with its effects (see `cm2cl simulate --list`) and reconstructed with "
             "the solver's defaults (and the variants named). Depth thirds split the true beads and the detections "
             "by depth.", "",
             "| scene | variant | planes x sensor | iterations | stop | recall | precision | recall / precision by "
             "depth third (near, middle, far) | beads per third | lateral RMS um | axial RMS um | PSF refinement | "
             "device MiB | s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        th = ", ".join(f"{a:.2f} / {b:.2f}" for a, b, _ in r["thirds"])
        n = ", ".join(str(c) for _, _, c in r["thirds"])
        lines.append(f"| {r['scene']} | {r['variant']} | {r['shape']} | {r['iterations']} | {r['stop']} | "
                     f"{r['recall']:.2f} | {r['precision']:.2f} | {th} | {n} | {r['lat']:.1f} | {r['ax']:.1f} | "
                     f"{r.get('refine', 'not run (plain solve)')} | {r['mib']:.0f} | {r['rec_s']:.0f} |")
    traced = [r for r in rows if r["trace"]]
    if traced:
        lines += ["", "The iterate scored along the way (recall / precision, and recall by depth third):", "",
                  "| scene | variant | iteration | recall | precision | recall by third |", "|---|---|---|---|---|---|"]
        for r in traced:
            for it, rc, pr, th in r["trace"]:
                th = [tuple(t) for t in th]
                lines.append(f"| {r['scene']} | {r['variant']} | {it} | {rc:.2f} | {pr:.2f} | "
                             + " / ".join(f"{a:.2f}" for a, _, _ in th) + " |")
    shown = dict.fromkeys(r["scene"] for r in rows if r["variant"].startswith("defaults") and "float64" not in r["variant"])
    lines += [""] + [f"![{name}](img/paper_{name}_mip.png)" for name in shown] + [""]
    doc = Path(args.doc)
    text = doc.read_text() if doc.exists() else ""
    if "\n## " in text:   # hand-written notes after the tables (what the figures mean) survive a re-run
        lines += [text[text.index("\n## ") + 1:]]
    doc.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()

"""The quality suite (issue 24, item 5): scenes rendered with a PSF the reconstruction is not given, and the
real DiffuserCam 2D/3D data, reconstructed by ``cm2cl.reconstruct`` with one or more configurations at 50,
200 and converged iterations and at the defaults, scored and written to docs/quality.md (table, summary,
MIPs in docs/img/quality_*.png; with ``--out docs/NAME.md``, docs/img/NAME_*.png).

    python tools/quality_suite.py [--config NAME=key=value,key=value ...] [--scenes a,b] [--quick]
        [--out docs/quality.md] [--no-reuse] [--real-bin 2] [--no-mips]

A configuration is a named set of ``cm2cl.reconstruct`` keywords, values read as Python literals (a value
that is not a literal is a string): ``--config points=tv_noise_ratio=0`` or
``--config w=tv_noise_ratio=0,l1_plane_power=2``; 'defaults' (no keywords) always runs first. A keyword
``reconstruct`` does not take is refused with one line before any solve. The suite's own keywords and value:
``suite_frame=raw`` gives the reconstruction the camera frame with its offset (default: the frame minus the
offset, as a user who subtracted it), and the value ``$camera`` stands for the scene's camera as a dict
(gain, offset, read_noise), e.g. ``--config cam=camera=$camera,suite_frame=raw``. ``suite_psf=calibrated``
gives the reconstruction, instead of the nominal PSF, the stack refined on a bead frame recorded through the
scene's optics (``cm2cl.analysis.quality.calibration_spec``; reconstructed at the defaults, its ``rec.psf``:
what ``cm2cl reconstruct BEADS --save-psf`` writes), the lab's calibration step; the real data have no such
frame and skip that configuration.

Iteration settings per (scene, configuration): '50' and '200' (max_iter 50 / 200, tol 0: exactly that many
iterations), 'converged' (max_iter 1000, the configuration's stopping rule), 'defaults' (the configuration
as given). With reuse (default), the 'defaults' row of a configuration that sets no stopping keyword is
the 'converged' run when that stopped within the default max_iter, else the '200' run when the default
max_iter is 200: the stopping rule does not change the iterates (tests/test_quality.py checks this).

Python: ``run_suite({'defaults': {}, 'points': {'tv_noise_ratio': 0}}, scenes=['beads'], quick=True)``
returns the rows as dicts.
"""

from __future__ import annotations

import argparse
import ast
import inspect
import math
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
from cm2cl.analysis import quality as Q  # noqa: E402
from benchlib import residual  # noqa: E402

DOCS = ROOT / "docs"
SETTINGS = ("50", "200", "converged", "defaults")
OVERRIDES = {"50": {"max_iter": 50, "tol": 0.0}, "200": {"max_iter": 200, "tol": 0.0},
             "converged": {"max_iter": 1000}, "defaults": {}}
STOP_KEYS = {"max_iter", "tol", "tol_change", "patience"}
SUITE_KEYS = {"suite_frame", "suite_psf"}
#: suite_psf's values: the nominal stack, or the one refined on the scene's calibration frame
SUITE_PSF = ("given", "calibrated")
#: keywords the suite passes itself (a configuration may not set them)
OWN_KEYS = {"measurement", "psf", "callback", "callback_every"}
REAL = {"dc2d": "DiffuserCam 2D (hand, real data, 1 plane; binned 4x: 300 x 400)",
        "dc3d": "DiffuserCam 3D (tilted resolution target, real data, 44 planes)"}
#: scenes whose MIPs the full run saves
MIP_SCENES = ("beads", "mm_all", "held_out", "dense", "fibres", "fibres_mm", "dc3d")
COLUMNS = ("scene", "kind", "config", "setting", "recall", "false_maxima", "false_per_10", "axial_err",
           "lateral_err", "f1", "nrmse", "energy_near", "residual", "iterations", "stop", "seconds", "n_beads",
           "reused")
HAND_MARK = "<!-- hand-written below this line: tools/quality_suite.py keeps it -->"


class ConfigError(ValueError):
    """A configuration the suite refuses (one line)."""


# ------------------------------------------------------------------------------------------------ configs
def _split_top(text: str, sep: str = ",") -> list[str]:
    """``text`` split at ``sep`` outside brackets and quotes."""
    out, depth, quote, cur = [], 0, None, []
    for ch in text:
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
        elif ch == sep and depth == 0:
            out.append("".join(cur))
            cur = []
            continue
        cur.append(ch)
    out.append("".join(cur))
    return [s for s in (p.strip() for p in out) if s]


def _value(text: str):
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def parse_config(text: str) -> tuple[str, dict]:
    """'NAME=key=value,key=value' (or 'NAME' alone: no keywords) -> (NAME, {key: literal value})."""
    name, _, rest = text.partition("=")
    name = name.strip()
    if not name or not name.replace("-", "").replace("_", "").replace(".", "").isalnum():
        raise ConfigError(f"--config {text!r}: expected NAME=key=value,key=value with a plain NAME")
    kw = {}
    for item in _split_top(rest):
        key, eq, val = item.partition("=")
        key = key.strip()
        if not eq or not key.isidentifier():
            raise ConfigError(f"--config {name}: {item!r} is not key=value")
        kw[key] = _value(val.strip())
    return name, kw


def reconstruct_keywords() -> set[str]:
    """The keywords ``cm2cl.reconstruct`` takes (its signature, which lists the declared parameters)."""
    sig = inspect.signature(cm2cl.reconstruct)
    return {p.name for p in sig.parameters.values()
            if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)} - OWN_KEYS


def check_configs(configs: dict) -> None:
    """Refuse (ConfigError, one line) a keyword ``reconstruct`` does not take, one the suite sets itself,
    or a solver parameter's value out of its bounds, before any solve."""
    from cm2cl.errors import InputError
    from cm2cl.solver.params import ADMMParams
    from dataclasses import fields

    known = reconstruct_keywords()
    declared = {f.name for f in fields(ADMMParams)}
    for name, kw in configs.items():
        bad = sorted(k for k in kw if k not in known and k not in SUITE_KEYS)
        if bad:
            raise ConfigError(f"config {name!r}: cm2cl.reconstruct takes no keyword {', '.join(map(repr, bad))}"
                              f" (it takes: {', '.join(sorted(known))})")
        own = sorted(k for k in kw if k in OWN_KEYS)
        if own:
            raise ConfigError(f"config {name!r}: the suite sets {', '.join(own)} itself")
        if kw.get("suite_frame", "offset-subtracted") not in ("raw", "offset-subtracted"):
            raise ConfigError(f"config {name!r}: suite_frame is 'raw' or 'offset-subtracted', got {kw['suite_frame']!r}")
        if kw.get("suite_psf", "given") not in SUITE_PSF:
            raise ConfigError(f"config {name!r}: suite_psf is {' or '.join(map(repr, SUITE_PSF))}, "
                              f"got {kw['suite_psf']!r}")
        try:
            ADMMParams(**{k: v for k, v in kw.items() if k in declared and v != "$camera"})
        except (InputError, TypeError, ValueError) as exc:
            raise ConfigError(f"config {name!r}: {str(exc).splitlines()[0]}") from None


def normalise_configs(configs) -> dict:
    """{name: kwargs} from a dict, or a list of 'NAME=k=v,...' strings or (name, kwargs) pairs; 'defaults'
    ({}) first unless given."""
    if isinstance(configs, dict):
        items = list(configs.items())
    else:
        items = [parse_config(c) if isinstance(c, str) else tuple(c) for c in (configs or [])]
    out = {}
    if "defaults" not in dict(items):
        out["defaults"] = {}
    for name, kw in items:
        if name in out:
            raise ConfigError(f"config {name!r} given twice")
        out[name] = dict(kw)
    check_configs(out)
    return out


# ------------------------------------------------------------------------------------------------ running
def _kwargs(kw: dict, setting: str, camera: dict | None) -> tuple[dict, str]:
    kw = dict(kw)
    frame = kw.pop("suite_frame", "offset-subtracted")
    kw.pop("suite_psf", None)
    kw = {k: (camera if v == "$camera" else v) for k, v in kw.items()}
    kw.update(OVERRIDES[setting])
    return kw, frame


def _solve(y, psf, kw):
    t = time.perf_counter()
    rec = cm2cl.reconstruct(y, psf, **kw)
    return rec, time.perf_counter() - t


def _row(scene_name, kind, config, setting, rec, secs, psf, y, sc=None, reused="") -> dict:
    row = dict.fromkeys(COLUMNS, float("nan"))
    row.update(scene=scene_name, kind=kind, config=config, setting=setting, iterations=int(rec.iterations),
               stop=str(rec.info.get("stop")), seconds=float(secs), reused=reused, residual=residual(psf, y, rec))
    if sc is not None:
        vol = rec.volume
        row["nrmse"] = Q.nrmse(vol, sc.truth)
        row["energy_near"] = Q.energy_near(vol, sc.truth)
        if sc.beads is not None:
            s = Q.score_beads(vol, sc.beads)
            row.update({k: s[k] for k in ("recall", "false_maxima", "false_per_10", "axial_err", "lateral_err", "f1")})
            row["n_beads"] = s["n_true"]
    return row


def _runs(kw: dict, reuse: bool):
    """The order of the settings and, per setting, None (run it) or the setting whose run it takes."""
    from cm2cl.solver.params import ADMMParams

    if reuse and not (STOP_KEYS & set(kw)):
        return ("converged", "200", "50", "defaults"), ADMMParams().max_iter
    return ("converged", "200", "50", "defaults"), None


def run_scene(name, kind, psf, y, configs, reuse, sc=None, raw=None, camera=None, keep=None, log=print,
              calibrated=None) -> list[dict]:
    """Every configuration x iteration setting on one scene; rows in SETTINGS order per configuration.
    ``keep`` (a dict) gets the 'defaults' volume per configuration. ``calibrated``: the PSF of the
    configurations with ``suite_psf='calibrated'`` (None: they are skipped, with a line in the log)."""
    rows = []
    given = psf
    for cname, ckw in configs.items():
        psf = given
        if ckw.get("suite_psf", "given") == "calibrated":
            if calibrated is None:
                log(f"{name:<12} {cname:<16} skipped: no calibration frame for this scene")
                continue
            psf = calibrated
        order, default_max = _runs(ckw, reuse)
        done, recs = {}, {}
        for setting in order:
            kw, frame = _kwargs(ckw, setting, camera)
            yy = raw if (frame == "raw" and raw is not None) else y
            src = ""
            if setting == "defaults" and default_max is not None:
                conv = recs["converged"][0]
                if conv.iterations <= default_max and conv.info.get("stop") != "max_iter":
                    src = "converged"
                elif default_max == 200:
                    src = "200"
            if src:
                rec, secs = recs[src]
                row = _row(name, kind, cname, setting, rec, secs, psf, y, sc, reused=src)
                if src == "200":
                    row["stop"] = "max_iter"
            else:
                rec, secs = _solve(yy, psf, kw)
                recs[setting] = (rec, secs)
                row = _row(name, kind, cname, setting, rec, secs, psf, y, sc)
            done[setting] = row
            if keep is not None and setting == "defaults":
                keep[cname] = rec.volume
            log(format_row(row))
        rows += [done[s] for s in SETTINGS]
    return rows


def calibrated_psf(spec, log=print) -> np.ndarray:
    """The PSF stack refined on ``spec``'s calibration frame (:func:`cm2cl.analysis.quality.calibration_spec`),
    reconstructed at the defaults from the nominal stack: ``rec.psf``."""
    cal = Q.render_scene(Q.calibration_spec(spec))
    t = time.perf_counter()
    rec = cm2cl.reconstruct(cal.y, cal.psf)
    pr = rec.info.get("psf_refine") or {}
    log(f"{spec.name:<12} calibration frame: psf_refine {pr.get('mode')}, {pr.get('rounds')} round(s), "
        f"{time.perf_counter() - t:.1f} s")
    return rec.psf if getattr(rec, "psf", None) is not None else cal.psf


def real_data(name: str, bin_factor: int):
    import datasets

    if name == "dc2d":
        if not datasets.available("diffusercam-2d"):
            return None
        return datasets.diffusercam_2d(4)
    if not datasets.available("diffusercam-3d"):
        return None
    return datasets.diffusercam_3d(bin_factor)


def _slug(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)


def scene_names(quick: bool = False) -> list[str]:
    return [s.name for s in Q.scene_specs(quick)] + ([] if quick else list(REAL))


def run_suite(configs, scenes=None, quick: bool = False, *, reuse: bool = True, real_bin: int = 2,
              mip_dir=None, mip_prefix: str = "quality", log=print) -> list[dict]:
    """Run the suite: ``configs`` ({name: reconstruct keywords}, or 'NAME=k=v,...' strings; 'defaults' is
    added first), ``scenes`` (names, default all of :func:`scene_names`), ``quick`` (the small scenes, no
    real data). Returns one dict per scene x config x setting with :data:`COLUMNS`. ``mip_dir``: save the
    MIPs of the representative scenes there, named ``{mip_prefix}_{scene}.png``."""
    configs = normalise_configs(configs)
    specs = {s.name: s for s in Q.scene_specs(quick)}
    known = list(specs) + ([] if quick else list(REAL))
    names = known if scenes is None else list(scenes)
    bad = [n for n in names if n not in known]
    if bad:
        raise ConfigError(f"unknown scene(s) {', '.join(bad)} (known{' with --quick' if quick else ''}: {', '.join(known)})")
    rows = []
    for n in names:
        keep = {} if (mip_dir is not None and n in MIP_SCENES) else None
        if n in specs:
            sc = Q.render_scene(specs[n])
            cal = calibrated_psf(specs[n], log) if any(kw.get("suite_psf") == "calibrated"
                                                       for kw in configs.values()) else None
            rows += run_scene(n, sc.spec.kind, sc.psf, sc.y, configs, reuse, sc=sc, raw=sc.raw,
                              camera=sc.spec.camera.as_dict(), keep=keep, log=log, calibrated=cal)
            if keep:
                mip_figure(keep, sc, Path(mip_dir) / f"{mip_prefix}_{n}.png", f"{n}: {sc.spec.what}")
        else:
            data = real_data(n, real_bin)
            if data is None:
                log(f"{n}: data not found in ../shared/data, skipped")
                continue
            psf, y = data
            rows += run_scene(n, "real", psf, y, configs, reuse, keep=keep, log=log)
            if keep and n == "dc3d":
                # depth-colour-coded XY / XZ / YZ MIPs (the tilted target: bar groups in XY, a streak in YZ)
                from cm2cl import analysis

                for cname, vol in keep.items():
                    analysis.mip_png(vol, Path(mip_dir) / f"{mip_prefix}_{n}_{_slug(cname)}.png", gamma=0.6,
                                     title=f"DiffuserCam 3D (binned {real_bin}x): {cname}, 'defaults' setting")
    return rows


# ------------------------------------------------------------------------------------------------ output
def _f(v, fmt="{:.2f}"):
    if isinstance(v, str):
        return v
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    return fmt.format(v)


def format_row(r: dict) -> str:
    return (f"{r['scene']:<12} {r['config']:<16} {r['setting']:<9} recall {_f(r['recall']):>4} "
            f"false/10 {_f(r['false_per_10'], '{:.1f}'):>4} ax {_f(r['axial_err']):>4} lat {_f(r['lateral_err']):>4} "
            f"nrmse {_f(r['nrmse']):>4} near {_f(r['energy_near']):>4} res {_f(r['residual'], '{:.4f}')} "
            f"it {r['iterations']:>4} {r['stop']:<9} {r['seconds']:6.1f} s{' (= ' + r['reused'] + ')' if r['reused'] else ''}")


def table(rows) -> list[str]:
    out = ["| scene | config | setting | recall | false max. | false / 10 beads | axial err (planes) | "
           "lateral err (vox) | NRMSE | energy near truth | data residual | iterations | stop | s |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        secs = f"{r['seconds']:.1f}" + (f" (= {r['reused']})" if r["reused"] else "")
        out.append(f"| {r['scene']} | {r['config']} | {r['setting']} | {_f(r['recall'])} | "
                   f"{_f(r['false_maxima'], '{:.0f}')} | {_f(r['false_per_10'], '{:.1f}')} | {_f(r['axial_err'])} | "
                   f"{_f(r['lateral_err'])} | {_f(r['nrmse'])} | {_f(r['energy_near'])} | {_f(r['residual'], '{:.4f}')} | "
                   f"{r['iterations']} | {r['stop']} | {secs} |")
    return out


def verdict(rows, scene, config) -> tuple[bool | None, str]:
    """(all targets met, a short text) for one scene x config at its 'defaults' row, with the convergence
    target (quality at 'converged' >= at '50')."""
    by = {r["setting"]: r for r in rows if r["scene"] == scene and r["config"] == config}
    d = by.get("defaults")
    if d is None:
        return None, ""
    if d["kind"] == "real":
        ok = d["stop"] != "max_iter"
        txt = (f"res {d['residual']:.4f}, {d['iterations']} it, {'stopped by the rule' if ok else 'hit max_iter'}"
               + (" (target visible? see its MIP)" if scene == "dc3d" else ""))
        if scene == "dc3d":
            ok = ok and d["residual"] <= 0.065
        return ok, ("pass: " if ok else "fail: ") + txt
    met = Q.targets_met(d)
    fails = []
    names = {"recall": ("recall", "{:.2f}"), "false_per_10": ("false/10", "{:.1f}"), "axial_err": ("axial", "{:.2f}"),
             "energy_near": ("near", "{:.3f}")}
    for k, ok in met.items():
        if not ok:
            fails.append(f"{names[k][0]} {_f(d[k], names[k][1])}")
    q50, qc = Q.quality_value(by["50"]), Q.quality_value(by["converged"])
    conv_ok = qc >= q50
    if not conv_ok:
        fails.append(f"conv < 50 it ({qc:.2f} < {q50:.2f})")
    ok = not fails
    if ok:
        txt = "pass" + (f" ({', '.join(f'{names[k][0]} {_f(d[k], names[k][1])}' for k in met)})")
    else:
        txt = "fail: " + ", ".join(fails)
    return ok, txt


def summary(rows, configs) -> list[str]:
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    out = ["| scene | " + " | ".join(configs) + " |", "|---" * (len(configs) + 1) + "|"]
    counts, runs = dict.fromkeys(configs, 0), dict.fromkeys(configs, 0)
    for s in scenes:
        cells = []
        for c in configs:
            ok, txt = verdict(rows, s, c)
            counts[c] += bool(ok)
            runs[c] += ok is not None
            cells.append(txt or "not run")
        out.append(f"| {s} | " + " | ".join(cells) + " |")
    out.append("| **passed** | " + " | ".join(f"**{counts[c]} of {runs[c]}**" for c in configs) + " |")
    return out


def mip_figure(volumes: dict, sc, path: Path, title: str, gamma: float = 0.6) -> Path:
    """XY and XZ maximum-intensity projections of each configuration's 'defaults' volume, one row per
    configuration, the true positions overlaid (beads: red circles; fibres: the truth's outline in cyan)."""
    from matplotlib.figure import Figure
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    n = len(volumes)
    nz, ny, nx = next(iter(volumes.values())).shape
    zs = max(1.0, 0.3 * nx / nz)
    fig = Figure(figsize=(9, 3.0 * n + 0.6), dpi=100)
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(n, 2, width_ratios=[nx, nx], hspace=0.35, wspace=0.15)
    for i, (cname, vol) in enumerate(volumes.items()):
        vol = np.maximum(np.asarray(vol, np.float64), 0)
        top = vol.max() or 1.0
        a1, a2 = fig.add_subplot(gs[i, 0]), fig.add_subplot(gs[i, 1])
        a1.imshow((vol.max(0) / top) ** gamma, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        a2.imshow((vol.max(1) / top) ** gamma, cmap="gray", vmin=0, vmax=1, interpolation="nearest",
                  aspect=zs, extent=(-0.5, nx - 0.5, nz - 0.5, -0.5))
        a1.set_title(f"{cname}: XY MIP", fontsize=9)
        a2.set_title(f"{cname}: XZ MIP (plane down)", fontsize=9)
        if sc is not None and sc.beads is not None:
            b = sc.beads
            a1.scatter(b[:, 2], b[:, 1], s=40, facecolors="none", edgecolors="red", linewidths=0.7)
            a2.scatter(b[:, 2], b[:, 0], s=40, facecolors="none", edgecolors="red", linewidths=0.7)
        elif sc is not None:
            a1.contour(sc.truth.max(0) > 0, levels=[0.5], colors="cyan", linewidths=0.5)
            a2.contour(sc.truth.max(1) > 0, levels=[0.5], colors="cyan", linewidths=0.5,
                       extent=(-0.5, nx - 0.5, -0.5, nz - 0.5), origin="upper")
        for a in (a1, a2):
            a.set_xticks([])
            a.set_yticks([])
    fig.suptitle(title, fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, facecolor="white", bbox_inches="tight")
    return path


def write_doc(path: Path, rows, configs, command: str, seconds: float, quick: bool, real_bin: int, mips) -> str:
    from cm2cl.device import get_runtime

    rt = get_runtime()
    old = path.read_text() if path.exists() else ""
    hand = old.split(HAND_MARK, 1)[1] if HAND_MARK in old else "\n\n(nothing yet)\n"
    specs = Q.scene_specs(quick)
    lines = ["# Quality suite", "",
             f"Made by `{command}` in {seconds / 60:.1f} min on {rt.caps.implementation} ({platform.processor() or platform.machine()}). "
             "Scenes are rendered with a PSF the reconstruction is not given (`cm2cl/analysis/quality.py`); "
             "what each column means is in the section after the tables.", "",
             "## Targets (issue 24)", "",
             f"- bead scenes at the defaults: recall >= {Q.TARGETS['recall']} (+-1 plane, 2 px), at most "
             f"{Q.TARGETS['false_per_10']:g} false maximum per 10 beads, mean |axial error| <= {Q.TARGETS['axial_err']} plane;",
             f"- fibre scenes: >= {Q.TARGETS['energy_near']:.0%} of the reconstructed energy within 2 voxels of the truth;",
             "- quality at convergence >= quality at 50 iterations on every scene (bead scenes: F1 of the +-1 plane match; "
             "fibres: energy near truth);",
             "- DiffuserCam 3D at the defaults: stops by the rule, residual <= 0.065, the tilted target visible "
             f"(here binned {real_bin}x: the residual is that of the binned problem).", "",
             "## Configurations", "",
             "| config | keywords of `cm2cl.reconstruct` |", "|---|---|"]
    for c, kw in configs.items():
        lines.append(f"| {c} | {', '.join(f'{k}={v!r}' for k, v in kw.items()) or '(none: the defaults)'} |")
    lines += ["", "## Summary: the 'defaults' row of each scene against the targets", "",
              "A cell passes when every target of its scene's kind holds at the configuration's own stopping rule "
              "and the converged run is no worse than 50 iterations; real data: stopped by the rule (and, for "
              "DiffuserCam 3D, residual <= 0.065).", ""] + summary(rows, configs)
    lines += ["", "## Scenes", "", "| scene | what | planes x sensor | beads / fibres |", "|---|---|---|---|"]
    for s in specs:
        if any(r["scene"] == s.name for r in rows):
            lines.append(f"| {s.name} | {s.what} | {s.nz} x {s.shape[0]} x {s.shape[1]} | "
                         f"{s.n_beads if s.kind == 'beads' else str(s.n_fibres) + ' fibres'} |")
    for n, what in REAL.items():
        if any(r["scene"] == n for r in rows):
            lines.append(f"| {n} | {what} | {'binned %dx' % real_bin if n == 'dc3d' else 'binned 4x'} | |")
    lines += ["", "## Every run", "", "Settings: '50' and '200' run exactly that many iterations (tol 0), 'converged' "
              "the stopping rule with max_iter 1000, 'defaults' the configuration as given; '(= converged)' or "
              "'(= 200)' marks a 'defaults' row that is the same run (see the tool's docstring).", ""] + table(rows)
    if mips:
        lines += ["", "## MIPs", "", "The 'defaults' volume of each configuration (grey, gamma 0.6; red circles: true beads, cyan: "
                  "true fibres); DiffuserCam 3D depth-colour-coded, one image per configuration.", ""]
        for p in mips:
            lines += [f"![{p.stem}](img/{p.name})", ""]
    text = "\n".join(lines) + "\n\n" + HAND_MARK + hand.rstrip("\n") + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return text


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", action="append", default=[], metavar="NAME=key=value,key=value",
                    help="a configuration (repeatable); 'defaults' always runs")
    ap.add_argument("--scenes", default=None, help="comma list of scene names (default: all)")
    ap.add_argument("--quick", action="store_true", help="a few small scenes, no real data (a smoke run)")
    ap.add_argument("--out", default=str(DOCS / "quality.md"), help="the markdown file (MIPs go to its img/)")
    ap.add_argument("--no-reuse", action="store_true", help="run the 'defaults' setting even where it is another run")
    ap.add_argument("--real-bin", type=int, default=2, help="binning of the DiffuserCam 3D data (default 2)")
    ap.add_argument("--no-mips", action="store_true")
    ap.add_argument("--list", action="store_true", help="list the scenes and exit")
    args = ap.parse_args(argv)
    if args.list:
        for s in Q.scene_specs(args.quick):
            print(f"{s.name:<12} {s.what}")
        if not args.quick:
            for n, w in REAL.items():
                print(f"{n:<12} {w}")
        return 0
    try:
        configs = normalise_configs(args.config)
        scenes = None if args.scenes is None else [s.strip() for s in args.scenes.split(",") if s.strip()]
        if scenes is not None:
            known = scene_names(args.quick)
            bad = [s for s in scenes if s not in known]
            if bad:
                raise ConfigError(f"unknown scene(s) {', '.join(bad)} (known: {', '.join(known)})")
    except ConfigError as exc:
        print(f"quality_suite: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    mip_dir = None if args.no_mips else out.parent / "img"
    t = time.perf_counter()
    rows = run_suite(configs, scenes, args.quick, reuse=not args.no_reuse, real_bin=args.real_bin, mip_dir=mip_dir,
                     mip_prefix=out.stem)
    secs = time.perf_counter() - t
    mips = []
    if mip_dir is not None:
        for n in MIP_SCENES:
            if any(r["scene"] == n for r in rows):
                names = ([f"{out.stem}_{n}_{_slug(c)}.png" for c in configs] if n == "dc3d"
                         else [f"{out.stem}_{n}.png"])
                mips += [mip_dir / f for f in names if (mip_dir / f).exists()]
    cmd = "python tools/quality_suite.py " + " ".join(
        [f"--config {c}={','.join(f'{k}={v!r}' for k, v in kw.items())}" for c, kw in configs.items() if c != "defaults"]
        + ([f"--scenes {args.scenes}"] if args.scenes else []) + (["--quick"] if args.quick else [])
        + (["--no-reuse"] if args.no_reuse else []) + ([f"--real-bin {args.real_bin}"] if args.real_bin != 2 else []))
    write_doc(out, rows, configs, cmd.strip(), secs, args.quick, args.real_bin, mips)
    print()
    print("\n".join(summary(rows, configs)))
    print(f"\n{len(rows)} rows in {secs:.0f} s; wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

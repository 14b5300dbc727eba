"""``cm2cl demo``: simulate the small built-in bead scene, reconstruct it, compare with the truth.

Prints the recovered vs true emitters (count, lateral and axial position errors in um) and the time
taken, and writes into OUTDIR: ``simulation/`` (measurement, PSF, ground truth, record),
``reconstruction.ome.tif`` (OME-TIFF with the object-space voxel size and depths), depth-colour-coded orthogonal MIPs of the reconstruction and of the ground
truth (PNG), and ``demo.json`` (written last).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..solver.params import ADMMParams

__all__ = ["register", "command", "demo"]

SCENE = "demo_beads"

#: the demo runs the solver's defaults (weights relative to the measurement's noise level, penalties from
#: the problem's scale, the convergence rule and its iteration cap). (A cap of 200, from the former
#: defaults, stopped the present ones before convergence: 24 maxima for 12 beads, against 15 converged.)
RECON = {"max_iter": ADMMParams().max_iter}


def register(subparsers):
    """Add the ``demo`` sub-command."""
    p = subparsers.add_parser(
        "demo", help="simulate a built-in bead scene, reconstruct it, report errors, save MIPs",
        description=__doc__.split("\n\n")[0] + " Runs in well under 2 minutes on a laptop CPU (PoCL).")
    p.add_argument("-o", "--output", dest="outdir", default="cm2cl-demo", metavar="OUTDIR",
                   help="output directory (default: ./cm2cl-demo)")
    p.add_argument("--device", default=None, help="OpenCL device index or name fragment (see `cm2cl devices`)")
    p.add_argument("--seed", type=int, default=None, help="simulation seed (default: the scene's)")
    p.add_argument("--iterations", type=int, default=RECON["max_iter"], help=f"ADMM iteration cap (default: the solver's, {RECON['max_iter']})")
    p.set_defaults(func=command)
    return p


def command(args) -> int:
    demo(args.outdir, device=args.device, seed=args.seed, max_iter=args.iterations, verbose=True)
    return 0


def demo(outdir="cm2cl-demo", *, device=None, seed=None, max_iter: int = RECON["max_iter"],
         verbose: bool = True) -> dict:
    """Run the demo; returns its summary (also written to OUTDIR/demo.json)."""
    from ..io import StagedOutput

    say = print if verbose else (lambda *a, **k: None)
    if max_iter < 1:
        raise InputError(f"--iterations: must be >= 1, got {max_iter}")
    out = Path(outdir)
    # checked and locked before any work, swapped in whole at the end (demo.json last)
    with StagedOutput(out, "demo.json", expected_bytes=8 << 20) as stage:   # the demo writes about 5 MB
        summary = _run(stage, device, seed, max_iter, say)
    say(f"  total {summary['seconds']['total']:.1f} s; wrote {out}/: simulation/, reconstruction.ome.tif, "
        "mip_reconstruction.png, mip_ground_truth.png, reconstruction_log.csv, demo.json")
    return summary


def _run(stage, device, seed, max_iter, say) -> dict:
    """Simulate, reconstruct, score, and write the outputs into ``stage`` (published last)."""
    from ..simulate import load_scene

    t0 = time.perf_counter()
    scene = load_scene(SCENE)
    say(f"cm2cl demo: simulating '{scene.name}': {scene.description}")
    sim, t_sim = _simulate(scene, seed, device, say)
    params = {**RECON, "max_iter": int(max_iter)}
    rec, t_rec = _reconstruct(sim, params, device, say)
    vol = np.asarray(rec.volume)
    m, summary = _score(vol, sim, scene, rec, params, say)
    summary["seconds"] = {"simulation": t_sim, "reconstruction": t_rec}
    _write(stage.dir, sim, scene, rec, vol, params, m)
    summary["seconds"]["total"] = time.perf_counter() - t0
    stage.publish("demo.json", json.dumps(summary, indent=2))
    return summary


def _simulate(scene, seed, device, say):
    from ..simulate import simulate_scene

    t = time.perf_counter()
    sim = simulate_scene(scene, seed, device)
    t_sim = time.perf_counter() - t
    say(f"  simulated a {sim.measurement.shape[0]} x {sim.measurement.shape[1]} {sim.measurement.dtype} "
        f"measurement and a {len(sim.depths_um)}-plane PSF in {t_sim:.1f} s "
        f"(seed {sim.record['seed']}, {sim.record['render']['path'].replace('_', '-')} model)")
    return sim, t_sim


def _reconstruct(sim, params, device, say):
    from ..solver import reconstruct

    say(f"  reconstructing (ADMM at the defaults, up to {params['max_iter']} iterations, padded to the PSF's "
        "support) ...", flush=True)
    t = time.perf_counter()
    # padding='support' (the linear convolution exactly, for a PSF whose light lies within its support:
    # the demo's drops none) on 0.69 of the 2M - 1 grid's voxels: 18.3 -> 14.9 s on 2 cores, the same beads
    rec = reconstruct(sim.measurement, sim.psf, device=device, padding="support",
                      voxel_size_um=sim.voxel_size_um, depths_um=sim.depths_um, **params)
    t_rec = time.perf_counter() - t
    from .frame import misfit_words

    conv = ("converged: relative residuals and change below "
            f"{rec.info['tol']:g}" if rec.info["converged"] else "NOT converged: stopped at the iteration cap")
    say(f"  reconstructed on {rec.info.get('device', '?')} in {t_rec:.1f} s: {rec.iterations} iterations, {conv}; "
        f"l1 {rec.info['l1']:.3g}, TV {rec.info['tv']:.3g} (volume-domain noise level {rec.info['noise_x']:.3g}; "
        f"measurement noise {rec.info['noise_sigma']:.3g} of the maximum); {misfit_words(rec.info['misfit'])}")
    return rec, t_rec


def _score(vol, sim, scene, rec, params, say):
    """(the bead matching, the summary without its times), the matched pairs and errors said."""
    from .. import analysis

    m = analysis.score_beads(vol, sim)
    found, true = m["found_um"], m["true_um"]
    rows = []
    for (i_det, i_true), lat, ax in zip(m["pairs"], m["lateral_error_um"], m["axial_error_um"]):
        rows.append({"true_um": true[i_true].round(1).tolist(), "found_um": found[i_det].round(1).tolist(),
                     "lateral_error_um": float(lat), "axial_error_um": float(ax)})
    rows.sort(key=lambda r: r["true_um"][2])
    say(f"\n  {'true x, y, z (um)':>26s}   {'recovered x, y, z (um)':>26s}   lateral  axial (um)")
    for r in rows:
        tx, ty, tz = r["true_um"]
        fx, fy, fz = r["found_um"]
        say(f"  {tx:8.0f} {ty:8.0f} {tz:8.0f}   {fx:8.0f} {fy:8.0f} {fz:8.0f}   {r['lateral_error_um']:7.1f} "
            f"{r['axial_error_um']:+7.1f}")
    lat, ax = m["lateral_error_um"], m["axial_error_um"]
    summary = {
        "scene": scene.name, "seed": sim.record["seed"], "device": rec.info.get("device", "?"),
        "emitters": {"true": m["n_true"], "detected": m["n_detected"], "matched": m["n_matched"],
                     "recall": m["recall"], "precision": m["precision"]},
        "lateral_error_um": {"mean": float(lat.mean()) if lat.size else None,
                             "rms": m["lateral_rms_um"], "max": float(lat.max()) if lat.size else None},
        "axial_error_um": {"mean": float(ax.mean()) if ax.size else None,
                           "rms": m["axial_rms_um"], "max_abs": float(np.abs(ax).max()) if ax.size else None},
        "voxel_size_um": list(sim.voxel_size_um), "depths_um": sim.depths_um.tolist(),
        "reconstruction": {"params": params, "iterations": rec.iterations, "stop": rec.info["stop"],
                           "converged": rec.info["converged"], "l1": rec.info["l1"], "tv": rec.info["tv"],
                           "noise_sigma": rec.info["noise_sigma"], "misfit": rec.info["misfit"],
                           "scaling": rec.scaling},
        "matching": {"threshold": analysis.emitters.DETECT_THRESHOLD,
                     "lateral_tolerance_um": m["lateral_tolerance_um"], "axial_tolerance_um": m["axial_tolerance_um"]},
        "pairs": rows,
    }
    say(f"\n  emitters: {m['n_true']} true, {m['n_detected']} detected, {m['n_matched']} matched "
        f"(recall {100 * m['recall']:.0f} %, precision {100 * m['precision']:.0f} %)")
    if lat.size:
        dz, dxy = sim.voxel_size_um[0], sim.voxel_size_um[1]
        say(f"  lateral error: mean {lat.mean():.1f} um, RMS {m['lateral_rms_um']:.1f} um, max {lat.max():.1f} um "
            f"(object voxel {dxy:.1f} um)")
        say(f"  axial error:   mean {ax.mean():+.1f} um, RMS {m['axial_rms_um']:.1f} um, max {np.abs(ax).max():.1f} um "
            f"(plane spacing {dz:.0f} um)")
    return m, summary


def _write(tmp, sim, scene, rec, vol, params, m) -> None:
    """The outputs, built in the staging folder ``tmp`` (swapped in for OUTDIR at the end, demo.json last)."""
    from .. import analysis
    from ..io import OBJECT_SPACE, write_tiff
    from ..simulate import write_simulation

    write_simulation(sim, tmp / "simulation")
    write_tiff(tmp / "reconstruction.ome.tif", vol.astype(np.float32), voxel_size_um=rec.voxel_size_um,
               depths_um=rec.depths_um,
               extra={"kind": "reconstruction", "scene": scene.name, "voxel_space": OBJECT_SPACE,
                      "params": params, "scaling": rec.scaling})
    title = f"{scene.name}: reconstruction ({m['n_matched']}/{m['n_true']} beads matched)"
    region = analysis.content_region(sim.ground_truth, margin=12)
    analysis.mip_png(vol, tmp / "mip_reconstruction.png", sim.voxel_size_um, sim.depths_um, title=title,
                     gamma=0.6, region=region)
    analysis.mip_png(sim.ground_truth, tmp / "mip_ground_truth.png", sim.voxel_size_um, sim.depths_um,
                     title=f"{scene.name}: ground truth", gamma=0.6, region=region)
    rec.write_log(tmp / "reconstruction_log.csv")

"""Warm starts and iterations to an answer (issue 28): how many iterations a solve needs to come within 1%
(and 0.1%) of the converged objective when it starts from

* ``cold``: zero (the default);
* ``answer``: the problem's own converged answer (a check: a consistent start stays there);
* ``next frame``: the converged answer of the previous frame of a series (beads brighter or dimmer by up to
  30%, fresh noise): what ``--warm-start`` does for a time series;
* ``coarse``: the 2x2-binned problem's answer, upsampled (a coarse-to-fine start); its own iterations
  are counted at their measured cost in fine iterations.

    python tools/warm_start_study.py [--cases beads,mm_aberr,demo,dc3d] [--iters 2000] [--out docs/warm_start.md]

The reference objective of a case is the lowest final objective of its long solves; "to 1%" is the iteration
after which the objective stays within 1% of it ('-' where it never does), as in tools/relaxation_study.py.
Every solve is ``cm2cl.reconstruct`` at the defaults with ``tol=0`` (the long solves) or at the defaults
(the 'stop' column: the default stopping rule from that start).
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
from relaxation_study import fmt, iterations_to, load_case  # noqa: E402

GAPS = (0.01, 0.001)


def bin_sensor(a):
    """2 x 2 sums of the last two axes (an odd last row or column dropped)."""
    ny, nx = a.shape[-2] // 2 * 2, a.shape[-1] // 2 * 2
    a = np.asarray(a, np.float64)[..., :ny, :nx]
    return a.reshape(a.shape[:-2] + (ny // 2, 2, nx // 2, 2)).sum(axis=(-3, -1))


def coarse_psf(psf):
    """The PSF of the binned problem for a volume constant on 2 x 2 blocks: with y and x binned by 2 x 2 sums,
    tap D (coarse offsets) is K(D) = 1/4 sum_e m(e) h(2D + e), m = (1, 2, 1) x (1, 2, 1), i.e. 4 (h * t)(2D)
    with t the 2D triangle [1, 2, 1]^2 / 16; taps follow the package's convention (tap r at offset r - M // 2)."""
    from scipy.ndimage import convolve1d

    psf = np.asarray(psf, np.float64)
    t = np.array([0.25, 0.5, 0.25])
    sm = convolve1d(convolve1d(psf, t, axis=-2, mode="constant"), t, axis=-1, mode="constant") * 4.0
    My, Mx = psf.shape[1:]
    my, mx = My // 2, Mx // 2
    rows = 2 * (np.arange(my) - my // 2) + My // 2
    cols = 2 * (np.arange(mx) - mx // 2) + Mx // 2
    out = np.zeros((psf.shape[0], my, mx))
    ry, rx = (rows >= 0) & (rows < My), (cols >= 0) & (cols < Mx)
    out[:, np.flatnonzero(ry)[:, None], np.flatnonzero(rx)[None, :]] = sm[:, rows[ry][:, None], cols[rx][None, :]]
    return out


def upsample(xc, shape):
    """The coarse volume (block sums) back on the fine grid: each block's value / 4 on its 2 x 2 voxels."""
    x = np.zeros(shape)
    up = np.repeat(np.repeat(xc, 2, -2), 2, -1) / 4.0
    x[:, :up.shape[1], :up.shape[2]] = up
    return x


def next_frame(name: str, seed: int = 5):
    """(psf, y) of a second frame of the case's scene: the same objects, each bead (connected object) 0.7-1.3x
    as bright, fresh shot and read noise; None for cases without a rendered truth."""
    from scipy import ndimage

    from cm2cl.analysis import quality as Q

    specs = {s.name: s for s in Q.scene_specs()}
    if name not in specs:
        return None
    sc = Q.render_scene(specs[name])
    rng = np.random.default_rng(seed)
    lab, n = ndimage.label(sc.truth > 0.02 * sc.truth.max())
    gain = np.concatenate([[1.0], rng.uniform(0.7, 1.3, n)])
    img = Q.object_image(sc.psf_true, sc.truth * gain[lab])
    img[img < 1e-9 * img.max()] = 0.0
    scale = sc.signal.max() / Q.object_image(sc.psf_true, sc.truth).max()
    y = rng.poisson(img * scale + sc.bg) + rng.normal(0.0, sc.spec.camera.read_noise, img.shape)
    return sc.psf, y


def solve(y, psf, iters, x0=None):
    t = time.perf_counter()
    long = cm2cl.reconstruct(y, psf, max_iter=iters, tol=0.0, x0=x0, psf_refine=0)
    tl = time.perf_counter() - t
    stop = cm2cl.reconstruct(y, psf, x0=x0, psf_refine=0)
    return np.asarray(long.history["objective"]), tl / iters, stop, long


def run_case(name: str, iters: int, log=print) -> list[dict]:
    psf, y, _ = load_case(name)
    runs = {}
    obj, spi, stop, long = solve(y, psf, iters)
    runs["cold"] = (obj, stop, 0.0)
    runs["answer"] = solve(y, psf, iters, long.volume)[0:3:2] + (0.0,)
    t = time.perf_counter()
    coarse = cm2cl.reconstruct(bin_sensor(y), coarse_psf(psf), psf_refine=0)
    cost = (time.perf_counter() - t) / spi   # the coarse solve in fine iterations
    o, _, st, _ = solve(y, psf, iters, upsample(coarse.volume, psf.shape))
    runs["coarse"] = (o, st, cost)
    ref = min(float(o[-1]) for o, _, _ in runs.values())
    rows = [row(name, k, *v, ref, spi) for k, v in runs.items()]
    nxt = next_frame(name)
    if nxt is not None:   # the next frame: its own reference, cold against warm from this frame's answer
        psf2, y2 = nxt
        o_cold, _, st_cold, _ = solve(y2, psf2, iters)
        o_warm, _, st_warm, _ = solve(y2, psf2, iters, long.volume)
        ref2 = min(float(o_cold[-1]), float(o_warm[-1]))
        rows += [row(name, "next frame: cold", o_cold, st_cold, 0.0, ref2, spi),
                 row(name, "next frame: warm", o_warm, st_warm, 0.0, ref2, spi)]
    for r in rows:
        log(f"{name} {r['start']}: first objective {r['first']:.3f}x, to 1% {r['to_0.01']}, "
            f"stop {r['stop_iter']} it (gap {r['stop_gap']:.2e})")
    return rows


def row(case, start, obj, stop, cost, ref, spi) -> dict:
    r = {"case": case, "start": start, "first": float(obj[0]) / ref, "at50": float(obj[min(49, len(obj) - 1)]) / ref,
         "coarse_cost": cost, "s_per_iter": spi}
    for g in GAPS:
        r[f"to_{g:g}"] = iterations_to(obj, ref, g)
    r["stop_iter"] = stop.iterations
    r["stop_gap"] = float(stop.history["objective"][-1]) / ref - 1
    return r


def total(r, key):
    """Iterations to a gap plus the coarse solve's cost in fine iterations."""
    return None if r[key] is None else r[key] + r["coarse_cost"]


def write_md(rows, path: Path, args, seconds: float) -> None:
    from cm2cl.device.runtime import get_runtime

    rt = get_runtime(None)
    try:
        import pyvkfft  # noqa: F401
        fft = "with pyvkfft"
    except ImportError:
        fft = "without pyvkfft"
    lines = [
        "# Warm starts: iterations to an answer",
        "",
        f"Made by `python tools/warm_start_study.py --cases {args.cases} --iters {args.iters}` in "
        f"{seconds / 60:.1f} min on {rt.caps.platform} ({rt.caps.name}, {platform.machine()}, {fft}), one run; "
        "every parameter at its default. 'first': the objective after the first iteration over the reference "
        "(the lowest final objective of the case's long solves); 'to 1%' / 'to 0.1%': the iteration after which "
        "the objective stays within that gap of it; 'coarse cost': the 2x2-binned solve's seconds in fine "
        "iterations (added in 'to 1% with the coarse solve'); 'stop': iterations of the default stopping rule "
        "from that start and its objective's gap. 'next frame' rows: a second frame of the scene (each bead "
        "0.7-1.3x as bright, fresh noise), cold or warm from the first frame's answer, against their own reference.",
        "",
        "| case | start | first | at 50 it | to 1% | to 0.1% | coarse cost | to 1% with the coarse solve | stop: iterations | stop: gap |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['case']} | {r['start']} | {r['first']:.3f} | {r['at50']:.4f} | {fmt(r['to_0.01'])} | "
                     f"{fmt(r['to_0.001'])} | {r['coarse_cost']:.0f} | {fmt(total(r, 'to_0.01'), '.0f')} | "
                     f"{r['stop_iter']} | {r['stop_gap']:.2e} |")
    lines.append("")
    path.write_text("\n".join(lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="beads,mm_aberr,demo,dc3d")
    ap.add_argument("--iters", type=int, default=2000)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "warm_start.md")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = []
    for c in args.cases.split(","):
        rows += run_case(c, args.iters)
    write_md(rows, args.out, args, time.perf_counter() - t0)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""Seconds per ADMM iteration of one problem on several padded grids (cm2cl.solver.forward.fast_grid's
reasons: plane strides that alias in the cache, rows that are not whole vectors), runs alternating
between the grids so that the machine's drift hits them alike. Writes a section of docs/benchmarks.md.

    python tools/bench_padding.py [--size 256x256x16] [--grids 512x512 540x512 ...] [--rounds 3]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import markdown_table, parse_size, write_section  # noqa: E402
from bench_admm import SKIP, per_iteration, problem  # noqa: E402

from cm2cl.device import get_runtime  # noqa: E402
from cm2cl.solver.admm import ADMMSolver  # noqa: E402
from cm2cl.solver.forward import choose_padded_shape  # noqa: E402
from cm2cl.solver.params import ADMMParams  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="256x256x16")
    ap.add_argument("--grids", nargs="+", default=["512x512", "auto", "512x560", "576x512", "512x640", "512x648",
                                                   "520x540", "540x520"])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--iters", type=int, default=8)
    a = ap.parse_args(argv)
    rt = get_runtime()
    my, mx, nz = parse_size(a.size)
    psf, y = problem(my, mx, nz, np.random.default_rng(0))
    grids = [choose_padded_shape((my, mx), "cl") if g == "auto" else tuple(int(v) for v in g.split("x"))
             for g in a.grids]
    p = ADMMParams(max_iter=SKIP + a.iters, tol=0)
    solvers = {}
    for g in grids:
        solvers[g] = ADMMSolver(psf, p, backend="cl", padded_shape=g)
        solvers[g].solve(y)   # warm-up
    times = {g: [] for g in grids}
    for _ in range(a.rounds):
        for g in grids:
            times[g].append(per_iteration(solvers[g].solve(y), SKIP))
    auto = choose_padded_shape((my, mx), "cl")
    rows = []
    for g in grids:
        t = np.array(times[g])
        pw = (g[0] * g[1]) & -(g[0] * g[1])
        rows.append([f"{g[0]} x {g[1]}" + (" (chosen)" if g == auto else ""), f"{g[0] * g[1] * 4 / 2**10:.0f}",
                     f"2^{pw.bit_length() - 1}", f"{g[1] % 8 == 0}", " / ".join(f"{v * 1e3:.0f}" for v in t),
                     f"{np.median(t) * 1e9 / (g[0] * g[1] * nz):.1f}"])
    head = ["padded grid", "plane KiB (float32)", "largest power of 2 in the plane's voxels", "rows whole vectors",
            "ms per iteration (each round)", "ns per voxel (median)"]
    text = (f"Device: **{rt.caps.name}** ({rt.caps.implementation}), {os.cpu_count()} host cores; float32, sensor "
            f"{my} x {mx}, {nz} planes, FFT backend cl; median time between iterations {SKIP + 1}-{SKIP + a.iters}, "
            f"{a.rounds} rounds alternating between the grids. `python tools/bench_padding.py --size {a.size}`\n\n"
            + markdown_table(head, rows))
    print(text)
    print("written to", write_section("Padded grid choice (tools/bench_padding.py)", text))


if __name__ == "__main__":
    main()

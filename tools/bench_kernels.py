"""Where an ADMM iteration's time goes, kernel by kernel, and how close each memory-bound kernel runs to
the device's copy bandwidth (issue 10, item 6: the stencil and reduction kernels against a copy).

Every kernel launch of a few iterations is timed alone (the queue is drained before and after it, so
launches do not overlap; the sum is therefore a little above an iteration's real time). Each kernel's
bytes are the minimum it must move per iteration, from what it reads and writes (V: one real volume of
all planes, S: one spectrum volume; the lean state of cm2cl/solver/admm.py), whatever its launches:

    rhs_volume 6V per launch (u, s, px, py, pz in; g out) update_w 4V (x, previous x, s in; s out)
    tv_residual 6V the first time (x, p in; r, z out), 5V after (z, p in; r out)
    tv_dual_step 7V per TV iteration (p, r in; p out)  tv_finish 9V (u, x, z, p, s in; u, next rhs out)
    (rhs_volume runs only where tv_finish's rhs does not apply: the first iteration, changed penalties)
    xstep_accumulate 2S (spectra, PSF spectra in; on CPUs in runs of ACC_PLANES planes, several launches)
    xstep_solve 3S per launch (spectra, PSF spectra in; out)
    FFT kernels of cm2cl's own backend, per volume transform: rows_r2c V + S, cols 2S, rows_c2r S + V;
    each iteration transforms the volume and one plane each way (the data split's H x and its rhs):
    rows_r2c and rows_c2r (V + S)(1 + 1/nz), cols 4S(1 + 1/nz); where xstep_solve runs inside the
    inverse's column pass (ADMMSolver.fuse_xstep), that pass also reads the PSF spectra (+S)

Writes a section of docs/benchmarks.md.

    python tools/bench_kernels.py [--size 324x432x16] [--iters 5]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pyopencl as cl

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import copy_bandwidth, markdown_table, parse_size, write_section  # noqa: E402
from bench_admm import SKIP, per_iteration, problem  # noqa: E402

from cm2cl.device import get_runtime  # noqa: E402
from cm2cl.solver.admm import ADMMSolver  # noqa: E402
from cm2cl.solver.params import ADMMParams  # noqa: E402


def bytes_model(tv_iters, nz, fused):
    """Bytes per iteration in units of (V, S), by kernel name; rhs_volume and xstep_solve: per launch
    (they run on some iterations, or only unfused)."""
    plane = 1 + 1 / nz   # the volume and one plane
    return {"update_w": (4, 0), "tv_residual": (6 + 5 * (tv_iters - 1), 0),
            "tv_dual_step": (7 * tv_iters, 0), "tv_finish": (9, 0), "xstep_accumulate": (0, 2),
            "rows_r2c": (plane, plane), "cols": (0, 4 * plane + (1 if fused else 0)), "rows_c2r": (plane, plane)}


PER_LAUNCH = {"rhs_volume": (6, 0), "xstep_solve": (0, 3)}


class KernelTimer:
    """Times every pyopencl kernel launch alone while active (drains the queue around each one)."""

    def __init__(self):
        self.seconds = defaultdict(float)
        self.calls = defaultdict(int)
        self.sizes = defaultdict(set)

    def __enter__(self):
        self._orig = cl.Kernel.__call__
        orig, me = self._orig, self

        def timed(k, queue, *args, **kw):
            queue.finish()
            t = time.perf_counter()
            ev = orig(k, queue, *args, **kw)
            queue.finish()
            me.seconds[k.function_name] += time.perf_counter() - t
            me.calls[k.function_name] += 1
            me.sizes[k.function_name].add(tuple(args[0]) if args and isinstance(args[0], tuple) else None)
            return ev

        cl.Kernel.__call__ = timed
        return self

    def __exit__(self, *exc):
        cl.Kernel.__call__ = self._orig


def measure(size: str, iters: int, backend: str, bw: float):
    my, mx, nz = parse_size(size)
    psf, y = problem(my, mx, nz, np.random.default_rng(0))
    p = ADMMParams(max_iter=SKIP + iters, tol=0)
    s = ADMMSolver(psf, p, backend=backend)
    s.solve(y)   # warm-up: kernel builds and first launches
    rec = s.solve(y)
    wall = per_iteration(rec, SKIP)
    kt = KernelTimer()

    def after(row):   # time the launches of iterations SKIP + 1 on (bench_admm.SKIP)
        if row["iter"] == SKIP:
            kt.__enter__()

    try:
        s.solve(y, callback=after)
    finally:
        kt.__exit__()
    V = nz * s.P[0] * s.P[1] * s.dtype.itemsize
    S = nz * int(np.prod(s.parts[0].spec_plane)) * 2 * s.dtype.itemsize
    fused = s.fuse_xstep and all(part.plan(b - a, s.backend).fuses_xstep for part in s.parts for a, b in part.bounds)
    model = bytes_model(p.tv_iters, nz, fused)
    rows, total = [], 0.0
    for name in sorted(kt.seconds, key=lambda n: -kt.seconds[n]):
        sec = kt.seconds[name] / iters
        total += sec
        calls = kt.calls[name] / iters
        if name in model or name in PER_LAUNCH:
            v, sp = PER_LAUNCH[name] if name in PER_LAUNCH else model[name]
            nbytes = (v * V + sp * S) * (calls if name in PER_LAUNCH else 1)
            rate = nbytes / sec
            rows.append([name, f"{calls:g}", f"{sec * 1e3:.1f}", f"{nbytes / 1e6:.0f}", f"{rate / 1e9:.1f}",
                         f"{rate / bw:.2f}"])
        else:
            rows.append([name, f"{calls:g}", f"{sec * 1e3:.1f}", "", "", ""])
    return s, rows, total, wall


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="324x432x16")
    ap.add_argument("--iters", type=int, default=5)
    ap.add_argument("--backend", default="cl")
    a = ap.parse_args(argv)
    rt = get_runtime()
    bw = copy_bandwidth(rt)
    s, rows, total, wall = measure(a.size, a.iters, a.backend, bw)
    head = ["kernel", "calls / iteration", "ms / iteration", "MB moved / iteration (model)", "GB/s",
            "x copy kernel"]
    text = (f"Device: **{rt.caps.name}** ({rt.caps.implementation}), {os.cpu_count()} host cores; float32, "
            f"{a.size} (padded {s.P[0]} x {s.P[1]}), FFT backend {a.backend}, tv_iters={s.p.tv_iters}; each launch "
            f"timed alone over iterations {SKIP + 1}-{SKIP + a.iters} (bench_admm.py: past the adaptive penalties' "
            f"first {SKIP}); copy kernel {bw / 1e9:.1f} GB/s (read + write). Sum of the "
            f"kernels {total * 1e3:.0f} ms per iteration against {wall * 1e3:.0f} ms between iterations of a "
            f"normal run. Bytes: the minimum each kernel must read and write (see the tool's docstring). "
            f"`python tools/bench_kernels.py --size {a.size} --iters {a.iters}`\n\n" + markdown_table(head, rows))
    print(text)
    print("written to", write_section("Kernels of one iteration (tools/bench_kernels.py)", text))


if __name__ == "__main__":
    main()

"""Seconds per ADMM iteration and device memory on the current OpenCL device, against the float32
numpy/scipy.fft version of the same algorithm (cm2cl.reference.admm with dtype=float32 and
scipy workers = all cores), per FFT backend; and the ratio to a memory-bandwidth floor (a copy
kernel's bytes/s on the same device times the bytes one iteration must move).
Writes the table to docs/benchmarks.md.

    python tools/bench_admm.py [--sizes 256x256x16 324x432x16] [--iters 10]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import scipy.fft

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import best_time, copy_bandwidth, markdown_table, parse_size, write_section  # noqa: E402

from cm2cl import reference
from cm2cl.device import fft  # noqa: E402
from cm2cl.solver.admm import ADMMSolver  # noqa: E402
from cm2cl.device import get_runtime  # noqa: E402
from cm2cl.solver.memory import iteration_bytes  # noqa: E402
from cm2cl.solver.params import ADMMParams  # noqa: E402
from cm2cl.solver.terms import default_terms  # noqa: E402


#: iterations before the timed ones: the adaptive penalty policy may change mu on each of the first ten
#: (cm2cl.solver.control), and then the x step makes its own rhs (rhs_volume) instead of taking the one
#: TV finish made; a solve of a hundred iterations or more spends most of them past that
SKIP = 10
#: device solves per row, each right after a copy-rate measurement: the row gives the median seconds
#: and the median of the per-solve ratios to the floor (this machine drifts by up to 1.5x between minutes,
#: copies and kernels alike, so a ratio of two measurements taken together is the steadier figure)
RUNS = 5


def per_iteration(rec, skip: int = 0) -> float:
    """Median seconds between consecutive iterations of a run's log after the first ``skip`` (setup and
    read-back excluded)."""
    return float(np.median(np.diff(rec.log_array("seconds"))[skip:]))


def fft_pass(s):
    """The FFTs of one iteration: forward and inverse of every slab (the lean layout: forward twice) and
    of one plane each way."""
    for part in s.parts:
        for j, n, a in part.slabs(scratch=("g", "spec")):
            for _ in range(2 if part.lean else 1):
                part.plan(n, s.backend).forward(a["g"], a["spec"])
            part.plan(n, s.backend).inverse(a["spec"], a["g"])
        pl = part.planes
        part.plan2d.forward(pl["r"], pl["R"])
        part.plan2d.inverse(pl["R"], pl["hx"])


def problem(my, mx, nz, rng):
    psf = np.zeros((nz, my, mx), np.float32)
    for i in range(nz):  # a 3x3 array of foci whose spacing changes with depth, like the CM2 PSF
        d = int(min(my, mx) * (0.25 + 0.15 * i / max(nz - 1, 1)))   # 0.25 + 0.01 i for 16 planes
        for a in (-1, 0, 1):
            for b in (-1, 0, 1):
                psf[i, my // 2 + a * d, mx // 2 + b * d] = 1.0
    y = rng.random((my, mx)).astype(np.float32)
    return psf, y


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", nargs="+", default=["256x256x16", "324x432x16"])
    ap.add_argument("--iters", type=int, default=10)
    a = ap.parse_args(argv)
    rt = get_runtime()
    rng = np.random.default_rng(0)
    p = ADMMParams(max_iter=SKIP + a.iters, tol=0)
    rows, bws = [], []
    for spec in a.sizes:
        my, mx, nz = parse_size(spec)
        psf, y = problem(my, mx, nz, rng)
        numpy_s = {}   # by padded grid
        # numpy/scipy's own best grid: the smallest fast length of twice the sensor per axis (issue 10)
        numpy_grid = tuple(scipy.fft.next_fast_len(2 * m, real=True) for m in (my, mx))

        def numpy_on(grid):
            if grid not in numpy_s:
                numpy_s[grid] = per_iteration(reference.admm(y, psf, p, padded_shape=grid, dtype=np.float32,
                                                             workers=-1), SKIP)
            return numpy_s[grid]
        # each backend in the layout a problem that fits gets, cm2cl's FFT in the lean layout too, and the
        # default (TV weight 0) with the state of the set with TV kept, as before the set without TV
        configs = [(b, False, False) for b in fft.available_backends()] + [("cl", True, False), ("cl", False, True)]
        for backend, lean, tv_state in configs:
            terms = default_terms(True, p.background, p.background_scale_px, tv=True) if tv_state else None
            s = ADMMSolver(psf, p, backend=backend, lean=lean, terms=terms)
            s.solve(y)  # warm-up: kernel builds, FFT plans
            # the TV set at weight 0 runs no TV iterations, only its finish pass
            tv_iters = (0 if tv_state else p.tv_iters) if s.terms.has_tv else None
            nbytes = iteration_bytes(nz, s.P, np.float32, backend, tv_iters, s.lean, p.relaxation != 1)
            runs = []
            for _ in range(RUNS):
                bw = copy_bandwidth(rt)
                runs.append((per_iteration(s.solve(y), SKIP), bw))
            dev = float(np.median([t for t, _ in runs]))
            ratio = float(np.median([t * bw / nbytes for t, bw in runs]))
            bw = float(np.median([b for _, b in runs]))
            bws.extend(b for _, b in runs)
            npy = numpy_on(s.P)
            best = numpy_on(numpy_grid)
            fft_t = best_time(lambda: fft_pass(s), 3, sync=rt.queue.finish)
            V = nz * s.P[0] * s.P[1] * 4
            spec_plane = s.parts[0].spec_plane
            target = 7 * V + nz * int(np.prod(spec_plane)) * 2 * 4   # issue 10: <= 7 volumes + PSF spectra
            floor = nbytes / bw
            label = backend + (" (lean)" if s.lean else "") + (" (TV state kept)" if tv_state else "")
            rows.append([f"{my} x {mx} x {nz}", label, f"{s.P[0]} x {s.P[1]}", f"{dev:.3f}", f"{npy:.3f}",
                         f"{npy / dev:.2f}", f"{best:.3f} ({numpy_grid[0]} x {numpy_grid[1]})", f"{best / dev:.2f}", f"{s.allocated_bytes / 2**20:.0f}", f"{target / 2**20:.0f}",
                         f"{floor * 1e3:.1f}", f"{ratio:.1f}", f"{fft_t * 1e3:.0f} ({fft_t / dev:.0%})"])
            print(" | ".join(rows[-1]), flush=True)
    head = ["sensor x planes", "FFT backend", "padded grid", "device s/iter", "numpy s/iter", "speed-up",
            "numpy s/iter on its best grid", "speed-up against that",
            "device MiB", "target MiB (7 V + PSF spectra)", "bandwidth floor ms", "x floor",
            "FFTs ms/iter (share)"]
    text = (f"Device: **{rt.caps.name}** ({rt.caps.implementation}; FFT backends {', '.join(fft.available_backends())}), "
            f"{os.cpu_count()} host cores; float32, "
            f"the default parameters (TV weight 0: the set without TV); median time between iterations {SKIP + 1}-{SKIP + a.iters} (past the "
            f"adaptive penalties' first {SKIP} iterations, where they may change on each) after a warm-up run, "
            f"the median of {RUNS} device solves (numpy: one); each solve right after a copy kernel's rate "
            f"({min(bws) / 1e9:.1f}-{max(bws) / 1e9:.1f} GB/s in this run): 'bandwidth floor ms' at the median "
            f"rate, 'x floor' the median of the solves' own ratios; 'device MiB' counts the buffers cm2cl allocates (FFT libraries may add "
            f"scratch): the depth planes' and the plane buffers' (v, xi, hx, the rhs plane, halos, R, S: a fixed cost of 12-15 "
            f"planes); 'target MiB' the depth planes' alone (issue 10: <= 7 real volumes + the PSF spectra per plane, what the "
            f"lean layout allocates per plane; section 'The lean layout'); '(lean)': the lean layout (`lean=True`: one slab of x spectra, one more forward FFT per "
            f"iteration, counted in its floor), which the planner takes where the whole state does not fit; '(TV state kept)': the default's TV weight of 0 solved by the set with TV's state (7 real volumes, u and p passed over each iteration), as before the set without TV (3 real volumes; the same iterates). numpy = `cm2cl.reference.admm(dtype=float32, workers=-1)`, on the device's padded grid and "
            f"on its own best grid (`scipy.fft.next_fast_len` of twice the sensor, per axis). "
            f"`python tools/bench_admm.py`\n\n" + markdown_table(head, rows))
    print(text)
    print("written to", write_section("ADMM iteration (tools/bench_admm.py)", text))


if __name__ == "__main__":
    main()

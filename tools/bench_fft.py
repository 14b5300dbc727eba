"""Batched 2D real-to-complex + complex-to-real FFT: milliseconds per plane, per backend, on the
current OpenCL device, against scipy.fft (float32, workers=-1) on the host in the same run.
Each row names its install path (OpenCL implementation, and how the backend got there).
Writes the table to docs/fft.md.

    python tools/bench_fft.py [--sizes 648x864x16 1944x2592x8] [--repeat 3]

Sizes are padded grids (py x px x planes).  reikna is timed on its own fast grid (powers of two,
complex-to-complex), as the solver would pad for it.
"""

from __future__ import annotations

import argparse
from importlib.metadata import version
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import DOCS, best_time, markdown_table, parse_size, write_section  # noqa: E402

from cm2cl.device import fft, get_runtime  # noqa: E402


def install_path(rt, backend: str) -> str:
    impl = rt.caps.implementation
    if backend == "cl":
        return f"{impl}; cm2cl kernels (plain pip install)"
    if backend == "vkfft":
        return f"{impl}; pyvkfft {version('pyvkfft')} (built from source)"
    if backend == "reikna":
        return f"{impl}; reikna {version('reikna')}"
    return f"host, {os.cpu_count()} cores; scipy {version('scipy')}"


def time_device(rt, backend, grid, planes, repeat):
    import pyopencl.array as cla

    plan = fft.get_plan(rt, grid, planes, np.float32, backend)
    x = cla.to_device(rt.queue, np.random.default_rng(0).standard_normal((planes,) + grid).astype(np.float32))
    spec = cla.empty(rt.queue, plan.spec_shape, plan.cdtype)

    def run():
        plan.forward(x, spec)
        plan.inverse(spec, x)

    return best_time(run, repeat, sync=rt.queue.finish) / planes


def time_scipy(grid, planes, repeat):
    from scipy import fft as sfft

    x = np.random.default_rng(0).standard_normal((planes,) + grid).astype(np.float32)

    def run():
        s = sfft.rfft2(x, workers=-1)
        sfft.irfft2(s, s=grid, workers=-1)

    return best_time(run, repeat) / planes


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", nargs="+", default=["648x864x16", "1944x2592x8"])
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    rt = get_runtime()
    rows = []
    for spec in a.sizes:
        py, px, planes = parse_size(spec)
        base = None
        for backend in fft.available_backends() + ["scipy"]:
            grid = (py, px) if backend != "reikna" else tuple(fft.good_size(n, "reikna") for n in (py, px))
            t = time_scipy(grid, planes, a.repeat) if backend == "scipy" else time_device(rt, backend, grid, planes,
                                                                                           a.repeat)
            base = t if backend == "cl" else base
            rows.append([f"{py} x {px} x {planes}", backend, f"{grid[0]} x {grid[1]}", f"{t * 1e3:.2f}",
                         f"{t / base:.2f}" if base else "", install_path(rt, backend)])
            print(" | ".join(rows[-1]), flush=True)
    head = ["padded grid x planes", "backend", "transformed grid", "ms per plane (r2c + c2r)", "x cl",
            "install path"]
    text = (f"Device: **{rt.caps.name}** ({rt.caps.implementation}), {os.cpu_count()} host cores; float32; "
            f"best of {a.repeat} runs of a batched forward + inverse 2D transform of all planes, per plane. "
            f"`python tools/bench_fft.py --sizes {' '.join(a.sizes)}`\n\n" + markdown_table(head, rows))
    print(text)
    print("written to", write_section("Batched 2D FFT (tools/bench_fft.py)", text, DOCS / "fft.md"))


if __name__ == "__main__":
    main()

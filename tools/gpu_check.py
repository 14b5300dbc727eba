"""The GPU check (issue 28): on the device ``CM2CL_DEVICE`` names (default: cm2cl's choice), build every kernel
in float32 (and float64 where the device has fp64), run the kernel-against-twin tests there, and time the
solver at the paper's full frame (1944 x 2592 sensor, 64 planes) with each FFT backend (cm2cl's own 'cl'
and VkFFT): seconds per iteration, the FFTs' share, the copy bandwidth and the x-over-floor ratio, device
memory. Writes the tables into docs/gpu_check.md (one section per device, kept across runs).

    python tools/gpu_check.py [--size 1944x2592x64] [--iters 5] [--tests-timeout 150] [--no-tests]
        [--out docs/gpu_check.md]

``tools/gpu_check.sh`` is the one command for a fresh GPU machine (registers NVIDIA's ICD when there is
none, then runs this). At a small ``--size`` it runs on PoCL (tests/test_gpu_check.py)."""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchlib import copy_bandwidth, markdown_table, parse_size, write_section  # noqa: E402

#: the kernel-against-twin tests (each device computation compared with its float64 numpy twin)
TWIN_TESTS = ("tests/test_kernels.py", "tests/test_fft_kernels.py", "tests/test_fft.py", "tests/test_forward.py",
              "tests/test_lean_state.py")


def build_all(rt) -> list[list[str]]:
    """Every kernels/*.cl program built on ``rt`` in float32 and, with fp64, float64: rows (file, dtype, s)."""
    from cm2cl.device import kernels

    names = sorted(p.name for p in kernels.kernel_dir().iterdir() if p.name.endswith(".cl") and p.name != "common.cl")
    rows = []
    dtypes = [np.float32] + ([np.float64] if rt.caps.fp64 else [])
    for dt in dtypes:
        for name in names:
            t = time.perf_counter()
            kernels.program(rt, name, dt)
            rows.append([name, np.dtype(dt).name, f"{time.perf_counter() - t:.2f}"])
    return rows


def twin_tests(timeout: float) -> tuple[str, int]:
    """The twin tests on this device (CM2CL_DEVICE passes through): (pytest's last line, exit code)."""
    cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *TWIN_TESTS]
    try:
        r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"stopped after {timeout:.0f} s (--tests-timeout)", 124
    last = [ln for ln in r.stdout.strip().splitlines() if ln.strip()]
    return (last[-1] if last else r.stderr.strip()[-200:]), r.returncode


def bench(size: str, iters: int, backends) -> list[list[str]]:
    """Seconds per iteration of the default solve at ``size`` per FFT backend."""
    from bench_admm import SKIP, fft_pass, per_iteration, problem

    from cm2cl.device import get_runtime
    from cm2cl.solver.admm import ADMMSolver
    from cm2cl.solver.memory import iteration_bytes
    from cm2cl.solver.params import ADMMParams

    rt = get_runtime()
    my, mx, nz = parse_size(size)
    psf, y = problem(my, mx, nz, np.random.default_rng(0))
    p = ADMMParams(max_iter=SKIP + iters, tol=0)
    rows = []
    for backend in backends:
        t0 = time.perf_counter()
        s = ADMMSolver(psf, p, backend=backend)
        setup = time.perf_counter() - t0
        rec = s.solve(y)
        dev = per_iteration(rec, min(SKIP, max(rec.iterations - 3, 0)))
        t = time.perf_counter()
        fft_pass(s)
        rt.queue.finish()
        fft_t = time.perf_counter() - t
        bw = copy_bandwidth(rt)
        nbytes = iteration_bytes(nz, s.P, np.float32, backend, p.tv_iters if s.terms.has_tv else None, s.lean,
                                 p.relaxation != 1)
        layout = "streamed" if any(q.streamed for q in s.parts) else ("lean" if s.lean else "resident")
        rows.append([f"{my} x {mx} x {nz}", backend, f"{s.P[0]} x {s.P[1]}", layout, f"{dev:.4f}",
                     f"{fft_t * 1e3:.1f} ({fft_t / dev:.0%})", f"{bw / 1e9:.0f}", f"{dev * bw / nbytes:.1f}",
                     f"{s.allocated_bytes / 2**30:.2f}", f"{setup:.1f}"])
        print(" | ".join(rows[-1]), flush=True)
        del s
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="1944x2592x64", help="sensor rows x columns x planes (default the paper's)")
    ap.add_argument("--iters", type=int, default=5, help="timed iterations per backend (after the first ones)")
    ap.add_argument("--tests-timeout", type=float, default=150.0)
    ap.add_argument("--no-tests", action="store_true", help="skip the twin tests")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "gpu_check.md")
    a = ap.parse_args(argv)

    from cm2cl.device import fft, get_runtime

    rt = get_runtime()
    caps = rt.caps
    t_all = time.perf_counter()
    print(f"device: {caps.name} ({caps.implementation}); fp64 {caps.fp64}", flush=True)
    builds = build_all(rt)
    print(f"built {len(builds)} programs in {sum(float(r[2]) for r in builds):.1f} s", flush=True)
    tests, code = ("skipped (--no-tests)", 0) if a.no_tests else twin_tests(a.tests_timeout)
    print(f"twin tests: {tests}", flush=True)
    backends = [b for b in ("cl", "vkfft") if b in fft.available_backends()]
    rows = bench(a.size, a.iters, backends)
    text = (f"Device: **{caps.name}** ({caps.implementation}), fp64 {caps.fp64}; host {platform.machine()}, "
            f"Python {platform.python_version()}, FFT backends here: {', '.join(fft.available_backends())}; "
            f"`python tools/gpu_check.py --size {a.size} --iters {a.iters}` in {time.perf_counter() - t_all:.0f} s.\n\n"
            f"- kernels built: {len(builds)} programs ({', '.join(sorted({r[1] for r in builds}))}), "
            f"{sum(float(r[2]) for r in builds):.1f} s in all\n"
            f"- kernel-against-twin tests ({', '.join(Path(t).name for t in TWIN_TESTS)}): {tests}\n\n"
            + markdown_table(["sensor x planes", "FFT backend", "padded grid", "layout", "s/iter", "FFTs ms (share)",
                              "copy GB/s", "x bandwidth floor", "device GiB", "setup s"], rows) + "\n")
    if not a.out.exists():
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text("# GPU check\n\nWritten by `tools/gpu_check.sh` (`tools/gpu_check.py`): one section per device, "
                         "kept across runs; re-run it on a device to refresh its section.\n")
    write_section(f"GPU check: {caps.name}", text, a.out)
    print(f"wrote {a.out}", flush=True)
    return 0 if code in (0, 5) else 1


if __name__ == "__main__":
    sys.exit(main())

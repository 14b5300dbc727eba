"""Run every OpenCL kernel of cm2cl under Oclgrind (Debian's `oclgrind`, 21.10) at small sizes, in float32
and float64, with row kernels at the GPU and CPU widths, slabbed and whole volumes, and report memory errors, data races
and non-uniform writes; writes docs/oclgrind.md.

    python tools/oclgrind_check.py            # needs `apt-get install oclgrind`; a few minutes

Oclgrind checks: out-of-bounds and invalid memory accesses (always), data races between work-items and
work-groups (`--data-races`), writes of different values to one location by work-items of a group
(`--uniform-writes`). `--uninitialized` is left off: it flags every store of a value computed from
partially-initialised vectors (seen as false positives in pyvkfft's and reikna's real-to-complex code).
It counts instructions per kernel (`--inst-counts`), from which this tool checks that every kernel in
kernels/*.cl ran. Exit code 1 when Oclgrind reports anything or a kernel did not run.

The workload (`--workload`, run inside Oclgrind) uses only cm2cl's own FFT kernels (backend cl): the
vkfft and reikna backends' kernels are those libraries'.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ERROR_PATTERNS = ("Invalid read", "Invalid write", "Data race", "Uniform write", "Work-group divergence",
                  "Invalid access", "out of bounds", "Uninitialized", "error", "Error")


def workload():
    """Every kernel at least once: forward/adjoint, the FFT (radices 2, 3, 4, 5, 7, 9; lines in local memory
    and through the multi-pass kernels; the GPU's and the CPU's work-group shapes), the reikna path's layout kernels, ADMM iterations with TV
    (isotropic and not), whole and in two slabs (halo paths), row kernels at the GPU and CPU widths, TV off, streamed
    slabs with plane-weighted l1."""
    import numpy as np
    import pyopencl.array as cl_array

    import cm2cl
    from cm2cl.device import fft, get_runtime, kernels
    from cm2cl.device.fft_kernels import ClPlan
    from cm2cl.solver.admm import ADMMSolver
    from cm2cl.solver.terms import default_terms
    from cm2cl.solver.forward import ForwardModel
    from cm2cl.solver.params import ADMMParams

    rt = get_runtime()
    rng = np.random.default_rng(0)
    for dtype in (np.float32, np.float64):
        if dtype == np.float64 and not rt.caps.fp64:
            continue
        # padded grids with radices 2 and 4 and 5 (16 x 20), 7 and 3 x 5 (14 x 15), 3^2 and 5^2 (9 x 25)
        for (nz, my, mx), pad in (((3, 8, 10), (16, 20)), ((2, 7, 8), (14, 15)), ((1, 5, 13), (9, 25))):
            psf = rng.random((nz, my, mx)) ** 4
            fm = ForwardModel(psf.astype(dtype), dtype=dtype, backend="cl", padded_shape=pad)
            fm.adjoint(fm.forward(rng.random((nz,) + pad).astype(dtype)))
            # the same lines through the multi-pass kernels (no line fits a local memory of 0 bytes)
            plan = ClPlan(rt, (nz,) + pad, dtype, local_limit=0)
            a = cl_array.to_device(rt.queue, rng.random((nz,) + pad).astype(dtype))
            spec = cl_array.empty(rt.queue, plan.spec_shape, plan.cdtype)
            plan.forward(a, spec)
            plan.inverse(spec, a)
        # the CPU shapes (V lines per work-item: blocks of V x V through the register transpose, the
        # values past the last whole block one at a time; a last work-item with fewer than V lines)
        for shape, group in (((3, 16, 20), (1, 1, 8)), ((5, 9, 26), (1, 1, 4)), ((1, 7, 14), (1, 2, 2))):
            plan = ClPlan(rt, shape, dtype, group=group)
            a = cl_array.to_device(rt.queue, rng.random(shape).astype(dtype))
            spec = cl_array.empty(rt.queue, plan.spec_shape, plan.cdtype)
            plan.forward(a, spec)
            plan.inverse(spec, a)
        if "reikna" in fft.available_backends():   # its FFT kernels are reikna's; the layout kernels ours
            psf = rng.random((1, 8, 16)) ** 4
            fm = ForwardModel(psf.astype(dtype), dtype=dtype, backend="reikna", padded_shape=(16, 32))
            fm.adjoint(fm.forward(rng.random((1, 16, 32)).astype(dtype)))
        k = kernels.kernel(rt, "layout.cl", "copy_real", dtype)   # the bandwidth benchmark's copy
        src = cl_array.to_device(rt.queue, rng.random(100).astype(dtype))
        dst = cl_array.empty_like(src)
        kernels.launch(rt, k, (100,), dst.data, src.data, np.uint64(100))
        assert np.array_equal(dst.get(), src.get())
        from cm2cl.device.morphology import grey_opening

        grey_opening(rng.random((9, 13)).astype(dtype), 1, 1)     # every line direction, min and max
        psf = rng.random((3, 8, 10)) ** 4
        meas = rng.random((8, 10))
        for vw, rows in ((1, None), (32 // np.dtype(dtype).itemsize, 3)):   # row kernels: GPU and CPU widths
            for slabs, iso in ((None, True), (2, False)):   # width 30: a partial vector ends each row
                s = ADMMSolver(psf.astype(dtype), ADMMParams(max_iter=3, tol=0, l1=1e-3, tv=1e-3, tv_isotropic=iso),
                               dtype=dtype, backend="cl", padded_shape=(16, 30), max_slab_planes=slabs)
                for part in s.parts:
                    s._row_layout(part, vw, rows)
                s.fuse_xstep = vw == 1   # the x step's solve inside the inverse FFT, and alone (xstep_solve)
                s.solve(meas.astype(dtype))
                for name in ("w", "rho", "eta"):   # the state the iteration derives (split_state, tv_eta)
                    s.get_volume(name)
                # the same objective term by term (kernels/terms.cl: each term's own state and kernels)
                g = ADMMSolver(psf.astype(dtype), ADMMParams(max_iter=3, tol=0, l1=1e-3, tv=1e-3, tv_isotropic=iso),
                               dtype=dtype, backend="cl", padded_shape=(16, 30), max_slab_planes=slabs,
                               terms=default_terms(False))
                for part in g.parts:
                    g._row_layout(part, vw, rows)
                g.solve(meas.astype(dtype))
        cm2cl.reconstruct(meas, psf, dtype=dtype, backend="cl", max_iter=2, tv=0.0, padded_shape=(16, 20), psf_refine=0)
        # reweighted l1 (l1_update with per-voxel weights) with the background in the model: a round after a 1-iteration "convergence"
        cm2cl.reconstruct(meas, psf, dtype=dtype, backend="cl", max_iter=4, tol=1e9, tol_change=1e9, patience=1,
                          l1=1e-3, l1_reweight=1, padded_shape=(16, 20), psf_refine=0)
        # streamed slabs (halo buffers, one-plane edge copies) with plane-weighted l1
        cm2cl.reconstruct(meas, psf, dtype=dtype, backend="cl", max_iter=2, l1=1e-3, tv=1e-3, padded_shape=(16, 20),
                          stream=True, max_slab_planes=1, l1_plane_power=2.0, psf_refine=0)
    print("workload done")


def kernel_names() -> set[str]:
    names = set()
    for f in sorted((ROOT / "kernels").glob("*.cl")):
        names |= set(re.findall(r"__kernel\s+void\s+(\w+)", f.read_text()))
    return names


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workload", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", default=str(ROOT / "docs" / "oclgrind.md"))
    args = ap.parse_args(argv)
    if args.workload:
        workload()
        return 0
    cmd = ["oclgrind", "--data-races", "--uniform-writes", "--inst-counts", sys.executable, __file__, "--workload"]
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    sec = time.perf_counter() - t
    text = proc.stdout + proc.stderr
    ran = set(re.findall(r"Instructions executed for kernel '(\w+)'", text))
    want = kernel_names()
    missing = sorted(want - ran)
    findings = [ln for ln in text.splitlines() if any(p in ln for p in ERROR_PATTERNS)
                and "Instructions executed" not in ln]
    ok = proc.returncode == 0 and not findings and not missing and "workload done" in text
    version = subprocess.run(["oclgrind", "--version"], capture_output=True, text=True).stdout.split()
    lines = ["# Oclgrind run of every kernel", "",
             f"Made by `python tools/oclgrind_check.py` ({' '.join(version[:2])}, flags `--data-races "
             f"--uniform-writes`), {sec:.0f} s. Workload: `tools/oclgrind_check.py --workload` (float32 and "
             "float64; cm2cl's own FFT on sizes with radices 2, 3, 4, 5, 7, 9; forward and adjoint; ADMM with "
             "isotropic and anisotropic TV, whole and in two slabs, row kernels at the GPU and CPU widths, the x step fused into the inverse FFT and not).", "",
             f"- kernels in `kernels/*.cl`: {len(want)}; ran under Oclgrind: {len(want & ran)}"
             + (f"; **not run: {', '.join(missing)}**" if missing else ""),
             f"- findings: {len(findings)}" + ("" if findings else " (no invalid access, data race or "
                                                                  "non-uniform write)"),
             f"- workload exit code: {proc.returncode}", ""]
    if findings:
        lines += ["```", *findings[:200], "```", ""]
    Path(args.out).write_text("\n".join(lines))
    print("\n".join(lines))
    if proc.returncode != 0:
        print(text[-4000:], file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

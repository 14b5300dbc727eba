"""The scheduler's plans and what streaming costs (issue 9's benchmark; not a test).

1. Plans for a full CM2 frame (1944 x 2592, 64 and 128 planes, padded 2M - 1 and to the PSF's support,
   K = 1350 px for the 3 x 3 array) on 8, 24 and 80 GB devices with 24, 128 and 256 GB hosts: the
   planner's layout, device and host memory and bytes moved per iteration (no device needed).
2. Measured on this machine's device: seconds per ADMM iteration with the planes streamed under a
   device memory cap (--max-memory) against the same solve kept in device memory, each run in its own
   process for its peak host RSS; the moved bytes; the iterates' distance (they should be equal).
3. A series at the demo size: frames per minute on one device and on two (the device split into two
   sub-devices, each with its own context; on a 2-core CPU they share the same cores).

    python tools/bench_schedule.py [--size 972x1296x64] [--iters 6] [--max-memory 2G] [--frames 20]

Writes docs/schedule.md.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import markdown_table, parse_size  # noqa: E402

from cm2cl.device.fft import good_size  # noqa: E402
from cm2cl.errors import DeviceError  # noqa: E402
from cm2cl.solver.memory import plan_layout, streamed_bytes_per_iteration  # noqa: E402

DOCS = Path(__file__).resolve().parents[1] / "docs"
GB = 1e9


def fake_device(gb):
    return SimpleNamespace(caps=SimpleNamespace(global_mem=int(gb * GB), name=f"{gb:g} GB device", index=0, kind="GPU"))


def plan_rows():
    sensor = (1944, 2592)
    rows = []
    for pad_name, K in (("2M - 1", None), ("support K = 1350", 1350)):
        P = tuple(good_size(2 * m - 1 if K is None else m + K - 1, "cl") for m in sensor)
        for nz in (64, 128):
            for dev in (8, 24, 80):
                try:
                    lay = plan_layout(nz, P, np.float32, "cl", [fake_device(dev)])
                except DeviceError as exc:
                    rows.append([f"{nz}", f"{P[0]} x {P[1]} ({pad_name})", f"{dev}", "refused: " + str(exc)[:60],
                                 "", "", "", "", ""])
                    continue
                lp = lay[0]
                inputs = 8 * 2 * (nz + 1) * sensor[0] * sensor[1]    # decoded float64 + a prepared copy
                host = lp.host_bytes + inputs
                fits = ", ".join(f"{h}" for h in (24, 128, 256) if host <= 0.9 * h * GB) or "none"
                moved = streamed_bytes_per_iteration(nz, P, np.float32, "cl", 2, relaxed=True) if lp.streamed else 0
                rows.append([f"{nz}", f"{P[0]} x {P[1]} ({pad_name})", f"{dev}",
                             (f"streamed, slabs of {lp.slab_planes}" + (", double-buffered" if lp.overlap else ""))
                             if lp.streamed else "resident, lean" if lp.lean else "resident",
                             f"{lp.device_bytes / GB:.1f}", f"{host / GB:.1f}", fits, f"{moved / GB:.1f}",
                             f"{nz * P[0] * P[1] / (2 * sensor[0] - 1) / (2 * sensor[1] - 1) / nz:.2f}"])
    return rows


def run_one(size, iters, max_memory, stream, overlap=True):
    """One solve in this process (called through a subprocess): JSON with s/iter and peak RSS."""
    import cm2cl
    from bench_admm import problem

    my, mx, nz = parse_size(size)
    psf, y = problem(my, mx, nz, np.random.default_rng(0))
    t = time.perf_counter()
    rec = cm2cl.reconstruct(y, psf, max_iter=iters, tol=0, max_memory=max_memory, overlap=overlap,
                            stream={"auto": "auto", "always": True, "never": False}[stream])
    wall = time.perf_counter() - t
    np.save(os.environ["BENCH_OUT"], rec.volume_padded[:: max(1, nz // 8)])
    sec = rec.log_array("seconds")
    lay = rec.info["layout"][0]
    print(json.dumps({"s_per_iter": float(np.median(np.diff(sec))), "wall": wall, "iters": rec.iterations,
                      "streamed": lay["streamed"], "slab_planes": lay["slab_planes"], "overlap": lay["overlap"],
                      "device_gib": rec.info["device_bytes"] / 2**30, "host_gib": rec.info["host_bytes"] / 2**30,
                      "moved_gb_per_iter": rec.info["moved_bytes"] / rec.iterations / GB,
                      "rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
                      "padded": list(rec.info["padded_shape"])}))


def measured(size, iters, max_memory, tmp, modes):
    out = {}
    for mode, cap, stream, overlap in [m for m in MODES if m[0] in modes]:
        env = {**os.environ, "BENCH_OUT": str(tmp / f"{mode.replace(' ', '_').replace(',', '')}.npy")}
        cmd = [sys.executable, __file__, "--run-one", size, str(iters), str(max_memory if cap else 0), stream,
               str(int(overlap))]
        res = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if res.returncode:
            out[mode] = {"error": (res.stderr.strip().splitlines() or ["?"])[-1]}
        else:
            out[mode] = json.loads(res.stdout.strip().splitlines()[-1])
        print(mode, out[mode], flush=True)
    a = tmp / "in_memory.npy"
    for mode, *_ in MODES[1:]:
        b = tmp / f"{mode.replace(' ', '_').replace(',', '')}.npy"
        if a.exists() and b.exists():
            va, vb = np.load(a), np.load(b)
            out.setdefault("distance", {})[mode] = float(np.linalg.norm(va - vb) / max(np.linalg.norm(va), 1e-30))
    return out


#: (mode, under the --max-memory cap, stream, double-buffered)
MODES = (("in memory", False, "never", True), ("streamed, one buffer", True, "always", False),
         ("streamed, double-buffered", True, "always", True))


def series_rate(frames):
    import pyopencl as cl
    from cm2cl import simulate
    from cm2cl.device import get_runtime
    from cm2cl.jobs import run_series  # noqa: F401
    import cm2cl

    sim = simulate.simulate_scene("demo_beads")
    rng = np.random.default_rng(1)
    ys = [sim.measurement * (1 + 0.05 * rng.standard_normal()) for _ in range(frames)]
    rt = get_runtime()
    subs = rt.device.create_sub_devices([cl.device_partition_property.EQUALLY, max(1, rt.caps.compute_units // 2)])[:2]
    rows = []
    import threading
    from cm2cl.solver.admm import ADMMSolver
    from cm2cl.solver.params import ADMMParams

    for name, devs in (("1 device (all cores)", [rt.device]), ("2 sub-devices", subs)):
        solvers = [ADMMSolver(sim.psf, ADMMParams(), device=d) for d in devs]
        solvers[0].solve(ys[0])   # warm-up: kernel builds
        for s in solvers[1:]:
            s.solve(ys[0])
        todo = list(range(frames))
        lock = threading.Lock()

        def worker(s):
            while True:
                with lock:
                    if not todo:
                        return
                    i = todo.pop()
                s.solve(ys[i])

        t = time.perf_counter()
        th = [threading.Thread(target=worker, args=(s,)) for s in solvers]
        for x in th:
            x.start()
        for x in th:
            x.join()
        dt = time.perf_counter() - t
        rows.append([name, f"{frames}", f"{dt:.1f}", f"{frames / dt * 60:.1f}"])
        print(rows[-1], flush=True)
    del cm2cl
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="972x1296x64")
    ap.add_argument("--iters", type=int, default=6)
    ap.add_argument("--max-memory", default="2G")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--modes", default=";".join(m[0] for m in MODES),
                    help="measured modes, ';'-separated (default all: " + "; ".join(m[0] for m in MODES) + ")")
    ap.add_argument("--skip", default="", help="comma list of parts to skip: plans,measured,series")
    a = ap.parse_args(argv)
    from cm2cl.cli.options import size as _size
    from cm2cl.device import get_runtime

    rt = get_runtime()
    skip = set(a.skip.split(","))
    text = [f"Made by `python tools/bench_schedule.py --size {a.size} --iters {a.iters} --max-memory {a.max_memory} "
            f"--frames {a.frames}`; device **{rt.caps.name}** ({rt.caps.implementation}), {os.cpu_count()} host "
            "cores, float32, FFT backend cl (cm2cl's own kernels, the plain pip install's path).", ""]
    if "plans" not in skip:
        head = ["planes", "padded grid", "device GB", "layout", "on the device GB", "host GB (streamed + inputs)",
                "hosts (GB) that hold it", "moved GB / iteration", "voxels vs 2M - 1"]
        text += ["## Plans for a full frame (1944 x 2592)", "",
                 "From `cm2cl.solver.memory.plan_layout` (90% of each device's memory usable).", "",
                 markdown_table(head, plan_rows()), ""]
    if "measured" not in skip:
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            m = measured(a.size, a.iters, _size(a.max_memory), Path(tmp), a.modes.split(";"))
        head = ["mode", "padded grid", "layout", "s / iteration", "x in memory", "job s", "device GiB",
                "host copies GiB", "moved GB / iteration", "peak RSS GiB"]
        rows = []
        base = m.get("in memory", {}).get("s_per_iter")
        for mode, *_ in MODES:
            if mode not in m:
                continue
            r = m[mode]
            if "error" in r:
                rows.append([mode, "", r["error"][:80], "", "", "", "", "", "", ""])
                continue
            rows.append([mode, " x ".join(map(str, r["padded"])),
                         (f"slabs of {r['slab_planes']}" + (", double-buffered" if r["overlap"] else ""))
                         if r["streamed"] else "resident", f"{r['s_per_iter']:.2f}",
                         f"{r['s_per_iter'] / base:.2f}" if base else "", f"{r['wall']:.0f}", f"{r['device_gib']:.2f}",
                         f"{r['host_gib']:.2f}", f"{r['moved_gb_per_iter']:.1f}", f"{r['rss_gib']:.1f}"])
        text += [f"## Streamed against in memory ({a.size}, --max-memory {a.max_memory})", "",
                 f"Median seconds between iterations over {a.iters} iterations and the whole job's seconds (setup, "
                 "iterations, result), each mode in its own process, one after another; "
                 "relative distance of the streamed volumes from the in-memory one: "
                 + ", ".join(f"{k} {v:.1e}" for k, v in m.get("distance", {}).items()) + ".", "",
                 markdown_table(head, rows), ""]
    if "series" not in skip:
        head = ["devices", "frames", "seconds", "frames / minute"]
        text += ["## A series at the demo size (324 x 432, 16 planes)", "",
                 "Frames solved by one worker per device after a warm-up frame each (kernel builds excluded).", "",
                 markdown_table(head, series_rate(a.frames)), ""]
    doc = DOCS / "schedule.md"
    notes = ""   # a hand-written "## Notes" section (what the figures mean) survives a re-run
    if doc.exists() and "\n## Notes" in doc.read_text():
        notes = doc.read_text()[doc.read_text().index("\n## Notes") + 1:]
    doc.write_text("# Scheduler benchmarks\n\n" + "\n".join(text) + ("\n" + notes if notes else ""))
    print("\n".join(text))


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--run-one":
        size, iters, cap, stream, overlap = sys.argv[2:7]
        run_one(size, int(iters), int(cap) or None, stream, bool(int(overlap)))
    else:
        main()

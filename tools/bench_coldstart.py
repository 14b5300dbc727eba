"""Cold and warm start of ``cm2cl demo``, the first command a newcomer runs: each run is a subprocess
timed from its start to its exit, cold (a new, empty PoCL kernel cache of its own, POCL_CACHE_DIR)
and then warm (the same cache again); medians over the repeats. Also the demo's own split
(simulation, reconstruction), the median seconds per ADMM iteration (from the run's log), the
run's CPU seconds, and the load average before each run (a shared machine makes timings noisy).
Then one more cold run per install with every OpenCL program build and every kernel's first launch
(per local size: PoCL compiles a kernel's work-group function there) timed, where the cold start's
extra seconds go.

    python tools/bench_coldstart.py [--repeat 3] [--cm2cl PATH [--cm2cl PATH ...]] [--label NAME ...] [--write]

``--cm2cl``: the ``cm2cl`` executable(s) to time (default: the one beside this Python), e.g. fresh
venvs of two commits; the runs of several alternate, so that they share the machine's load. The
device is the demo's own choice (set CM2CL_DEVICE to pick one). ``--write`` puts the table into
docs/benchmarks.md, section "Cold start".
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import markdown_table, write_section  # noqa: E402

_ABOUT = """
import json
from importlib.metadata import PackageNotFoundError, version
from cm2cl.device import get_runtime
def v(name):
    try:
        return version(name)
    except PackageNotFoundError:
        return None
print(json.dumps({"implementation": get_runtime().caps.implementation, "device": get_runtime().caps.name,
                  "pyopencl": v("pyopencl"), "pocl-binary-distribution": v("pocl-binary-distribution")}))
"""


def about(exe: Path) -> dict:
    """The device and OpenCL implementation the install behind ``exe`` chooses (its venv's Python)."""
    out = subprocess.run([str(exe.parent / "python"), "-c", _ABOUT], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def child_trace(json_path: str, argv: list[str]) -> int:
    """(Runs inside the timed install's Python.) ``cm2cl <argv>`` with each program build and each
    kernel's first launch per local size timed (queue drained before and after); the list goes to
    ``json_path``."""
    import pyopencl as cl

    t0 = time.perf_counter()
    builds, launches, seen = [], [], set()
    real_build, real_call = cl.Program.build, cl.Kernel.__call__

    def build(self, options=None, devices=None, cache_dir=None):
        t = time.perf_counter()
        prg = real_build(self, options, devices, cache_dir)
        opts = options if isinstance(options, str) else " ".join(options or [])
        names = re.findall(r"__kernel\s+void\s+(\w+)", getattr(self, "_source", "") or "")
        builds.append({"at": t - t0, "s": time.perf_counter() - t, "kernels": names,
                       "defines": re.findall(r"FFT_(?:N|HALF)=\d+", opts)})
        return prg

    def call(self, queue, global_size, local_size, *args, **kw):
        key = (self.function_name, self.program.int_ptr, tuple(local_size or ()))
        if key in seen:
            return real_call(self, queue, global_size, local_size, *args, **kw)
        seen.add(key)
        queue.finish()
        t = time.perf_counter()
        ev = real_call(self, queue, global_size, local_size, *args, **kw)
        queue.finish()
        launches.append({"at": t - t0, "s": time.perf_counter() - t, "kernel": key[0], "local": list(key[2])})
        return ev

    cl.Program.build, cl.Kernel.__call__ = build, call
    from cm2cl.cli import main as cm2cl_main

    rc = cm2cl_main(argv)
    Path(json_path).write_text(json.dumps({"builds": builds, "launches": launches, "wall": time.perf_counter() - t0}))
    return rc


def trace_demo(exe: Path) -> dict:
    """One cold ``cm2cl demo`` of the install behind ``exe``, traced by :func:`child_trace`."""
    tmp = Path(tempfile.mkdtemp(prefix="cm2cl-coldstart-"))
    env = dict(os.environ, POCL_CACHE_DIR=str(tmp / "cache"))
    (tmp / "cache").mkdir()
    subprocess.run([str(exe.parent / "python"), __file__, "--child-trace", str(tmp / "trace.json"), "demo", "-o",
                    str(tmp / "demo")], env=env, capture_output=True, text=True, check=True)
    trace = json.loads((tmp / "trace.json").read_text())
    trace["seconds"] = json.loads((tmp / "demo" / "demo.json").read_text())["seconds"]
    shutil.rmtree(tmp)
    return trace


def breakdown(label: str, t: dict) -> list:
    """A table row: where a traced cold run's seconds went."""
    b, k = t["builds"], t["launches"]
    fft = sorted({" ".join(x["defines"]) for x in b if x["defines"]})
    top = sorted(k, key=lambda x: -x["s"])[:3]
    return [label, f"{len(b)}: {sum(x['s'] for x in b):.1f}", f"{max(x['s'] for x in b):.2f}",
            f"{len(k)}: {sum(x['s'] for x in k):.1f}", ", ".join(f"{x['kernel']} {x['s']:.2f}" for x in top),
            "; ".join(fft), f"{t['seconds']['simulation']:.1f}", f"{t['seconds']['reconstruction']:.1f}"]


def run_demo(exe: Path, cache: Path) -> dict:
    """One ``cm2cl demo`` with PoCL's kernel cache in ``cache``: wall and CPU seconds, the demo's split."""
    out = Path(tempfile.mkdtemp(prefix="cm2cl-coldstart-"))
    env = dict(os.environ, POCL_CACHE_DIR=str(cache))
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run([str(exe), "demo", "-o", str(out / "demo")], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{exe} demo failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    summary = json.loads((out / "demo" / "demo.json").read_text())
    with open(out / "demo" / "reconstruction_log.csv", newline="") as f:
        seconds = [float(r["seconds"]) for r in csv.DictReader(f)]
    shutil.rmtree(out)
    return {"wall": wall, "cpu": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
            "simulation": summary["seconds"]["simulation"], "reconstruction": summary["seconds"]["reconstruction"],
            "iteration_ms": 1e3 * float(np.median(np.diff(seconds))), "iterations": len(seconds), "load": load}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child-trace"]:
        return child_trace(argv[1], argv[2:])
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cm2cl", action="append", type=Path, default=None,
                    help="cm2cl executable to time (repeatable; default: the one beside this Python)")
    ap.add_argument("--label", action="append", default=None, help="a name for each --cm2cl, in order")
    ap.add_argument("--repeat", type=int, default=3, help="cold + warm pairs per executable (default 3)")
    ap.add_argument("--write", action="store_true", help="write the table into docs/benchmarks.md")
    a = ap.parse_args(argv)
    exes = a.cm2cl or [Path(sys.executable).parent / "cm2cl"]
    labels = a.label or [str(e.parent.parent) for e in exes]
    if len(labels) != len(exes):
        ap.error("give one --label per --cm2cl")
    infos = [about(e) for e in exes]
    runs = {(i, kind): [] for i in range(len(exes)) for kind in ("cold", "warm")}
    for r in range(a.repeat):
        for i, exe in enumerate(exes):
            cache = Path(tempfile.mkdtemp(prefix="pocl-cache-"))
            for kind in ("cold", "warm"):
                res = run_demo(exe, cache)
                runs[i, kind].append(res)
                print(f"[{labels[i]}] {kind} {r + 1}/{a.repeat}: {res['wall']:.1f} s wall, {res['cpu']:.1f} s CPU, "
                      f"load {res['load']:.2f}", flush=True)
            shutil.rmtree(cache)

    med = lambda i, kind, key: float(np.median([x[key] for x in runs[i, kind]]))  # noqa: E731
    rows = []
    for i, label in enumerate(labels):
        walls = sorted(x["wall"] for x in runs[i, "cold"])
        rows.append([label, f"{med(i, 'cold', 'wall'):.1f} ({walls[0]:.1f}-{walls[-1]:.1f})",
                     f"{med(i, 'warm', 'wall'):.1f}", f"{med(i, 'cold', 'wall') - med(i, 'warm', 'wall'):.1f}",
                     f"{med(i, 'cold', 'cpu'):.1f} / {med(i, 'warm', 'cpu'):.1f}",
                     f"{med(i, 'cold', 'simulation'):.1f} / {med(i, 'cold', 'reconstruction'):.1f}",
                     f"{med(i, 'warm', 'simulation'):.1f} / {med(i, 'warm', 'reconstruction'):.1f}",
                     f"{med(i, 'warm', 'iteration_ms'):.0f}", str(runs[i, "warm"][0]["iterations"]),
                     f"{np.median([x['load'] for k in ('cold', 'warm') for x in runs[i, k]]):.1f}"])
    head = ["install", "cold s (min-max)", "warm s", "cold - warm s", "CPU s cold / warm",
            "cold: simulation / reconstruction s", "warm: simulation / reconstruction s", "warm ms/iteration",
            "iterations", "load avg"]
    traces = [trace_demo(e) for e in exes]
    bhead = ["install", "programs built: s", "slowest build s", "first launches: s",
             "slowest first launches (s)", "FFT specialisations", "simulation s", "reconstruction s"]
    brows = [breakdown(label, t) for label, t in zip(labels, traces)]
    impl = "; ".join(sorted({f"{x['device']}, {x['implementation']}; installed: pyopencl {x['pyopencl']}, "
                             f"pocl-binary-distribution {x['pocl-binary-distribution']}" for x in infos}))
    text = (f"`cm2cl demo` from start to exit, {a.repeat} cold + warm pairs per install, medians; cold = a new "
            "empty PoCL kernel cache (POCL_CACHE_DIR), warm = the same cache again. Device: "
            f"{impl}; {os.cpu_count()} host cores. `python tools/bench_coldstart.py`\n\n"
            + markdown_table(head, rows)
            + "\n\nWhere a cold run's extra seconds go (one more traced cold run per install): OpenCL programs "
            "built (count: seconds), kernels' first launches per local size (count: seconds; PoCL compiles a "
            "kernel's work-group function there, so this is mostly compile time), the FFT line lengths the "
            "programs were specialised for, and the demo's own split.\n\n"
            + markdown_table(bhead, brows))
    print("\n" + text)
    if a.write:
        print(f"wrote {write_section('Cold start', text)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

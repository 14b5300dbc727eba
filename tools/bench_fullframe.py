"""The paper's full-resolution frame on this machine (issue 28; a benchmark, not a test).

A 1944 x 2592 sensor and 64 planes 40 um apart over 2.52 mm (the paper's stated resolution needs planes
<= 40 um apart), the PSF stack from cm2cl's CM2 model (cm2cl.optics), a measurement of beads with shot
noise; the solve runs a few iterations through ``cm2cl.reconstruct`` in a child process of its own, so
that its peak resident memory and disk traffic are its own:

    python tools/bench_fullframe.py [--planes 64] [--iters 5] [--padding support] [--bin 1]

Reported: the planner's layout, device and host bytes, seconds to set up (PSF spectra) and per
iteration, the whole solve projected to the default iteration cap and to the iterations the default
stopping rule took on the study's cases (docs/relaxation.md), peak RSS (ru_maxrss, which counts every
page the process touched, and the anonymous peak from /proc), and the bytes the child read and wrote
on disk (/proc/self/io). Writes docs/fullframe.md.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import markdown_table  # noqa: E402

DOCS = Path(__file__).resolve().parents[1] / "docs"
GIB = 2 ** 30
#: the projection's typical count of iterations: the default stopping rule took 293 to 756 on the penalty
#: study's cases (docs/penalty.md, mu_v 0.2) and 700 on DiffuserCam 3D binned 2x (docs/iterations.md);
#: 800 stays above all of them (before mu_v 0.2 the stops were 700 to 940: docs/relaxation.md)
TYPICAL_ITERS = 800


def _proc_status(key: str) -> int:
    """A /proc/self/status figure in bytes (VmHWM: peak RSS; RssAnon: anonymous RSS now), 0 off Linux."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def _disk_io(pid="self") -> dict:
    """Bytes a process (this one, or ``pid``) read from and wrote to storage (/proc/PID/io), zeros off Linux
    or once it has exited."""
    out = {"read_bytes": 0, "write_bytes": 0}
    try:
        for line in Path(f"/proc/{pid}/io").read_text().splitlines():
            k, v = line.split(":")
            if k in out:
                out[k] = int(v)
    except (OSError, ValueError):
        pass
    return out


class Sampler:
    """``read()`` sampled by a thread every ``every`` s while something runs, folded by ``keep(kept, new)``
    (the peak: max; the last sample: the new one where there is one); :meth:`stop` returns what it kept."""

    def __init__(self, read, keep, start, every=0.2):
        import threading

        self.read, self.keep, self.kept, self.every = read, keep, start, every
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self):
        while not self._stop.is_set():
            self.kept = self.keep(self.kept, self.read())
            self._stop.wait(self.every)

    def stop(self):
        self._stop.set()
        self._t.join()
        return self.kept


def anon_peak() -> Sampler:
    """The largest anonymous RSS of this process seen (page cache excluded)."""
    return Sampler(lambda: _proc_status("RssAnon"), max, 0)


def child_io(pid) -> Sampler:
    """The storage bytes child ``pid`` has read and written, its last sample before it exits."""
    return Sampler(lambda: _disk_io(pid), lambda kept, new: new if any(new.values()) else kept,
                   {"read_bytes": 0, "write_bytes": 0}, every=0.5)


def make_inputs(args):
    """(psf, y): the CM2 model's PSF stack (float32) and a frame of ``args.beads`` beads with shot noise."""
    from cm2cl.optics.geometry import CM2Optics, depth_planes
    from cm2cl.optics.psf import axial_psf_stack

    optics = CM2Optics(binning=args.bin)
    half = (args.planes - 1) * args.dz / 2
    depths = depth_planes(-half, half, args.dz)
    psf = axial_psf_stack(optics, depths, dtype=np.float32)
    rng = np.random.default_rng(0)
    nz, my, mx = psf.shape
    # beads: each a copy of its plane's PSF shifted laterally (a point source's image), 1000 photons at
    # the brightest pixel, Poisson noise
    y = np.zeros((my, mx))
    for _ in range(args.beads):
        z = int(rng.integers(nz))
        dy, dx = (int(rng.integers(-n // 4, n // 4)) for n in (my, mx))
        y += np.roll(psf[z], (dy, dx), axis=(0, 1)) * rng.uniform(0.5, 1.0)
    return psf, rng.poisson(y / y.max() * 1000.0).astype(np.float64)


def child(args) -> None:
    """Make the inputs, solve ``args.iters`` iterations, print one JSON line of figures."""
    import cm2cl

    peak = anon_peak()
    t0 = time.perf_counter()
    psf, y = make_inputs(args)
    nz, my, mx = psf.shape
    t_inputs = time.perf_counter() - t0
    io0 = _disk_io()
    times = []
    t1 = time.perf_counter()
    rec = cm2cl.reconstruct(y, psf, padding=args.padding, max_iter=args.iters, tol=0.0, tol_change=0.0,
                            callback=lambda row: times.append(time.perf_counter()))
    t_solve = time.perf_counter() - t1
    io1 = _disk_io()
    log = rec.log
    per_iter = float(np.median(np.diff([t1] + times)[1:])) if len(times) > 1 else float("nan")
    setup = (times[0] - t1) - per_iter if times else float("nan")
    print(json.dumps({
        "sensor": [my, mx], "planes": nz, "dz_um": args.dz, "padded": list(rec.info["padded_shape"]),
        "layout": rec.info["layout"], "device_bytes": rec.info["device_bytes"], "host_bytes": rec.info["host_bytes"],
        "moved_bytes": rec.info["moved_bytes"], "device": rec.info["device"], "backend": rec.info["backend"],
        "iters": len(log), "per_iter_s": per_iter, "setup_s": setup, "solve_s": t_solve, "inputs_s": t_inputs,
        "peak_rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "peak_anon": max(peak.stop(), _proc_status("RssAnon")),
        "disk_read": io1["read_bytes"] - io0["read_bytes"], "disk_write": io1["write_bytes"] - io0["write_bytes"],
        "padding": rec.info.get("padding", {}), "volume_max": float(rec.volume.max())}))


def write_inputs(args) -> None:
    """Make the inputs and write them where the command line reads them: ``DIR/frame.tif`` (float32) and
    ``DIR/psf.ome.tif`` (object-space voxel size: the plane spacing and the model's object pixel)."""
    import tifffile

    from cm2cl import io as cio
    from cm2cl.optics.geometry import CM2Optics

    psf, y = make_inputs(args)
    d = Path(args.write)
    tifffile.imwrite(d / "frame.tif", y.astype(np.float32), photometric="minisblack")
    px = CM2Optics(binning=args.bin).object_pixel_um()
    cio.write_tiff(d / "psf.ome.tif", psf, voxel_size_um=(args.dz, px, px), extra={"voxel_space": cio.OBJECT_SPACE})


def run_cli(args) -> dict:
    """The full frame through ``cm2cl reconstruct`` as a user runs it: the inputs written to files by one child
    process, then the command in another, whose own peak RSS (wait4), wall time, storage traffic and
    iteration log are measured."""
    with tempfile.TemporaryDirectory(dir=args.scratch) as d:
        made = subprocess.run([sys.executable, __file__, "--write", d, "--planes", str(args.planes), "--dz",
                               str(args.dz), "--beads", str(args.beads), "--bin", str(args.bin)],
                              capture_output=True, text=True)
        if made.returncode != 0:
            sys.exit(f"bench_fullframe: making the inputs failed: {made.stderr.strip()[-2000:]}")
        out = Path(d) / "vol.ome.tif"
        opts = ["--padding", args.padding, "--max-iter", str(args.iters), "--tol", "0", "--quiet"]
        # `python -m cm2cl` of this interpreter: the `cm2cl` command of its environment, activated or not
        cmd = [sys.executable, "-m", "cm2cl", "reconstruct", str(Path(d) / "frame.tif"), "--psf",
               str(Path(d) / "psf.ome.tif"), "-o", str(out)] + opts
        err = Path(d) / "stderr.txt"   # a file, not a pipe: nothing read while it runs can fill and block it
        t0 = time.perf_counter()
        with open(err, "w") as fe:
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=fe)
            io = child_io(proc.pid)
            _, status, usage = os.wait4(proc.pid, 0)   # its own rusage: peak RSS of this child alone
        wall = time.perf_counter() - t0
        traffic = io.stop()
        proc.returncode = code = os.waitstatus_to_exitcode(status)
        if code != 0:
            sys.exit(f"bench_fullframe: `cm2cl reconstruct ...` failed (exit {code}): {err.read_text().strip()[-2000:]}")
        from cm2cl.io.publish import sidecar_names

        side = sidecar_names(out)
        secs = np.atleast_1d(np.genfromtxt(side["log"], delimiter=",", names=True)["seconds"])
        record = json.loads(side["record"].read_text())
        return {"command": " ".join(["cm2cl reconstruct frame.tif --psf psf.ome.tif -o vol.ome.tif"] + opts),
                "wall_s": wall, "peak_rss": usage.ru_maxrss * 1024, "disk_read": traffic["read_bytes"],
                "disk_write": traffic["write_bytes"], "output_bytes": out.stat().st_size,
                "iters": int(secs.size), "per_iter_s": float(np.median(np.diff(secs))) if secs.size > 1 else float("nan"),
                "first_iter_s": float(secs[0]),
                "layout": record.get("info", {}).get("layout", []),
                "padded": record.get("info", {}).get("padded_shape")}


def layout_text(lay) -> str:
    """The planner's layout (a record's ``info['layout']``) in words."""
    return "; ".join(f"planes {p['planes'][0]}..{p['planes'][1] - 1} on {p['device']}: "
                     + ("streamed" if p["streamed"] else "resident, lean" if p["lean"] else "resident")
                     + f" (slabs of {p['slab_planes']})" for p in lay) or "-"


def cli_section(args, r) -> str:
    """The command line's section of docs/fullframe.md."""
    proj = lambda n: r["wall_s"] + (n - r["iters"]) * r["per_iter_s"]  # noqa: E731
    rows = [["command", f"`{r['command']}`"],
            ["padded grid", " x ".join(str(n) for n in r["padded"]) if r["padded"] else "-"],
            ["layout", layout_text(r["layout"])],
            ["wall time, start to exit", f"{r['wall_s']:.0f} s for {r['iters']} iterations"],
            ["first iteration (from the solve's start: plans, PSF spectra)", f"{r['first_iter_s']:.0f} s"],
            ["seconds per iteration (median)", f"{r['per_iter_s']:.2f} s"],
            ["peak RSS of the command (wait4 ru_maxrss)", f"{r['peak_rss'] / GIB:.2f} GiB"],
            ["storage read / written by the command (sampled every 0.5 s: the last writes may be missing)", f"{r['disk_read'] / GIB:.2f} / {r['disk_write'] / GIB:.2f} GiB"],
            ["the volume written (OME-TIFF)", f"{r['output_bytes'] / GIB:.2f} GiB"],
            [f"projected: {TYPICAL_ITERS} iterations", f"{proj(TYPICAL_ITERS) / 3600:.2f} h"],
            ["projected: 1000 iterations (the default cap)", f"{proj(1000) / 3600:.2f} h"]]
    binned = f" --bin {args.bin}" if args.bin != 1 else ""
    return (f"{CLI_MARK}\n\nMade by `python tools/bench_fullframe.py --cli --planes {args.planes} --iters {args.iters}{binned} "
            f"--padding {args.padding}` on {install_path()}: the same frame and PSF written to files (a float32 TIFF "
            "and an OME-TIFF stack), then the command a user runs, in a process of its own.\n\n"
            f"{markdown_table(['quantity', 'measured'], rows)}\n")


#: the heading of the command line's section in the output file (replaced by --cli runs, kept by the others)
CLI_MARK = "## The command line"


def install_path() -> str:
    from cm2cl.device import get_runtime
    from cm2cl.device.fft import available_backends

    rt = get_runtime()
    pocl = "system PoCL" if "debian" in rt.caps.implementation.lower() else "PyPI PoCL" \
        if "pypi" in rt.caps.implementation.lower() else rt.caps.implementation
    return f"{rt.caps.name} ({pocl}), pyvkfft {'installed' if 'vkfft' in available_backends() else 'not installed'}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--planes", type=int, default=64)
    ap.add_argument("--dz", type=float, default=40.0, help="plane spacing, um")
    ap.add_argument("--iters", type=int, default=5)
    ap.add_argument("--beads", type=int, default=200)
    ap.add_argument("--bin", type=int, default=1)
    ap.add_argument("--padding", choices=["full", "support"], default="support")
    ap.add_argument("--out", type=Path, default=DOCS / "fullframe.md")
    ap.add_argument("--cli", action="store_true",
                    help="run the frame through `cm2cl reconstruct` from files instead (its section of --out)")
    ap.add_argument("--scratch", default=None, help="--cli: where the input and output files go (default: TMPDIR)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--write", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    if args.write:
        write_inputs(args)
        return
    old = args.out.read_text() if args.out.exists() else ""
    if args.cli:
        section = cli_section(args, run_cli(args))
        print(section)
        head = old.split(CLI_MARK)[0].rstrip() if old else "# The full-resolution frame"
        args.out.write_text(head + "\n\n" + section)
        return
    cmd = [sys.executable, __file__, "--child", "--planes", str(args.planes), "--dz", str(args.dz),
           "--iters", str(args.iters), "--beads", str(args.beads), "--bin", str(args.bin), "--padding", args.padding]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"bench_fullframe: the solve failed (exit {proc.returncode}): {proc.stderr.strip()[-2000:]}")
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    from cm2cl.solver.memory import host_available_bytes
    import psutil

    ram = psutil.virtual_memory().total
    lay = r["layout"]
    how = layout_text(lay)
    proj = lambda n: r["setup_s"] + n * r["per_iter_s"]  # noqa: E731
    rows = [
        ["sensor x planes", f"{r['sensor'][0]} x {r['sensor'][1]} x {r['planes']} ({r['dz_um']:g} um apart)"],
        ["padded grid", f"{r['padded'][0]} x {r['padded'][1]} (padding {args.padding}"
         + (f", PSF support {r['padding'].get('support_px')} px" if r["padding"].get("support_px") else "") + ")"],
        ["layout", how],
        ["device buffers", f"{r['device_bytes'] / GIB:.2f} GiB"],
        ["host copies of streamed slabs", f"{r['host_bytes'] / GIB:.2f} GiB"],
        ["peak RSS (ru_maxrss)", f"{r['peak_rss'] / GIB:.2f} GiB of {ram / GIB:.1f} GiB RAM"],
        ["peak anonymous RSS (sampled)", f"{r['peak_anon'] / GIB:.2f} GiB"],
        ["disk read / written by the solve", f"{r['disk_read'] / GIB:.2f} / {r['disk_write'] / GIB:.2f} GiB"],
        ["host <-> device copies", f"{r['moved_bytes'] / GIB:.2f} GiB in {r['iters']} iterations"],
        ["making the inputs (PSF model, beads)", f"{r['inputs_s']:.0f} s"],
        ["setup (plan, PSF spectra, first-iteration extras)", f"{r['setup_s']:.0f} s"],
        ["seconds per iteration (median)", f"{r['per_iter_s']:.2f} s"],
        [f"projected: {TYPICAL_ITERS} iterations (the default stop's typical count)", f"{proj(TYPICAL_ITERS) / 3600:.2f} h"],
        ["projected: 1000 iterations (the default cap)", f"{proj(1000) / 3600:.2f} h"],
        ["the paper (256 GB Xeon node, MATLAB)", "2.5 h"],
    ]
    table = markdown_table(["quantity", "measured"], rows)
    text = (f"# The full-resolution frame\n\nMade by `python tools/bench_fullframe.py --planes {args.planes} "
            f"--iters {args.iters} --padding {args.padding}` ({wall / 60:.1f} min) on {install_path()}, "
            f"FFT backend {r['backend']}, float32; host {os.cpu_count()} cores, {ram / GIB:.1f} GiB RAM, "
            f"{host_available_bytes() / GIB:.1f} GiB available after the run.\n\n{table}\n\n"
            "The solve is `cm2cl.reconstruct(y, psf, padding='support')` at the default parameters (TV weight 0: "
            "the fused set without TV, 3 real volumes per voxel; docs/design.md section 4), the planner's "
            "budget on a CPU device the host's available memory less the result and the runtime "
            "(`cm2cl.solver.memory.device_budget`). Peak RSS counts the inputs the caller holds (the float32 PSF "
            "stack, 1.2 GiB, and its copy truncated to the support) and the result read back (one volume on "
            "the padded grid). The projection assumes each iteration costs what the measured ones did.\n")
    print(text)
    cli = old[old.index(CLI_MARK):] if CLI_MARK in old else ""
    args.out.write_text(text + ("\n" + cli if cli else ""))


if __name__ == "__main__":
    main()

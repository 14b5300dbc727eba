"""Series jobs (issue 9, part): frames read from headers, an OME-Zarr store that resumes a killed job to
the same bits, refuses another job's store, and runs on a Dask LocalCluster on loopback."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

zarr = pytest.importorskip("zarr")

import cm2cl  # noqa: E402
from cm2cl import io as cio  # noqa: E402
from cm2cl.errors import InputError  # noqa: E402
from cm2cl.jobs import FrameSeries  # noqa: E402
from test_admm import bead_problem  # noqa: E402

P = (64, 80)
ARGS = ["--max-iter", "25", "--tol", "0", "--quiet"]


def _series(tmp_path, n=4):
    """n frames: the bead problem's emitters moved between frames; a (n, My, Mx) multi-page TIFF and the
    PSF as an OME-TIFF with an object-space voxel size."""
    psf, _, _ = bead_problem(7)
    frames = []
    for t in range(n):
        _, x, _ = bead_problem(7, emitters=((t % 4, 10 + t, 12), (1, 20, 30 - t), (2, 5 + t, 25)))
        from cm2cl import reference as ref
        frames.append(ref.forward(psf, x, P) * 1000)
    frames = np.stack(frames).astype(np.float32)
    tifffile.imwrite(tmp_path / "series.tif", frames, photometric="minisblack")
    cio.write_tiff(tmp_path / "psf.ome.tif", psf.astype(np.float32), voxel_size_um=(10.0, 2.0, 2.0),
                   extra={"voxel_space": cio.OBJECT_SPACE})
    return psf, frames


def _cli(*args, env=None):
    e = {**os.environ, **(env or {})}
    return subprocess.run([sys.executable, "-m", "cm2cl", *map(str, args)], capture_output=True, text=True, env=e)


def _job(tmp_path, out, *extra, env=None):
    return _cli("reconstruct", tmp_path / "series.tif", "--psf", tmp_path / "psf.ome.tif", "-o", out, *ARGS, *extra,
                env=env)


def test_series_frames_equal_single_frame_solves_and_carry_the_scale(rt, tmp_path):
    psf, frames = _series(tmp_path)
    r = _job(tmp_path, tmp_path / "out.ome.zarr", "--psf-refine", "0")
    assert r.returncode == 0, r.stderr
    assert "4 frames" in r.stdout and "4 computed" in r.stdout
    g = zarr.open_group(str(tmp_path / "out.ome.zarr"), mode="r")
    arr = np.asarray(g["0"])
    assert arr.shape == (4, 4, 32, 40)
    ms = g.attrs["multiscales"][0]
    assert [a["name"] for a in ms["axes"]] == ["t", "z", "y", "x"]
    assert ms["axes"][1]["unit"] == "micrometer"
    assert ms["datasets"][0]["coordinateTransformations"][0]["scale"] == [1.0, 10.0, 2.0, 2.0]
    for t in (0, 3):   # the solver built once and reused gives what a fresh solve of that frame gives
        one = cm2cl.reconstruct(frames[t], psf.astype(np.float32), max_iter=25, tol=0, psf_refine=0)
        np.testing.assert_array_equal(arr[t], one.volume)


def test_series_refines_the_psf_on_its_first_frame_and_resumes_with_it(rt, tmp_path):
    """--psf-refine on a series: the PSF is self-calibrated on frame 0 and kept as OUT.psf.ome.tif with the
    job's fingerprint; every frame equals the single-frame solve with that stack (no refinement of its own);
    a resumed job reads the stack back instead of refining again; with finished frames and the stack gone it
    stops before any work."""
    psf, frames = _series(tmp_path, n=3)
    out, side = tmp_path / "r.ome.zarr", tmp_path / "r.psf.ome.tif"
    refine = ("--psf-refine", "2", "--psf-refine-iter", "10")
    r = _job(tmp_path, out, *refine)
    assert r.returncode == 0, r.stderr
    h, meta = cio.read_tiff(side)
    assert h.dtype == np.float64 and h.shape == psf.shape and meta["extra"]["psf_refine"] == 2
    assert not np.allclose(h / h.sum(), psf / psf.sum(), atol=1e-6)        # refined, not the given stack
    one = cm2cl.reconstruct(frames[0], psf.astype(np.float32), max_iter=25, tol=0, psf_refine=2, psf_refine_iter=10)
    np.testing.assert_array_equal(h, one.psf)                             # frame 0's refinement, bit for bit
    arr = np.asarray(zarr.open_group(str(out), mode="r")["0"])
    for t in (0, 2):
        np.testing.assert_array_equal(arr[t], cm2cl.reconstruct(frames[t], h, max_iter=25, tol=0, psf_refine=0).volume)
    # resume: frame 2 undone; the stack is read back (not written again), the frame comes back the same
    (tmp_path / ".r.ome.zarr.cm2cl-done" / "00000002").unlink()
    before = side.stat().st_mtime_ns
    r = _job(tmp_path, out, *refine)
    assert r.returncode == 0 and "read back" in r.stderr and "1 computed" in r.stdout, r.stderr
    assert side.stat().st_mtime_ns == before
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(out), mode="r")["0"])[2], arr[2])
    side.unlink()
    (tmp_path / ".r.ome.zarr.cm2cl-done" / "00000001").unlink()
    r = _job(tmp_path, out, *refine)
    assert r.returncode == 2 and "r.psf.ome.tif" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not side.exists()


def test_series_with_support_padding_and_streamed_slabs(rt, tmp_path):
    """--padding support measures the PSF's support once for the whole series (each frame equals the
    single-frame solve with padding='support'); a device cap streams the slabs and changes no bit."""
    psf, frames = _series(tmp_path, n=2)
    r = _job(tmp_path, tmp_path / "sup.ome.zarr", "--padding", "support")
    assert r.returncode == 0, r.stderr
    arr = np.asarray(zarr.open_group(str(tmp_path / "sup.ome.zarr"), mode="r")["0"])
    one = cm2cl.reconstruct(frames[1], psf.astype(np.float32), max_iter=25, tol=0, padding="support")
    assert tuple(one.info["padding"]["padded_shape"]) != (64, 80)      # the support grid is smaller
    np.testing.assert_array_equal(arr[1], one.volume)
    r = _job(tmp_path, tmp_path / "cap.ome.zarr", "--padding", "support", "--stream", "always")
    assert r.returncode == 0, r.stderr
    assert "GB streamed between host and devices" in r.stdout and " 0.00 GB streamed" not in r.stdout
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(tmp_path / "cap.ome.zarr"), mode="r")["0"]), arr)


def test_warm_start_takes_fewer_iterations_and_resumes_to_the_same_bits(rt, tmp_path):
    """--warm-start: frame t starts from frame t - 1's stored volume. On a slowly changing series it
    stops by the rule in fewer iterations than cold starts, and a job killed after frame 1 resumes (frame
    2 starting from frame 1 read back from the store) to the bits of an uninterrupted run."""
    psf, _, _ = bead_problem(7)
    from cm2cl import reference as ref

    _, x, _ = bead_problem(7)
    frames = np.stack([ref.forward(psf, x * (1 + 0.02 * t), P) * 1000 for t in range(4)]).astype(np.float32)
    tifffile.imwrite(tmp_path / "series.tif", frames, photometric="minisblack")
    cio.write_tiff(tmp_path / "psf.ome.tif", psf.astype(np.float32), voxel_size_um=(10.0, 2.0, 2.0),
                   extra={"voxel_space": cio.OBJECT_SPACE})
    args = ["--max-iter", "400", "--quiet", "--background", "none"]   # noise-free: the background converges slowly
    base = ["reconstruct", tmp_path / "series.tif", "--psf", tmp_path / "psf.ome.tif"]
    for name, extra in (("cold", []), ("warm", ["--warm-start"])):
        r = _cli(*base, "-o", tmp_path / f"{name}.ome.zarr", *args, *extra)
        assert r.returncode == 0, r.stderr
    info = {name: [json.loads((tmp_path / f".{name}.ome.zarr.cm2cl-done" / f"{i:08d}").read_text())
                   for i in range(4)] for name in ("cold", "warm")}
    iters = {k: [f["iterations"] for f in v] for k, v in info.items()}
    assert all(f["converged"] for v in info.values() for f in v), info
    assert iters["warm"][0] == iters["cold"][0]                     # frame 0 starts cold either way
    print("iterations per frame", iters)
    assert sum(iters["warm"][1:]) < 0.7 * sum(iters["cold"][1:]), iters
    # killed after frame 1: the resumed job equals the uninterrupted one bit for bit
    r = _cli(*base, "-o", tmp_path / "part.ome.zarr", *args, "--warm-start", env={"CM2CL_FAULT": "after_chunk.1"})
    assert r.returncode == -9, r.stderr
    r = _cli(*base, "-o", tmp_path / "part.ome.zarr", *args, "--warm-start")
    assert r.returncode == 0, r.stderr
    a = np.asarray(zarr.open_group(str(tmp_path / "part.ome.zarr"), mode="r")["0"])
    b = np.asarray(zarr.open_group(str(tmp_path / "warm.ome.zarr"), mode="r")["0"])
    np.testing.assert_array_equal(a, b)
    r = _cli(*base, "-o", tmp_path / "x.ome.zarr", *args, "--warm-start", "--device", "0,0")
    assert r.returncode == 2 and not (tmp_path / "x.ome.zarr").exists()


def test_killed_job_resumes_to_identical_output(rt, tmp_path):
    """Killed (SIGKILL) after frame 1's chunk is written but before it is marked done: the rerun of the
    same command recomputes only frames 1.., and the store equals an uninterrupted run's bit for bit."""
    _series(tmp_path)
    ref = tmp_path / "ref.ome.zarr"
    assert _job(tmp_path, ref).returncode == 0
    out = tmp_path / "out.ome.zarr"
    r = _job(tmp_path, out, env={"CM2CL_FAULT": "after_chunk.1"})
    assert r.returncode == -9, (r.returncode, r.stderr)
    done = sorted(p.name for p in (out.parent / f".{out.name}.cm2cl-done").iterdir() if not p.name.startswith("."))
    assert done == ["00000000"]
    r = _job(tmp_path, out)
    assert r.returncode == 0, r.stderr
    assert "3 computed" in r.stdout and "1 already done" in r.stdout
    a = np.asarray(zarr.open_group(str(out), mode="r")["0"])
    b = np.asarray(zarr.open_group(str(ref), mode="r")["0"])
    np.testing.assert_array_equal(a, b)
    info = json.loads((out.parent / f".{out.name}.cm2cl-done" / "00000002").read_text())
    assert info["iterations"] == 25
    r = _job(tmp_path, out)       # nothing left to do
    assert r.returncode == 0 and "0 computed" in r.stdout and "4 already done" in r.stdout


def test_a_store_of_another_job_is_refused_and_left_alone(rt, tmp_path):
    _series(tmp_path)
    out = tmp_path / "out.ome.zarr"
    assert _job(tmp_path, out).returncode == 0
    before = np.asarray(zarr.open_group(str(out), mode="r")["0"])
    r = _job(tmp_path, out, "--l1", "0.01")
    assert r.returncode == 2
    assert "holds another job" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(out), mode="r")["0"]), before)
    # a folder that is not a cm2cl store is not touched either
    (tmp_path / "other.zarr").mkdir()
    (tmp_path / "other.zarr" / "keep.txt").write_text("mine")
    r = _job(tmp_path, tmp_path / "other.zarr")
    assert r.returncode == 2 and "not a cm2cl OME-Zarr store" in r.stderr
    assert (tmp_path / "other.zarr" / "keep.txt").read_text() == "mine"


def test_bad_series_inputs_are_refused_before_any_output(rt, tmp_path):
    _series(tmp_path)
    tifffile.imwrite(tmp_path / "odd.tif", np.zeros((30, 40), np.float32))
    out = tmp_path / "o.ome.zarr"
    r = _cli("reconstruct", tmp_path / "series.tif", tmp_path / "odd.tif", "--psf", tmp_path / "psf.ome.tif",
             "-o", out, *ARGS)
    assert r.returncode == 2 and "odd.tif" in r.stderr and "differs from the first frame" in r.stderr
    r = _job(tmp_path, out, "--device", "17")
    assert r.returncode == 2 and "17" in r.stderr
    r = _job(tmp_path, out, "--device", " ")
    assert r.returncode == 2 and "names no device" in r.stderr and "Traceback" not in r.stderr, r.stderr
    r = _job(tmp_path, out, "--scheduler", "tcp://127.0.0.1:9")
    assert r.returncode == 2 and "no Dask scheduler answers" in r.stderr
    r = _cli("reconstruct", tmp_path / "series.tif", tmp_path / "odd.tif", "--psf", tmp_path / "psf.ome.tif",
             "-o", tmp_path / "v.ome.tif", *ARGS)
    assert r.returncode == 2 and "needs an OME-Zarr output" in r.stderr
    assert not out.exists() and not (tmp_path / "v.ome.tif").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    with pytest.raises(InputError, match="no such file"):
        FrameSeries([tmp_path / "missing.tif"])


def test_frames_of_files_with_singleton_axes_read_as_counted(tmp_path):
    """Issue 27 F5: a (1, 2, 1, My, Mx) TCZYX file counts as 2 frames and a (1, 1, 1, My, Mx) one as 1; each
    reads as its own pixels (reading one used to raise ValueError after the store was created). tifffile
    keeps the singleton axes of its own 'shaped' files (an OME file's series comes squeezed)."""
    rng = np.random.default_rng(5)
    two, one, flat = (rng.random(s).astype(np.float32) for s in ((1, 2, 1, 12, 10), (1, 1, 1, 12, 10), (12, 10)))
    tifffile.imwrite(tmp_path / "a.tif", flat)
    tifffile.imwrite(tmp_path / "b.tif", two, metadata={"axes": "TCZYX"})
    tifffile.imwrite(tmp_path / "c.tif", one, metadata={"axes": "TCZYX"})
    s = FrameSeries([tmp_path / "a.tif", tmp_path / "b.tif", tmp_path / "c.tif"])
    assert len(s) == 4 and s.shape == (12, 10)
    for i, want in enumerate((flat, two[0, 0, 0], two[0, 1, 0], one[0, 0, 0])):
        np.testing.assert_array_equal(s.read(i), want)


@pytest.mark.parametrize("extra, flag", [
    (["--dry-run"], "--dry-run"), (["--mask", "saturated"], "--mask"), (["--mask", "bogus"], "--mask"),
    (["--saturation", "1000"], "--saturation"), (["--tile", "32", "32"], "--tile"), (["--padded"], "--padded"),
    (["--save-background"], "--save-background"), (["--host-memory", "1G"], "--host-memory"),
    (["--background", "opening:10px"], "--background opening:R"), (["--background", "garbage"], "background"),
    (["--camera", "gain=2,read-noise=1"], "--camera"), (["--psf-refine", "2", "--padding", "support"], "--psf-refine"),
    (["--save-psf", "--psf-refine", "0"], "--save-psf"), (["--emission-nm", "510"], "--emission-nm")])
def test_series_refuses_the_frame_options_it_does_not_honour(rt, tmp_path, capsys, extra, flag):
    """A series job given an option it does not apply (issue 27: they used to change nothing) stops before
    any work with one line naming the option, and creates no store."""
    from cm2cl.cli import main

    _series(tmp_path, n=2)
    out = tmp_path / "o.ome.zarr"
    code = main(["reconstruct", str(tmp_path / "series.tif"), "--psf", str(tmp_path / "psf.ome.tif"), "-o", str(out),
                 *ARGS, *extra])
    err = capsys.readouterr().err
    assert code == 2 and flag in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_series_that_cannot_fit_is_refused_before_its_store_exists(rt, tmp_path, capsys):
    """--stream never with a device cap far below one frame's state: refused by the planner before the
    store is created (it used to leave an empty store)."""
    from cm2cl.cli import main

    _series(tmp_path, n=2)
    out = tmp_path / "o.ome.zarr"
    code = main(["reconstruct", str(tmp_path / "series.tif"), "--psf", str(tmp_path / "psf.ome.tif"), "-o", str(out),
                 *ARGS, "--stream", "never", "--max-memory", "64K"])
    err = capsys.readouterr().err
    assert code == 2 and "too large to keep on the device" in err, err
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_store_this_run_created_is_removed_when_the_job_fails_before_its_first_frame(tmp_path):
    """Issue 27 F10/F11: a job that failed before any frame (its workers' devices cannot compile, a frame
    too large for them) left an empty store and its job record. A store this run created and left without
    a finished frame is removed; one with a finished frame, or one that existed before, is kept."""
    from cm2cl.jobs import FrameStore

    out, book = tmp_path / "e.ome.zarr", tmp_path / ".e.ome.zarr.cm2cl-done"
    kw = dict(fingerprint="f", n_frames=2, volume_shape=(2, 4, 4), dtype=np.float32)
    with pytest.raises(RuntimeError):
        with FrameStore.open(out, **kw) as store:
            assert store.created and out.is_dir() and book.is_dir()
            raise RuntimeError("the workers' device cannot compile")
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    with pytest.raises(RuntimeError):
        with FrameStore.open(out, **kw) as store:
            store.write(0, np.ones((2, 4, 4)))
            raise RuntimeError("stopped after a frame")
    with FrameStore.open(out, **kw) as store:
        assert not store.created and store.done() == {0}
    (book / "00000000").unlink()
    with pytest.raises(RuntimeError):
        with FrameStore.open(out, **kw) as store:   # an existing store, even without frames, is not ours to remove
            raise RuntimeError("again")
    assert out.is_dir() and book.is_dir() and not (tmp_path / ".e.ome.zarr.cm2cl-lock").exists()


def test_a_local_device_that_cannot_compile_is_refused_before_the_store(rt, tmp_path, capsys, monkeypatch):
    """Issue 27 F11: a series on a device whose compiler cannot build (PyPI's PoCL 3.0 on an unknown CPU)
    is refused by the compiler probe before the store exists, in one line naming the device."""
    import cm2cl.device
    from cm2cl.cli import main

    _series(tmp_path, n=2)
    monkeypatch.setattr(cm2cl.device, "compiler_works", lambda d: (False, "error: unknown target CPU 'generic'"))
    out = tmp_path / "o.ome.zarr"
    code = main(["reconstruct", str(tmp_path / "series.tif"), "--psf", str(tmp_path / "psf.ome.tif"), "-o", str(out),
                 *ARGS])
    err = capsys.readouterr().err
    assert code == 2 and "its OpenCL compiler cannot build kernels (error: unknown target CPU 'generic')" in err
    assert len(err.strip().splitlines()) == 1, err
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_cluster_error_is_cut_at_a_space_and_marked():
    """Issue 27 F9: the first line of a Dask failure was cut at 200 characters, mid-option ('-D FFT_')."""
    from cm2cl.jobs.executors import _first_line

    opts = " ".join(f"-D FFT_R{k}={k}" for k in range(60))
    first = f"build failed (options {opts})"
    line = _first_line(RuntimeError(first + "\nthe log"))
    kept = line[:-len(" ...")]
    assert len(line) <= 304 and line.endswith(" ...") and first.startswith(kept) and first[len(kept)] == " "
    assert _first_line(RuntimeError("short\nsecond")) == "short"


def test_dask_logs_are_silenced_while_the_job_holds_a_client_it_made():
    """Issue 27 F8: a killed scheduler made distributed.client and distributed.core log some 30 lines of
    tracebacks before the job's one line. While a job holds the client it made, distributed's loggers are
    off (ours stay on) and they are back after; with a client the caller gave, the caller's logging holds."""
    import logging

    pytest.importorskip("distributed")
    from cm2cl.jobs.executors import DaskCluster

    seen = []

    class Keep(logging.Handler):
        def emit(self, record):
            seen.append(record.getMessage())

    h = Keep()
    ours, theirs = logging.getLogger("cm2cl.test"), logging.getLogger("distributed.client")
    for lg in (ours, theirs):
        lg.addHandler(h)
    try:
        with DaskCluster("tcp://127.0.0.1:1").quiet():
            theirs.error("Failed to reconnect to scheduler after 10.00 seconds, closing client")
            logging.getLogger("distributed.core").error("Exception while handling op ...")
            ours.warning("ours")
        theirs.error("after the job")
        with DaskCluster(object()).quiet():       # a client the caller gave
            theirs.error("the caller's")
    finally:
        for lg in (ours, theirs):
            lg.removeHandler(h)
    assert seen == ["ours", "after the job", "the caller's"]


def test_sizes_below_a_byte_are_refused(rt, tmp_path, capsys):
    """--max-memory 0.5 and --host-memory 0.5 used to round to 0 bytes, which means no limit."""
    from cm2cl.cli import main

    _series(tmp_path, n=2)
    for opt in ("--max-memory", "--host-memory"):
        with pytest.raises(SystemExit) as e:
            main(["reconstruct", str(tmp_path / "series.tif"), "--psf", str(tmp_path / "psf.ome.tif"),
                  "-o", str(tmp_path / "o.ome.zarr"), opt, "0.5"])
        assert e.value.code == 2 and "at least 1 byte" in capsys.readouterr().err


def test_dask_local_cluster_gives_the_local_result(rt, tmp_path):
    import distributed   # in the test extra: this test runs wherever the suite does
    _series(tmp_path, n=3)
    ref = tmp_path / "ref.ome.zarr"
    assert _job(tmp_path, ref).returncode == 0
    b = np.asarray(zarr.open_group(str(ref), mode="r")["0"])
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, host="127.0.0.1", processes=True,
                                  dashboard_address=None) as cluster:
        r = _job(tmp_path, tmp_path / "dask.ome.zarr", "--scheduler", cluster.scheduler_address)
        assert r.returncode == 0, r.stderr
        assert "3 computed" in r.stdout and cluster.scheduler_address in r.stdout
        a = np.asarray(zarr.open_group(str(tmp_path / "dask.ome.zarr"), mode="r")["0"])
        np.testing.assert_array_equal(a, b)
        # the client killed (SIGKILL) between frame 1's chunk and its mark; the same command resumes
        out = tmp_path / "killed.ome.zarr"
        r = _job(tmp_path, out, "--scheduler", cluster.scheduler_address, env={"CM2CL_FAULT": "after_chunk.1"})
        assert r.returncode == -9, (r.returncode, r.stderr)
        r = _job(tmp_path, out, "--scheduler", cluster.scheduler_address)
        assert r.returncode == 0, r.stderr
        assert "already done" in r.stdout and "3 computed" not in r.stdout
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(out), mode="r")["0"]), b)


def test_executors_are_chosen_by_the_job_and_checked_before_any_output(rt, tmp_path):
    """Issue 23 item 4: one executor protocol (in order with warm start, local devices, Dask) instead of an
    if/elif; a job run through an explicit executor equals the one chosen for it."""
    from cm2cl.jobs import DaskCluster, FrameStore, InOrder, LocalDevices, executor_for, run_series
    from cm2cl.jobs.run import fingerprint
    from cm2cl.solver.params import ADMMParams

    assert isinstance(executor_for([None]), LocalDevices) and isinstance(executor_for([0], None, True), InOrder)
    assert isinstance(executor_for([None], "tcp://127.0.0.1:9"), DaskCluster)
    with pytest.raises(InputError, match="^warm_start: "):
        executor_for([None], "tcp://127.0.0.1:9", warm_start=True)
    import importlib.util

    if importlib.util.find_spec("distributed"):
        with pytest.raises(InputError, match=r"^scheduler 'tcp://127.0.0.1:9': no Dask scheduler answers"):
            DaskCluster("tcp://127.0.0.1:9").check(np.float32)
    psf, frames = _series(tmp_path, n=2)
    series = FrameSeries(tmp_path / "series.tif")
    params = ADMMParams(max_iter=5, tol=0)
    key = fingerprint(psf, params, series, np.float32, "auto", {})
    vols = []
    for name, ex in (("a", InOrder(None)), ("b", None)):
        with FrameStore.open(tmp_path / f"{name}.ome.zarr", fingerprint=key, n_frames=2, volume_shape=(4, 32, 40),
                             dtype=np.float32) as store:
            s = run_series(series, psf, store, params=params, key=key, executor=ex, warm_start=ex is None)
            assert s.computed == 2 and s.iterations == 10
            vols.append(np.stack([store.read(i) for i in range(2)]))
            assert store.info(1)["warm"] is True
            for i in range(2):   # each frame's marker keeps the data misfit its solve reached
                mis = store.info(i)["misfit"]
                assert 0 < mis["relative"] < 1 and mis["ratio"] > 0 and mis["pixels"] == 32 * 40
    np.testing.assert_array_equal(vols[0], vols[1])


@pytest.mark.parametrize("sig, code", [("SIGTERM", 143), ("SIGHUP", 129)])
def test_sigterm_stops_a_frame_cleanly_and_leaves_no_lock(rt, tmp_path, sig, code):
    """SIGTERM during a single frame's solve (a batch system stopping the job), or SIGHUP (its terminal
    closed; issue 27 X1): exit 143 / 129 with one line that says so, no output and no lock file left (both
    used to exit silently and keep the lock)."""
    import signal
    import time

    psf, frames = _series(tmp_path, n=1)
    tifffile.imwrite(tmp_path / "f.tif", frames[0])
    out = tmp_path / "v.ome.tif"
    p = subprocess.Popen([sys.executable, "-m", "cm2cl", "reconstruct", str(tmp_path / "f.tif"), "--psf",
                          str(tmp_path / "psf.ome.tif"), "-o", str(out), "--max-iter", "1000000", "--tol", "0",
                          "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lock = tmp_path / f".{out.name}.cm2cl-lock"
    t0 = time.time()
    while not lock.exists() and time.time() - t0 < 60 and p.poll() is None:
        time.sleep(0.05)
    assert lock.exists(), p.communicate()
    time.sleep(0.5)                                   # inside the solve
    p.send_signal(getattr(signal, sig))
    _, err = p.communicate(timeout=60)
    assert p.returncode == code and f"terminated ({sig})" in err and len(err.strip().splitlines()) == 1, err
    assert not lock.exists() and not out.exists()
    assert sorted(q.name for q in tmp_path.iterdir()) == ["f.tif", "psf.ome.tif", "series.tif"]


@pytest.mark.parametrize("sig, code", [("SIGINT", 130), ("SIGTERM", 143)])
def test_a_stopped_local_series_says_so_and_resumes(rt, tmp_path, sig, code):
    """Ctrl-C or SIGTERM during a local series: exit 130 / 143 with the one line that says so (Ctrl-C used
    to print it and then abort, exit 134: a worker thread was still inside the OpenCL runtime), and the
    same command then finishes the job."""
    import signal
    import time

    _series(tmp_path, n=2)
    out = tmp_path / "s.ome.zarr"
    argv = [sys.executable, "-m", "cm2cl", "reconstruct", str(tmp_path / "series.tif"), "--psf",
            str(tmp_path / "psf.ome.tif"), "-o", str(out), "--max-iter", "1500", "--tol", "0", "--quiet"]
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    while not (out / ".zattrs").exists() and time.time() - t0 < 60 and p.poll() is None:
        time.sleep(0.05)
    time.sleep(1.0)                                   # inside frame 0's solve
    p.send_signal(getattr(signal, sig))
    _, err = p.communicate(timeout=120)
    assert p.returncode == code, (p.returncode, err)
    assert err.strip().splitlines() == [err.strip().splitlines()[0]] and "resumes" in err
    r = subprocess.run(argv, capture_output=True, text=True)
    assert r.returncode == 0 and "2 frames" in r.stdout, r.stderr


def test_a_scheduler_port_that_never_answers_is_refused_in_bounded_time(rt, tmp_path):
    """A port that accepts the connection and never speaks (the client's own timeout did not cover it: the
    job hung forever): one line and exit 2 within ~10 s (5 s handshake + 5 s margin), and no store."""
    import distributed  # noqa: F401 - in the test extra; the job's client needs it
    import socket
    import threading
    import time

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    held = []
    threading.Thread(target=lambda: [held.append(srv.accept()) for _ in range(8)], daemon=True).start()
    _series(tmp_path, n=2)
    out = tmp_path / "o.ome.zarr"
    t = time.time()
    r = _job(tmp_path, out, "--scheduler", f"tcp://127.0.0.1:{srv.getsockname()[1]}")
    took = time.time() - t
    srv.close()
    assert r.returncode == 2 and "no Dask scheduler answers" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert took < 40 and not out.exists()


def test_a_lost_or_overwritten_chunk_is_found_and_recomputed(rt, tmp_path, capsys):
    """Each done frame carries its volume's SHA-256: `cm2cl verify` passes a whole store (exit 0), and after
    frame 0's chunk is deleted and frame 1's overwritten with random bytes it names both (exit 1); the same
    job's command then recomputes exactly those two, and the store equals the original bit for bit (they
    used to stay "done" and read as zeros)."""
    from cm2cl.cli import main

    _series(tmp_path, n=3)
    out = tmp_path / "s.ome.zarr"
    assert _job(tmp_path, out).returncode == 0
    good = np.asarray(zarr.open_group(str(out), mode="r")["0"])
    assert main(["verify", str(out)]) == 0 and "3 match their checksums" in capsys.readouterr().out
    chunks = sorted(p for p in (out / "0").rglob("*") if p.is_file() and not p.name.startswith("."))
    by_frame = {int(p.relative_to(out / "0").parts[0].split(".")[0]): p for p in chunks}
    by_frame[0].unlink()
    by_frame[1].write_bytes(np.random.default_rng(0).bytes(by_frame[1].stat().st_size))
    assert main(["verify", str(out)]) == 1
    err = capsys.readouterr().err
    assert "frame(s) 0, 1 do not match" in err and len(err.strip().splitlines()) == 1
    r = _job(tmp_path, out)
    assert r.returncode == 0 and "2 computed" in r.stdout and "1 already done" in r.stdout, (r.stdout, r.stderr)
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(out), mode="r")["0"]), good)
    assert main(["verify", str(out)]) == 0
    assert main(["verify", str(tmp_path / "series.tif")]) == 2


def test_a_warm_start_from_an_undecodable_chunk_without_checksum_recomputes_it(rt, tmp_path, capsys):
    """Issue 27 F4: a chunk overwritten with random bytes whose marker has no checksum (stores of older
    cm2cl) was trusted, and the warm start of the next frame died decoding it (blosc RuntimeError). The
    chunk is found when the store is reopened and the frame computed again: the store ends as an
    uninterrupted warm-start job's, to the bit; verify reports it before."""
    from cm2cl.cli import main

    _series(tmp_path, n=3)
    argv = ["reconstruct", str(tmp_path / "series.tif"), "--psf", str(tmp_path / "psf.ome.tif"), *ARGS, "--warm-start"]
    ref, out = tmp_path / "ref.ome.zarr", tmp_path / "o.ome.zarr"
    assert main(argv + ["-o", str(ref)]) == 0 and main(argv + ["-o", str(out)]) == 0
    chunks = [p for p in (out / "0" / "1").rglob("*") if p.is_file() and not p.name.startswith(".")]
    assert chunks
    for p in chunks:
        p.write_bytes(np.random.default_rng(1).bytes(3000))
    book = tmp_path / ".o.ome.zarr.cm2cl-done"
    (book / "00000001").write_text("{}")          # a marker as cm2cl wrote it before checksums
    (book / "00000002").unlink()
    capsys.readouterr()
    assert main(["verify", str(out)]) == 1 and "frame(s) 1 do not match" in capsys.readouterr().err
    assert main(argv + ["-o", str(out)]) == 0
    cap = capsys.readouterr()
    assert "2 computed" in cap.out and "frame 1 does not match" in cap.err and "Traceback" not in cap.err
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(out), mode="r")["0"]),
                                  np.asarray(zarr.open_group(str(ref), mode="r")["0"]))


def test_broken_store_metadata_and_overlong_names_get_one_line(rt, tmp_path):
    """Issue 27's tracebacks: a store whose .zarray is truncated or whose cm2cl record is not an object is
    refused in one line (exit 2) and left alone; an output name too long for the folder once the staged
    names beside it are counted is refused before any work, for a frame and for a series, with nothing
    created (a frame's used to fail after the solve and keep its lock)."""
    import shutil

    psf, frames = _series(tmp_path, n=2)
    tifffile.imwrite(tmp_path / "f.tif", frames[0])
    good = tmp_path / "a.ome.zarr"
    assert _job(tmp_path, good).returncode == 0
    for name, spoil in (("trunc", lambda s: (s / "0" / ".zarray").write_text((s / "0" / ".zarray").read_text()[:20])),
                        ("attrs", lambda s: (s / ".zattrs").write_text(json.dumps(
                            {**json.loads((s / ".zattrs").read_text()), "cm2cl": 5})))):
        bad = tmp_path / f"{name}.ome.zarr"
        shutil.copytree(good, bad)
        spoil(bad)
        before = sorted(p.name for p in bad.rglob("*"))
        r = _job(tmp_path, bad)
        assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert "is not a" in r.stderr and sorted(p.name for p in bad.rglob("*")) == before
    listing = sorted(p.name for p in tmp_path.iterdir())
    long = "x" * 240
    r = _cli("reconstruct", tmp_path / "f.tif", "--psf", tmp_path / "psf.ome.tif", "-o", tmp_path / f"{long}.ome.tif",
             *ARGS)
    assert r.returncode == 2 and "too long for its folder" in r.stderr and "Traceback" not in r.stderr, r.stderr
    r = _job(tmp_path, tmp_path / f"{long}.ome.zarr")
    assert r.returncode == 2 and "too long for its folder" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == listing


@pytest.mark.parametrize("key, value, said", [
    (("cm2cl", "display_max"), "x", "cm2cl.display_max is 'x', not a finite number"),
    (("cm2cl", "display_max"), [1], "cm2cl.display_max is [1], not a finite number"),
    (("omero", "channels"), "x", "omero.channels is 'x', not a list of channel mappings"),
    (("omero", "channels"), ["x"], "omero.channels is ['x'], not a list of channel mappings"),
    (("omero",), 7, "omero is 7, not a mapping")])
def test_store_attributes_of_the_wrong_type_are_refused_before_any_work(rt, tmp_path, capsys, key, value, said):
    """Issue 27 F2: a store whose display window attributes were edited to the wrong type failed with a
    traceback after the solve (at close); the resume is refused in one line naming the attribute, before
    any frame is computed, and leaves no lock."""
    import shutil
    from cm2cl.cli import main

    _series(tmp_path, n=2)
    good, out = tmp_path / "good.ome.zarr", tmp_path / "o.ome.zarr"
    argv = ["reconstruct", str(tmp_path / "series.tif"), "--psf", str(tmp_path / "psf.ome.tif"), *ARGS]
    assert main(argv + ["-o", str(good)]) == 0
    shutil.copytree(good, out)
    shutil.copytree(tmp_path / ".good.ome.zarr.cm2cl-done", tmp_path / ".o.ome.zarr.cm2cl-done")
    (tmp_path / ".o.ome.zarr.cm2cl-done" / "00000001").unlink()
    attrs = json.loads((out / ".zattrs").read_text())
    node = attrs
    for k in key[:-1]:
        node = node[k]
    node[key[-1]] = value
    (out / ".zattrs").write_text(json.dumps(attrs))
    capsys.readouterr()
    assert main(argv + ["-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert said in err and "o.ome.zarr" in err and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in (tmp_path / ".o.ome.zarr.cm2cl-done").iterdir()) == ["00000000"]
    assert not (tmp_path / ".o.ome.zarr.cm2cl-lock").exists()


def test_an_immutable_store_is_refused_before_any_work(rt, tmp_path, capsys):
    """Issue 27 F3: a store that cannot be written (root ignores chmod; the immutable flag stops it) failed
    with a PermissionError traceback after the first frame's solve; the resume is refused in one line
    before any work, saying the frames are kept, and leaves no lock."""
    import shutil
    from cm2cl.cli import main

    _series(tmp_path, n=2)
    out = tmp_path / "o.ome.zarr"
    argv = ["reconstruct", str(tmp_path / "series.tif"), "--psf", str(tmp_path / "psf.ome.tif"), "-o", str(out), *ARGS]
    assert main(argv) == 0
    (tmp_path / ".o.ome.zarr.cm2cl-done" / "00000001").unlink()
    if shutil.which("chattr") is None or subprocess.run(["chattr", "-R", "+i", str(out)]).returncode != 0:
        pytest.skip("needs chattr +i (root, a file system with the immutable flag)")
    try:
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "cannot be written" in err and "frames it holds are kept" in err and "o.ome.zarr" in err
        assert len(err.strip().splitlines()) == 1, err
        assert sorted(p.name for p in (tmp_path / ".o.ome.zarr.cm2cl-done").iterdir()) == ["00000000"]
        assert not (tmp_path / ".o.ome.zarr.cm2cl-lock").exists()
    finally:
        subprocess.run(["chattr", "-R", "-i", str(out)])


def test_a_write_that_fails_during_a_job_is_one_line_and_marks_nothing(rt, tmp_path, caplog):
    """Issue 27 F3: a chunk or marker that cannot be written once the job runs (disk full, the store made
    read-only meanwhile) is a JobError naming the store and the frame and saying how to resume; the frame is
    not marked done. A display window that cannot be updated at close is a warning: the frames are done."""
    import errno
    from cm2cl.errors import JobError
    from cm2cl.jobs import FrameStore

    out = tmp_path / "w.ome.zarr"

    class Full:
        def __init__(self, a):
            self.a, self.shape, self.dtype = a, a.shape, a.dtype

        def __getitem__(self, k):
            return self.a[k]

        def __setitem__(self, k, v):
            raise OSError(errno.ENOSPC, "No space left on device")

    with FrameStore.open(out, fingerprint="f", n_frames=2, volume_shape=(2, 4, 4), dtype=np.float32) as store:
        store.write(0, np.ones((2, 4, 4)))
        real = store.array
        store.array = Full(real)
        with pytest.raises(JobError, match=r"output '.*w.ome.zarr': frame 1 could not be written \(No space left "
                                           r"on device\); the frames finished before it are kept: rerun the same "
                                           r"command"):
            store.write(1, np.ones((2, 4, 4)))
        store.array = real
        assert store.done() == {0}

        def refuse():
            raise PermissionError(errno.EPERM, "Operation not permitted")

        store._widen_window = refuse
    assert "display window could not be updated (Operation not permitted)" in caplog.text
    assert not (tmp_path / ".w.ome.zarr.cm2cl-lock").exists()


def test_a_nan_frame_is_named_with_its_file(rt, tmp_path):
    """A series whose second frame holds NaN stops in one line naming that frame, its file and page;
    the first frame stays done and resumable."""
    psf, frames = _series(tmp_path, n=2)
    frames[1, 3, 4] = np.nan
    tifffile.imwrite(tmp_path / "series.tif", frames, photometric="minisblack")
    r = _job(tmp_path, tmp_path / "n.ome.zarr")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "frame 1 (" in r.stderr and "series.tif" in r.stderr and "page 1" in r.stderr and "NaN" in r.stderr, r.stderr
    assert (tmp_path / ".n.ome.zarr.cm2cl-done" / "00000000").exists()


@pytest.mark.parametrize("extra", [["--warm-start"], ["--scheduler", "tcp://127.0.0.1:9"], ["--pyramid", "3"],
                                   ["--frame-interval", "0.5"]])
def test_series_options_are_refused_for_one_frame(rt, tmp_path, capsys, extra):
    """A series-only option given with a single-frame output stops before any work with one line."""
    from cm2cl.cli import main

    _series(tmp_path, n=1)
    code = main(["reconstruct", str(tmp_path / "series.tif"), "--psf", str(tmp_path / "psf.ome.tif"), "-o",
                 str(tmp_path / "v.ome.tif"), *ARGS, *extra])
    err = capsys.readouterr().err
    assert code == 2 and extra[0] in err and "only for a series" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "v.ome.tif").exists()


def test_cli_series_pyramid_and_frame_interval(rt, tmp_path):
    import zarr

    _series(tmp_path, n=2)
    out = tmp_path / "p.ome.zarr"
    r = _job(tmp_path, out, "--pyramid", "2", "--frame-interval", "0.25", "--channel", "GCaMP")
    assert r.returncode == 0, r.stderr
    attrs = dict(zarr.open_group(str(out), mode="r").attrs)
    ms = attrs["multiscales"][0]
    assert [d["path"] for d in ms["datasets"]] == ["0", "1"] and ms["axes"][0]["unit"] == "second"
    assert ms["datasets"][0]["coordinateTransformations"][0]["scale"][0] == 0.25
    assert attrs["omero"]["channels"][0]["label"] == "GCaMP"
    r = _job(tmp_path, out, "--frame-interval", "0.25", "--channel", "GCaMP")      # other levels: refused
    assert r.returncode == 2 and "resolution level" in r.stderr

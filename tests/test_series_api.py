"""cm2cl.reconstruct_series (issue 26): a series job from Python in one call, with the frames each equal to
a single-frame solve, resumed like the CLI, on a Dask Client with a bounded number of frames in flight."""

import numpy as np
import pytest
import zarr

import cm2cl
from cm2cl.errors import InputError
from cm2cl.jobs import FrameSeries
from test_jobs import ARGS, _series  # noqa: F401 - the series of the CLI's tests

KW = dict(max_iter=25, tol=0.0, psf_refine=0)   # the PSF as given, unless a test refines


def _frames(tmp_path, n=3):
    psf, frames = _series(tmp_path, n=n)
    return psf.astype(np.float64), frames.astype(np.float64)


def test_array_frames_equal_single_frame_solves_and_resume(rt, tmp_path):
    psf, frames = _frames(tmp_path)
    out = tmp_path / "s.ome.zarr"
    seen = []
    s = cm2cl.reconstruct_series(frames, psf, out, progress=lambda i, info: seen.append(i), **KW)
    assert (s.frames, s.computed, s.skipped) == (3, 3, 0) and sorted(seen) == [0, 1, 2]
    vol = np.asarray(zarr.open_group(str(out), mode="r")["0"])
    for t in range(3):
        one = cm2cl.reconstruct(frames[t], psf, **KW).volume
        np.testing.assert_allclose(vol[t], one, rtol=1e-5, atol=1e-6 * one.max())
    # the same call resumes: nothing to do; a frame whose chunk is damaged is computed again, to the same bits
    s = cm2cl.reconstruct_series(frames, psf, out, **KW)
    assert (s.computed, s.skipped) == (0, 3)
    (out / "0" / "1" / "0" / "0" / "0").write_bytes(b"\0" * 50)   # NGFF 0.4's "/" chunk keys
    s = cm2cl.reconstruct_series(frames, psf, out, **KW)
    assert (s.computed, s.skipped) == (1, 2)
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(out), mode="r")["0"]), vol)
    # another job (other parameters) on the same store is refused
    with pytest.raises(InputError, match="another"):
        cm2cl.reconstruct_series(frames, psf, out, max_iter=26, tol=0.0)


def test_psf_refine_refines_on_the_first_frame_and_solves_every_frame_with_it(rt, tmp_path):
    """reconstruct_series(..., psf_refine=N): the stack refined on frame 0 (what reconstruct(frames[0], psf,
    psf_refine=N) gives) is kept as OUT.psf.ome.tif and every frame is the plain solve with it."""
    from cm2cl import io

    psf, frames = _frames(tmp_path)
    out = tmp_path / "p.ome.zarr"
    s = cm2cl.reconstruct_series(frames, psf, out, psf_refine_iter=10, **{**KW, "psf_refine": 2})
    assert s.computed == 3
    h, meta = io.read_tiff(tmp_path / "p.psf.ome.tif")
    np.testing.assert_array_equal(h, cm2cl.reconstruct(frames[0], psf, psf_refine_iter=10, **{**KW, "psf_refine": 2}).psf)
    vol = np.asarray(zarr.open_group(str(out), mode="r")["0"])
    one = cm2cl.reconstruct(frames[2], h, **KW).volume
    np.testing.assert_allclose(vol[2], one, rtol=1e-5, atol=1e-6 * one.max())
    # with finished frames and the stack gone: refused, nothing solved
    (tmp_path / "p.psf.ome.tif").unlink()
    (out / "0" / "1" / "0" / "0" / "0").write_bytes(b"\0" * 50)
    with pytest.raises(InputError, match="p.psf.ome.tif"):
        cm2cl.reconstruct_series(frames, psf, out, psf_refine_iter=10, **{**KW, "psf_refine": 2})


def test_file_frames_and_psf_path_label_the_store(rt, tmp_path):
    _frames(tmp_path)
    out = tmp_path / "new" / "f.ome.zarr"     # its missing folder is made
    s = cm2cl.reconstruct_series(str(tmp_path / "series.tif"), tmp_path / "psf.ome.tif", out, warm_start=True, **KW)
    assert s.computed == 3
    attrs = dict(zarr.open_group(str(out), mode="r").attrs)
    assert attrs["cm2cl"]["voxel_size_um"] == [10.0, 2.0, 2.0]


def test_bad_calls_are_refused_before_any_store(rt, tmp_path):
    psf, frames = _frames(tmp_path)
    out = tmp_path / "x.ome.zarr"
    for kw, msg in ((dict(client="tcp://127.0.0.1:9", warm_start=True), "client:"),
                    (dict(l1=-1.0), "l1")):
        with pytest.raises(InputError, match=msg):
            cm2cl.reconstruct_series(frames, psf, out, **kw)
    with pytest.raises(InputError, match="does not match the PSF's sensor grid"):
        cm2cl.reconstruct_series(frames[:, :-1], psf, out)
    with pytest.raises(InputError, match=r"\(T, My, Mx\)"):
        cm2cl.reconstruct_series(frames[0], psf, out)
    with pytest.raises(TypeError, match="unexpected keyword"):
        cm2cl.reconstruct_series(frames, psf, out, bogus=1)
    assert not out.exists()


class _CountingSeries(FrameSeries):
    """A FrameSeries that records, for each frame read, how many frames had finished by then."""

    def __init__(self, *a, finished=None, **k):
        super().__init__(*a, **k)
        self.finished, self.reads = finished, []

    def read(self, i):
        self.reads.append(len(self.finished))
        return super().read(i)


def test_dask_client_with_backpressure(rt, tmp_path):
    import distributed

    _frames(tmp_path, n=6)
    finished = []
    series = _CountingSeries(str(tmp_path / "series.tif"), finished=finished)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, host="127.0.0.1", processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        s = cm2cl.reconstruct_series(series, tmp_path / "psf.ome.tif", tmp_path / "d.ome.zarr", client=client,
                                     progress=lambda i, info: finished.append(i), **KW)
        assert s.computed == 6 and client.status == "running"   # the caller's client is left open
    # one worker: two frames in flight; frame k (k >= 2) is read only after k - 1 frames finished
    assert len(series.reads) == 6 and all(r >= k - 1 for k, r in enumerate(series.reads) if k >= 2), series.reads
    ref = cm2cl.reconstruct_series(str(tmp_path / "series.tif"), tmp_path / "psf.ome.tif", tmp_path / "l.ome.zarr", **KW)
    assert ref.computed == 6
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(tmp_path / "d.ome.zarr"), mode="r")["0"]),
                                  np.asarray(zarr.open_group(str(tmp_path / "l.ome.zarr"), mode="r")["0"]))


def test_dask_worker_killed_mid_job_resubmits_and_cluster_lost_says_how_to_resume(rt, tmp_path, caplog):
    """Issue 27: the only worker killed (SIGKILL) after the first frame took the scattered PSF with it: the
    PSF is sent again and the lost frames resubmitted, to the local result's bits. The cluster closed under
    the job: one JobError line saying what, the frames kept, and how to resume; the rerun completes it."""
    import logging
    import os
    import signal

    import distributed

    from cm2cl.errors import JobError

    _frames(tmp_path, n=5)
    series, psf = str(tmp_path / "series.tif"), tmp_path / "psf.ome.tif"
    ref = tmp_path / "l.ome.zarr"
    cm2cl.reconstruct_series(series, psf, ref, **KW)
    caplog.set_level(logging.WARNING, logger="cm2cl")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, host="127.0.0.1", processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        pids = list(client.run(os.getpid).values())
        done = []

        def kill_after_first(i, info):
            done.append(i)
            if len(done) == 1:
                for p in pids:
                    os.kill(p, signal.SIGKILL)

        out = tmp_path / "k.ome.zarr"
        s = cm2cl.reconstruct_series(series, psf, out, client=client, progress=kill_after_first, **KW)
        assert s.computed == 5
        assert any("PSF is sent again" in r.getMessage() for r in caplog.records), [r.getMessage() for r in caplog.records]
        np.testing.assert_array_equal(np.asarray(zarr.open_group(str(out), mode="r")["0"]),
                                      np.asarray(zarr.open_group(str(ref), mode="r")["0"]))
    cluster = distributed.LocalCluster(n_workers=1, threads_per_worker=1, host="127.0.0.1", processes=True,
                                       dashboard_address=None)
    client = distributed.Client(cluster)
    out = tmp_path / "c.ome.zarr"
    try:
        def close_after_first(i, info):
            if not getattr(close_after_first, "done", False):
                close_after_first.done = True
                cluster.close()

        with pytest.raises(JobError) as info:
            cm2cl.reconstruct_series(series, psf, out, client=client, progress=close_after_first, **KW)
        msg = str(info.value)
        assert "the job stopped" in msg and "rerun the same command to resume" in msg and "\n" not in msg, msg
    finally:
        client.close()
        cluster.close()
    s = cm2cl.reconstruct_series(series, psf, out, **KW)       # resumed locally: the finished frames kept
    assert s.skipped >= 1 and s.computed + s.skipped == 5
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(out), mode="r")["0"]),
                                  np.asarray(zarr.open_group(str(ref), mode="r")["0"]))


def test_dask_worker_whose_device_cannot_compile_stops_in_one_line_and_resumes(rt, tmp_path, monkeypatch):
    """Issue 27: a worker whose OpenCL device cannot build the kernels (here: from the second frame on) stops
    the job with the build failure's one line (what failed where), not a Dask traceback; the frame finished
    before it is kept, and a rerun on a working cluster computes only the rest, to the local result's bits."""
    import distributed

    from cm2cl.errors import KernelBuildError
    from cm2cl.jobs import executors

    _frames(tmp_path, n=4)
    series, psf = str(tmp_path / "series.tif"), tmp_path / "psf.ome.tif"
    ref = tmp_path / "l.ome.zarr"
    cm2cl.reconstruct_series(series, psf, ref, **KW)
    real, count = executors.solve_frame, tmp_path / "calls"

    def broken(*a, **k):      # counted in a file: Dask sends the function to its worker by value
        with open(count, "a") as f:
            f.write("x")
        if count.stat().st_size > 1:
            raise KernelBuildError("build failed\nlog", summary="kernels/splits.cl did not build on 'cpu-znver5': "
                                   "error: unable to create target")
        return real(*a, **k)

    out = tmp_path / "b.ome.zarr"
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        monkeypatch.setattr(executors, "solve_frame", broken)
        with pytest.raises(KernelBuildError) as info:
            cm2cl.reconstruct_series(series, psf, out, client=client, **KW)
        assert "unable to create target" in info.value.summary and "\n" not in info.value.summary
        monkeypatch.undo()
        from cm2cl.jobs.store import FrameStore

        st = FrameStore.open_readonly(out)
        try:
            assert len(st.done()) == 1
        finally:
            st.close()
        s = cm2cl.reconstruct_series(series, psf, out, client=client, **KW)
        assert s.computed == 3
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(out), mode="r")["0"]),
                                  np.asarray(zarr.open_group(str(ref), mode="r")["0"]))

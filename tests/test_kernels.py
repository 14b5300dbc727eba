import numpy as np
import pytest

from cm2cl.device import kernels
from cm2cl.errors import KernelBuildError


def test_programs_are_built_once_per_context(rt):
    a = kernels.program(rt, "fft_conv.cl", np.float32)
    assert kernels.program(rt, "fft_conv.cl", np.float32) is a
    assert kernels.kernel(rt, "layout.cl", "crop", np.float32) is kernels.kernel(rt, "layout.cl", "crop", np.float32)


def test_build_failure_names_file_and_shows_log(rt, monkeypatch):
    monkeypatch.setitem(kernels._SOURCES, "broken.cl", "__kernel void f(__global real_t *a) { a[0] = undefined_name; }")
    with pytest.raises(KernelBuildError) as err:
        kernels.program(rt, "broken.cl", np.float32)
    assert "kernels/broken.cl" in str(err.value) and "undefined_name" in str(err.value)


def test_a_build_failure_survives_dask_pickling_with_its_summary_first(rt, monkeypatch):
    """Issue 27 F9: a Dask worker whose device cannot compile sent back a generic Exception (pyopencl's
    error, chained to ours, holds an _ErrorRecord that cannot be pickled). The error carries no pyopencl
    object, goes through Dask's own error message and back as itself, and its first line is the summary."""
    pytest.importorskip("distributed")
    from distributed.core import error_message
    from distributed.protocol import pickle as dask_pickle

    monkeypatch.setitem(kernels._SOURCES, "broken.cl", "__kernel void f(__global real_t *a) { a[0] = undefined_name; }")
    with pytest.raises(KernelBuildError) as err:
        kernels.program(rt, "broken.cl", np.float32)
    e = err.value
    assert e.__cause__ is None and e.__context__ is None
    assert str(e).splitlines()[0] == e.summary and "undefined_name" in e.summary and "-D" not in e.summary
    back = dask_pickle.loads(error_message(e)["exception"].data)   # what the worker sends the client
    assert type(back) is KernelBuildError and back.summary == e.summary and back.log == e.log


def test_no_fast_math(rt, monkeypatch):
    """Programs are built without fast-math: the options handed to the compiler carry none, and a
    kernel built through the loader still sees NaN (finite-math-only would fold isnan to false)."""
    import pyopencl as cl

    seen = []
    real_build = cl.Program.build

    def spy(self, options=None, *a, **k):
        seen.append(list(options or []))
        return real_build(self, options, *a, **k)

    monkeypatch.setattr(cl.Program, "build", spy)
    monkeypatch.setitem(kernels._SOURCES, "nan_probe.cl",
                        "__kernel void f(__global const real_t *a, __global int *o) {"
                        " const size_t i = get_global_id(0); o[i] = isnan(a[i]) ? 1 : (isinf(a[i]) ? 2 : 0); }")
    for dt in (np.float32,) + ((np.float64,) if rt.caps.fp64 else ()):
        k = kernels.kernel(rt, "nan_probe.cl", "f", dt)
        a = np.array([1.0, np.nan, np.inf, -np.inf, 0.0], dt)
        import pyopencl.array as cla
        da, do = cla.to_device(rt.queue, a), cla.zeros(rt.queue, a.size, np.int32)
        k(rt.queue, (a.size,), None, da.data, do.data)
        assert do.get().tolist() == [0, 1, 2, 2, 0], dt
    assert seen and not any("fast" in o or "unsafe" in o or "finite" in o for opts in seen for o in opts)


def test_work_group_size_is_queried_per_kernel(rt):
    """The local size comes from each kernel's own limit on this device: the largest power of two
    within it (and within the cap)."""
    import pyopencl as cl

    class Fake:
        def __init__(self, limit):
            self.limit, self.asked = limit, []

        def get_work_group_info(self, what, dev):
            self.asked.append((what, dev))
            return self.limit

    for limit, cap, want in ((48, 256, 32), (1, 256, 1), (1024, 64, 64), (200, 256, 128)):
        f = Fake(limit)
        assert kernels.work_group_size(rt, f, cap) == min(want, rt.caps.max_work_group_size)
        assert f.asked == [(cl.kernel_work_group_info.WORK_GROUP_SIZE, rt.device)]
    k = kernels.kernel(rt, "fft_conv.cl", "spectral_mac", np.float32)
    lim = k.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, rt.device)
    n = kernels.work_group_size(rt, k, 1 << 20)
    assert n & (n - 1) == 0 and n <= lim < 2 * n or n == rt.caps.max_work_group_size


def test_kernel_sources_ship_with_the_package():
    names = {p.name for p in kernels.kernel_dir().iterdir()}
    assert {"common.cl", "fft_conv.cl", "layout.cl"} <= names


def test_a_group_of_files_is_one_program(rt):
    """The files of a group share one program (one build on a cold start); a kernel of any of them
    comes from it, and other files stay on their own."""
    group = kernels.GROUPS[0]
    prg = kernels.program(rt, group[0], np.float32)
    assert all(kernels.program(rt, f, np.float32) is prg for f in group)
    assert kernels.kernel(rt, "xstep.cl", "xstep_hx", np.float32).program.int_ptr == prg.int_ptr
    assert kernels.group_of("morphology.cl") == ("morphology.cl",)
    assert kernels.program(rt, "morphology.cl", np.float32) is not prg


def test_build_failure_in_a_group_names_its_files(rt, monkeypatch):
    monkeypatch.setattr(kernels, "GROUPS", (("layout.cl", "broken.cl"),))
    monkeypatch.setitem(kernels._SOURCES, "broken.cl", "__kernel void f(__global real_t *a) { a[0] = undefined_name; }")
    with pytest.raises(KernelBuildError) as err:
        kernels.program(rt, "broken.cl", np.float32)
    assert "kernels/layout.cl + kernels/broken.cl" in str(err.value) and "undefined_name" in str(err.value)
    assert "broken.cl:1" in str(err.value)   # the compiler's log names the file and line


def test_fill_and_scale_match_numpy(rt, dtype):
    """fill and scale (no pyopencl elementwise kernels) on real and complex arrays; fill also on a view at
    an offset into its buffer."""
    import pyopencl.array as cla

    from cm2cl.device.volume import fill, scale

    real = np.dtype(dtype)
    for dt in (real, np.result_type(real, np.complex64)):
        rng = np.random.default_rng(1)
        host = rng.standard_normal(1001).astype(dt) + (1j * rng.standard_normal(1001) if dt.kind == "c" else 0)
        host = host.astype(dt)
        a = cla.to_device(rt.queue, host)
        scale(rt, a, 0.37)
        want = host * real.type(0.37)
        assert np.array_equal(a.get(), want), dt
        fill(rt, a[3:900], 2.5)
        want[3:900] = 2.5
        assert np.array_equal(a.get(), want), dt
        fill(rt, a)
        assert not a.get().any(), dt

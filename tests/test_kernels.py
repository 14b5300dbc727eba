import numpy as np
import pytest

from cm2cl import kernels
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


def test_no_fast_math(rt):
    opts = kernels.build_options(np.float32) + kernels.build_options(np.float64)
    assert not any("fast" in o or "unsafe" in o for o in opts)


def test_work_group_size_is_queried_per_kernel(rt):
    k = kernels.kernel(rt, "fft_conv.cl", "spectral_mac", np.float32)
    n = kernels.work_group_size(rt, k)
    assert n >= 1 and n & (n - 1) == 0 and n <= rt.caps.max_work_group_size


def test_kernel_sources_ship_with_the_package():
    names = {p.name for p in kernels.kernel_dir().iterdir()}
    assert {"common.cl", "fft_conv.cl", "layout.cl"} <= names

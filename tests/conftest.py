"""Shared fixtures: the OpenCL runtime (skips cleanly without a device) and real types."""

import numpy as np
import pytest

from cm2cl import device
from cm2cl.device import fft
from cm2cl.errors import DeviceError


@pytest.fixture(scope="session")
def rt():
    try:
        return device.get_runtime()
    except DeviceError as exc:
        pytest.skip(f"no OpenCL device: {exc}")


@pytest.fixture
def rt64(rt):
    """The runtime, for tests that compare against the float64 twin to float64 rounding."""
    if not rt.caps.fp64:
        pytest.skip(f"device '{rt.caps.name}' has no fp64 support (cl_khr_fp64)")
    return rt


@pytest.fixture(params=["float32", "float64"])
def dtype(request, rt):
    dt = np.dtype(request.param)
    if dt == np.float64 and not rt.caps.fp64:
        pytest.skip(f"device '{rt.caps.name}' has no fp64 support (cl_khr_fp64)")
    return dt


@pytest.fixture(params=fft.BACKENDS)
def backend(request):
    if request.param not in fft.available_backends():
        pytest.skip(f"FFT backend {request.param!r} not installed (pip install 'cm2cl[vkfft]')")
    return request.param


def rtol_for(dtype) -> float:
    """Relative tolerance of one FFT-based operator application against the float64 reference:
    a few ulps per FFT stage times log2(N) stages, with a margin (float32 eps = 1.2e-7)."""
    return 1e-5 if np.dtype(dtype) == np.float32 else 1e-12

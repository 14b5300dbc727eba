import numpy as np
import pyopencl.array as cla
import pytest

from cm2cl import fft

SHAPES = [(64, 128), (48, 60), (42, 70), (45, 63), (31, 17)]  # pow2, smooth, 7-smooth, odd, prime


@pytest.mark.parametrize("shape", SHAPES)
def test_fft_matches_numpy_float64(rt, backend, dtype, shape):
    rng = np.random.default_rng(sum(shape))
    batch = 3
    x = rng.standard_normal((batch,) + shape)
    plan = fft.get_plan(rt, shape, batch, dtype, backend)
    xd = cla.to_device(rt.queue, x.astype(dtype))
    spec = cla.empty(rt.queue, plan.spec_shape, plan.cdtype)
    plan.forward(xd, spec)
    ref = np.fft.fft2(x)[..., : plan.spec_shape[-1]]
    tol = 1e-5 if dtype == np.float32 else 1e-12
    err = np.linalg.norm(spec.get() - ref) / np.linalg.norm(ref)
    assert err <= tol, f"forward relative error {err:.2e}"
    # inverse of a known spectrum (numpy's), normalised
    spec.set(ref.astype(plan.cdtype))
    back = cla.empty(rt.queue, plan.real_shape, dtype)
    plan.inverse(spec, back)
    err = np.linalg.norm(back.get() - x) / np.linalg.norm(x)
    assert err <= tol, f"inverse relative error {err:.2e}"


def test_good_size_per_backend():
    assert fft.good_size(647, "reikna") == 1024
    assert fft.good_size(647, "vkfft") == 648  # 2^3 3^4
    assert fft.good_size(863, "vkfft") == 864
    for n in range(1, 300):
        g = fft.good_size(n, "vkfft")
        assert g >= n and g % 2 == 0 and fft._is_smooth(g)


def test_plans_are_cached(rt):
    a = fft.get_plan(rt, (32, 32), 2, np.float32, "reikna")
    assert fft.get_plan(rt, (32, 32), 2, np.float32, "reikna") is a


def test_unknown_backend_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown backend 'cufft'"):
        fft.resolve_backend("cufft")

import numpy as np
import pyopencl.array as cla
import pytest

from cm2cl.device import fft

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


from hypothesis import given, settings, strategies as st  # noqa: E402

from cm2cl.device.volume import slab_bounds  # noqa: E402


@settings(max_examples=200, deadline=None)
@given(n=st.integers(1, 5000), backend=st.sampled_from(["vkfft", "reikna"]))
def test_good_size_is_the_smallest_fast_size(n, backend):
    g = fft.good_size(n, backend)
    fast = (lambda m: m & (m - 1) == 0) if backend == "reikna" else (lambda m: m % 2 == 0 and fft._is_smooth(m))
    assert g >= n and fast(g)
    assert not any(fast(m) for m in range(n, g))


@settings(max_examples=200, deadline=None)
@given(nz=st.integers(1, 300), plane=st.integers(1, 10**6), per=st.integers(1, 64),
       cap=st.one_of(st.none(), st.integers(1, 50)))
def test_slab_bounds_cover_the_volume_within_the_largest_buffer(nz, plane, per, cap):
    bounds = slab_bounds(nz, plane, plane * per, cap)
    assert bounds[0][0] == 0 and bounds[-1][1] == nz
    assert all(b[1] == c[0] for b, c in zip(bounds, bounds[1:]))
    assert all(0 < (z1 - z0) * plane <= plane * per and (cap is None or z1 - z0 <= cap) for z0, z1 in bounds)


def test_a_plane_larger_than_the_largest_buffer_is_a_clear_error():
    from cm2cl.errors import DeviceError

    with pytest.raises(DeviceError, match=r"one depth plane needs .* MiB but the device's largest buffer is"):
        slab_bounds(4, 3 * 2**20, 2**20)

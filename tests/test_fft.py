import numpy as np
import pyopencl.array as cla
import pytest

from cm2cl.device import fft
from cm2cl.errors import InputError

SHAPES = [(64, 128), (48, 60), (42, 70), (45, 63), (31, 17)]  # pow2, smooth, 7-smooth, odd, prime


@pytest.mark.parametrize("shape", SHAPES)
def test_fft_matches_numpy_float64(rt, backend, dtype, shape):
    rng = np.random.default_rng(sum(shape))
    batch = 3
    x = rng.standard_normal((batch,) + shape)
    if backend == "cl" and not all(fft._is_smooth(n, (2, 3, 5, 7, 11, 13)) for n in shape):
        with pytest.raises(InputError, match=r"fft size p[xy]=\d+: .* prime factor \d+ > 13"):
            fft.get_plan(rt, shape, batch, dtype, backend)
        return
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
    for b in ("vkfft", "cl"):
        assert fft.good_size(647, b) == 648  # 2^3 3^4
        assert fft.good_size(863, b) == 864
        for n in range(1, 300):
            g = fft.good_size(n, b)
            assert g >= n and g % 2 == 0 and fft._is_smooth(g)


def test_plans_are_cached(rt):
    a = fft.get_plan(rt, (32, 32), 2, np.float32, "reikna")
    assert fft.get_plan(rt, (32, 32), 2, np.float32, "reikna") is a


def test_unknown_backend_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown backend 'cufft'"):
        fft.resolve_backend("cufft")


def test_auto_backend_is_the_own_kernels_on_a_cpu(rt):
    """The rule of docs/fft.md: cl on CPU devices (measured at least as fast as VkFFT there)."""
    assert fft.resolve_backend("auto") == "cl"
    if rt.caps.kind == "CPU":
        assert fft.resolve_backend("auto", rt) == "cl"
    assert fft.spectrum_shape((4, 6, 10), "cl") == (4, 6, 6)
    assert fft.spectrum_shape((4, 6, 10), "reikna") == (4, 6, 10)


def test_reconstruction_leaves_numpy_unchanged(rt, backend):
    """No backend may add names to NumPy (reikna 0.8 needed np.float_, np.cast, ... patched in):
    the names in numpy's namespace are the same before and after a reconstruction, except for
    NumPy's own submodules that get imported on first use.  In a fresh interpreter, so that no
    earlier test has changed NumPy already."""
    import subprocess
    import sys

    script = f"""
import numpy as np, cm2cl
names = lambda: {{k for k, v in np.__dict__.items()
                 if not (type(v) is type(np) and v.__name__.startswith("numpy."))}}
rng = np.random.default_rng(3)
psf, y = rng.random((2, 8, 8)).astype(np.float32), rng.random((8, 8)).astype(np.float32)
before = names()
rec = cm2cl.reconstruct(y, psf, backend={backend!r}, device={rt.caps.index}, max_iter=2)
assert rec.volume.shape == (2, 8, 8), rec.volume.shape
print(sorted(names() ^ before))
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]", f"numpy's names changed: {out.stdout.strip()}"


from hypothesis import given, settings, strategies as st  # noqa: E402

from cm2cl.device.volume import slab_bounds  # noqa: E402


@settings(max_examples=200, deadline=None)
@given(n=st.integers(1, 5000), backend=st.sampled_from(["cl", "vkfft", "reikna"]))
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


@pytest.mark.parametrize("plane_shape", [(16, 32), (3, 5)], ids=["aligned", "unaligned"])
def test_slabbed_volume_round_trips_in_one_allocation_where_aligned(rt, plane_shape):
    """A volume in several slabs is one buffer with a sub-buffer per slab where each slab starts at the
    device's base-address alignment (16 x 32 float32 planes: 2 KiB), separate buffers otherwise
    (3 x 5: 60 bytes); either way set, get, fill and scale act on the planes they should."""
    from cm2cl.device.volume import Volume

    rng = np.random.default_rng(8)
    bounds = [(0, 2), (2, 4), (4, 5)]
    vol = Volume(rt, bounds, plane_shape, np.float32)
    align = rt.device.mem_base_addr_align // 8
    one = 2 * 16 * 32 * 4 % align == 0 if plane_shape == (16, 32) else False
    assert (vol._whole is not None) is one
    host = rng.standard_normal((5,) + plane_shape).astype(np.float32)
    np.testing.assert_array_equal(vol.set(host).get(), host)
    vol.slabs[1].set(np.zeros((2,) + plane_shape, np.float32))   # a slab's writes stay in its planes
    want = host.copy()
    want[2:4] = 0
    np.testing.assert_array_equal(vol.get(), want)
    np.testing.assert_allclose(vol.scale(2.0).get(), 2 * want)
    np.testing.assert_array_equal(vol.fill(3).get(), np.full_like(host, 3))

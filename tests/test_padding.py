"""Padding from the PSF's support (issue 9 item 2): M + K - 1 instead of 2M - 1, with no wrap-around into
the sensor, and the same reconstruction on the sensor."""

import numpy as np

import cm2cl
from cm2cl import reference as ref
from cm2cl.solver.forward import ForwardModel, crop_offsets, psf_support, support_padding

M = (32, 40)


def _compact_psf(seed=0):
    """Foci only within a 9 x 11 window around the array centre (like a binned or small-array PSF)."""
    rng = np.random.default_rng(seed)
    psf = np.zeros((3,) + M)
    cy, cx = M[0] // 2, M[1] // 2
    for i in range(3):
        for _ in range(4):
            psf[i, cy + rng.integers(-4, 5), cx + rng.integers(-5, 6)] += rng.uniform(0.5, 1.0)
    return psf


def test_support_is_measured_and_the_grid_shrinks():
    psf = _compact_psf()
    (y0, y1), (x0, x1) = psf_support(psf, 1.0)
    assert y0 >= 16 - 4 and y1 <= 16 + 4 and x0 >= 20 - 5 and x1 <= 20 + 5
    t, P, info = support_padding(psf, "cl")
    assert info["light_dropped"] <= 1e-6 and np.allclose(t.sum(), psf.sum(), rtol=1e-6)
    K = info["support_px"]
    assert all(p >= m + k - 1 for p, m, k in zip(P, M, K))
    assert info["voxel_fraction"] < 0.75 and tuple(info["full_padded_shape"]) == (64, 80)


def test_support_is_measured_in_float64_without_copying_a_float32_stack():
    """A full frame's stack is gigabytes: the support is found from per-plane float64 profiles (the same
    as from the float64 stack), the stack is copied only where something is truncated, and in its dtype."""
    rng = np.random.default_rng(4)
    psf = _compact_psf(2).astype(np.float32)
    t, P, info = support_padding(psf, "cl")
    assert t.dtype == np.float32 and t is not psf
    # all the light within the support: the first and last lit rows and columns of the whole stack
    rows, cols = (np.flatnonzero(np.abs(psf.astype(np.float64)).sum(axis=(0, a))) for a in (2, 1))
    assert psf_support(psf, 1.0) == ((rows[0], rows[-1]), (cols[0], cols[-1]))
    wide = rng.random((2,) + M).astype(np.float32)   # light everywhere: the support is the whole sensor
    t, P, info = support_padding(wide, "cl")
    assert t is wide and info["light_dropped"] == 0 and info["support_px"] == list(M)


def test_no_wrap_around_into_the_sensor(rt):
    """The device forward model on the support grid equals the float64 linear convolution (2M - 1 grid)
    on the sensor, for an object filling everything that can reach the sensor."""
    psf = _compact_psf(1)
    t, P, info = support_padding(psf, "cl")
    full = (64, 80)
    rng = np.random.default_rng(2)
    x_full = rng.random((3,) + full)
    # the object region that reaches the sensor through the support: the P grid centred like the sensor
    oy, ox = crop_offsets(M, full)
    py, px = crop_offsets(M, P)
    x_p = x_full[:, oy - py:oy - py + P[0], ox - px:ox - px + P[1]]
    x_in = np.zeros_like(x_full)
    x_in[:, oy - py:oy - py + P[0], ox - px:ox - px + P[1]] = x_p
    want = ref.forward(t, x_in, full)
    got = ForwardModel(t, dtype=np.float64 if rt.caps.fp64 else np.float32, padded_shape=P).forward(x_p)
    tol = 1e-12 if rt.caps.fp64 else 1e-5
    assert np.linalg.norm(got - want) <= tol * np.linalg.norm(want)


def test_support_padding_reconstructs_like_full_padding(rt):
    psf = _compact_psf(3)
    x = np.zeros((3, 64, 80))
    for z, r, c, a in ((0, 24, 30, 1.0), (1, 40, 50, 0.7), (2, 30, 44, 0.4)):   # unequal: one brightest voxel
        x[z, r, c] = a
    y = ref.forward(psf, x, (64, 80))
    a = cm2cl.reconstruct(y, psf, max_iter=150)
    b = cm2cl.reconstruct(y, psf, max_iter=150, padding="support")
    assert b.info["padding"]["voxel_fraction"] < 0.75
    assert b.volume.shape == a.volume.shape
    assert np.linalg.norm(b.volume - a.volume) <= 0.05 * np.linalg.norm(a.volume)
    assert np.unravel_index(b.volume.argmax(), b.volume.shape) == np.unravel_index(a.volume.argmax(), a.volume.shape)


def test_padded_grid_avoids_cache_aliasing_strides_and_partial_row_vectors():
    """choose_padded_shape: large planes get no voxel count with a power of two above 2^13 (a plane of a
    multiple of 64 KiB in float32 maps every plane to the same cache sets) and rows of a multiple of 8;
    grids that already are so stay; reikna keeps its powers of two; small grids keep good_size."""
    from cm2cl.device import fft
    from cm2cl.solver.forward import FAST_GRID_MAX_POW2, choose_padded_shape, fast_grid

    assert choose_padded_shape((324, 432), "cl") == (648, 864)        # the demo
    assert choose_padded_shape((972, 1296), "cl") == (1944, 2592)     # the fig3 scene
    assert choose_padded_shape((256, 256), "cl") == (540, 512)        # not 512 x 512 (2^18 voxels)
    assert choose_padded_shape((256, 256), "reikna") == (512, 512)
    assert choose_padded_shape((32, 40), "cl") == (64, 80)            # small: plain good sizes
    for need in [(511, 511), (1023, 1279), (2047, 2047), (777, 1001), (1943, 2591), (300, 4000)]:
        py, px = fast_grid(need, "cl")
        assert py >= need[0] and px >= need[1]
        assert fft.good_size(py, "cl") == py and fft.good_size(px, "cl") == px
        assert (py * px) & -(py * px) <= FAST_GRID_MAX_POW2 and px % 8 == 0, (need, py, px)
        # the price: a few per cent more voxels than the plain good sizes
        assert py * px <= 1.1 * fft.good_size(need[0], "cl") * fft.good_size(need[1], "cl"), (need, py, px)

"""The device forward model (paper Eq. 3) against the float64 numpy reference."""

import numpy as np
import pytest

from cm2cl import reference as ref
from cm2cl.solver.forward import ForwardModel, centered_psf
from conftest import rtol_for

# (nz, My, Mx): single plane, odd, non-power-of-two, rectangular, more planes than one slab
SHAPES = [(1, 16, 16), (1, 15, 21), (3, 24, 20), (4, 17, 33), (6, 12, 10)]


def _problem(rng, nz, my, mx):
    psf = rng.random((nz, my, mx)) ** 4  # peaky, positive, like a real PSF
    return psf


def _rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


@pytest.mark.parametrize("shape", SHAPES)
def test_forward_and_adjoint_match_reference(rt, backend, dtype, shape):
    rng = np.random.default_rng(hash(shape) % 2**32)
    psf = _problem(rng, *shape)
    m = ForwardModel(psf.astype(dtype), dtype=dtype, backend=backend, max_slab_planes=2)
    assert len(m.bounds) == (shape[0] + 1) // 2  # several slabs when nz > 2
    x = rng.random((shape[0],) + m.padded_shape)
    y = m.forward(x.astype(dtype))
    assert y.shape == shape[1:] and y.dtype == dtype
    assert _rel(y, ref.forward(psf, x, m.padded_shape)) <= rtol_for(dtype)
    v = rng.standard_normal(shape[1:])
    a = m.adjoint(v.astype(dtype))
    assert _rel(a, ref.adjoint(psf, v, m.padded_shape)) <= rtol_for(dtype)
    c = m.convolve(x.astype(dtype))
    assert _rel(c, ref.convolve(psf, x, m.padded_shape)) <= rtol_for(dtype)


@pytest.mark.parametrize("shape", [(1, 20, 28), (5, 19, 23)])
def test_adjoint_dot_test(rt, backend, dtype, shape):
    """<C H x, v> = <x, H^T C^T v> to the rounding of the real type."""
    rng = np.random.default_rng(7)
    psf = _problem(rng, *shape).astype(dtype)
    m = ForwardModel(psf, dtype=dtype, backend=backend, max_slab_planes=3)
    x = rng.standard_normal((shape[0],) + m.padded_shape).astype(dtype)
    v = rng.standard_normal(shape[1:]).astype(dtype)
    lhs = np.vdot(m.forward(x).astype(np.float64), v)
    rhs = np.vdot(x.astype(np.float64), m.adjoint(v).astype(np.float64))
    scale = np.linalg.norm(m.forward(x)) * np.linalg.norm(v)
    assert abs(lhs - rhs) <= 10 * rtol_for(dtype) * scale


def test_linearity(rt, backend):
    rng = np.random.default_rng(3)
    psf = _problem(rng, 3, 18, 22).astype(np.float32)
    m = ForwardModel(psf, backend=backend)
    x1, x2 = (rng.random((3,) + m.padded_shape).astype(np.float32) for _ in range(2))
    a, b = np.float32(2.5), np.float32(-0.75)
    lhs = m.forward(a * x1 + b * x2)
    rhs = a * m.forward(x1) + b * m.forward(x2)
    assert _rel(lhs, rhs) <= 1e-5


def test_lateral_shift_equivariance(rt, backend):
    """Shifting the object shifts the image by the same pixels, away from the boundary."""
    rng = np.random.default_rng(4)
    nz, my, mx = 2, 24, 30
    psf = _problem(rng, nz, my, mx).astype(np.float32)
    m = ForwardModel(psf, backend=backend)
    x = np.zeros((nz,) + m.padded_shape, np.float32)
    x[:, 10:-10, 12:-12] = rng.random((nz, m.padded_shape[0] - 20, m.padded_shape[1] - 24))
    sy, sx = 3, 5
    y1 = m.forward(x)
    y2 = m.forward(np.roll(x, (sy, sx), axis=(1, 2)))
    assert _rel(y2[sy:, sx:], y1[:-sy, :-sx]) <= 1e-5


def test_point_source_images_the_psf(rt, backend):
    """A unit emitter on the optical axis of plane i gives exactly the PSF of plane i (Eq. 3)."""
    rng = np.random.default_rng(5)
    psf = _problem(rng, 3, 16, 20)
    m = ForwardModel(psf.astype(np.float32), backend=backend)
    x = np.zeros((3,) + m.padded_shape, np.float32)
    oy, ox = m.offsets
    x[1, oy + 8, ox + 10] = 1.0
    assert _rel(m.forward(x), psf[1]) <= 1e-5


def test_centered_psf_puts_the_axis_at_the_origin():
    psf = np.zeros((1, 5, 6))
    psf[0, 2, 3] = 1
    assert centered_psf(psf, (9, 11))[0, 0, 0] == 1


# ---- bad input -------------------------------------------------------------------------
def test_bad_inputs_are_clear_errors(rt):
    good = np.ones((2, 8, 8), np.float32)
    with pytest.raises(ValueError, match=r"psf: dtype uint16 is not floating point"):
        ForwardModel(good.astype(np.uint16))
    bad = good.copy()
    bad[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match=r"psf: contains 1 NaN/Inf values \(first at index \(1, 2, 3\)\)"):
        ForwardModel(bad)
    bad = good.copy()
    bad[0] = 0
    with pytest.raises(ValueError, match=r"psf: depth plane\(s\) \[0\] are all zero"):
        ForwardModel(bad)
    with pytest.raises(ValueError, match=r"padded_shape: \(10, 16\) is smaller than sensor \+ PSF support - 1"):
        ForwardModel(good, padded_shape=(10, 16))
    m = ForwardModel(good)
    with pytest.raises(ValueError, match=r"x: shape \(2, 8, 8\) does not fit the model"):
        m.forward(good)
    with pytest.raises(ValueError, match=r"y: shape \(9, 8\) does not match the PSF's sensor grid \(8, 8\)"):
        m.adjoint(np.ones((9, 8), np.float32))
    yy = np.ones((8, 8), np.float32)
    yy[2, 5] = np.inf
    with pytest.raises(ValueError, match=r"y: contains 1 NaN/Inf values \(first at index \(2, 5\)\)"):
        m.adjoint(yy)
    with pytest.raises(ValueError, match=r"psf: expected 2D or 3D array"):
        ForwardModel(np.ones(8, np.float32))

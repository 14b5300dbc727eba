"""A warm start (``x0``) consistent with the data term: v starts at H x0 and the data dual xi at the data
term's gradient there (the background, where modelled, fitted to y - C H x0 first); the regularisers' duals
start at 0. Checked against an independent numpy forward model, against the float64 twin, and by what it is
for: a start at the answer stays near it, where the former start (v at its x = 0 minimiser, xi = 0) came
back at 8.6x the converged objective on the suite's bead scene."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

import cm2cl
from cm2cl import reference as ref
from cm2cl.reference.forward import embed
from cm2cl.reference.terms import LeastSquaresBackground
from cm2cl.solver.admm import ADMMSolver
from cm2cl.solver.control import ADAPT_FROM
from cm2cl.solver.params import ADMMParams

from test_admm import bead_problem

P = (64, 80)


def full_convolution(psf, x_sensor, P):
    """sum_z h_z * x_z on the padded grid P with the package's conventions written out (docs/design.md):
    the volume's sensor window at ((P - M) // 2), PSF tap (r, c) at offset (r - My // 2, c - Mx // 2)."""
    nz, My, Mx = psf.shape
    oy, ox = (P[0] - My) // 2, (P[1] - Mx) // 2
    out = np.zeros(P)
    taps = np.argwhere(np.abs(psf).sum(axis=0) > 0)
    for z in range(nz):
        xz = np.zeros(P)
        xz[oy:oy + My, ox:ox + Mx] = x_sensor[z]
        for r, c in taps:
            out += psf[z, r, c] * np.roll(xz, (r - My // 2, c - Mx // 2), axis=(0, 1))
    return out


def started(psf, y, x0, weights=None, **kw):
    """A float64 solver at its start from x0: (solver, y_scale)."""
    s = ADMMSolver(psf, ADMMParams(**{"max_iter": 1, **kw}), dtype=np.float64, backend="cl", padded_shape=P,
                   max_slab_planes=2)
    y_scale = s._measurement(y, weights)
    s._start(x0, y_scale, None, 1)
    return s, y_scale


def test_warm_start_puts_v_at_h_x0_and_xi_at_the_data_gradient(rt64):
    psf, _, y = bead_problem(3)
    rng = np.random.default_rng(11)
    x0 = rng.random((psf.shape[0],) + psf.shape[1:]) * (rng.random((psf.shape[0],) + psf.shape[1:]) < 0.05)
    wts = np.ones(y.shape)
    wts[rng.random(y.shape) < 0.1] = 0.0          # masked pixels: no data gradient there
    wts[5, :] = 0.5
    s, y_scale = started(psf, y, x0, weights=wts, background="none")
    hx = y_scale * full_convolution(psf, x0, P)    # the normalisation cancels in H x: psf_n x_n = y_scale H x
    v, xi = s.get_plane("v")[0], s.get_plane("xi")[0]
    np.testing.assert_allclose(v, hx, rtol=0, atol=1e-12 * np.abs(hx).max())
    expect = np.zeros(P)
    expect[s.crop] = wts * (hx[s.crop] - y * y_scale)
    np.testing.assert_allclose(xi, expect, rtol=0, atol=1e-12 * np.abs(expect).max())
    assert np.count_nonzero(expect) > 0.5 * y.size
    # x itself is left at x0 by the start (the x step that gives H x0 writes its copy of x0 to scratch)
    np.testing.assert_allclose(s.get_volume("x")[:, s.crop[0], s.crop[1]], x0 * y_scale / s.psf_scale, rtol=1e-12)


def test_warm_background_is_the_weighted_nonnegative_fit_to_the_rest(rt64):
    """With the background in the model, b starts at argmin_{c >= 0} ||W^(1/2) (B c - (y - C H x0))||, which is
    the twin's (scipy NNLS on the whole design matrix), and xi = W (C H x0 + b - y)."""
    psf, x_true, y = bead_problem(4)
    oy, ox = (P[0] - y.shape[0]) // 2, (P[1] - y.shape[1]) // 2
    x0 = 0.8 * x_true[:, oy:oy + y.shape[0], ox:ox + y.shape[1]]
    haze = 0.2 * y.max() * np.outer(np.hanning(y.shape[0]), np.hanning(y.shape[1]))
    y = y + haze
    s, y_scale = started(psf, y, x0, background="model", background_scale_px=10)
    b = s.terms.data.background(s)
    assert b.min() >= 0 and b.mean() > 0.1 * (haze.mean() * y_scale)
    hx = y_scale * full_convolution(psf, x0, P)
    ys = y * y_scale
    twin = LeastSquaresBackground(embed(ys, P), embed(np.ones(y.shape), P), ys, np.ones(y.shape), y.shape,
                                  np.float64, 10.0)
    twin.warm(hx)
    np.testing.assert_allclose(b, twin.b, rtol=0, atol=1e-7 * np.abs(twin.b).max())
    np.testing.assert_allclose(s.get_plane("xi")[0], twin.xi, rtol=0, atol=1e-9 * np.abs(twin.xi).max())
    hx = s.get_plane("v")[0]
    expect = np.zeros(P)
    expect[s.crop] = hx[s.crop] + b - y * y_scale
    np.testing.assert_allclose(s.get_plane("xi")[0], expect, rtol=0, atol=1e-9 * np.abs(expect).max())


@pytest.mark.parametrize("kw", [dict(background="none", tv=1e-3), dict(background="model", tv=0.0),
                                dict(background="model", l1_reweight=1, tv=1e-3)])
def test_warm_started_iterates_equal_the_twins(rt, dtype, kw):
    """The device's warm-started solve equals the float64 twin's from the same x0: the objective of every
    iteration and the volume (the default fused set, and the generic set of reweighted l1)."""
    psf, x_true, y = bead_problem(6)
    y = y + 0.05 * y.max()                       # a flat background for the modelled one to take
    x0 = gaussian_filter(x_true, 1.0) * 3.0      # a blurred start: not the answer
    prm = dict(l1=2e-3, max_iter=25, tol=0, **kw)
    r0 = ref.admm(y, psf, padded_shape=P, x0=x0, **prm)
    s = ADMMSolver(psf.astype(dtype), ADMMParams(**prm), dtype=dtype, backend="cl", padded_shape=P, max_slab_planes=3)
    r1 = s.solve(y.astype(dtype), x0=x0)
    tol = 1e-9 if dtype == np.float64 else 2e-4
    np.testing.assert_allclose(r1.log_array("objective"), r0.log_array("objective"), rtol=tol)
    v0 = r0.volume_padded
    assert np.linalg.norm(r1.volume_padded - v0) <= tol * 10 * np.linalg.norm(v0)


def test_a_start_at_the_answer_stays_near_it(rt):
    """From its own converged answer a solve's first iterate is within 4x of the converged objective where a
    cold start begins at 7x (the regularisers' duals start at 0, so the first w step shrinks x once, by
    l1 / mu_w: at the default mu_v 0.2 5x more than at 1, where it came back at 1.41x; the former start at
    5.3x), and the stopping rule stops in under 0.65 of the cold solve's iterations (the former start: 1.06x)."""
    psf, x_true, y = bead_problem(7, emitters=((0, 10, 12), (1, 20, 30), (2, 5, 25), (3, 25, 8), (1, 12, 20)))
    y = np.random.default_rng(7).poisson(np.maximum(200 * y / y.max(), 0) + 2.0).astype(np.float64)
    cold = cm2cl.reconstruct(y, psf, padded_shape=P, psf_refine=0)
    long = cm2cl.reconstruct(y, psf, padded_shape=P, max_iter=3000, tol=0.0, psf_refine=0)
    best = float(long.history["objective"][-1])
    warm = cm2cl.reconstruct(y, psf, padded_shape=P, x0=long.volume, psf_refine=0)
    first = float(warm.history["objective"][0]) / best
    assert first < 4.0, first                                      # measured 3.65 (1.41 at mu_v 1)
    assert float(cold.history["objective"][0]) / best > 2.0       # what a start without the answer begins at
    assert warm.iterations < 0.65 * cold.iterations, (warm.iterations, cold.iterations)  # 187 / 320 (mu_v 1: 150 / 327)
    assert float(warm.history["objective"][-1]) <= 1.01 * best
    # a cold start waits out its transient before rebalancing; a start at x0 rebalances from the first iteration
    # (from iteration 10 this warm solve took 291 iterations)
    assert cold.info["adapt_from"] == ADAPT_FROM == 10 and warm.info["adapt_from"] == 1

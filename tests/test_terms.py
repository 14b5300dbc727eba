"""The objective as terms (cm2cl.solver.terms): the default terms run term by term (the generic set, each
with its own state and kernels) give the fused default set's iterates; the generic set against the float64
twin; the typed kernel launcher; the memory model counts from the terms."""

import numpy as np

import cm2cl
import pytest

from cm2cl import reference as ref
from cm2cl.solver.admm import ADMMSolver
from cm2cl.solver.launch import Kernels, signatures
from cm2cl.solver.memory import memory_estimate
from cm2cl.solver.params import ADMMParams
from cm2cl.solver.terms import default_terms
from test_admm import bead_problem


def _noisy(seed, nz=5):
    emitters = tuple(e for e in ((0, 10, 12), (1, 20, 30), (2, 5, 25), (4, 25, 8)) if e[0] < nz)
    psf, _, y = bead_problem(seed, nz=nz, emitters=emitters)
    return psf, y + 0.01 * np.random.default_rng(seed).standard_normal(y.shape)


@pytest.mark.parametrize("layout", [{}, {"max_slab_planes": 2}, {"stream": True, "max_slab_planes": 2}])
@pytest.mark.parametrize("params", [{"background": "none"}, {"penalty": "balance", "background": "none"},
                                    {"tv": 0.0, "background": "none"}, {"background": "model"},
                                    {"tv_isotropic": False, "l1_plane_power": 2.0, "tv_axial_weight": 0.5}])
def test_generic_terms_give_the_fused_iterates(rt64, layout, params):
    """Fused (s, p; w, rho, eta derived) and generic (w, rho, u, eta stored, one kernel per term) runs of the
    default objective: 50 float64 iterations agree to float64 rounding in the volume, the objective and the
    residuals, on every layout and with the penalties changing (balance) or TV off."""
    psf, y = _noisy(3)
    out = []
    for fused in (True, False):
        prm = ADMMParams(max_iter=50, tol=0, **{"l1": 2e-3, "tv": 1e-3, **params})
        s = ADMMSolver(psf, prm, dtype=np.float64, backend="cl", terms=default_terms(fused, prm.background), **layout)
        assert s.terms.fused is fused
        out.append(s.solve(y))
    a, b = out
    assert np.linalg.norm(a.volume_padded) > 0.5   # emitters recovered, not a vanishing volume
    assert np.linalg.norm(a.volume_padded - b.volume_padded) / np.linalg.norm(a.volume_padded) < 1e-12
    for key in ("objective", "primal", "dual", "rel_change", "mu_w", "mu_u"):
        np.testing.assert_allclose(b.history[key], a.history[key], rtol=1e-9, err_msg=key)
    # the two really are different code: the generic run keeps w and rho as volumes of their own
    assert {"w", "rho", "u", "eta"} <= set(s.terms.volumes) and "s" not in s.terms.volumes


@pytest.mark.parametrize("background", ["none", "model"])
def test_generic_terms_match_the_float64_twin(rt, dtype, background):
    """The generic set on the device against the twin's terms (cm2cl.reference.terms); the background's
    coefficients come from the normal equations on the device side (condition ~1e6 at this size: ~1e-10
    relative per fit) and from the whole design matrix in the twin, so float64 agrees to 1e-8 there."""
    psf, y = _noisy(5)
    kw = dict(l1=2e-3, tv=1e-3, max_iter=30, tol=0, l1_plane_power=2.0, background=background)
    r0 = ref.admm(y, psf, padded_shape=(64, 80), **kw)
    s = ADMMSolver(psf.astype(dtype), ADMMParams(**kw), dtype=dtype, backend="cl", padded_shape=(64, 80),
                   max_slab_planes=2, terms=default_terms(False, background))
    r1 = s.solve(y.astype(dtype))
    tol64 = 1e-10 if background == "none" else 1e-8
    err = np.linalg.norm(r1.volume_padded - r0.volume_padded) / np.linalg.norm(r0.volume_padded)
    assert err < (tol64 if dtype == np.float64 else 2e-5), err
    np.testing.assert_allclose(r1.history["objective"], r0.history["objective"],
                               rtol=tol64 if dtype == np.float64 else 1e-5)
    # its stored state is the twin's
    state = {}
    ref.admm(y, psf, padded_shape=(64, 80), state=state, **kw)
    for name in ("w", "rho", "u", "eta"):
        np.testing.assert_allclose(s.get_volume(name), state[name], atol=(tol64 if dtype == np.float64 else 2e-5)
                                   * np.abs(state[name]).max(), err_msg=name)


def test_lean_is_refused_for_generic_terms(rt):
    from cm2cl.errors import InputError

    psf, _ = _noisy(1, nz=2)
    with pytest.raises(InputError, match="lean"):
        ADMMSolver(psf, ADMMParams(), backend="cl", lean=True, terms=default_terms(False))


def test_memory_counts_from_the_terms(rt):
    """The planner's per-plane bytes follow the term set's volumes: the generic default set keeps
    x, g, w, rho, u, eta, z, px, py, pz (10 real volumes), the fused one 7; the allocation matches."""
    psf, _ = _noisy(2, nz=3)
    for fused, nvol in ((True, 7), (False, 10)):
        s = ADMMSolver(psf, ADMMParams(), dtype=np.float32, backend="cl", padded_shape=(64, 80),
                       terms=default_terms(fused, "model"))
        assert len(s.terms.volumes) == nvol and s.terms.planes == ("ytb",)
        est = memory_estimate(3, (64, 80), np.float32, "cl", real_volumes=nvol, nslots=len(s.slots), planes=1)
        assert s.memory["per_plane"] == est["per_plane"]
        vols = sum(v.nbytes for v in s.parts[0].vol.values())
        assert vols == 3 * est["volumes_per_plane"]
        assert s.parts[0].device_bytes - vols <= est["fixed"]


def test_kernel_signatures_come_from_the_source():
    text = """__kernel void k(__global real_t *a, __global const real_t *b, const real_t s, const int n,
                              const ulong m, __local real_t *scratch) {}"""
    assert signatures(text) == {"k": (("a", "buf"), ("b", "buf"), ("s", "real"), ("n", "int"), ("m", "ulong"),
                                      ("scratch", "local"))}


def test_kernel_arguments_are_named_and_typed(rt):
    ks = Kernels(rt, np.float32, (("xstep.cl", "rhs_plane"),))
    r, v, xi = (rt.zeros(6, np.float32) for _ in range(3))
    v.set(np.arange(6, dtype=np.float32))
    xi.fill(1.0)
    ks("rhs_plane", (6,), r=r, v=v, xi=xi, mu_v=2, n=6)
    np.testing.assert_array_equal(r.get(), 2 * np.arange(6) - 1)
    with pytest.raises(TypeError, match="missing \\['n'\\]"):
        ks("rhs_plane", (6,), r=r, v=v, xi=xi, mu_v=2)
    with pytest.raises(TypeError, match="unknown \\['mu'\\]"):
        ks("rhs_plane", (6,), r=r, v=v, xi=xi, mu_v=2, n=6, mu=1)


def test_background_basis_is_a_non_negative_partition_of_unity():
    from cm2cl.reference.terms import background_basis
    from cm2cl.solver.terms.background import knot_spacing, spline_basis

    for n, h in ((37, 9.25), (100, 30.0), (9, 8.0), (256, 64.0)):
        B = spline_basis(n, h)
        assert B.min() >= 0 and np.allclose(B.sum(axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(B, background_basis(n, h), atol=1e-14)   # the twin's closed form
        assert (n - 1) / (B.shape[1] - 3) <= h + 1e-9     # knots at most h apart
    assert knot_spacing((200, 160), (100, 100)) == 50.0 and knot_spacing((10, 10), (100, 100)) == 8.0
    assert knot_spacing((10, 10), (100, 100), given=3.0) == 3.0


def test_background_fit_is_the_exact_non_negative_least_squares_solution():
    """The fit of b = By C Bx^T >= 0 to a plane (normal equations, separable) against scipy's NNLS on the
    whole weighted design matrix, with weights that vary and some masked pixels."""
    from scipy.optimize import nnls

    from cm2cl.solver.terms.background import Background

    rng = np.random.default_rng(4)
    bg = Background((30, 44), 12.0)
    q = rng.uniform(0.2, 1.0, (30, 44))
    q[3:9, 5:20] = 0.0
    r = rng.standard_normal((30, 44)) + 0.5
    b = bg.fit(r, q, key=1)
    B = np.kron(bg.By, bg.Bx)
    c, _ = nnls(np.sqrt(q).ravel()[:, None] * B, (np.sqrt(q) * r).ravel())
    np.testing.assert_allclose(bg.c.ravel(), c, atol=1e-8)
    np.testing.assert_allclose(b, (B @ c).reshape(r.shape), atol=1e-8)
    assert np.any(bg.c == 0) and b.min() >= -1e-12   # the constraint is active somewhere and b >= 0


def test_background_in_the_model_recovers_beads_under_haze(rt):
    """Beads under a smooth haze of 30% of the bead image's peak: with the background in the model the
    haze goes to b (b within 5% of the haze over the sensor) and the volume holds the beads' light; without
    it the haze is reconstructed as volume."""
    psf, _, y = bead_problem(6)
    yy, xx = np.mgrid[:32, :40]
    haze = 0.3 * y.max() * np.exp(-((yy - 12) ** 2 + (xx - 25) ** 2) / (2 * 15.0 ** 2))
    kw = dict(l1=1e-3, tv=1e-3, max_iter=400, padded_shape=(64, 80))
    clean = cm2cl.reconstruct(y, psf, background="none", **kw)
    rec = cm2cl.reconstruct(y + haze, psf, **kw)
    plain = cm2cl.reconstruct(y + haze, psf, background="none", **kw)
    assert np.abs(rec.background - haze).max() < 0.05 * haze.max()
    assert abs(rec.volume.sum() / clean.volume.sum() - 1) < 0.1
    assert plain.volume.sum() > 3 * clean.volume.sum()
    assert rec.info["background"]["model"] != "none" and plain.info["background"] == {"model": "none"}


def test_reweighted_l1_matches_the_twin_and_reweights_after_convergence(rt64):
    """l1_reweight: each time the solve converges the voxels' l1 weights become eps / (x + eps) and it goes
    on; the device (generic set, l1_update with per-voxel weights) and the float64 twin take the same rounds at the
    same iterations and agree to rounding; the rounds change the answer."""
    psf, y = _noisy(7)
    kw = dict(l1=3e-3, tv=0.0, max_iter=600, l1_reweight=2, l1_reweight_eps=0.2, background="none")
    r0 = ref.admm(y, psf, padded_shape=(64, 80), **kw)
    r1 = cm2cl.reconstruct(y, psf, dtype=np.float64, padded_shape=(64, 80), **kw, psf_refine=0)
    plain = cm2cl.reconstruct(y, psf, dtype=np.float64, padded_shape=(64, 80), **{**kw, "l1_reweight": 0}, psf_refine=0)
    assert r1.iterations == r0.iterations and r1.info["converged"]
    assert r1.iterations > plain.iterations + 20        # two more rounds ran after the first convergence
    err = np.linalg.norm(r1.volume_padded - r0.volume_padded) / np.linalg.norm(r0.volume_padded)
    assert err < 1e-9, err
    assert np.linalg.norm(r1.volume - plain.volume) > 0.01 * np.linalg.norm(plain.volume)


def test_background_twin_stops_where_the_device_does(rt64):
    """Under haze with the background in the model and the default stopping rule, the float64 twin and the
    device stop at the same iteration, and both held on until b's relative change (logged as
    rel_change_b) fell below tol_change as well as the volume's."""
    psf, _, y = bead_problem(6)
    yy, xx = np.mgrid[:32, :40]
    y = y + 0.3 * y.max() * np.exp(-((yy - 12) ** 2 + (xx - 25) ** 2) / (2 * 15.0 ** 2))
    kw = dict(l1=1e-3, tv=1e-3, max_iter=2000, padded_shape=(64, 80))
    r0 = ref.admm(y, psf, **kw)
    r1 = cm2cl.reconstruct(y, psf, dtype=np.float64, **kw, psf_refine=0)
    assert r0.info["converged"] and r1.info["converged"] and r1.iterations == r0.iterations
    for r in (r0, r1):
        b = r.log_array("rel_change_b")
        assert b[-1] <= r.params["tol_change"] < b.max()
    np.testing.assert_allclose(r0.log_array("rel_change_b"), r1.log_array("rel_change_b"), rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("tv", [0.0, 1e-3])
def test_over_relaxation_keeps_the_minimiser_and_matches_the_twin(rt64, tv):
    """Over-relaxation (Eckstein & Bertsekas) changes the path, not the fixed point: solves at alpha 1 and
    1.8 reach the same volume and objective (to the distance 2000 iterations leave), after 30 iterations
    their iterates differ (the option is wired through), and the device equals its float64 twin at
    alpha 1.8 on the fused and generic sets, with TV off and on."""
    psf, y = _noisy(7)
    kw = dict(l1=2e-3, tv=tv, background="model", padded_shape=(64, 80))
    short = {a: ADMMSolver(psf, ADMMParams(max_iter=30, tol=0, relaxation=a, **{k: v for k, v in kw.items()
                                                                                if k != "padded_shape"}),
                           dtype=np.float64, backend="cl", padded_shape=(64, 80)).solve(y) for a in (1.0, 1.8)}
    d = np.linalg.norm(short[1.0].volume_padded - short[1.8].volume_padded) / np.linalg.norm(short[1.0].volume_padded)
    assert d > 1e-3
    p18 = {k: v for k, v in kw.items() if k != "padded_shape"}
    r0 = ref.admm(y, psf, padded_shape=(64, 80), max_iter=30, tol=0, relaxation=1.8, **p18)
    for fused in (True, False):
        prm = ADMMParams(max_iter=30, tol=0, relaxation=1.8, **p18)
        r1 = ADMMSolver(psf, prm, dtype=np.float64, backend="cl", padded_shape=(64, 80), max_slab_planes=2,
                        terms=default_terms(fused, "model")).solve(y)
        err = np.linalg.norm(r1.volume_padded - r0.volume_padded) / np.linalg.norm(r0.volume_padded)
        assert err < 1e-8, (fused, err)
    long = {a: ADMMSolver(psf, ADMMParams(max_iter=2000, tol=0, relaxation=a, penalty="fixed", **p18),
                          dtype=np.float64, backend="cl", padded_shape=(64, 80)).solve(y) for a in (1.0, 1.8)}
    o1, o18 = (long[a].history["objective"][-1] for a in (1.0, 1.8))
    assert abs(o18 / o1 - 1) < 1e-4, (o1, o18)
    v1, v18 = (long[a].volume_padded for a in (1.0, 1.8))
    assert np.linalg.norm(v18 - v1) / np.linalg.norm(v1) < 0.02

"""The objective as terms (cm2cl.solver.terms): the default terms run term by term (the generic set, each
with its own state and kernels) give the fused default set's iterates; the generic set against the float64
twin; the typed kernel launcher; the memory model counts from the terms."""

import numpy as np
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
@pytest.mark.parametrize("params", [{}, {"penalty": "balance"}, {"tv": 0.0},
                                    {"tv_isotropic": False, "l1_plane_power": 2.0, "tv_axial_weight": 0.5}])
def test_generic_terms_give_the_fused_iterates(rt, layout, params):
    """Fused (s, p; w, rho, eta derived) and generic (w, rho, u, eta stored, one kernel per term) runs of the
    default objective: 50 float64 iterations agree to float64 rounding in the volume, the objective and the
    residuals, on every layout and with the penalties changing (balance) or TV off."""
    if not rt.caps.fp64:
        pytest.skip("float64 needed to compare the two paths to rounding")
    psf, y = _noisy(3)
    out = []
    for fused in (True, False):
        s = ADMMSolver(psf, ADMMParams(max_iter=50, tol=0, **{"l1": 2e-3, "tv": 1e-3, **params}), dtype=np.float64,
                       backend="cl",
                       terms=default_terms(fused), **layout)
        assert s.terms.fused is fused
        out.append(s.solve(y))
    a, b = out
    assert np.linalg.norm(a.volume_padded) > 0.5   # emitters recovered, not a vanishing volume
    assert np.linalg.norm(a.volume_padded - b.volume_padded) / np.linalg.norm(a.volume_padded) < 1e-12
    for key in ("objective", "primal", "dual", "rel_change", "mu_w", "mu_u"):
        np.testing.assert_allclose(b.history[key], a.history[key], rtol=1e-9, err_msg=key)
    # the two really are different code: the generic run keeps w and rho as volumes of their own
    assert {"w", "rho", "u", "eta"} <= set(s.terms.volumes) and "s" not in s.terms.volumes


def test_generic_terms_match_the_float64_twin(rt, dtype):
    """The generic set on the device against the twin's terms (cm2cl.reference.terms)."""
    psf, y = _noisy(5)
    kw = dict(l1=2e-3, tv=1e-3, max_iter=30, tol=0, l1_plane_power=2.0)
    r0 = ref.admm(y, psf, padded_shape=(64, 80), **kw)
    s = ADMMSolver(psf.astype(dtype), ADMMParams(**kw), dtype=dtype, backend="cl", padded_shape=(64, 80),
                   max_slab_planes=2, terms=default_terms(False))
    r1 = s.solve(y.astype(dtype))
    err = np.linalg.norm(r1.volume_padded - r0.volume_padded) / np.linalg.norm(r0.volume_padded)
    assert err < (1e-10 if dtype == np.float64 else 2e-5), err
    np.testing.assert_allclose(r1.history["objective"], r0.history["objective"],
                               rtol=1e-10 if dtype == np.float64 else 1e-5)
    # its stored state is the twin's
    state = {}
    ref.admm(y, psf, padded_shape=(64, 80), state=state, **kw)
    for name in ("w", "rho", "u", "eta"):
        np.testing.assert_allclose(s.get_volume(name), state[name], atol=(1e-10 if dtype == np.float64 else 2e-5)
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
                       terms=default_terms(fused))
        assert len(s.terms.volumes) == nvol
        est = memory_estimate(3, (64, 80), np.float32, "cl", real_volumes=nvol, nslots=len(s.slots))
        assert s.memory["per_plane"] == est["per_plane"]
        vols = sum(v.nbytes for v in s.parts[0].vol.values())
        assert vols == 3 * est["volumes_per_plane"]


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

"""The lean iteration (cm2cl.solver.admm, module docstring): 7 real volumes per plane (3 without TV), and w, rho, eta
derived from the state (s, p) equal to the float64 twin's explicit ones, across penalty changes and from
a warm start."""

import numpy as np
import pytest

from cm2cl import reference as ref
from cm2cl.device.fft import spectrum_shape
from cm2cl.solver.admm import ADMMSolver
from cm2cl.solver.memory import REAL_VOLUMES, memory_estimate
from cm2cl.solver.params import ADMMParams
from cm2cl.solver.parts import COMPLEX, REAL
from cm2cl.solver.terms import state_counts

from test_admm import bead_problem

P = (64, 80)


def rel(a, b):
    return float(np.linalg.norm(np.asarray(a, np.float64) - b) / max(np.linalg.norm(b), 1e-300))


@pytest.mark.parametrize("warm", [False, True])
def test_derived_state_equals_the_twins_explicit_one(rt, dtype, warm):
    """After 12 iterations whose penalties change (residual balancing at a tight ratio), w and rho derived from
    s with the weight and penalty s was made with, and eta derived from the TV dual, equal the twin's
    explicitly updated ones; with a warm start (w = x0 > 0, rho = 0 at the start) too."""
    psf, x_true, y = bead_problem(5)
    kw = dict(l1=2e-3, tv=1e-3, max_iter=12, tol=0, tv_axial_weight=0.5, l1_plane_power=2.0, penalty="balance",
              balance_ratio=1.2, balance_factor=1.5)   # penalties change at most iterations
    x0 = 0.5 * x_true + 0.01 if warm else None     # every voxel positive: w = x0 needs the (0, 1) split
    twin = {}
    r0 = ref.admm(y, psf, padded_shape=P, state=twin, x0=x0, **kw)
    assert len(np.unique(r0.log_array("mu_w"))) > 1 and len(np.unique(r0.log_array("mu_u"))) > 1   # changed
    s = ADMMSolver(psf.astype(dtype), ADMMParams(**kw), dtype=dtype, backend="cl", padded_shape=P,
                   max_slab_planes=3)
    r1 = s.solve(y.astype(dtype), x0=x0)
    np.testing.assert_allclose(r1.log_array("mu_w"), r0.log_array("mu_w"), rtol=1e-6)
    assert s.l1_split == (pytest.approx(r1.info["l1"]), r1.log[-1]["mu_w"])
    tol = 1e-10 if dtype == np.float64 else 2e-4
    for name in ("x", "u", "px", "py", "pz", "w", "rho", "eta"):
        assert rel(s.get_volume(name), twin[name]) < tol, name
    assert np.linalg.norm(twin["rho"]) > 0 and np.linalg.norm(twin["eta"]) > 0


def test_penalty_change_keeps_w_and_rho(rt):
    """The exact form: one w update at a new penalty mu_w from a state s made at another (mu_s, l1_s)
    gives the twin's w' = max(a + (rho - l1 c)/mu_w, 0) and rho' = rho + mu_w (a - w') with the over-relaxed
    a = alpha x + (1 - alpha) w, from the explicit w, rho that state stands for (read at the new penalty, s
    would stand for other ones)."""
    rng = np.random.default_rng(4)
    psf, _, y = bead_problem(2)
    nz = psf.shape[0]
    prm = ADMMParams(l1=0.05, tv=0.0, max_iter=1, tol=0, penalty="fixed", mu_w=0.3, l1_plane_power=2.0,
                     normalize=False, relaxation=1.7)
    s = ADMMSolver(psf, prm, dtype=np.float64, backend="cl", padded_shape=P, max_slab_planes=2)
    state = rng.standard_normal((nz,) + P)
    s.set_volume("s", state)
    s.l1_split = (0.02, 1.7)                      # made with another weight and penalty
    w, rho = s.get_volume("w"), s.get_volume("rho")
    c = s.l1_plane_weights[:, None, None]
    np.testing.assert_allclose(w, np.maximum(state - 0.02 * c / 1.7, 0), rtol=1e-15)
    np.testing.assert_allclose(rho, np.minimum(1.7 * state, 0.02 * c), rtol=1e-15)
    # the solver's w step on this state at another weight and penalty
    x = rng.random((nz,) + P)
    s.set_volume("x", x)
    s.set_volume("g", x)
    s.w_step(0.05, 0.3)
    assert s.l1_split == (0.05, 0.3)
    a = 1.7 * x - 0.7 * w
    w_new = np.maximum(a + (rho - 0.05 * c) / 0.3, 0)
    rho_new = rho + 0.3 * (a - w_new)
    np.testing.assert_allclose(s.get_volume("w"), w_new, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(s.get_volume("rho"), rho_new, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("tv", [1e-3, 0.0])
def test_solver_keeps_seven_real_volumes_per_plane(rt, dtype, tv):
    """Per depth plane the device holds 7 real volumes (3 without TV: x, g, s) and the 2 complex ones,
    and the memory model's per-plane figure is what the parts allocate (resident), what the host holds
    (streamed)."""
    psf, _, _ = bead_problem(3)
    nz = psf.shape[0]
    assert len(REAL) == REAL_VOLUMES == 7 and COMPLEX == ("spec", "hs")
    real = REAL if tv else ("x", "g", "s")
    s = ADMMSolver(psf.astype(dtype), ADMMParams(tv=tv), dtype=dtype, backend="cl", padded_shape=P, max_slab_planes=3)
    counts = state_counts(s.terms)
    assert counts["real_volumes"] == len(real) and counts["nslots"] == len(s.slots)
    est = memory_estimate(nz, P, dtype, "cl", **counts)
    item = np.dtype(dtype).itemsize
    spec = int(np.prod(spectrum_shape(P, "cl"))) * 2 * item
    assert est["volumes_per_plane"] == len(real) * P[0] * P[1] * item + 2 * spec
    (part,) = s.parts
    assert set(part.vol) == set(real) | set(COMPLEX)
    assert sum(v.nbytes for v in part.vol.values()) == nz * est["volumes_per_plane"]
    assert part.device_bytes - nz * est["volumes_per_plane"] <= est["fixed"]
    st = ADMMSolver(psf.astype(dtype), ADMMParams(tv=tv), dtype=dtype, backend="cl", padded_shape=P, stream=True,
                    max_slab_planes=2)
    assert st.host_bytes == nz * est["volumes_per_plane"]
    assert sum(a.nbytes for a in st.parts[0].slots[0].values()) == 2 * est["volumes_per_plane"]


@pytest.mark.parametrize("tv", [1e-3, 0.0])
def test_lean_layout_keeps_seven_real_volumes_and_the_psf_spectra_per_plane(rt, dtype, tv):
    """The lean layout (cm2cl.solver.parts.LEAN_SCRATCH): per depth plane the device holds the 7 real
    volumes (3 without TV) and the PSF spectra, nothing else; the x spectra are one slab, whatever the
    depth; the memory model's figures are what the part allocates."""
    psf, _, _ = bead_problem(3)
    nz = psf.shape[0]
    item = np.dtype(dtype).itemsize
    spec = int(np.prod(spectrum_shape(P, "cl"))) * 2 * item
    real = REAL if tv else ("x", "g", "s")
    s = ADMMSolver(psf.astype(dtype), ADMMParams(tv=tv), dtype=dtype, backend="cl", padded_shape=P, lean=True,
                   max_slab_planes=1)
    (part,) = s.parts
    assert part.lean and s.lean and set(part.vol) == set(real) | {"hs"} and set(part.scratch) == {"spec"}
    assert sum(v.nbytes for v in part.vol.values()) == nz * (len(real) * P[0] * P[1] * item + spec)
    assert part.scratch["spec"].nbytes == spec        # one slab of one plane
    counts = state_counts(s.terms)
    est = memory_estimate(nz, P, dtype, "cl", lean_slab=1, **counts)
    assert s.memory == est and est["volumes_per_plane"] == len(real) * P[0] * P[1] * item + spec
    assert 0 <= part.device_bytes - nz * est["volumes_per_plane"] <= est["fixed"]
    whole = memory_estimate(nz, P, dtype, "cl", **counts)
    assert whole["total"] - est["total"] == (nz - 1) * spec - P[0] * P[1] * item


def test_lean_parts_launch_the_kernels_without_scratch_once_over_all_planes(rt, monkeypatch):
    """In the lean layout (here 1-plane slabs, one allocation per volume) the w split and TV finish run
    as one launch over all planes per iteration; the TV residual and dual step, which use the one slab of
    scratch, run per slab; the iterates are those of the one-slab solve."""
    psf, _, y = bead_problem(3)
    nz = psf.shape[0]
    prm = ADMMParams(max_iter=4, tol=0, tv_axial_weight=0.5, tv_noise_ratio=30.0)
    whole = ADMMSolver(psf, prm, backend="cl", padded_shape=P).solve(y)
    s = ADMMSolver(psf, prm, backend="cl", padded_shape=P, lean=True, max_slab_planes=1)
    assert len(s.parts[0].bounds) == nz > 1
    calls = {}
    for method in ("reduce_rows", "row_grid"):
        real = getattr(ADMMSolver, method)

        def counted(self, part, name, *args, _real=real, **kw):
            calls[name] = calls.get(name, 0) + 1
            return _real(self, part, name, *args, **kw)
        monkeypatch.setattr(ADMMSolver, method, counted)
    lean = s.solve(y)
    assert calls["update_w"] == calls["tv_finish"] == 4
    assert calls["tv_residual"] == calls["tv_dual_step"] == 4 * prm.tv_iters * nz
    assert rel(lean.volume, whole.volume) < 2e-6


def test_host_holds_no_copy_of_the_psf_stack_and_one_of_the_result(rt):
    """A full frame's PSF stack and volume are gigabytes each (1944 x 2592 x 64): setup scales and uploads
    the PSF a plane at a time and keeps none of those planes (pyopencl keeps each copy's event, which
    holds its host array, until the array is waited for: cm2cl.device.volume.upload), and the result is
    read back into one host array, clipped in place. Host allocations traced by tracemalloc (numpy's are):
    the leak kept 8-12 padded planes after setup, and the read-back made 3 volumes."""
    import tracemalloc

    nz, M, Pg = 48, (48, 64), (96, 128)
    rng = np.random.default_rng(3)
    psf, y = rng.random((nz,) + M).astype(np.float32), rng.random(M).astype(np.float32)
    plane = Pg[0] * Pg[1] * 4
    ADMMSolver(psf, ADMMParams(max_iter=2), padded_shape=Pg).solve(y)   # kernels and plans built first
    tracemalloc.start()
    try:
        s = ADMMSolver(psf, ADMMParams(max_iter=2), padded_shape=Pg)
        held = tracemalloc.get_traced_memory()[0]
        assert held < 3 * plane, held / plane
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        rec = s.solve(y)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    # the volume (nz planes) and the data term's sensor-sized planes (~14 padded planes here, any depth)
    assert rec.volume_padded.nbytes == nz * plane and peak < 1.5 * nz * plane, peak / plane

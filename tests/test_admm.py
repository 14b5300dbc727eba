"""The device ADMM against the float64 reference, and the physics it must get right."""

from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from cm2cl import reference as ref
from cm2cl.solver.admm import ADMMSolver
from cm2cl.solver.api import reconstruct
from cm2cl.errors import DeviceError
from cm2cl.solver.params import ADMMParams
from cm2cl.solver.terms import default_terms

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "diffusercam-2d"


def bead_problem(seed, nz=4, M=(32, 40), P=(64, 80), emitters=((0, 10, 12), (1, 20, 30), (2, 5, 25), (3, 25, 8))):
    """A few-foci PSF per depth (like the CM2 array PSF, with depth-dependent foci), point emitters."""
    rng = np.random.default_rng(seed)
    psf = np.zeros((nz,) + M)
    for i in range(nz):
        for _ in range(5):
            psf[i, rng.integers(4, M[0] - 4), rng.integers(4, M[1] - 4)] += 1
    psf = np.stack([gaussian_filter(p, 0.7) for p in psf])
    x = np.zeros((nz,) + P)
    oy, ox = (P[0] - M[0]) // 2, (P[1] - M[1]) // 2
    for z, r, c in emitters:
        x[z, oy + r, ox + c] = 1.0
    return psf, x, ref.forward(psf, x, P)


def precision(rt):
    """(dtype, tolerance between two device paths, tolerance against the float64 reference): float64 where
    the device has it, else float32 (measured there: the paths agree exactly, the reference to 1e-6)."""
    return (np.float64, 1e-12, 1e-10) if rt.caps.fp64 else (np.float32, 1e-6, 2e-5)


@pytest.mark.parametrize("tv", [True, False])
@pytest.mark.parametrize("slabs", [None, 2])
def test_x_step_solves_its_normal_equations(rt, dtype, backend, slabs, tv):
    """Residual of (mu_v H^T H + c I) x - rhs with spatial-domain (shift-and-add) operators, for the
    default set with TV (its state s, u, p) and without (TV's weight 0: s alone, c = mu_w).

    The PSF is scaled to ||H|| = 1 (as the solver's normalisation does), so the system's condition
    number is <= (c + mu_v) / c = 2.8 and the relative residual is a few float roundings."""
    rng = np.random.default_rng(11)
    nz, M, P = 3, (10, 12), (20, 24)
    psf = rng.random((nz,) + M) ** 3
    psf *= ref.normalisation(psf, np.ones(M), P)[0]
    prm = ADMMParams(normalize=False, tv_axial_weight=0.6, l1_plane_power=2.0, tv=1.0 if tv else 0.0)
    s = ADMMSolver(psf.astype(dtype), prm, dtype=dtype, backend=backend, padded_shape=P, max_slab_planes=slabs)
    assert s.terms.volumes == (("x", "g", "s", "u", "px", "py", "pz") if tv else ("x", "g", "s"))
    # the lean state: s (w and rho derive from it), u, the TV dual p (eta derives from it)
    st = {k: rng.standard_normal((nz,) + P) for k in (("u", "s", "px", "py", "pz") if tv else ("s",))}
    v, xi = rng.standard_normal(P), rng.standard_normal(P)
    for k, a in st.items():
        s.set_volume(k, a)
    s.set_plane("v", v)
    s.set_plane("xi", xi)
    s.l1_split, s.tv_split = (0.3, 0.9), 0.2 if tv else 0.0   # s made with l1 = 0.3 at mu_w = 0.9; eta = 0.2 div p
    mu_v, mu_u, mu_w = 0.7, 1.3 if tv else 0.0, 0.4
    s.x_step(mu_v, mu_u, mu_w)
    x = s.get_volume("g").astype(np.float64)
    lw = s.l1_plane_weights[:, None, None]
    w, rho = np.maximum(st["s"] - 0.3 * lw / 0.9, 0), np.minimum(0.9 * st["s"], 0.3 * lw)
    rhs = ref.correlate_spatial(psf, mu_v * v - xi) + (mu_w * w - rho)
    if tv:
        rhs += mu_u * st["u"] - 0.2 * ref.tv_div(st["px"], st["py"], st["pz"], 0.6)
    Hx = ref.convolve_spatial(psf, x)
    lhs = mu_v * ref.correlate_spatial(psf, Hx) + (mu_u + mu_w) * x
    tol = 2e-6 if dtype == np.float32 else 1e-13
    assert np.linalg.norm(lhs - rhs) / np.linalg.norm(rhs) < tol
    # and H x comes out of the same step
    hx = s.get_plane("hx")[0]
    assert np.linalg.norm(hx - Hx) / np.linalg.norm(Hx) < 10 * tol


@pytest.mark.parametrize("tv_isotropic", [True, False])
def test_device_matches_float64_reference(rt, backend, tv_isotropic):
    """Float32 device vs float64 numpy after 30 iterations with the same splits and control.

    Tolerance 2e-5 relative: each iteration is a contraction of the ADMM map, so float32
    rounding (~1e-7 per operation, a few hundred operations per voxel) does not grow much;
    seen: < 1e-6."""
    psf, _, y = bead_problem(1)
    kw = dict(l1=1e-3, tv=1e-3, max_iter=30, tol=0, tv_isotropic=tv_isotropic, tv_axial_weight=0.5)
    r0 = ref.admm(y, psf, padded_shape=(64, 80), **kw)
    r1 = reconstruct(y.astype(np.float32), psf.astype(np.float32), backend=backend,
                     padded_shape=(64, 80), max_slab_planes=3, **kw, psf_refine=0)
    err = np.linalg.norm(r1.volume_padded - r0.volume_padded) / np.linalg.norm(r0.volume_padded)
    assert err < 2e-5
    # the shared control sees the same norms (to float32 rounding), so it adapts the penalties alike
    for mu in ("mu_v", "mu_u", "mu_w"):
        np.testing.assert_allclose(r1.log_array(mu), r0.log_array(mu), rtol=1e-5)
    np.testing.assert_allclose(r1.log_array("objective"), r0.log_array("objective"), rtol=1e-5)


def test_float64_device_matches_reference_to_rounding(rt64):
    psf, _, y = bead_problem(2)
    kw = dict(l1=2e-3, tv=5e-4, max_iter=25, tol=0)
    r0 = ref.admm(y, psf, padded_shape=(64, 80), **kw)
    r1 = reconstruct(y, psf, dtype=np.float64, padded_shape=(64, 80), max_slab_planes=1, **kw, psf_refine=0)
    err = np.linalg.norm(r1.volume_padded - r0.volume_padded) / np.linalg.norm(r0.volume_padded)
    assert err < 1e-10


def test_beads_converge_and_emitters_are_recovered(rt):
    emitters = ((0, 10, 12), (1, 20, 30), (2, 5, 25), (3, 25, 8), (1, 8, 34))
    psf, x, y = bead_problem(3, emitters=emitters)
    rec = reconstruct(y.astype(np.float32), psf.astype(np.float32), padded_shape=(64, 80),
                      l1=1e-3, tv=1e-4, max_iter=1000, tol=0, psf_refine=0)
    obj = rec.log_array("objective")
    assert obj[-1] < 0.1 * obj[0]    # (the first iterate's objective depends on the initial penalty: 2.07 at 0.2)
    # plateau: the last 100 of 1000 iterations change the objective by < 1 % (seen: 0.13 -> 0.128)
    assert abs(obj[-1] - obj[-101]) < 0.01 * obj[-1]
    vol = rec.volume
    for z, r, c in emitters:
        # the brightest voxel of the emitter's plane near its position is at the emitter
        zz, rr, cc = np.unravel_index(np.argmax(vol[:, r - 3:r + 4, c - 3:c + 4]), (4, 7, 7))
        assert (zz, rr + r - 3, cc + c - 3) == (z, r, c)
    # and most of the energy is in the emitters' voxels
    assert sum(vol[z, r, c] for z, r, c in emitters) > 0.5 * vol.sum()


def test_scale_invariance(rt):
    psf, _, y = bead_problem(4)
    kw = dict(l1=1e-3, tv=1e-3, max_iter=15, tol=0, padded_shape=(64, 80))
    base = reconstruct(y.astype(np.float32), psf.astype(np.float32), **kw)
    for a in (1e-3, 0.37, 1e3):
        r = reconstruct((a * y).astype(np.float32), psf.astype(np.float32), **kw)
        err = np.linalg.norm(r.volume - a * base.volume) / np.linalg.norm(a * base.volume)
        assert err < 1e-5, (a, err)
        assert r.scaling["y_scale"] == pytest.approx(base.scaling["y_scale"] / a, rel=1e-6)


def _diffusercam():
    import tifffile

    from cm2cl.io.prepare import prepare
    psf_raw = tifffile.imread(DATA / "psf_sample.tif")
    meas_raw = tifffile.imread(DATA / "rawdata_hand_sample.tif")
    from cm2cl.io.prepare import estimate_offset
    off = estimate_offset(psf_raw)
    return prepare(psf_raw, offset=off, bin_factor=4), prepare(meas_raw, offset=off, bin_factor=4)


@pytest.mark.skipif(not DATA.exists(), reason="../shared/data/diffusercam-2d not present")
def test_real_diffusercam_data(rt):
    """Real lensless data, nz = 1, 300 x 400 after 4x binning, padded to 600 x 800."""
    psf, y = _diffusercam()
    assert psf.shape == y.shape == (300, 400)
    # rebalanced from the first iteration: these weights start the penalties ~300x too low, so with the default
    # start at iteration 10 they would still be rising (x1.5 every 10th) at 100, and the check below needs them settled
    kw = dict(l1=1e-4, tv=1e-4, max_iter=100, tol=0, adapt_from=1)
    rec = reconstruct(y.astype(np.float32), psf[None].astype(np.float32), backend="auto", **kw, psf_refine=0)
    data = rec.log_array("data")
    y_energy = 0.5 * np.sum((y * rec.scaling["y_scale"]) ** 2)
    # the data residual falls by more than 200x from that of x = 0 (||y||^2/2), and the first iterate
    # already moves towards the data; seen (the default penalties of stop 50): 15.2 at iteration 1, 0.85 after 100
    assert data[0] < 0.5 * y_energy
    assert data[-1] < y_energy / 200
    obj = rec.log_array("objective")
    # no rise once the penalties have settled: x1.5 steps rebalance them until iteration 40 here
    assert np.all(np.diff(obj[50:]) < 1e-3 * obj[50])
    r0 = ref.admm(y, psf, padded_shape=rec.info["padded_shape"], **kw)
    err = np.linalg.norm(rec.volume - r0.volume) / np.linalg.norm(r0.volume)
    assert err < 1e-4


def test_bad_inputs(rt, monkeypatch):
    psf, _, y = bead_problem(5)
    psf32, y32 = psf.astype(np.float32), y.astype(np.float32)
    with pytest.raises(ValueError, match=r"measurement: shape \(32, 41\) does not match the PSF's sensor grid \(32, 40\)"):
        reconstruct(np.zeros((32, 41), np.float32), psf32)
    bad = y32.copy()
    bad[3, 4] = np.nan
    with pytest.raises(ValueError, match=r"measurement: contains 1 NaN/Inf"):
        reconstruct(bad, psf32)
    for name, val in (("l1", -1.0), ("tv", -0.1), ("mu_v", 0.0), ("tv_axial_weight", 0.0)):
        with pytest.raises(ValueError, match=rf"^{name}: must be >=? ?0, got "):
            reconstruct(y32, psf32, **{name: val})
    zero = psf32.copy()
    zero[2] = 0
    with pytest.raises(ValueError, match=r"psf: depth plane\(s\) \[2\] are all zero"):
        reconstruct(y32, zero)
    with pytest.raises(TypeError, match=r"unexpected keyword argument 'lambda1'"):
        reconstruct(y32, psf32, lambda1=1.0)
    import cm2cl.device as device
    fake = device.Capabilities(**{**rt.caps.__dict__, "fp64": False})
    monkeypatch.setattr(rt, "caps", fake)
    with pytest.raises(DeviceError, match="float64 requested but device .* has no fp64 support"):
        reconstruct(y, psf, dtype=np.float64)
    # 640 KiB of device memory: the 4 planes (3 real volumes each without TV) do not fit resident, so
    # they are streamed in slabs; kept resident on request that is refused; 256 KiB do not hold even one
    # streamed plane. Faked as a GPU: a CPU device's memory is the host's (memory.device_budget)
    small = device.Capabilities(**{**rt.caps.__dict__, "global_mem": 640 * 2**10, "kind": "GPU"})
    monkeypatch.setattr(rt, "caps", small)
    with pytest.raises(DeviceError, match=r"problem too large to keep on the device: 4 planes on a 64 x 80 padded grid need [0-9.]+ KiB per device, [0-9.]+ KiB available"):
        reconstruct(y32, psf32, padded_shape=(64, 80), stream=False)
    rec = reconstruct(y32, psf32, padded_shape=(64, 80), max_iter=2)
    assert rec.info["layout"][0]["streamed"] and rec.info["device_bytes"] <= 0.9 * 640 * 2**10
    tiny = device.Capabilities(**{**rt.caps.__dict__, "global_mem": 2**18, "kind": "GPU"})
    monkeypatch.setattr(rt, "caps", tiny)
    with pytest.raises(DeviceError, match=r"problem too large even streamed: one depth plane of a 64 x 80 padded grid needs [\d.]+ KiB on device .*, [\d.]+ KiB available"):
        reconstruct(y32, psf32, padded_shape=(64, 80))


@pytest.mark.parametrize("penalty", ["balance", "adaptive"])
def test_set_without_tv_gives_the_iterates_of_a_tv_weight_of_zero(rt, penalty):
    """A TV weight of 0 (the default) gets the fused set without TV's state (x, g, s: 3 real volumes per
    voxel, the rhs made from s every iteration); its iterates are those of the set with TV's state at a
    weight of 0 (to float rounding: the same sums in another order) and of the float64 reference, its
    reports of the u split those of u = x exactly (a zero primal residual and a zero dual)."""
    dtype, same, tol = precision(rt)
    psf, _, y = bead_problem(4)
    kw = dict(l1=1e-3, tv=0.0, max_iter=25, tol=0, penalty=penalty)
    out = []
    for terms in (None, default_terms(True, ADMMParams().background, tv=True)):
        s = ADMMSolver(psf, ADMMParams(**kw), dtype=dtype, backend="cl", padded_shape=(64, 80), max_slab_planes=3,
                       terms=terms)
        if terms is None:
            assert s.terms.volumes == ("x", "g", "s") and not s.terms.has_tv
            s.parts[0].k["rhs_volume"] = counted = _Counted(s.parts[0].k["rhs_volume"])
        rec = s.solve(y)
        if terms is None:
            assert counted.calls == 2 * 25   # two slabs, every iteration
            assert np.all(np.asarray(rec.history["r_u"]) == 0)
            np.testing.assert_array_equal(s.get_volume("u"), s.get_volume("x"))
            assert not np.any(s.get_volume("eta"))
        out.append(rec.volume_padded)
    # streamed from host memory in slabs of 2 planes and in the lean layout: the same iterates
    for layout in (dict(stream=True, max_slab_planes=2), dict(lean=True, max_slab_planes=1)):
        s = ADMMSolver(psf, ADMMParams(**kw), dtype=dtype, backend="cl", padded_shape=(64, 80), **layout)
        assert not s.terms.has_tv
        other = s.solve(y).volume_padded
        assert np.linalg.norm(other - out[0]) / np.linalg.norm(out[0]) < 10 * same, layout
    r0 = ref.admm(y, psf, padded_shape=(64, 80), **kw)
    assert np.linalg.norm(out[0] - out[1]) / np.linalg.norm(out[1]) < 10 * same
    assert np.linalg.norm(out[0] - r0.volume_padded) / np.linalg.norm(r0.volume_padded) < tol
    with pytest.raises(ValueError, match="terms: a TV weight of 0.001 for a set without TV"):
        ADMMSolver(psf, ADMMParams(**{**kw, "tv": 1e-3}), dtype=dtype, backend="cl", padded_shape=(64, 80),
                   terms=default_terms(True, ADMMParams().background, tv=False)).solve(y)

@pytest.mark.parametrize("P", [(64, 90), (63, 84)])
@pytest.mark.parametrize("dtype,vw,rows", [(np.float32, 1, None), (np.float32, None, 5), (np.float32, None, None),
                                           (np.float64, None, 5), (np.float64, 1, 7)])
def test_row_kernel_layouts_match_the_reference(rt, dtype, vw, rows, P):
    """The row kernels (kernels/common.cl) run VW neighbouring x per work-item (the device's width when
    None: 8 float32 / 4 float64 on CPUs, 1 on GPUs) over `rows` rows, and the spectral ones CW = VW/2
    frequencies. A padded width of 90 leaves a partial vector at every row's end (90 = 11*8 + 2 =
    22*4 + 2), 5 or 7 rows a partial block of rows (64 = 12*5 + 4 = 9*7 + 1, 63 = 12*5 + 3), and
    63 x 84 a partial vector of frequencies (63 * 43 = 2709 = 677*4 + 1 = 1354*2 + 1). Every layout, on
    whatever device this is, against the float64 reference."""
    if dtype == np.float64 and not rt.caps.fp64:
        pytest.skip(f"device '{rt.caps.name}' has no fp64 support")
    psf, _, y = bead_problem(8)
    kw = dict(l1=1e-3, tv=1e-3, max_iter=12, tol=0)
    s = ADMMSolver(psf.astype(dtype), ADMMParams(**kw), dtype=dtype, padded_shape=P, max_slab_planes=3)
    for part in s.parts:
        s._row_layout(part, vw or part.vw, rows)
        assert (part.vw, part.rows) == (vw or (32 // np.dtype(dtype).itemsize if rt.caps.kind == "CPU" else 1),
                                        rows or part.rows)
    r1 = s.solve(y.astype(dtype))
    r0 = ref.admm(y, psf, padded_shape=P, **kw)
    err = np.linalg.norm(r1.volume_padded - r0.volume_padded) / np.linalg.norm(r0.volume_padded)
    if dtype == np.float32:
        np.testing.assert_allclose(r1.log_array("objective"), r0.log_array("objective"), rtol=1e-5)
        np.testing.assert_allclose(r1.log_array("primal"), r0.log_array("primal"), rtol=1e-4)
        assert err < 2e-5
    else:   # every logged norm and the volume to float64 rounding
        for key in ("objective", "tv", "primal", "dual", "rel_change"):
            np.testing.assert_allclose(r1.log_array(key), r0.log_array(key), rtol=1e-10, err_msg=key)
        assert err < 1e-10, err


def test_plane_weighted_l1_matches_the_twin(rt):
    """l1_plane_power: plane i's l1 weight is ||h_i||^q (sum h_i)^(1-q) / mean (the same), in the device kernel
    and in the float64 twin alike (planes blurred by different amounts, so their norms differ by ~4x, and
    dimmed unequally, so their light differs by 3x)."""
    dtype, _, tol = precision(rt)
    psf, _, y = bead_problem(3)
    light = np.array([1.0, 0.6, 0.8, 0.33])
    psf = np.stack([gaussian_filter(p, s) * a for p, s, a in zip(psf, (0.5, 1.0, 1.5, 2.5), light)])
    kw = dict(l1=2e-3, tv=5e-4, max_iter=25, tol=0, l1_plane_power=2.0, background="none")
    r0 = ref.admm(y, psf, padded_shape=(64, 80), **kw)
    r1 = reconstruct(y, psf, dtype=dtype, padded_shape=(64, 80), max_slab_planes=3, **kw, psf_refine=0)
    err = np.linalg.norm(r1.volume_padded - r0.volume_padded) / np.linalg.norm(r0.volume_padded)
    assert err < tol, err
    n2 = np.sum(psf.reshape(4, -1) ** 2, axis=1) / psf.reshape(4, -1).sum(axis=1)   # q = 2: ||h||^2 / sum h
    np.testing.assert_allclose(r1.info["l1_plane_weights"], n2 / n2.mean(), rtol=1e-9)
    # the weights matter: the unweighted solve differs
    r2 = reconstruct(y, psf, dtype=dtype, padded_shape=(64, 80), **{**kw, "l1_plane_power": 0.0}, psf_refine=0)
    assert np.linalg.norm(r2.volume_padded - r1.volume_padded) > 1e-3 * np.linalg.norm(r1.volume_padded)


class _Counted:
    """A kernel that counts its launches."""

    def __init__(self, k):
        self.k, self.calls = k, 0

    def __call__(self, *args, **kw):
        self.calls += 1
        return self.k(*args, **kw)

    def __getattr__(self, name):
        return getattr(self.k, name)


@pytest.mark.parametrize("tv,penalty", [(1e-3, "adaptive"), (1e-3, "balance"), (0.0, "balance")])
def test_rhs_made_by_tv_finish_gives_the_same_iterates(rt, tv, penalty):
    """tv_finish makes the next x step's rhs for the penalties of its iteration; the x step uses it where
    mu_u and mu_w still hold and runs rhs_volume only on the first iteration and after they changed.
    Solves with and without that agree to float64 rounding (slabs: halos of pz), and with the reference;
    "balance" changes the penalties on most iterations here, "adaptive" on none. The set with TV's state
    throughout (at a weight of 0 too: its tau = 0 branch)."""
    dtype, same, tol = precision(rt)
    psf, _, y = bead_problem(4)
    # plain ADMM: over-relaxed, "balance" changes a penalty on every one of these 25 iterations
    # (mu_v 1: from the default 0.2 "balance" changes a penalty on all 25, and the reuse is never exercised)
    kw = dict(l1=1e-3, tv=tv, max_iter=25, tol=0, penalty=penalty, relaxation=1.0, mu_v=1.0)
    out, calls = [], []
    for early in (True, False):
        s = ADMMSolver(psf, ADMMParams(**kw), dtype=dtype, backend="cl", padded_shape=(64, 80), max_slab_planes=3,
                       terms=default_terms(True, ADMMParams().background, tv=True))
        s.rhs_in_tv_finish = early
        s.parts[0].k["rhs_volume"] = counted = _Counted(s.parts[0].k["rhs_volume"])
        rec = s.solve(y)
        out.append(rec.volume_padded)
        calls.append(counted.calls)
    mus = list(zip(rec.history["mu_u"], rec.history["mu_w"]))
    changed = sum(a != b for a, b in zip(mus[:-1], mus[1:]))
    assert changed < 24 and (changed > 0) == (penalty == "balance")
    assert calls == [2 * (1 + changed), 2 * 25]   # two slabs
    r0 = ref.admm(y, psf, padded_shape=(64, 80), **kw)
    assert np.linalg.norm(out[0] - out[1]) / np.linalg.norm(out[1]) < same
    assert np.linalg.norm(out[0] - r0.volume_padded) / np.linalg.norm(r0.volume_padded) < tol


def test_fused_x_step_inverse_gives_the_same_iterates(rt):
    """With cm2cl's FFT the x step's last stage (xstep_solve) runs inside the inverse FFT's column pass;
    solves with and without that fusion agree to float64 rounding, and with the float64 reference."""
    dtype, same, tol = precision(rt)
    psf, _, y = bead_problem(9)
    kw = dict(l1=1e-3, tv=1e-3, max_iter=15, tol=0)
    out = []
    for fuse in (True, False):
        s = ADMMSolver(psf, ADMMParams(**kw), dtype=dtype, backend="cl", padded_shape=(64, 80), max_slab_planes=3)
        assert s.parts[0].plan(3, "cl").fuses_xstep
        s.fuse_xstep = fuse
        out.append(s.solve(y).volume_padded)
    r0 = ref.admm(y, psf, padded_shape=(64, 80), **kw)
    assert np.linalg.norm(out[0] - out[1]) / np.linalg.norm(out[1]) < same
    assert np.linalg.norm(out[0] - r0.volume_padded) / np.linalg.norm(r0.volume_padded) < tol


def test_accumulate_in_runs_of_planes_gives_the_same_iterates(rt, dtype):
    """xstep_accumulate in runs of planes (ACC_PLANES on CPUs; here 1, 3 and 7 planes over slabs of 7 and
    4 + 3 planes) continues the Kahan sum from what the previous run stored: the same additions, so the
    same volume bit for bit as one launch per slab, and the launches are counted (a run that dropped or
    repeated a plane would change the sum)."""
    psf, _, y = bead_problem(5, nz=7, emitters=((0, 10, 12), (3, 20, 30), (6, 5, 25)))
    kw = dict(l1=1e-3, tv=1e-3, max_iter=6, tol=0)
    out = {}
    for slab in (None, 4):
        for run in (None, 1, 3, 7):
            s = ADMMSolver(psf, ADMMParams(**kw), dtype=dtype, backend="cl", padded_shape=(64, 80),
                           max_slab_planes=slab)
            part = s.parts[0]
            part.acc_planes = run
            part.k["xstep_accumulate"] = counted = _Counted(part.k["xstep_accumulate"])
            out[slab, run] = s.solve(y).volume_padded
            slabs = [b - a for a, b in part.bounds]
            assert counted.calls == 6 * sum(-(-n // (run or n)) for n in slabs)
    r0 = ref.admm(y, psf, padded_shape=(64, 80), **kw).volume_padded
    tol = 1e-10 if dtype == np.float64 else 2e-5
    for key, v in out.items():
        assert np.array_equal(v, out[key[0], None]), key
        assert np.linalg.norm(v - r0) / np.linalg.norm(r0) < tol
    # sabotage check of the comparison itself: a run that skips the last plane of each launch differs
    s = ADMMSolver(psf, ADMMParams(**kw), dtype=dtype, backend="cl", padded_shape=(64, 80))

    class Short(_Counted):   # p1 - 1: drops the last plane of each run of 2 or more
        def __call__(self, queue, gs, ls, *args):
            args = list(args)
            args[6] = np.int32(max(int(args[5]) + 1, int(args[6]) - 1))
            return self.k(queue, gs, ls, *args)

    s.parts[0].acc_planes = 3
    s.parts[0].k["xstep_accumulate"] = Short(s.parts[0].k["xstep_accumulate"])
    assert not np.array_equal(s.solve(y).volume_padded, out[None, None])

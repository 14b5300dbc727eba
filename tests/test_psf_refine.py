"""PSF self-calibration (cm2cl.solver.psf_refine, reconstruct(psf_refine=...)): the kernel fit recovers known
kernels, the lenslet footprints cover the sensor, and on a scene made with a PSF that differs from the given
one by per-lenslet kernels the refined PSF moves towards the true one and the beads come back."""

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage, signal

import cm2cl
from cm2cl.analysis import quality as Q
from cm2cl.errors import InputError
from cm2cl.solver.params import ADMMParams
from cm2cl.solver import psf_refine as R


def _shift_kernel(r, dy, dx, gain=1.0):
    k = np.zeros((2 * r + 1, 2 * r + 1))
    k[r + dy, r + dx] = gain
    return k


def test_fit_recovers_known_kernels_from_noise_free_data():
    """target = C sum_j k_j (*) F_j made with scipy's convolution (not the fit's shifted columns): the
    fit with a vanishing ridge returns the kernels to 1e-8."""
    rng = np.random.default_rng(3)
    M, P, r, n = (20, 24), (40, 48), 2, 3
    F = rng.random((n,) + P)
    k_true = rng.random((n, 2 * r + 1, 2 * r + 1)) * (rng.random((n, 2 * r + 1, 2 * r + 1)) > 0.4)
    full = sum(signal.convolve2d(F[j], k_true[j], mode="same") for j in range(n))
    oy, ox = (P[0] - M[0]) // 2, (P[1] - M[1]) // 2
    target = full[oy:oy + M[0], ox:ox + M[1]]
    w = 0.5 + rng.random(M)
    k = R.fit_kernels(F, target, M, r, weights=w, ridge=1e-14)
    assert np.abs(k - k_true).max() < 1e-8


def test_fit_is_non_negative_and_ridge_pulls_to_identity():
    """Data that no kernel fits (noise): the kernels stay >= 0, and a heavy ridge returns the identity."""
    rng = np.random.default_rng(4)
    M, P, r = (16, 16), (32, 32), 1
    F = rng.random((2,) + P)
    target = rng.standard_normal(M)
    k = R.fit_kernels(F, target, M, r)
    assert k.min() >= 0
    k = R.fit_kernels(F, target, M, r, ridge=1e9)
    assert np.allclose(k, [_shift_kernel(r, 0, 0)] * 2, atol=1e-6)


def test_lenslet_labels_cover_the_sensor_one_label_per_lenslet():
    psf = Q.array_psf(5, (64, 64))
    lab = R.lenslet_labels(psf)
    assert lab.shape == (64, 64) and lab.min() == 1 and lab.max() == 9
    # each lenslet's spots (every plane) sit in one label, and no two lenslets share one
    peaks = psf.max(axis=0) > 0.5 * psf.max()
    from scipy import ndimage
    spots, n = ndimage.label(peaks)
    assert n == 9
    owners = [set(lab[spots == i + 1].tolist()) for i in range(n)]
    assert all(len(o) == 1 for o in owners) and len(set.union(*owners)) == 9
    # a diffuser-like caustic (many pieces): one kernel for the whole stack
    rng = np.random.default_rng(0)
    speckle = (rng.random((3, 64, 64)) > 0.97).astype(float)
    assert R.lenslet_labels(speckle).max() == 1


def test_apply_kernels_identity_shift_and_total():
    psf = Q.array_psf(4, (48, 48))
    lab = R.lenslet_labels(psf)
    n, r = lab.max(), 2
    same = R.apply_kernels(psf, lab, np.array([_shift_kernel(r, 0, 0)] * n))
    assert np.allclose(same, psf, atol=1e-12)
    moved = R.apply_kernels(psf, lab, np.array([_shift_kernel(r, 1, 0)] * n))
    # the light shifted off the last row is given back to each plane (each plane's total kept: a plane's scale
    # and its volume's brightness trade one for the other in the data, so the kernels' gains cannot set it)
    lost = psf[:, -1].sum(axis=1) / psf.sum(axis=(1, 2))
    assert np.allclose(moved[:, 1:], psf[:, :-1] / (1 - lost)[:, None, None], rtol=1e-9, atol=1e-15)
    assert np.allclose(moved.sum(axis=(1, 2)), psf.sum(axis=(1, 2)), rtol=1e-12)
    s = R.kernel_summary(np.array([_shift_kernel(r, 1, -2, 0.5)]))[0]
    assert s["gain"] == pytest.approx(0.5) and s["shift_px"] == pytest.approx([1, -2]) and s["rms_width_px"] < 1e-12


def _kernel_mismatch_scene(seed=2):
    """Beads imaged by the given PSF with each lenslet blurred, shifted and dimmed by its own kernel."""
    nz, shape = 6, (64, 64)
    psf = Q.array_psf(nz, shape)
    lab = R.lenslet_labels(psf)
    rng = np.random.default_rng(seed)
    r = 3
    ker = []
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    for _ in range(lab.max()):
        cy, cx = rng.uniform(-1.2, 1.2, 2)
        g = np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * 0.9 ** 2))
        ker.append(rng.uniform(0.5, 1.0) * g / g.sum())
    psf_true = R.apply_kernels(psf, lab, np.array(ker)) * 0.8      # total light not preserved either
    beads = Q.place_beads(12, nz, shape, seed, margin=10)
    truth = Q.bead_volume(beads, np.ones(len(beads)), nz, shape)
    y = Q.object_image(psf_true, truth)
    y = rng.poisson(y / y.max() * 2000.0) / 2000.0 * y.max()
    return psf, psf_true, y, beads


def test_refinement_moves_the_psf_to_the_true_one_and_finds_the_beads(rt):
    """On the kernel-mismatch scene the refined PSF is closer to the true one (both at unit light) than
    the given one was, the misfit falls round by round, and the beads found improve on the unrefined solve."""
    psf, psf_true, y, beads = _kernel_mismatch_scene()
    kw = dict(max_iter=400, background="none")
    plain = cm2cl.reconstruct(y, psf, **kw, psf_refine=0)
    rec = cm2cl.reconstruct(y, psf, psf_refine=4, psf_refine_iter=100, **kw)
    info = rec.info["psf_refine"]
    assert info["rounds"] == 4 and info["lenslets"] == 9 and len(info["per_round"]) == 4
    assert rec.psf.shape == psf.shape and rec.psf.min() >= 0 and rec.psf.sum() == pytest.approx(psf.sum())

    def err(h):
        return np.linalg.norm(h / h.sum() - psf_true / psf_true.sum()) / np.linalg.norm(psf_true / psf_true.sum())

    assert err(rec.psf) < 0.5 * err(psf)
    misfit = [r["residual"] for r in info["per_round"]]
    assert misfit[-1] < 0.8 * misfit[0]
    s0, s1 = Q.score_beads(plain.volume, beads), Q.score_beads(rec.volume, beads)
    assert s1["f1"] > s0["f1"] and s1["recall"] >= 0.9, (s0, s1)


def test_rounds_keep_their_penalties_and_the_final_solve_takes_the_default(rt):
    """The refinement's rounds start at mu_v = 1 with rebalancing steps up to x3 (ROUND_PENALTIES: their 100
    iterations shape the volume the kernels are fitted to), rebalancing from the first iteration; the final
    solve at the solver's default 0.2 with steps up to x1.5 from iteration 10. A mu_v the caller gives applies
    to both."""
    from cm2cl.solver.control import ADAPT_FROM, ADAPT_MAX_STEP, DATA_PENALTY

    psf, _, y, _ = _kernel_mismatch_scene()
    kw = dict(psf_refine=2, psf_refine_iter=20, max_iter=80, background="none")
    rec = cm2cl.reconstruct(y, psf, **kw)
    assert [r["mu_v"] for r in rec.info["psf_refine"]["per_round"]] == [R.ROUND_PENALTIES["mu_v"]] * 2 == [1.0] * 2
    assert rec.info["initial_penalties"]["mu_v"] == DATA_PENALTY
    assert [r["adapt_max_step"] for r in rec.info["psf_refine"]["per_round"]] == [3.0, 3.0]
    assert rec.info["adapt_max_step"] == ADAPT_MAX_STEP == 1.5
    # the rounds rebalance from their first iteration, the final solve after the cold start's transient
    assert [r["adapt_from"] for r in rec.info["psf_refine"]["per_round"]] == [1, 1]
    assert rec.info["adapt_from"] == ADAPT_FROM == 10
    steps = [rec.history[f"mu_{n}"][1:] / rec.history[f"mu_{n}"][:-1] for n in ("v", "w")]
    assert max(float(np.max(np.maximum(q, 1 / q))) for q in steps) <= ADAPT_MAX_STEP * (1 + 1e-6)
    assert R.round_params(ADMMParams(adapt_max_step=2.0)) == ADMMParams(adapt_max_step=2.0, mu_v=1.0, adapt_from=1)
    assert R.round_params(ADMMParams(adapt_from=5)).adapt_from == 5   # given: the rounds take it too
    given = cm2cl.reconstruct(y, psf, mu_v=0.5, **kw)
    assert [r["mu_v"] for r in given.info["psf_refine"]["per_round"]] == [0.5, 0.5]
    assert given.info["initial_penalties"]["mu_v"] == 0.5


def test_refinement_leaves_a_matching_psf_alone(rt):
    """Data made by the given PSF: every fitted kernel is near the identity (gain 1, no shift, no blur)."""
    nz, shape = 6, (64, 64)
    psf = Q.array_psf(nz, shape)
    beads = Q.place_beads(12, nz, shape, 5, margin=10)
    y = Q.object_image(psf, Q.bead_volume(beads, np.ones(len(beads)), nz, shape))
    rows = []
    rec = cm2cl.reconstruct(y, psf, psf_refine=12, max_iter=300, background="none", callback=rows.append)
    # the callback's iterations count on across the rounds (a progress bar's total is all of them)
    its = [r["iter"] for r in rows]
    assert its == list(range(1, len(its) + 1)) and its[-1] == rec.info["psf_refine"]["iterations_total"]
    for k in rec.info["psf_refine"]["per_round"][-1]["kernels"]:
        assert abs(k["gain"] - 1) < 0.15 and np.hypot(*k["shift_px"]) < 0.25 and k["rms_width_px"] < 0.6, k
    assert Q.score_beads(rec.volume, beads)["recall"] == 1.0


def test_refinement_refuses_what_it_cannot_do(rt):
    psf = Q.array_psf(2, (32, 32))
    y = Q.object_image(psf, np.ones((2, 32, 32)))
    with pytest.raises(InputError, match="padding='support'"):
        cm2cl.reconstruct(y, psf, psf_refine=1, padding="support")
    with pytest.raises(InputError, match="psf_refine"):
        cm2cl.reconstruct(y, psf, psf_refine=-1)


def test_cli_psf_refine_saves_the_refined_psf(rt, tmp_path, capsys):
    """--psf-refine 1 --save-psf writes OUT.psf.ome.tif (the stack the final solve used, readable as a
    --psf), and --save-psf with --psf-refine 0 or with --tile is refused with one line before any work."""
    import tifffile

    from cm2cl import io
    from cm2cl.cli import main

    psf, _, y, _ = _kernel_mismatch_scene()
    tifffile.imwrite(tmp_path / "psf.tif", psf.astype(np.float32), photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", (y / y.max() * 1000).astype(np.float32))
    base = ["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "--max-iter", "20",
            "--quiet"]
    assert main(base + ["-o", str(tmp_path / "v.ome.tif"), "--psf-refine", "1", "--psf-refine-iter", "20",
                        "--save-psf"]) == 0
    h, _ = io.read_tiff(tmp_path / "v.psf.ome.tif")
    assert h.shape == psf.shape and h.min() >= 0 and not np.allclose(h / h.sum(), psf / psf.sum(), atol=1e-6)
    capsys.readouterr()
    for extra, msg in ((["--save-psf", "--psf-refine", "0"], "not 0"),
                       (["--save-psf", "--preset", "fast"], "not 0"),
                       (["--psf-refine", "1", "--tile", "32", "32", "--save-psf"], "--tile")):
        assert main(base + ["-o", str(tmp_path / "w.ome.tif"), *extra]) == 2
        err = capsys.readouterr().err
        assert msg in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "w.ome.tif").exists()


def test_depth_weights_interpolate_between_nodes():
    W = R.depth_weights(7, 3)
    assert W.shape == (3, 7) and np.allclose(W.sum(axis=0), 1.0)
    # nodes at planes 0, 3 and 6; halfway between two nodes half of each
    assert np.allclose(W[:, 0], [1, 0, 0]) and np.allclose(W[:, 3], [0, 1, 0]) and np.allclose(W[:, 6], [0, 0, 1])
    assert np.allclose(W[:, 1], [2 / 3, 1 / 3, 0]) and np.allclose(W[:, 5], [0, 1 / 3, 2 / 3])
    assert np.array_equal(R.depth_weights(7, 1), np.ones((1, 7)))
    assert R.depth_weights(2, 5).shape == (2, 2) and R.depth_weights(1, 3).shape == (1, 1)


def test_lenslet_images_per_depth_node_are_the_weighted_forward_model():
    """F_jg cropped to the sensor = C H x with lenslet j's PSF weighted by node g's hat over the planes (the
    float64 reference's forward model), and the F_jg of all j, g add up to the whole model."""
    from cm2cl import reference

    rng = np.random.default_rng(8)
    nz, M = 5, (64, 64)
    psf = Q.array_psf(nz, M)
    lab = R.lenslet_labels(psf)
    assert lab.max() == 9
    P = (128, 128)
    x = rng.random((nz,) + P) * (rng.random((nz,) + P) > 0.97)
    W = R.depth_weights(nz, 3)
    F = R.lenslet_images(psf, lab, x, W)
    oy, ox = (P[0] - M[0]) // 2, (P[1] - M[1]) // 2
    assert F.shape == (lab.max() * 3,) + P
    for j in (0, 4, 8):
        for g in range(3):
            want = reference.forward(psf * (lab == j + 1) * W[g][:, None, None], x, P)
            assert np.allclose(F[j * 3 + g, oy:oy + M[0], ox:ox + M[1]], want, atol=1e-12 * np.abs(want).max())
    assert np.allclose(F.sum(axis=0)[oy:oy + M[0], ox:ox + M[1]], reference.forward(psf, x, P), atol=1e-12)


def test_apply_kernels_interpolates_the_kernel_over_depth():
    """Two nodes, identity at the first plane and a one-pixel shift at the last: the middle plane gets half of
    each (before the stack's total light is restored)."""
    psf = Q.array_psf(3, (48, 48))
    lab = R.lenslet_labels(psf)
    n, r = lab.max(), 2
    ker = np.array([_shift_kernel(r, 0, 0), _shift_kernel(r, 0, 1)] * n)
    out = R.apply_kernels(psf, lab, ker, R.depth_weights(3, 2))
    want = np.stack([psf[0], 0.5 * psf[1] + 0.5 * np.roll(psf[1], 1, axis=1), np.roll(psf[2], 1, axis=1)])
    want[:, :, 0] -= np.stack([0 * psf[0, :, -1], 0.5 * psf[1, :, -1], psf[2, :, -1]])  # no wrap-around
    # each plane's light is restored to the input plane's: compare plane by plane up to that factor
    assert np.allclose(out.sum(axis=(1, 2)), psf.sum(axis=(1, 2)), rtol=1e-12)
    for i in range(3):
        assert np.allclose(out[i] * (want[i].sum() / out[i].sum()), want[i], atol=1e-12)
    with pytest.raises(ValueError, match="depth nodes"):
        R.apply_kernels(psf, lab, ker[:-1], R.depth_weights(3, 2))


def test_fit_recovers_depth_varying_kernels_from_noise_free_data():
    """A PSF whose lenslets' kernels vary over depth (node kernels interpolated by the hat weights, convolved by
    scipy here): the fit on the per-node lenslet images returns the node kernels."""
    rng = np.random.default_rng(11)
    nz, M, r = 5, (40, 40), 1
    psf = Q.array_psf(nz, M, grid=2, pitch_frac=0.4)
    lab = R.lenslet_labels(psf)
    n, G = lab.max(), 3
    W = R.depth_weights(nz, G)
    k_true = rng.random((n * G, 2 * r + 1, 2 * r + 1))
    true = np.zeros_like(psf)
    for j in range(n):
        for i in range(nz):
            k = sum(W[g, i] * k_true[j * G + g] for g in range(G))
            true[i] += signal.convolve2d(psf[i] * (lab == j + 1), k, mode="same")
    P = (80, 80)
    x = rng.random((nz,) + P) * (rng.random((nz,) + P) > 0.9)
    from cm2cl import reference
    target = reference.forward(true, x, P)
    k = R.fit_kernels(R.lenslet_images(psf, lab, x, W), target, M, r, ridge=1e-14)
    # the nodes' images overlap (hat weights): the normal equations are less well conditioned than with one
    # kernel per lenslet, so 1e-3 of the kernels' values (a wrong interpolation or indexing is off by O(1))
    assert np.abs(k - k_true).max() < 1e-3 * k_true.max()


def test_round_schedule_starts_sparse_and_with_one_kernel_per_lenslet():
    s = [R.round_schedule(i, 12, 12.0, 3) for i in range(12)]
    assert s[0] == (pytest.approx(12.0), 1) and s[-1] == (pytest.approx(1.0), 3)
    assert [n for _, n in s] == [1] * 4 + [3] * 8
    assert np.allclose(np.diff(np.log([v for v, _ in s])), -np.log(12.0) / 11)
    assert R.round_schedule(0, 1, 12.0, 3) == (pytest.approx(12.0), 3)


def test_l1_scale_multiplies_the_weight_the_rule_gives(rt):
    psf = Q.array_psf(3, (32, 32))
    y = Q.object_image(psf, np.random.default_rng(1).random((3, 32, 32)))
    a = cm2cl.reconstruct(y, psf, max_iter=2, psf_refine=0)        # the PSF refined at each scale would differ
    b = cm2cl.reconstruct(y, psf, max_iter=2, psf_refine=0, l1_scale=3.0)
    assert b.info["l1"] == pytest.approx(3.0 * a.info["l1"]) and b.info["l1"] > 0


def test_refinement_fixes_the_aberrated_scene_of_the_quality_suite(rt):
    """The suite's aberrated-PSF scene (per-lenslet elongation and coma that grow with the spot, so no single
    kernel per lenslet fits it): unrefined, ghosts; refined with the default schedule (depth nodes, sparse
    start), the beads at the issue's targets. The plane weights are held at ||h_i|| (q = 1), where the schedule
    was set: at the default q = 1/2 this frame keeps 37 of 40 beads (docs/psf_refine.md, "Halfway")."""
    spec = {s.name: s for s in Q.scene_specs()}["mm_aberr"]
    sc = Q.render_scene(spec)
    plain = Q.score_beads(cm2cl.reconstruct(sc.y, sc.psf, psf_refine=0, l1_plane_power=1.0).volume, sc.beads)
    rec = cm2cl.reconstruct(sc.y, sc.psf, psf_refine=12, l1_plane_power=1.0)
    s = Q.score_beads(rec.volume, sc.beads)
    assert plain["false_per_10"] > 5
    assert s["recall"] >= 0.95 and s["false_per_10"] <= 1.0 and s["axial_err"] <= 0.5, s
    info = rec.info["psf_refine"]
    assert info["depth_nodes"] == 3 and [r["depth_nodes"] for r in info["per_round"]] == [1] * 4 + [3] * 8


# ---------------------------------------------------------------------------------------------------- auto
def _per_lenslet_kernels(n, r, seed, spread):
    """n normalised Gaussian kernels, each shifted and widened by its own draw (``spread`` 0: all alike)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    out = []
    for _ in range(n):
        cy, cx = spread * rng.uniform(-1.2, 1.2, 2) + 0.4
        s = 0.8 + spread * rng.uniform(0.0, 0.6)
        g = np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * s ** 2))
        out.append(g / g.sum())
    return np.array(out)


def test_sensor_model_is_the_forward_model_with_the_kernels_applied():
    """C sum_j k_j (*) F_j (the check's model) equals the forward model of the stack with each lenslet's
    kernel applied (apply_kernels before its clip and per-plane scaling, which keep light here) and, with
    identity kernels, the forward model of the given stack."""
    nz, shape = 3, (64, 64)
    psf = Q.array_psf(nz, shape)
    lab = R.lenslet_labels(psf)
    x = np.zeros((nz,) + shape)
    rng = np.random.default_rng(3)
    x[rng.integers(0, nz, 15), rng.integers(12, 52, 15), rng.integers(12, 52, 15)] = rng.uniform(0.5, 1, 15)
    P = (2 * shape[0], 2 * shape[1])
    xp = np.zeros((nz,) + P)
    xp[:, (P[0] - shape[0]) // 2:(P[0] - shape[0]) // 2 + shape[0], (P[1] - shape[1]) // 2:(P[1] - shape[1]) // 2 + shape[1]] = x
    F = R.lenslet_images(psf, lab, xp)
    np.testing.assert_allclose(R.sensor_model(F, None, shape), Q.object_image(psf, x), atol=1e-12 * Q.object_image(psf, x).max())
    k = _per_lenslet_kernels(int(lab.max()), 3, 1, 1.0)
    # the kernels move no light across the sensor's edge here, so apply_kernels' per-plane scaling is exact
    want = Q.object_image(R.apply_kernels(psf, lab, k), x)
    np.testing.assert_allclose(R.sensor_model(F, k, shape), want, rtol=0, atol=2e-3 * want.max())


def test_view_disagreement_tells_a_common_kernel_from_kernels_per_lenslet():
    """Data from the same volume with white noise: a blur, shift and gain common to every lenslet is explained
    by one kernel (the separate kernels fit only noise: F below 1, no refinement, though on this small sensor
    they remove more of the misfit than the size threshold); lenslets each with their own kernel are not
    (F and the misfit fraction far above their thresholds)."""
    nz, shape = 4, (64, 64)
    psf = Q.array_psf(nz, shape)
    lab = R.lenslet_labels(psf)
    n = int(lab.max())
    beads = Q.place_beads(10, nz, shape, 4, margin=10)
    x = Q.bead_volume(beads, np.ones(len(beads)), nz, shape)
    xp = np.zeros((nz, 128, 128))
    xp[:, 32:96, 32:96] = x
    F = R.lenslet_images(psf, lab, xp)
    common = np.repeat(_per_lenslet_kernels(1, 3, 2, 0.0), n, axis=0) * 1.3
    own = _per_lenslet_kernels(n, 3, 2, 1.0) * np.linspace(0.6, 1.4, n)[:, None, None]
    for seed in (7, 8, 9):
        noise = np.random.default_rng(seed).normal(size=shape)
        stats = {}
        for name, k in (("common", common), ("own", own)):
            clean = R.sensor_model(F, k, shape)
            target = clean + 0.01 * clean.max() * noise
            stats[name] = R.view_disagreement(F, R.fit_kernels(F, target, shape, 3), target, shape, 3)
        c, o = stats["common"], stats["own"]
        # non-negative kernels use fewer than their p taps on noise, so F falls below 1 (the test is conservative)
        assert 0.05 < c["f_statistic"] < 1.0 and not c["refine"], c
        assert c["disagreement"] > R.VIEW_DISAGREEMENT   # on 64 x 64 pixels noise alone passes the size threshold
        assert o["f_statistic"] > 10 and o["disagreement"] > 0.5 and o["refine"], o
        assert o["lenslets"] == n == 9 and len(o["gains"]) == n


def test_view_thresholds_follow_the_pixel_weights():
    """The lower pair where every pixel the data term keeps counts alike (no weights, ones, a 0/1 mask), the
    former one where the weights vary (a camera model's variances); view_disagreement records and applies it."""
    shape = (40, 40)
    plain = (R.VIEW_DISAGREEMENT, R.VIEW_F)
    assert plain == (0.015, 0.6) and (R.VIEW_DISAGREEMENT_WEIGHTED, R.VIEW_F_WEIGHTED) == (0.025, 1.25)
    mask = np.ones(shape)
    mask[:5] = 0
    varying = 1.0 / (1.0 + np.random.default_rng(3).uniform(0, 2, shape))
    assert R.view_thresholds(None) == R.view_thresholds(np.ones(shape)) == R.view_thresholds(2 * mask) == plain
    assert R.view_thresholds(varying) == (R.VIEW_DISAGREEMENT_WEIGHTED, R.VIEW_F_WEIGHTED)
    psf = Q.array_psf(2, shape)
    lab = R.lenslet_labels(psf)
    x = np.zeros((2, 80, 80))
    x[:, 30:50:4, 30:50:5] = 1.0
    F = R.lenslet_images(psf, lab, x)
    own = _per_lenslet_kernels(int(lab.max()), 3, 2, 1.0)
    target = R.sensor_model(F, own, shape) + 0.002 * np.random.default_rng(4).normal(size=shape)
    k = R.fit_kernels(F, target, shape, 3)
    for w in (None, varying):
        c = R.view_disagreement(F, k, target, shape, 3, w)
        assert (c["threshold"], c["f_threshold"]) == R.view_thresholds(w)
        assert c["refine"] == (c["disagreement"] > c["threshold"] and c["f_statistic"] > c["f_threshold"])


def test_auto_refines_the_lenslets_of_a_blurred_and_aberrated_psf_unless_pixels_are_weighted(rt):
    """The suite's blurred and aberrated PSF (mm_blur_aberr): the views disagree less than an aberration alone
    makes them (d between the two thresholds), yet one common kernel leaves ghosts. Without pixel weights 'auto'
    refines the lenslets and the ghosts go; under the camera model's variance weights the check keeps the former
    thresholds (kernels per lenslet made matched frames worse there) and the answer stays 'common'."""
    sc = Q.render_scene({s.name: s for s in Q.scene_specs()}["mm_blur_aberr"])
    kw = dict(max_iter=300)
    one = Q.score_beads(cm2cl.reconstruct(sc.y, sc.psf, psf_refine="common", **kw).volume, sc.beads)
    rec = cm2cl.reconstruct(sc.y, sc.psf, psf_refine="auto", **kw)
    check = rec.info["psf_refine"]["check"]
    assert R.VIEW_DISAGREEMENT < check["disagreement"] < R.VIEW_DISAGREEMENT_WEIGHTED, check
    assert check["refine"] and rec.info["psf_refine"]["rounds"] == R.AUTO_ROUNDS
    s = Q.score_beads(rec.volume, sc.beads)
    assert one["false_per_10"] > 5 and s["false_per_10"] <= 1.0 and s["recall"] >= 0.95, (one, s)
    cam = cm2cl.reconstruct(sc.raw, sc.psf, psf_refine="auto", camera=sc.spec.camera.as_dict(), **kw)
    info = cam.info["psf_refine"]
    weighted = (R.VIEW_DISAGREEMENT_WEIGHTED, R.VIEW_F_WEIGHTED)
    assert (info["check"]["threshold"], info["check"]["f_threshold"]) == weighted
    assert not info["check"]["refine"] and info["rounds"] == R.COMMON_ROUNDS, info["check"]


def test_auto_stays_common_on_a_matching_psf_and_refines_the_lenslets_of_a_mismatched_one(rt):
    """psf_refine='auto': its first round is 'common' (one kernel for every lenslet), then the view check on that
    round's volume. On beads imaged by the given PSF the views agree and the answer is 'common''s bit for bit; on
    the quality suite's vignetted scene (lenslets dimmed by up to 60%, a field stop) they disagree, the rest of
    the rounds fit kernels per lenslet, and the ghosts that the PSF as given and 'common' both leave are gone."""
    spec = {s.name: s for s in Q.scene_specs()}
    kw = dict(max_iter=300, psf_refine_iter=50)   # half the rounds' iterations: the same decisions and targets
    matched = Q.render_scene(spec["beads"])
    rec = cm2cl.reconstruct(matched.y, matched.psf, psf_refine="auto", **kw)
    info = rec.info["psf_refine"]
    assert info["mode"] == "auto" and info["refined"] and info["rounds"] == R.COMMON_ROUNDS and rec.psf is not None
    assert info["common_only"] and info["lenslets"] == 1
    assert info["check"]["disagreement"] < R.VIEW_DISAGREEMENT and info["check"]["f_statistic"] < R.VIEW_F
    # one kernel per depth node, common to every lenslet, in every round
    assert all(len(r["kernels"]) == info["depth_nodes"] == 3 for r in info["per_round"])
    assert "lenslet_kernels" not in info["per_round"][0]
    assert info["reweight"] is None and rec.params["l1_reweight"] == 0    # plain l1 where no kernels per lenslet
    common = cm2cl.reconstruct(matched.y, matched.psf, **kw, psf_refine="common")
    np.testing.assert_array_equal(rec.volume, common.volume)
    np.testing.assert_array_equal(rec.psf, common.psf)
    sc = Q.render_scene(spec["mm_trunc"])
    plain = Q.score_beads(cm2cl.reconstruct(sc.y, sc.psf, **kw, psf_refine=0).volume, sc.beads)
    one_rec = cm2cl.reconstruct(sc.y, sc.psf, **kw, psf_refine="common")
    one = Q.score_beads(one_rec.volume, sc.beads)
    rec = cm2cl.reconstruct(sc.y, sc.psf, psf_refine="auto", **kw)
    info = rec.info["psf_refine"]
    assert info["mode"] == "auto" and info["refined"] and info["rounds"] == R.AUTO_ROUNDS
    assert info["check"]["disagreement"] > 3 * R.VIEW_DISAGREEMENT and info["check"]["f_statistic"] > 3 * R.VIEW_F
    assert rec.psf is not None and len(info["per_round"]) == R.AUTO_ROUNDS
    assert len(info["per_round"][0]["kernels"]) == 3 and len(info["per_round"][0]["lenslet_kernels"]) == 9
    assert all(len(r["kernels"]) >= 9 for r in info["per_round"][1:])
    # the common kernel's answer was solved beside them (the same as 'common''s) and fits the data worse
    assert info["compared"]["kept"] == "lenslets" and info["compared"]["lenslets"]["rms"] == rec.info["misfit"]["rms"]
    assert info["compared"]["common"]["rms"] == one_rec.info["misfit"]["rms"] > rec.info["misfit"]["rms"]
    alone = cm2cl.reconstruct(sc.y, sc.psf, psf_refine="auto", psf_refine_compare=False, **kw)
    assert alone.info["psf_refine"]["compared"] is None and alone.info["psf_refine"]["rounds"] == R.AUTO_ROUNDS
    np.testing.assert_array_equal(alone.volume, rec.volume)
    # the final solve, after kernels per lenslet, reweights l1 (psf_refine_reweight rounds at eps REWEIGHT_EPS)
    assert info["reweight"] == {"rounds": 1, "eps": R.REWEIGHT_EPS}
    assert rec.params["l1_reweight"] == 1 and rec.params["l1_reweight_eps"] == R.REWEIGHT_EPS
    s = Q.score_beads(rec.volume, sc.beads)
    assert plain["false_per_10"] > 2 and one["false_per_10"] > 2, (plain, one)
    assert s["false_per_10"] <= 1.0 and s["recall"] >= 0.95, (plain, one, s)


def test_spot_width_is_the_half_maximum_diameter_of_the_sharpest_spot():
    """spot_width_px: the diameter of the disc whose area is the half-maximum piece around the stack's brightest
    pixel, in the plane of the highest peak. For a Gaussian of FWHM f (sigma f / 2.3548) sampled on pixels it is
    f within a pixel; a dimmer, wider plane and a second spot elsewhere do not change it."""
    yy, xx = np.mgrid[:64, :64]
    for fwhm in (2.5, 4.0, 7.0):
        s = fwhm / 2.3548
        spot = lambda cy, cx, sig: np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * sig * sig))  # noqa: E731
        psf = np.stack([0.3 * spot(30, 30, 2 * s), spot(31.3, 29.6, s) + spot(12, 50, s)])
        assert abs(R.spot_width_px(psf) - fwhm) < 1.0, (fwhm, R.spot_width_px(psf))
    assert R.spot_width_px(np.zeros((2, 8, 8))) == 1.0


def test_extended_share_tells_points_from_lines():
    """extended_share: the share of a volume's energy in pieces wider than EXTENDED_SPOTS spots. Blurred points
    give 0, lines through the volume 1, and a mix the lines' share of the energy; a level below 10% of the
    maximum does not join the pieces."""
    rng = np.random.default_rng(5)
    pts = np.zeros((8, 96, 96))
    for y in (64, 80):   # 14 points 12-16 px apart, jittered
        for x in range(8, 90, 12):
            pts[rng.integers(1, 7), y + rng.integers(-1, 2), x + rng.integers(-1, 2)] = rng.uniform(0.5, 1.0)
    pts = ndimage.gaussian_filter(pts, (0.7, 1.0, 1.0))
    assert R.extended_share(pts, 2.5) == 0.0
    lines = np.zeros_like(pts)
    lines[3, 20, 10:80] = 1.0                                          # along x
    for z in range(8):   # oblique through depth: a 5-px segment in every plane
        lines[z, 40 + z, 60 - 5 * z - np.arange(6)] = 1.0
    lines = ndimage.gaussian_filter(lines, (0.7, 1.0, 1.0))
    assert R.extended_share(lines, 2.5) > 0.999
    assert R.extended_share(lines, 30.0) == 0.0                        # the same lines are 'points' of 30-px spots
    mix = pts / pts.max() + lines / lines.max()   # the points lie in rows 60-90, the lines in rows 20-47
    above = np.where(mix > R.EXTENDED_LEVEL * mix.max(), mix, 0.0)
    share = float(above[:, :55].sum() / above.sum())
    assert 0.3 < share < 0.9 and abs(R.extended_share(mix, 2.5) - share) < 1e-9, (R.extended_share(mix, 2.5), share)
    assert R.extended_share(np.zeros((2, 4, 4)), 2.5) == 0.0


def test_auto_fits_each_lenslets_gain_alone_for_fibres_whose_views_disagree(rt):
    """Fibres through a PSF whose outer lenslets are vignetted (the quality suite's fibres_trunc): the views
    disagree with the given PSF, but the volume is extended, where kernels per lenslet trade shifts with it
    (docs/psf_refine.md). 'auto' then fits each lenslet's gain alone: radius-0 kernels after the common round,
    no reweighting. The refined lenslets' light follows the vignetting (corners dimmest, the centre brightest),
    and the fibres come out with far more of their energy near the truth than 'common' leaves them."""
    spec = {s.name: s for s in Q.scene_specs()}
    sc = Q.render_scene(spec["fibres_trunc"])
    kw = dict(max_iter=300)
    rec = cm2cl.reconstruct(sc.y, sc.psf, psf_refine="auto", **kw)
    info = rec.info["psf_refine"]
    check = info["check"]
    assert check["views_disagree"] and check["disagreement"] > R.VIEW_DISAGREEMENT and check["f_statistic"] > R.VIEW_F
    assert check["extended_share"] > R.EXTENDED_SHARE and not check["refine"], check
    assert info["lenslet_gains_only"] and info["rounds"] == 1 + R.AUTO_GAIN_ROUNDS and info["reweight"] is None
    for r in info["per_round"][1:]:          # one gain per lenslet: no blur, no shift
        assert r["depth_nodes"] == 1 and len(r["kernels"]) == 9
        assert all(k["rms_width_px"] == 0 and k["shift_px"] == [0.0, 0.0] for k in r["kernels"]), r["kernels"]
    lab = R.lenslet_labels(sc.psf)
    light = np.array([rec.psf[:, lab == j + 1].sum() / sc.psf[:, lab == j + 1].sum() for j in range(9)])
    true = np.array([sc.psf_true[:, lab == j + 1].sum() / sc.psf[:, lab == j + 1].sum() for j in range(9)])
    assert np.corrcoef(light, true)[0, 1] > 0.9, (light, true)
    assert np.argmax(light) == np.argmax(true) and set(np.argsort(light)[:4]) == set(np.argsort(true)[:4])
    common = cm2cl.reconstruct(sc.y, sc.psf, psf_refine="common", **kw)
    near, near_common = Q.energy_near(rec.volume, sc.truth), Q.energy_near(common.volume, sc.truth)
    assert near >= Q.TARGETS["energy_near"] and near > near_common + 0.15, (near, near_common)


def test_auto_keeps_one_common_kernel_for_fibres_whose_views_agree(rt):
    """Fibres through a PSF blurrier than the given one and off in depth (fibres_blur): one common kernel
    explains the mismatch, the views agree, and 'auto' is 'common' bit for bit: no gains are fitted."""
    spec = {s.name: s for s in Q.scene_specs()}
    sc = Q.render_scene(spec["fibres_blur"])
    kw = dict(max_iter=200)
    rec = cm2cl.reconstruct(sc.y, sc.psf, psf_refine="auto", **kw)
    info = rec.info["psf_refine"]
    assert not info["check"]["views_disagree"] and info["rounds"] == R.COMMON_ROUNDS and info["common_only"]
    assert not info["lenslet_gains_only"]
    np.testing.assert_array_equal(rec.volume, cm2cl.reconstruct(sc.y, sc.psf, psf_refine="common", **kw).volume)


def test_auto_is_common_where_the_views_cannot_be_compared_and_steps_aside_where_it_cannot_refine(rt):
    """A PSF of one view and spots that are no views through depth: 'auto' is 'common' bit for bit and says
    why it did not compare views; padding='support' and lateral tiles: the PSF as given (the plain solve's
    bits), said why; nothing refused."""
    nz, shape = 3, (48, 48)
    psf = np.zeros((nz,) + shape)
    yy, xx = np.mgrid[:48, :48]
    for i in range(nz):
        psf[i] = np.exp(-((yy - 24) ** 2 + (xx - 24) ** 2) / (2 * (1 + i) ** 2))
    x = np.zeros((nz,) + shape)
    x[1, 20, 22] = 1.0
    y = Q.object_image(psf, x)
    rec = cm2cl.reconstruct(y, psf, max_iter=30, psf_refine="auto")
    info = rec.info["psf_refine"]
    assert info["check_skipped"] == "the PSF has one view" and info["check"] is None
    assert info["rounds"] == R.COMMON_ROUNDS and info["common_only"]
    np.testing.assert_array_equal(rec.volume, cm2cl.reconstruct(y, psf, max_iter=30, psf_refine="common").volume)
    scattered = np.zeros((nz,) + shape)          # 4 spots per plane, each plane's elsewhere
    rng = np.random.default_rng(2)
    for i in range(nz):
        scattered[i, rng.integers(8, 40, 4), rng.integers(8, 40, 4)] = 1.0
    scattered = ndimage.gaussian_filter(scattered, (0, 1.0, 1.0))
    y2 = Q.object_image(scattered, x)
    rec = cm2cl.reconstruct(y2, scattered, max_iter=30, psf_refine="auto")
    assert rec.info["psf_refine"]["check_skipped"] == "the PSF's pieces are not views through its depth"
    np.testing.assert_array_equal(rec.volume,
                                  cm2cl.reconstruct(y2, scattered, max_iter=30, psf_refine="common").volume)
    arr = Q.array_psf(nz, (64, 64))
    assert R.views_through_depth(arr, R.lenslet_labels(arr))
    x = np.zeros((nz, 64, 64))
    x[1, 30, 28] = 1.0
    y = Q.object_image(arr, x)
    rec = cm2cl.reconstruct(y, arr, max_iter=30, padding="support", psf_refine="auto")
    assert rec.info["psf_refine"]["skipped"] == "padding='support'"
    from cm2cl.jobs.tiles import reconstruct_tiled

    # tiles take 'auto' and solve each tile with the PSF as given (a compact PSF, so that tiles pay)
    y1 = Q.object_image(psf, np.pad(x[:, 8:56, 8:56], ((0, 0), (0, 0), (0, 0))))
    vol, _ = reconstruct_tiled(y1, psf, (24, 24), max_iter=10, psf_refine="auto")
    ref_vol, _ = reconstruct_tiled(y1, psf, (24, 24), max_iter=10, psf_refine=0)
    np.testing.assert_array_equal(vol, ref_vol)
    with pytest.raises(InputError, match="lateral tiles"):
        reconstruct_tiled(y1, psf, (24, 24), max_iter=10, psf_refine=2)


def test_cli_psf_refine_takes_auto_and_zero(rt, tmp_path, capsys):
    """--psf-refine auto checks first and refines here (each lenslet blurred and shifted by its own kernel),
    and the summary says so with what the check measured; --psf-refine 0 (the PSF as given) neither checks nor
    refines; a word that is neither a number nor 'auto' is refused by the parser (exit 2), before any output."""
    import json

    import tifffile

    from cm2cl.cli import main

    psf, _, y, _ = _kernel_mismatch_scene()
    tifffile.imwrite(tmp_path / "psf.tif", psf.astype(np.float32), photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", (y / y.max() * 1000).astype(np.float32))
    base = ["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "--max-iter", "100",
            "--psf-refine-iter", "100", "--quiet"]
    for word, refined in (("auto", True), ("0", False)):
        out = tmp_path / f"v{word}.ome.tif"
        assert main(base + ["-o", str(out), "--psf-refine", word]) == 0
        info = json.loads((tmp_path / f"v{word}.cm2cl.json").read_text())["info"]
        assert (info.get("psf_refine") or {}).get("refined", False) is refined, info.get("psf_refine")
        said = capsys.readouterr().out
        if refined:   # the summary says what the check measured and that it refined
            assert "PSF refined in 12 rounds" in said and "views disagree with the PSF" in said, said
        else:
            assert "PSF refined" not in said and "PSF used as given" not in said, said
    with pytest.raises(SystemExit) as e:
        main(base + ["-o", str(tmp_path / "w.ome.tif"), "--psf-refine", "some"])
    assert e.value.code == 2 and not (tmp_path / "w.ome.tif").exists()


def test_series_auto_decides_on_frame_0_once(rt, tmp_path, monkeypatch):
    """reconstruct_series(..., psf_refine='auto'): frames whose views disagree with the PSF (each lenslet blurred
    and shifted by its own kernel) get the stack refined per lenslet on frame 0, frames made by the given PSF
    one refined by a common kernel; either way it is kept as OUT.psf.ome.tif, the stack frame 0's own
    reconstruction refines, and every frame is the solve with it and frame 0's final l1 (reweighted where it
    fitted kernels per lenslet), in the first run and in a resumed one that reads the stack back."""
    import zarr

    import cm2cl.jobs.series as S
    from cm2cl import io

    solved_with = []
    real_run_series = S.run_series

    def spy(*a, **k):
        solved_with.append(k["params"])
        return real_run_series(*a, **k)

    monkeypatch.setattr(S, "run_series", spy)

    psf, _, y, _ = _kernel_mismatch_scene()
    kw = dict(max_iter=40, tol=0.0, psf_refine_iter=40)
    nz, shape = psf.shape[0], psf.shape[1:]
    beads = Q.place_beads(12, nz, shape, 5, margin=10)
    clean = Q.object_image(psf, Q.bead_volume(beads, np.ones(len(beads)), nz, shape))
    noisy = np.random.default_rng(4).poisson(np.maximum(clean, 0) / clean.max() * 2000.0) / 2000.0
    for name, frame, rounds in (("m", y, R.AUTO_ROUNDS), ("a", noisy, R.COMMON_ROUNDS)):
        frames = np.stack([frame, 1.1 * frame])
        s = cm2cl.reconstruct_series(frames, psf, tmp_path / f"{name}.ome.zarr", psf_refine="auto", **kw)
        assert s.computed == 2
        h, meta = io.read_tiff(tmp_path / f"{name}.psf.ome.tif")
        first = cm2cl.reconstruct(frames[0], psf, psf_refine="auto", **kw)
        assert first.info["psf_refine"]["rounds"] == rounds, (name, first.info["psf_refine"]["check"])
        np.testing.assert_array_equal(h, first.psf)
        # every frame is solved as frame 0's final solve was: with its reweighted l1 where it fitted kernels per
        # lenslet (the record beside the stack says so, for a resumed job)
        reweight = first.info["psf_refine"]["reweight"]
        assert meta["extra"]["reweight"] == reweight and (reweight is not None) == (name == "m")
        again = cm2cl.reconstruct_series(frames, psf, tmp_path / f"{name}.ome.zarr", psf_refine="auto", **kw)
        assert again.computed == 0
        want = (reweight["rounds"], reweight["eps"]) if reweight else (0, 0.1)
        assert [(p.l1_reweight, p.l1_reweight_eps, p.psf_refine) for p in solved_with[-2:]] == [want + (0,)] * 2
        vol = np.asarray(zarr.open_group(str(tmp_path / f"{name}.ome.zarr"), mode="r")["0"])
        one = cm2cl.reconstruct(frames[1], h, **kw, psf_refine=0, psf_refine_reweight=0,
                                **({"l1_reweight": reweight["rounds"], "l1_reweight_eps": reweight["eps"]}
                                   if reweight else {})).volume
        np.testing.assert_allclose(vol[1], one, rtol=1e-5, atol=1e-6 * one.max())


def test_final_reweight_only_after_kernels_per_lenslet():
    """psf_refine='auto' reweights l1 in its final solve only where it fitted kernels per lenslet (its volume is
    then made of points, and the PSF fits every view); psf_refine_reweight=0 turns it off, and a reweighting the
    user asked for (l1_reweight) is theirs, everywhere."""
    from cm2cl.solver.params import ADMMParams

    p = ADMMParams()
    assert p.psf_refine_reweight == 1 and p.l1_reweight == 0
    assert R.final_reweight(p, True) == {"rounds": 1, "eps": R.REWEIGHT_EPS}
    assert R.final_reweight(p, False) is None
    assert R.final_reweight(replace(p, psf_refine_reweight=0), True) is None
    assert R.final_reweight(replace(p, l1_reweight=2), True) is None
    q = R.with_reweight(p, {"rounds": 3, "eps": 0.25})
    assert (q.l1_reweight, q.l1_reweight_eps) == (3, 0.25) and replace(q, l1_reweight=0, l1_reweight_eps=0.1) == p
    assert R.with_reweight(p, None) is p


def test_refinement_steps_aside_where_it_needs_more_than_half_the_host_memory(monkeypatch):
    """refine_skipped: 'auto' holds its lenslet images and, where it solves both answers, the per-lenslet one's
    stack and volumes while the common one is solved, so it asks for more host memory than 'common'; past half
    of what the host has the PSF is used as given, with the reason."""
    from cm2cl.solver import api, memory

    psf = Q.array_psf(8, (64, 64))
    P = (128, 128)
    plenty = 1 << 40
    monkeypatch.setattr(memory, "host_available_bytes", lambda: plenty)
    assert api.refine_skipped(psf, P, mode="auto") is None and api.refine_skipped(psf, P, mode="common") is None
    planes = P[0] * P[1] * 8
    auto = planes * (5 * 8 + 9 * 3 + 4)
    common = planes * (3 * 8 + 1 * 3 + 4)
    for avail, want in ((2 * auto + 16, (None, None)), (2 * auto - 16, ("auto", None)), (2 * common - 16,
                                                                                          ("auto", "common"))):
        monkeypatch.setattr(memory, "host_available_bytes", lambda a=avail: a)
        got = [api.refine_skipped(psf, P, mode=m) for m in ("auto", "common")]
        for g, m in zip(got, ("auto", "common")):
            assert (g is not None) == (m in want), (avail, got)
            assert g is None or g.startswith("the refinement needs") and g.endswith("GiB of host memory")


def test_lenslets_keep_only_where_they_fit_the_data_better_than_their_taps_fit_noise():
    """The comparison of psf_refine='auto''s two answers: kernels per lenslet keep where their final residual sum
    of squares, less KERNEL_NOISE_F x their extra taps per degree of freedom, is below the common kernel's."""
    check = {"lenslets": 9, "taps": 49}
    extra = 8 * 49
    pixels = 16384
    noise = 1.0 + R.KERNEL_NOISE_F * extra / (pixels - extra)
    common = {"rms": 10.0, "pixels": pixels}
    assert not R.lenslets_fit_better({"rms": 10.0, "pixels": pixels}, common, check)      # a tie: common
    # what the extra taps fit of noise is not enough, a little more is
    assert not R.lenslets_fit_better({"rms": 10.0 / np.sqrt(noise) * 1.0001, "pixels": pixels}, common, check)
    assert R.lenslets_fit_better({"rms": 10.0 / np.sqrt(noise) * 0.9999, "pixels": pixels}, common, check)
    assert R.lenslets_fit_better({"rms": 8.0, "pixels": pixels}, common, check)
    assert not R.lenslets_fit_better({"rms": 10.5, "pixels": pixels}, common, check)
    # one lenslet: nothing extra, the smaller misfit keeps
    assert R.lenslets_fit_better({"rms": 9.999, "pixels": pixels}, common, {"lenslets": 1, "taps": 49})


def test_auto_keeps_the_common_answer_where_kernels_per_lenslet_fit_the_data_worse(rt):
    """A frame at 298 photons of 20 beads through a PSF 1 px blurrier than the stack (a mismatch common to every
    lenslet; tools/random_scenes.py's seed 58, frame 5598): its sparse first volume misses faint beads, the
    lenslets' kernels fitted to it disagree (the check sends 'auto' to kernels per lenslet), and their rounds
    lose beads. Both answers are solved; the common kernel's fits the data better, is kept, is 'common''s answer
    bit for bit, and meets the bead targets."""
    spec = Q.SceneSpec("low", "20 beads, random 16%, 298 photons, blur 1 px", n_beads=20,
                       mismatch=Q.Mismatch(blur=1.0), background="random", bg_level=0.16, photons=298.0, seed=5598)
    sc = Q.render_scene(spec)
    kw = dict(psf_refine_iter=50, max_iter=300)   # half the defaults' time; the same decision and targets
    rec = cm2cl.reconstruct(sc.y, sc.psf, **kw)
    info = rec.info["psf_refine"]
    assert info["check"]["refine"], info["check"]
    cmp = info["compared"]
    assert cmp["kept"] == "common" and cmp["lenslets"]["rms"] > cmp["common"]["rms"], cmp
    assert info["common_only"] and info["rounds"] == R.COMMON_ROUNDS and info["reweight"] is None
    assert info["lenslets"] == 1 and len(info["per_round"]) == R.COMMON_ROUNDS
    assert info["iterations_total"] > cmp["lenslets"]["iterations"] + cmp["common"]["iterations"]
    common = cm2cl.reconstruct(sc.y, sc.psf, psf_refine="common", **kw)
    np.testing.assert_array_equal(rec.volume, common.volume)
    assert rec.info["misfit"] == common.info["misfit"] == {k: v for k, v in cmp["common"].items()
                                                             if k != "iterations"}
    s = Q.score_beads(rec.volume, sc.beads)
    assert s["recall"] >= 0.95 and s["false_per_10"] <= 1.0, s


def test_refine_line_says_what_the_refinement_did():
    from cm2cl.cli.frame import refine_line

    check = {"refine": False, "disagreement": 0.004, "threshold": 0.025, "f_statistic": 0.3, "f_threshold": 1.25}
    assert refine_line(None) == ""
    agreed = {"refined": True, "mode": "auto", "rounds": 2, "common_only": True, "iterations_total": 300,
              "check": check}
    assert refine_line(agreed) == ("PSF refined in 2 rounds, one kernel common to every lenslet (300 iterations in "
                                   "all); --psf-refine auto: the lenslets' views agree with the PSF: separate kernels "
                                   "explain 0.004 of the misfit (threshold 0.025), F 0.30 (threshold 1.25)")
    # a record of one common round (an earlier version's, read back from a store) says so
    old = {"refined": True, "mode": "auto", "rounds": 1, "iterations_total": 300, "check": check}
    assert refine_line(old).startswith("PSF refined in 1 round, one kernel common to every lenslet (300 iterations")
    line = refine_line({**agreed, "rounds": 12, "common_only": False, "check": {**check, "refine": True,
                                                                                "disagreement": 0.2},
                        "reweight": {"rounds": 1, "eps": 0.3}})
    assert line.startswith("PSF refined in 12 rounds (one kernel common to every lenslet, then kernels per lenslet), "
                           "then l1 reweighted 1x (eps 0.3 of the maximum)")
    assert "views disagree" in line and "0.200 of the misfit" in line
    gated = {**check, "views_disagree": True, "disagreement": 0.05, "extended_share": 0.81, "extended_threshold": 0.5}
    line = refine_line({**old, "check": gated})
    assert line.startswith("PSF refined in 1 round, one kernel common to every lenslet")
    assert "views disagree with the PSF (separate kernels explain 0.050 of the misfit), but the volume is extended " \
           "(0.81 of its energy in pieces wider than 3 spots, threshold 0.5)" in line
    line = refine_line({**agreed, "rounds": 4, "common_only": False, "check": gated, "lenslet_gains_only": True})
    assert line.startswith("PSF refined in 4 rounds (one kernel common to every lenslet, then each lenslet's gain)")
    assert line.endswith("kernels per lenslet would trade shifts with it; each lenslet's gain fitted alone")
    both = {"lenslets": {"rms": 7.502}, "common": {"rms": 7.046}, "kept": "common"}
    line = refine_line({**agreed, "check": {**check, "refine": True, "disagreement": 0.044}, "compared": both})
    assert line.startswith("PSF refined in 2 rounds, one kernel common to every lenslet (300 iterations in all)")
    assert line.endswith("both answers solved: kernels per lenslet reach a misfit of 7.502 (rms), the common "
                         "kernel 7.046, so the common kernel's answer is kept")
    line = refine_line({**agreed, "rounds": 12, "common_only": False, "check": {**check, "refine": True},
                        "compared": {**both, "kept": "lenslets"}})
    assert line.endswith("so kernels per lenslet are kept") and "then kernels per lenslet)" in line
    line = refine_line({**agreed, "check": None, "check_skipped": "the PSF has one view"})
    assert line.endswith("--psf-refine auto: the lenslets' views not compared (the PSF has one view)")
    assert refine_line({"refined": False, "skipped": "padding='support'"}).endswith("(padding='support')")
    line = refine_line({"refined": True, "rounds": 4, "iterations_total": 500, "check": None})
    assert line == "PSF refined in 4 rounds (500 iterations in all)"


# -------------------------------------------------------------------------------------------------- common
def test_common_kernel_removes_the_ghosts_of_a_blurrier_psf_off_in_depth(rt):
    """psf_refine='common' on the quality suite's mm_issue scene (the issue's mismatch: every spot blurrier by
    1 px and the stack 0.4 plane off in depth, haze, 800 photons): two rounds with one kernel for every lenslet
    (3 depth nodes) brings the PSF closer to the one that made the data, and the spurious maxima the plain
    solve leaves go below the issue's 1 per 10 beads with every bead found."""
    sc = Q.render_scene({s.name: s for s in Q.scene_specs()}["mm_issue"])
    plain = Q.score_beads(cm2cl.reconstruct(sc.y, sc.psf, psf_refine=0).volume, sc.beads)
    rec = cm2cl.reconstruct(sc.y, sc.psf, psf_refine="common")
    info = rec.info["psf_refine"]
    assert info["mode"] == "common" and info["refined"] and info["rounds"] == R.COMMON_ROUNDS and info["lenslets"] == 1
    assert info["depth_nodes"] == 3 and all(len(r["kernels"]) == 3 for r in info["per_round"])

    def err(h):
        h = h / h.sum(axis=(1, 2), keepdims=True)
        t = sc.psf_true / sc.psf_true.sum(axis=(1, 2), keepdims=True)
        return np.linalg.norm(h - t) / np.linalg.norm(t)

    assert err(rec.psf) < 0.95 * err(sc.psf), (err(rec.psf), err(sc.psf))   # measured 0.39 against 0.44
    s = Q.score_beads(rec.volume, sc.beads)
    assert plain["false_per_10"] > 1.0, plain
    assert s["recall"] >= 0.95 and s["false_per_10"] <= 1.0 and s["axial_err"] <= 0.5, (plain, s)


def test_a_second_common_round_keeps_the_converged_answer_no_worse_than_50_iterations(rt):
    """Issue 24's check on the quality suite's mm_issue frame (a blurrier PSF off in depth, haze, 800 photons) at
    the defaults: the answer at convergence has no more false maxima than at 50 iterations and an F1 no lower.
    With one common round (COMMON_ROUNDS 1) the converged answer had 3 ghosts against 2 (F1 0.952 < 0.968): the
    first round's kernel, fitted to a sparse solve, leaves the blur half-corrected; the second, fitted to a
    solve at the final l1 weight, corrects the rest."""
    sc = Q.render_scene({s.name: s for s in Q.scene_specs()}["mm_issue"])
    short = Q.score_beads(cm2cl.reconstruct(sc.y, sc.psf, max_iter=50, tol=0.0).volume, sc.beads)
    rec = cm2cl.reconstruct(sc.y, sc.psf)
    assert rec.info["psf_refine"]["rounds"] == R.COMMON_ROUNDS == 2 and rec.info["stop"] == "converged"
    conv = Q.score_beads(rec.volume, sc.beads)
    assert conv["f1"] >= short["f1"] and conv["false_maxima"] <= short["false_maxima"], (short, conv)
    assert conv["recall"] >= 0.95 and conv["false_per_10"] <= 1.0, conv


def test_common_steps_aside_where_it_cannot_run(rt):
    """padding='support' and lateral tiles: 'common' solves with the PSF as given (the plain solve's bits),
    records why, and refuses nothing (a number of rounds is refused there)."""
    nz = 3
    arr = Q.array_psf(nz, (64, 64))
    x = np.zeros((nz, 64, 64))
    x[1, 30, 28] = 1.0
    y = Q.object_image(arr, x)
    rec = cm2cl.reconstruct(y, arr, max_iter=30, padding="support", psf_refine="common")
    assert rec.info["psf_refine"] == {"mode": "common", "refined": False, "rounds": 0, "skipped": "padding='support'"}
    plain = cm2cl.reconstruct(y, arr, max_iter=30, padding="support", psf_refine=0)
    np.testing.assert_array_equal(rec.volume, plain.volume)
    from cm2cl.jobs.tiles import reconstruct_tiled

    spot = np.zeros((nz, 48, 48))          # a compact PSF, so that tiles pay
    yy, xx = np.mgrid[:48, :48]
    for i in range(nz):
        spot[i] = np.exp(-((yy - 24) ** 2 + (xx - 24) ** 2) / (2 * (1 + i) ** 2))
    y1 = Q.object_image(spot, x[:, 8:56, 8:56])
    vol, _ = reconstruct_tiled(y1, spot, (24, 24), max_iter=10, psf_refine="common")
    np.testing.assert_array_equal(vol, reconstruct_tiled(y1, spot, (24, 24), max_iter=10, psf_refine=0)[0])
    assert R.explicit_rounds(3) and not R.explicit_rounds("common") and not R.explicit_rounds(0)
    assert [R.plan_rounds(v) for v in (0, 5, "common", "auto")] == [0, 5, R.COMMON_ROUNDS, R.AUTO_ROUNDS]


def test_cli_and_series_take_common(rt, tmp_path, capsys):
    """--psf-refine common: the summary says one kernel common to every lenslet was fitted, --save-psf writes
    the stack the solve used; with --padding support --save-psf is refused in one line before any work; a
    series refines on frame 0 and keeps the stack beside the store, every frame solved with it."""
    import zarr
    import tifffile

    from cm2cl import io
    from cm2cl.cli import main

    sc = Q.render_scene({s.name: s for s in Q.scene_specs()}["mm_issue"])   # a blur and focus shift of every spot
    psf, y = sc.psf, sc.y
    tifffile.imwrite(tmp_path / "psf.tif", psf.astype(np.float32), photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", y.astype(np.float32))
    base = ["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "--max-iter", "60",
            "--psf-refine", "common"]
    assert main(base + ["-o", str(tmp_path / "v.ome.tif"), "--save-psf"]) == 0
    said = capsys.readouterr().out
    assert "PSF refined in 2 rounds, one kernel common to every lenslet" in said, said
    h, meta = io.read_tiff(tmp_path / "v.psf.ome.tif")
    assert h.shape == psf.shape and np.abs(h / h.sum() - psf / psf.sum()).max() > 0.01 * (psf / psf.sum()).max()
    assert "self-calibrated" in meta["extra"]["what"]
    assert main(base + ["-o", str(tmp_path / "w.ome.tif"), "--save-psf", "--padding", "support"]) == 2
    err = capsys.readouterr().err
    assert "--save-psf" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "w.ome.tif").exists()
    kw = dict(max_iter=60, tol=0.0)
    frames = np.stack([y, 1.1 * y])
    s = cm2cl.reconstruct_series(frames, psf, tmp_path / "m.ome.zarr", psf_refine="common", **kw)
    assert s.computed == 2
    h, _ = io.read_tiff(tmp_path / "m.psf.ome.tif")
    np.testing.assert_array_equal(h, cm2cl.reconstruct(frames[0], psf, psf_refine="common", **kw).psf)
    vol = np.asarray(zarr.open_group(str(tmp_path / "m.ome.zarr"), mode="r")["0"])
    one = cm2cl.reconstruct(frames[1], h, psf_refine=0, **kw).volume
    np.testing.assert_allclose(vol[1], one, rtol=1e-5, atol=1e-6 * one.max())


def test_a_round_whose_volume_explains_nothing_keeps_the_psf(rt):
    """A round whose sparse solve leaves the volume empty (here l1 at 1e6 x its weight; the camera model's
    weights did so at 200 photons) has no kernel to fit: the PSF is kept as given, no second round follows, and
    the record says so; the final solve is the plain one's answer from that start."""
    sc = Q.render_scene({s.name: s for s in Q.scene_specs()}["beads"])
    rec = cm2cl.reconstruct(sc.y, sc.psf, psf_refine="common", psf_refine_l1_start=1e6)
    assert len(rec.info["psf_refine"]["per_round"]) == rec.info["psf_refine"]["rounds"] == 1
    r = rec.info["psf_refine"]["per_round"][0]
    assert r["kept"] and r["residual"] >= R.EMPTY_MISFIT and not rec.info["psf_refine"]["refined"]
    from cm2cl.cli.frame import refine_line

    assert refine_line(rec.info["psf_refine"]).startswith("PSF used as given: the refinement's sparse volume")
    np.testing.assert_array_equal(rec.psf, np.asarray(sc.psf, np.float64))
    assert all(k["gain"] == pytest.approx(1.0) and k["rms_width_px"] == 0.0 for k in r["kernels"])
    assert Q.score_beads(rec.volume, sc.beads)["recall"] >= 0.95

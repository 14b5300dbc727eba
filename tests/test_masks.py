"""Saturated and hot pixels: found, reported, and masked in the data term (issue 8 item 12, issue 12
item 3); the weighted data step equals its float64 twin."""

import json

import numpy as np
import pytest
import tifffile

import cm2cl
from cm2cl import reference as ref
from cm2cl.analysis import check_pixels, hot_pixels, mask_weights
from cm2cl.cli import main
from test_admm import bead_problem

P = (64, 80)


def test_saturated_and_hot_pixels_are_found_and_beads_are_not():
    from cm2cl import simulate

    sim = simulate.simulate_scene("demo_beads", seed=2)
    meas = sim.measurement                       # uint16 camera counts with noise, real bead spots
    assert hot_pixels(meas).size > 0             # a fixed 3x ratio flags the in-focus spots of this coarse sensor
    assert hot_pixels(meas, sim.psf).size == 0   # no spot is sharper than the PSF allows
    m = meas.copy()
    m[10, 20] = 65535
    m[100, 7] = min(int(m.max()) * 5, 60000)
    rep = check_pixels(m, psf=sim.psf)
    assert rep["saturated"]["count"] == 1 and rep["saturated"]["first"] == [(10, 20)]
    assert rep["saturated"]["level"] == 65535.0
    assert (100, 7) in rep["hot"]["first"] and (10, 20) in rep["hot"]["first"]
    w = mask_weights(m, ["saturated"])
    assert w[10, 20] == 0 and w.sum() == w.size - 1


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_weighted_data_step_matches_the_twin(rt, dtype):
    if dtype == "float64" and not rt.caps.fp64:
        pytest.skip("no fp64")
    psf, _, y = bead_problem(4)
    rng = np.random.default_rng(8)
    w = (rng.random(y.shape) > 0.1).astype(float) * rng.uniform(0.5, 2.0, y.shape)
    kw = dict(l1=1e-3, tv=1e-3, max_iter=15, tol=0, padded_shape=P, background="none")
    dev = cm2cl.reconstruct(y, psf, dtype=np.dtype(dtype), weights=w, **kw, psf_refine=0)
    twin = ref.admm(y, psf, weights=w, **kw)
    err = np.linalg.norm(dev.volume_padded - twin.volume_padded) / np.linalg.norm(twin.volume_padded)
    assert err < (2e-5 if dtype == "float32" else 1e-12), err
    np.testing.assert_allclose(dev.log_array("data"), twin.log_array("data"), rtol=1e-4)
    plain = cm2cl.reconstruct(y, psf, dtype=np.dtype(dtype), **kw, psf_refine=0)
    assert np.linalg.norm(plain.volume - dev.volume) > 1e-3 * np.linalg.norm(plain.volume)   # the weights act


def test_masking_a_hot_pixel_recovers_the_emitters(rt):
    """One pixel at 100x the brightest bead's peak: unmasked, the volume moves away from the clean frame's
    answer (seen: by 25% of its norm at the defaults, 88% at mu_v = 1); masked, it is the clean frame's answer
    and the four emitters are the four brightest local maxima."""
    psf, x, y = bead_problem(7)
    hot = y.copy()
    hot[5, 33] = 100 * y.max()
    kw = dict(max_iter=150, padded_shape=P)
    truth = {tuple(int(v) for v in p) for p in np.argwhere(x[:, 16:48, 20:60] > 0)}

    def top4(vol):
        from scipy.ndimage import maximum_filter

        peaks = (vol == maximum_filter(vol, size=3)) & (vol > 0)
        idx = np.argwhere(peaks)
        order = np.argsort(vol[peaks])[::-1][:4]
        return {tuple(int(v) for v in idx[i]) for i in order}

    bad = cm2cl.reconstruct(hot, psf, **kw, psf_refine=0)
    assert [tuple(p) for p in hot_pixels(hot, psf)] == [(5, 33)]
    good = cm2cl.reconstruct(hot, psf, weights=mask_weights(hot, ["hot"], psf=psf), **kw, psf_refine=0)
    clean = cm2cl.reconstruct(y, psf, **kw, psf_refine=0)
    assert top4(clean.volume) == truth
    assert top4(good.volume) == truth

    def off(rec):
        return np.linalg.norm(rec.volume - clean.volume) / np.linalg.norm(clean.volume)

    assert off(good) < 0.01 and off(bad) > 0.1      # the hot pixel pulls the unmasked answer away


def test_cli_reports_and_masks(rt, tmp_path, capsys):
    psf, _, y = bead_problem(6)
    meas = (y / y.max() * 3000 + 100).astype(np.uint16)
    meas[3, 4] = 65535
    tifffile.imwrite(tmp_path / "psf.tif", psf.astype(np.float32), photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", meas)
    base = ["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "--offset", "100",
            "--max-iter", "5", "--quiet"]
    assert main(base + ["-o", str(tmp_path / "a.ome.tif")]) == 0
    out = capsys.readouterr().out
    assert "1 saturated pixel(s)" in out and "(3, 4)" in out and "not masked (--mask saturated)" in out
    assert main(base + ["-o", str(tmp_path / "b.ome.tif"), "--mask", "saturated,hot"]) == 0
    assert "masked in the data term" in capsys.readouterr().out
    rec = json.loads((tmp_path / "b.cm2cl.json").read_text())
    assert rec["info"]["pixels"]["saturated"]["count"] == 1 and rec["info"]["pixels"]["masked"] == ["saturated", "hot"]
    assert main(base + ["-o", str(tmp_path / "c.ome.tif"), "--mask", "cold"]) == 2
    assert "--mask: unknown 'cold'" in capsys.readouterr().err and not (tmp_path / "c.ome.tif").exists()


def test_a_reused_solver_takes_new_weights_with_the_background_in_the_model(rt64):
    """A series reuses one solver for frame after frame, each with its own pixel weights: the background's
    fit must weigh the second frame's pixels by the second set of weights, not keep the first set's Q.
    Checked against a fresh solver (the same bits) and against the float64 twin."""
    from cm2cl.solver.admm import ADMMSolver
    from cm2cl.solver.params import ADMMParams

    psf, _, y = bead_problem(4)
    rng = np.random.default_rng(21)
    y = y + 0.05 * y.max() * (1 + np.linspace(0, 1, y.shape[1]))[None, :]   # a haze for b to take
    w1 = rng.uniform(0.5, 2.0, y.shape)
    w2 = (rng.random(y.shape) > 0.2) * rng.uniform(0.2, 3.0, y.shape)
    kw = dict(l1=1e-3, tv=0.0, max_iter=25, tol=0, background="model", psf_refine=0)

    def solver():
        return ADMMSolver(psf, ADMMParams(**kw), dtype=np.float64, backend="cl", padded_shape=P)

    reused = solver()
    first = reused.solve(y, weights=w1).volume_padded
    again = reused.solve(y, weights=w2).volume_padded
    fresh = solver().solve(y, weights=w2).volume_padded
    np.testing.assert_array_equal(again, fresh)
    twin = ref.admm(y, psf, weights=w2, padded_shape=P, **{k: v for k, v in kw.items() if k != "psf_refine"})
    err = np.linalg.norm(again - twin.volume_padded) / np.linalg.norm(twin.volume_padded)
    assert err < 1e-8, err   # the background's twin tolerance (tests/test_terms.py): its NNLS solves differ in rounding
    assert np.linalg.norm(first - again) > 1e-3 * np.linalg.norm(again)     # the two weightings differ

"""The data misfit a solve reaches (``rec.info['misfit']``, :func:`cm2cl.solver.control.data_misfit`): what its
estimator reads on images of known noise and structure, that the device's record equals the float64 forward
model's residual of the answer, and that it tells a PSF that made the frame from one that did not."""

import numpy as np
import pytest

from cm2cl.solver.control import data_misfit


def _smooth_field(shape, rng, scale=12.0):
    """A smooth random field (sum of broad Gaussians), zero mean, unit RMS."""
    yy, xx = np.mgrid[:shape[0], :shape[1]].astype(float)
    f = np.zeros(shape)
    for _ in range(12):
        cy, cx = rng.uniform(0, shape[0]), rng.uniform(0, shape[1])
        f += rng.normal() * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * scale ** 2))
    f -= f.mean()
    return f / np.sqrt(np.mean(f ** 2))


def test_white_noise_reads_one_and_smooth_structure_reads_above_it():
    """White noise of sigma 2: white_rms within 3% of 2 and ratio within 3% of 1 (65k pixels: the estimates'
    sampling error is below 1%). Smooth structure of 3 sigma^2 variance added: the white part still reads sigma
    (the 4-neighbour difference cancels structure 12 px wide to 1-2% of its variance) and the ratio sqrt(1 + 3) = 2.
    Pixels of weight 0 count nowhere, whatever they hold; weights scale the residual by their square root."""
    rng = np.random.default_rng(5)
    shape, sigma = (256, 256), 2.0
    noise = rng.normal(0.0, sigma, shape)
    y = 100.0 + noise
    m = data_misfit(y, np.full(shape, 100.0))
    assert m["pixels"] == 256 * 256
    assert m["white_rms"] == pytest.approx(sigma, rel=0.03) and m["ratio"] == pytest.approx(1.0, abs=0.03)
    assert m["rms"] == pytest.approx(np.sqrt(np.mean(noise ** 2)), rel=1e-12)
    assert m["relative"] == pytest.approx(np.linalg.norm(noise) / np.linalg.norm(y), rel=1e-12)

    structure = np.sqrt(3.0) * sigma * _smooth_field(shape, rng)
    m2 = data_misfit(y + structure, np.full(shape, 100.0))
    assert m2["white_rms"] == pytest.approx(sigma, rel=0.05) and m2["ratio"] == pytest.approx(2.0, rel=0.05)

    w = np.ones(shape)
    w[100:140, 50:90] = 0.0
    spoiled = y.copy()
    spoiled[100:140, 50:90] = 1e6                       # a saturated patch, masked
    mw = data_misfit(spoiled, np.full(shape, 100.0), w)
    assert mw["pixels"] == 256 * 256 - 40 * 40
    assert mw["ratio"] == pytest.approx(1.0, abs=0.03) and mw["rms"] == pytest.approx(sigma, rel=0.03)
    m4 = data_misfit(y, np.full(shape, 100.0), np.full(shape, 4.0))   # weights 4: the residual doubles
    assert m4["rms"] == pytest.approx(2 * m["rms"], rel=1e-12) and m4["ratio"] == pytest.approx(m["ratio"], rel=1e-12)


def test_undefined_parts_are_none():
    """A noise-free exact fit has no white part (ratio None), an all-zero frame no relative misfit, a frame
    whose every pixel is masked nothing at all."""
    y = np.arange(64.0).reshape(8, 8)
    exact = data_misfit(y, y)
    assert exact["rms"] == 0 and exact["white_rms"] == 0 and exact["ratio"] is None and exact["relative"] == 0
    assert data_misfit(np.zeros((8, 8)), np.ones((8, 8)))["relative"] is None
    none = data_misfit(y, y, np.zeros((8, 8)))
    assert none["pixels"] == 0 and none["rms"] is None and none["ratio"] is None


def test_the_solve_records_the_misfit_of_its_answer_through_the_float64_forward_model(rt):
    """The device's record (H x of the last iterate on the device, in float32, plus the background model) equals
    the misfit of the returned answer through the reference package's float64 forward model with the PSF the
    final solve used, for solves stopped by the rule: within 1e-3 relative (the record's iterate is not clipped at
    0, the answer is: at convergence they differ by 1e-4 here, at 150 iterations of an unconverged solve by 1%;
    float32 rounding is 1e-6)."""
    import cm2cl
    from cm2cl.analysis import quality as Q
    from cm2cl.reference import forward

    sc = Q.render_scene(Q.SceneSpec("t", "t", nz=6, shape=(64, 64), n_beads=12, background="haze", bg_level=0.05,
                                    photons=1000.0, seed=3))
    for kw in ({"psf_refine": 0}, {"psf_refine": "common"}):
        rec = cm2cl.reconstruct(sc.y, sc.psf, **kw)
        assert rec.info["converged"]
        h = rec.psf if rec.psf is not None else sc.psf
        vp = np.asarray(rec.volume_padded, np.float64)
        model = forward(h, vp, vp.shape[1:]) + rec.background
        host = data_misfit(sc.y, model)
        rec_m = rec.info["misfit"]
        for k in ("relative", "rms", "white_rms", "ratio"):
            assert rec_m[k] == pytest.approx(host[k], rel=1e-3), (kw, k)
        assert rec_m["pixels"] == 64 * 64


def test_the_ratio_tells_the_psf_that_made_the_frame_from_one_that_did_not(rt):
    """12 beads rendered through the suite's array PSF (1000 photons at the peak), reconstructed with the PSF as
    given: where it made the frame the residual is its noise (ratio 1.08 measured), where the frame's lenslets are
    aberrated (1.56) or its stack lies half a plane deeper (1.49) the residual holds the structure the given PSF
    cannot draw."""
    import cm2cl
    from cm2cl.analysis import quality as Q

    ratio = {}
    for name, mm in (("matched", Q.Mismatch()), ("aberrated", Q.Mismatch(aberration=1.0)),
                     ("deeper", Q.Mismatch(dz=0.5))):
        sc = Q.render_scene(Q.SceneSpec("t", "t", nz=6, shape=(64, 64), n_beads=12, mismatch=mm, photons=1000.0,
                                        seed=3))
        ratio[name] = cm2cl.reconstruct(sc.y, sc.psf, psf_refine=0).info["misfit"]["ratio"]
    assert ratio["matched"] < 1.2
    assert ratio["aberrated"] > 1.35 and ratio["deeper"] > 1.35

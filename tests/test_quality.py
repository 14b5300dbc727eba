"""The quality suite: its scores on volumes whose right answer is known, its scene renderer (the mismatched
PSFs really differ, the background and photon counts are what was asked), its configuration parsing, and
one quick scene through the tool's Python API."""

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cm2cl.analysis import quality as Q

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

NZ, SHAPE = 10, (64, 64)


def beads_and_volume(n=20, seed=4, sigma=0.8):
    beads = Q.place_beads(n, NZ, SHAPE, seed, margin=6)
    amp = np.random.default_rng(seed).uniform(0.5, 1.0, n)
    return beads, Q.bead_volume(beads, amp, NZ, SHAPE, sigma)


# ------------------------------------------------------------------------------------------------- scores
@pytest.mark.parametrize("sigma", [0.0, 0.8])
def test_the_truth_scores_perfectly(sigma):
    beads, vol = beads_and_volume(sigma=sigma)
    s = Q.score_beads(vol, beads)
    assert (s["n_true"], s["n_detected"], s["n_matched"], s["false_maxima"]) == (20, 20, 20, 0)
    assert s["matched"] == list(range(20))
    assert s["recall"] == 1.0 and s["f1"] == 1.0 and s["false_per_10"] == 0.0
    assert s["axial_err"] == pytest.approx(0.0, abs=1e-12)
    assert s["lateral_err"] == pytest.approx(0.0, abs=1e-9)
    assert Q.nrmse(vol, vol) == pytest.approx(0.0, abs=1e-12)
    assert Q.nrmse(7.5 * vol, vol) == pytest.approx(0.0, abs=1e-12)     # the scale is free
    assert Q.energy_near(vol, vol) == 1.0


def test_bead_moments_read_a_blobs_light_and_spread():
    """A 3D Gaussian of known widths gives back its sum, its peak and its standard deviations (the window holds
    +-5 sigma laterally, +-4 axially: truncation changes them by < 1e-3); a single voxel has no spread; the
    same light spread over three planes keeps its flux and loses its peak; an empty window gives NaN moments."""
    nz, ny, nx = 13, 31, 31
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    sz, sl, c = 1.5, 1.2, (6, 15, 16)
    g = np.exp(-0.5 * ((z - c[0]) ** 2 / sz ** 2 + ((y - c[1]) ** 2 + (x - c[2]) ** 2) / sl ** 2))
    m = Q.bead_moments(g, [c], half=(6, 6, 6))
    assert m["flux"][0] == pytest.approx(g.sum()) and m["peak"][0] == pytest.approx(1.0)
    assert m["axial_sd"][0] == pytest.approx(sz, rel=1e-3)
    assert m["lateral_rms"][0] == pytest.approx(sl * math.sqrt(2), rel=1e-3)
    point = np.zeros((nz, ny, nx))
    point[c] = 3.0
    spread = np.zeros_like(point)
    spread[c[0] - 1:c[0] + 2, c[1], c[2]] = 1.0
    mp, ms = Q.bead_moments(point, [c]), Q.bead_moments(spread, [c])
    assert (mp["flux"][0], mp["peak"][0], mp["axial_sd"][0], mp["lateral_rms"][0]) == (3.0, 3.0, 0.0, 0.0)
    assert ms["flux"][0] == 3.0 and ms["peak"][0] == 1.0
    assert ms["axial_sd"][0] == pytest.approx(math.sqrt(2 / 3)) and ms["lateral_rms"][0] == 0.0
    # negative values are not light; a window at the corner is clipped to the volume
    e = Q.bead_moments(-point, [c, (0, 0, 0)])
    assert e["flux"].tolist() == [0.0, 0.0] and np.isnan(e["axial_sd"]).all()
    with pytest.raises(Q.InputError, match="half"):
        Q.bead_moments(point, [c], half=(1, -1, 1))


def test_a_bead_two_planes_off_is_lost_and_false_one_plane_off_is_matched():
    beads, vol = beads_and_volume(sigma=0.0)
    z, y, x = beads[0]
    dz = 2 if z + 2 < NZ else -2
    moved = vol.copy()
    moved[z + dz, y, x], moved[z, y, x] = vol[z, y, x], 0.0
    s = Q.score_beads(moved, beads)
    assert s["n_matched"] == 19 and s["recall"] == pytest.approx(0.95) and s["matched"] == list(range(1, 20))
    assert s["false_maxima"] == 1 and s["false_per_10"] == pytest.approx(0.5)
    assert s["axial_err"] == pytest.approx(0.0, abs=1e-12)
    # one plane off: still matched (+-1 plane), the mean axial error is 1 / 20
    one = vol.copy()
    step = 1 if z + 1 < NZ else -1
    one[z + step, y, x], one[z, y, x] = vol[z, y, x], 0.0
    s1 = Q.score_beads(one, beads)
    assert s1["recall"] == 1.0 and s1["false_maxima"] == 0
    assert s1["axial_err"] == pytest.approx(1 / 20)
    # errors of both signs: the mean of their magnitudes
    both = one.copy()
    z2, y2, x2 = beads[1]
    step2 = -1 if z2 > 0 else 1
    if step2 == step:
        z2, y2, x2 = next(b for b in beads[2:] if (b[0] > 0 if step > 0 else b[0] < NZ - 1))
        step2 = -step
    both[z2 + step2, y2, x2], both[z2, y2, x2] = vol[z2, y2, x2], 0.0
    assert Q.score_beads(both, beads)["axial_err"] == pytest.approx(2 / 20)
    # laterally: 2 px matches (lateral error 2 / 20), 3 px does not
    for d, matched in ((2, True), (3, False)):
        lat = vol.copy()
        xx = x + d if x + d < SHAPE[1] else x - d
        lat[z, y, xx], lat[z, y, x] = vol[z, y, x], 0.0
        sl = Q.score_beads(lat, beads)
        if matched:
            assert sl["recall"] == 1.0 and sl["lateral_err"] == pytest.approx(d / 20)
        else:
            assert sl["recall"] == pytest.approx(0.95) and sl["false_maxima"] == 1


def test_spurious_maxima_are_counted_and_faint_ones_are_not():
    beads, vol = beads_and_volume(sigma=0.0)
    occupied = {tuple(b) for b in beads}
    rng = np.random.default_rng(9)
    spur = vol.copy()
    added = 0
    while added < 3:
        p = (rng.integers(NZ), rng.integers(SHAPE[0]), rng.integers(SHAPE[1]))
        far = all(abs(p[0] - b[0]) > 1 or math.hypot(p[1] - b[1], p[2] - b[2]) > 3 for b in beads)
        if far and p not in occupied and spur[p] == 0:
            spur[p] = 0.5 * vol.max()
            occupied.add(p)
            added += 1
    s = Q.score_beads(spur, beads)
    assert s["recall"] == 1.0 and s["false_maxima"] == 3 and s["false_per_10"] == pytest.approx(1.5)
    assert s["f1"] == pytest.approx(40 / 43)
    # below 20% of the maximum: not a detection
    faint = vol.copy()
    faint[spur != vol] = 0.15 * vol.max()
    assert Q.score_beads(faint, beads)["false_maxima"] == 0


def test_nrmse_and_energy_near_values():
    t = np.zeros((4, 16, 16))
    t[2, 8, 8] = 1.0
    assert Q.nrmse(np.zeros_like(t), t) == 1.0
    other = np.zeros_like(t)
    other[0, 2, 2] = 5.0
    assert Q.nrmse(other, t) == pytest.approx(1.0)                       # orthogonal
    x = t.copy()
    x[2, 8, 12] = 1.0                                                    # half the energy 4 px off
    assert Q.nrmse(x, t) == pytest.approx(math.sqrt(0.5))                # best scale 1/2: (1/2, 1/2) off (1, 0)
    assert Q.energy_near(x, t) == pytest.approx(0.5)
    x[2, 8, 10] = 2.0                                                    # exactly 2 voxels away: near
    x[1, 7, 9] = 1.0                                                     # sqrt 3 away (diagonal): near
    x[0, 8, 8] = 1.0                                                     # 2 planes away: near
    x[3, 10, 10] = 1.0                                                   # sqrt 9 = 3 away: not
    assert Q.energy_near(x, t) == pytest.approx(5.0 / 7.0)
    assert Q.energy_near(-x, t) != Q.energy_near(-x, t)                  # all-negative: NaN


def test_targets_and_quality_value():
    row = {"kind": "beads", "recall": 0.95, "false_per_10": 1.0, "axial_err": 0.5, "f1": 0.9}
    assert all(Q.targets_met(row).values())
    assert not Q.targets_met({**row, "recall": 0.94})["recall"]
    assert not Q.targets_met({**row, "axial_err": float("nan")})["axial_err"]
    assert Q.quality_value(row) == 0.9
    fib = {"kind": "fibres", "energy_near": 0.59}
    assert Q.targets_met(fib) == {"energy_near": False} and Q.quality_value(fib) == 0.59


# ------------------------------------------------------------------------------------------------- scenes
def test_nominal_psf_model():
    psf = Q.array_psf(NZ, SHAPE)
    assert psf.shape == (NZ,) + SHAPE and np.all(psf >= 0)
    assert psf.sum(axis=(1, 2)) == pytest.approx(np.ones(NZ), abs=1e-9)
    # the foci spread with depth: the mean distance of the light from the axis grows with the plane
    Y, X = np.mgrid[:SHAPE[0], :SHAPE[1]] - np.array(SHAPE)[:, None, None] // 2
    rad = np.array([(np.hypot(Y, X) * p).sum() for p in psf])
    assert np.all(np.diff(rad) > 0)
    # in focus mid-stack, blurrier towards both ends
    peak = psf.max(axis=(1, 2))
    assert peak[NZ // 2] > 1.5 * peak[0] and peak[NZ // 2] > 1.5 * peak[-1]


def test_mismatches_differ_from_the_nominal_psf_as_described():
    nom = Q.array_psf(NZ, SHAPE)

    def rel(a):
        return np.linalg.norm(a - nom) / np.linalg.norm(nom)

    blur = Q.array_psf(NZ, SHAPE, Q.Mismatch(blur=1.0))
    assert rel(blur) > 0.15 and np.all(blur.max(axis=(1, 2)) < 0.85 * nom.max(axis=(1, 2)))
    assert blur.sum(axis=(1, 2)) == pytest.approx(np.ones(NZ), abs=1e-9)          # blur keeps the light
    # off in depth: the model in the plane coordinate, so a whole plane's offset is the next plane
    one = Q.array_psf(NZ + 1, SHAPE, Q.Mismatch(dz=1.0))
    assert one[:-1] == pytest.approx(np.roll(Q.array_psf(NZ + 1, SHAPE), -1, axis=0)[:-1], abs=1e-12)
    half = Q.array_psf(NZ, SHAPE, Q.Mismatch(dz=0.4))
    assert rel(half) > 0.1
    # aberrated: an edge lenslet's spot is elongated (second moments differ), the centre one stays near round
    ab = Q.array_psf(NZ, SHAPE, Q.Mismatch(aberration=1.0))
    assert rel(ab) > 0.3
    z = NZ // 2
    cy, cx = SHAPE[0] // 2, SHAPE[1] // 2
    pitch = round(0.27 * SHAPE[0])
    yy, xx = np.mgrid[-8:9, -8:9]

    def moments(p):
        win = p[z, cy - 8:cy + 9, cx + pitch - 8:cx + pitch + 9]
        m = win / win.sum()
        my, mx = (m * yy).sum(), (m * xx).sum()
        return mx, (m * (yy - my) ** 2).sum(), (m * (xx - mx) ** 2).sum()

    mx, vy, vx = moments(ab)
    mx0, vy0, vx0 = moments(nom)
    assert vx0 == pytest.approx(vy0, rel=1e-6)   # the nominal spot is round
    assert vx > 1.5 * vy                   # the edge lenslet on the x axis is stretched along x (radially)
    assert mx > mx0 + 0.3                  # and its coma tail throws light outward
    # truncated: the outer lenslets lose light, the centre lenslet keeps it
    tr = Q.array_psf(NZ, SHAPE, Q.Mismatch(vignette=0.6))
    assert np.all(tr.sum(axis=(1, 2)) < 0.75)
    c = (slice(None), slice(cy - 6, cy + 7), slice(cx - 6, cx + 7))
    assert tr[c].sum() == pytest.approx(nom[c].sum(), rel=1e-3)   # (only the neighbours' far tails differ)
    corner = (slice(None), slice(cy - pitch - 6, cy - pitch + 7), slice(cx - pitch - 6, cx - pitch + 7))
    assert tr[corner].sum() < 0.5 * nom[corner].sum()


@pytest.mark.parametrize("kind", ["haze", "ramp", "blob", "random"])
def test_background_fields(kind):
    f = Q.background_field(SHAPE, kind, seed=3)
    assert f.shape == SHAPE and f.max() == pytest.approx(1.0) and f.min() >= 0
    assert np.array_equal(f, Q.background_field(SHAPE, kind, seed=3))
    # smooth: neighbouring pixels differ by a few percent of the range at most
    assert np.abs(np.diff(f, axis=1)).max() < 0.1
    assert not np.allclose(f, Q.background_field(SHAPE, kind, seed=4))


def small(**kw):
    base = Q.SceneSpec("t", "test", nz=NZ, shape=SHAPE, n_beads=12, seed=2)
    return replace(base, **kw)


def test_beads_between_planes_are_imaged_by_the_psf_of_their_own_depth():
    """depth_jitter: each bead's depth is its plane plus a draw within +-jitter (inside the stack), its image
    the PSF rendered at that depth (array_psf's planes; plane coordinate t + 0.4 is the stack 0.4 plane off),
    and the scored positions carry the fractional depth."""
    assert Q.array_psf(NZ, SHAPE, planes=np.arange(NZ) + 0.4) == pytest.approx(
        Q.array_psf(NZ, SHAPE, Q.Mismatch(dz=0.4)), abs=1e-12)
    spec = small(depth_jitter=0.5, n_beads=5, photons=1000.0)
    sc = Q.render_scene(spec)
    on = Q.render_scene(replace(spec, depth_jitter=0.0))
    t = sc.beads[:, 0]
    assert np.all(np.abs(t - on.beads[:, 0]) <= 0.5) and np.all((t >= 0) & (t <= NZ - 1))
    assert np.abs(t - np.round(t)).max() > 0.1                         # some bead really between planes
    np.testing.assert_array_equal(sc.beads[:, 1:], on.beads[:, 1:])
    # the noiseless image: each bead's blob through the PSF of its own depth, written here bead by bead
    img = 0.0
    for b, (z, y, x) in enumerate(on.beads):
        one = np.zeros((1,) + SHAPE)
        one[0, y - 1:y + 2, x - 1:x + 2] = on.truth[z, y - 1:y + 2, x - 1:x + 2]
        img = img + Q.object_image(Q.array_psf(NZ, SHAPE, planes=[t[b]]), one)
    np.testing.assert_allclose(sc.signal, img * (1000.0 / img.max()), atol=1e-6)
    assert not np.allclose(sc.signal, on.signal, atol=1.0)


def test_scene_background_level_photons_and_noise_are_as_asked():
    spec = small(background="blob", bg_level=0.15, photons=800.0, mismatch=Q.Mismatch(blur=0.5))
    sc = Q.render_scene(spec)
    assert sc.signal.max() == pytest.approx(800.0)                      # photons at the object image's peak
    assert sc.bg.max() == pytest.approx(0.15 * 800.0)                   # background: 15% of that peak
    assert np.allclose(sc.expected, sc.signal + sc.bg)
    assert not np.allclose(sc.psf_true, sc.psf)                         # the data are made with the other PSF
    assert np.allclose(sc.psf, Q.array_psf(NZ, SHAPE))                  # the reconstruction gets the nominal one
    assert np.allclose(sc.raw - spec.camera.offset, sc.y)
    # at the peak pixel the counts are the expected photons within Poisson error (5 sigma)
    p = np.unravel_index(sc.signal.argmax(), SHAPE)
    sd = math.sqrt(sc.expected[p] + spec.camera.read_noise ** 2)
    assert abs(sc.y[p] - sc.expected[p]) < 5 * sd
    # over the frame: the mean is the expectation and the variance Poisson + read noise
    n = sc.y.size
    assert abs((sc.y - sc.expected).sum()) < 5 * math.sqrt(sc.expected.sum() + n * spec.camera.read_noise ** 2)
    var = ((sc.y - sc.expected) ** 2).mean() / (sc.expected + spec.camera.read_noise ** 2).mean()
    assert var == pytest.approx(1.0, abs=0.05)
    # the same spec renders the same scene; another seed another
    assert np.array_equal(Q.render_scene(spec).y, sc.y)
    assert not np.array_equal(Q.render_scene(replace(spec, seed=3)).y, sc.y)


def test_photons_scale_the_counts_and_the_truth_is_on_the_reconstruction_grid():
    lo, hi = Q.render_scene(small(photons=200.0)), Q.render_scene(small(photons=5000.0))
    assert lo.expected.max() == pytest.approx(200.0) and hi.expected.max() == pytest.approx(5000.0)
    assert np.allclose(hi.expected / 25.0, lo.expected)
    # the object image is C H x of the truth with the measurement PSF, by the solver's own conventions
    from cm2cl.reference import embed, forward

    P = (128, 128)
    img = forward(lo.psf_true, embed(lo.truth, P), P)
    assert np.allclose(lo.signal, np.where(img < 1e-9 * img.max(), 0, img) * 200.0 / img.max(), rtol=1e-9, atol=1e-9)
    # beads sit at their listed voxels; edge-plane scenes only in those planes
    assert np.all(lo.truth[tuple(lo.beads.T)] >= 0.5)
    edge = Q.render_scene(small(bead_planes=(0, NZ - 1)))
    assert set(edge.beads[:, 0]) <= {0, NZ - 1}
    fib = Q.render_scene(small(kind="fibres", n_fibres=3))
    assert fib.beads is None and fib.truth.max() > 0.5
    assert np.count_nonzero(fib.truth.max(axis=(1, 2))) >= NZ // 2      # fibres run through depth


def test_suite_specs_are_renderable_and_distinct():
    names = [s.name for s in Q.scene_specs()]
    assert len(names) == len(set(names)) >= 15
    q = Q.scene_specs(quick=True)
    assert {s.name for s in q} <= set(names) and all(s.shape == (96, 96) for s in q)


def test_calibration_frame_shares_the_optics_not_the_beads_or_the_noise():
    spec = {s.name: s for s in Q.scene_specs()}["fibres_mm"]
    cal = Q.calibration_spec(spec)
    assert (cal.kind, cal.n_beads, cal.seed) == ("beads", 40, spec.seed + Q.CALIBRATION_SEED_OFFSET)
    assert (cal.mismatch, cal.background, cal.bg_level, cal.photons, cal.camera, cal.nz, cal.shape) == (
        spec.mismatch, spec.background, spec.bg_level, spec.photons, spec.camera, spec.nz, spec.shape)
    small = replace(spec, nz=NZ, shape=SHAPE)
    sc, cs = Q.render_scene(small), Q.render_scene(Q.calibration_spec(small))
    np.testing.assert_array_equal(cs.psf_true, sc.psf_true)       # the same optics
    np.testing.assert_array_equal(cs.psf, sc.psf)                 # and the same nominal stack given
    assert not np.allclose(cs.psf_true, cs.psf)                   # which they differ from
    assert cs.beads is not None and len(cs.beads) == 40 and sc.beads is None
    # the background is of the same kind and level, its field drawn with the calibration frame's own seed
    assert cs.bg.max() == pytest.approx(sc.bg.max(), rel=0.5) and not np.allclose(cs.bg, sc.bg)


# ------------------------------------------------------------------------------------------------- the tool
def test_config_parsing_and_refusal_before_any_solve(monkeypatch):
    import quality_suite as qs

    assert qs.parse_config("w=tv_noise_ratio=0,l1_plane_power=2") == ("w", {"tv_noise_ratio": 0, "l1_plane_power": 2})
    assert qs.parse_config("s=padded_shape=(256, 256),penalty=fixed,l1=1e-3") == (
        "s", {"padded_shape": (256, 256), "penalty": "fixed", "l1": 1e-3})
    assert qs.parse_config("c=camera={'gain': 2, 'offset': 100},background=model") == (
        "c", {"camera": {"gain": 2, "offset": 100}, "background": "model"})
    assert qs.parse_config("plain") == ("plain", {})
    with pytest.raises(qs.ConfigError):
        qs.parse_config("x=notkeyvalue")

    def no_solve(*a, **k):
        raise AssertionError("solved before refusing the configuration")

    monkeypatch.setattr(qs.cm2cl, "reconstruct", no_solve)
    for bad, word in (("x=not_a_keyword=1", "not_a_keyword"), ("x=tol=-1", "tol"), ("x=callback=1", "callback")):
        with pytest.raises(qs.ConfigError, match=word) as exc:
            qs.run_suite([bad], scenes=["beads"], quick=True)
        assert "\n" not in str(exc.value)
    with pytest.raises(qs.ConfigError, match="unknown scene"):
        qs.run_suite({}, scenes=["nope"], quick=True)
    assert qs.main(["--quick", "--scenes", "beads", "--config", "x=nope=1"]) == 2


def test_suite_psf_calibrated_solves_with_the_stack_refined_on_the_calibration_frame(monkeypatch):
    import quality_suite as qs

    with pytest.raises(qs.ConfigError, match="suite_psf"):
        qs.run_suite(["x=suite_psf=measured"], scenes=["beads"], quick=True)
    real = qs.cm2cl.reconstruct
    calls = []

    def spy(y, psf, **kw):   # short solves, one round of refinement: what is checked is which frame and PSF
        rec = real(y, psf, **{**kw, "max_iter": min(kw.get("max_iter", 30), 30), "psf_refine": "common"})
        calls.append((np.array(y), np.array(psf), rec, kw))
        return rec

    monkeypatch.setattr(qs.cm2cl, "reconstruct", spy)
    spec = {s.name: s for s in Q.scene_specs(quick=True)}["mm_all"]
    sc, cs = Q.render_scene(spec), Q.render_scene(Q.calibration_spec(spec))
    logged = []
    rows = qs.run_suite({"cal": {"suite_psf": "calibrated"}}, scenes=["mm_all"], quick=True, log=logged.append)
    assert {r["config"] for r in rows} == {"defaults", "cal"}
    # the calibration: the calibration frame (not the scene's) with the nominal stack, at the defaults
    y0, psf0, rec0, kw0 = calls[0]
    assert kw0 == {}
    np.testing.assert_array_equal(y0, cs.y)
    np.testing.assert_array_equal(psf0, sc.psf)
    assert rec0.psf is not None and not np.allclose(rec0.psf, sc.psf)
    assert "calibration frame" in logged[0]
    # every later solve is the scene's frame: 'defaults' with the nominal stack, 'cal' with the refined one
    later = calls[1:]
    assert all(np.array_equal(y, sc.y) for y, _, _, _ in later)
    given = [c for c in later if np.array_equal(c[1], sc.psf)]
    refined = [c for c in later if np.array_equal(c[1], rec0.psf)]
    assert len(given) + len(refined) == len(later) and given and refined
    assert sum(r["config"] == "cal" and not r["reused"] for r in rows) == len(refined)
    # the real data have no calibration frame: the configuration is skipped there and the summary says so
    logged.clear()
    assert qs.run_scene("dc3d", "real", sc.psf, sc.y, {"cal": {"suite_psf": "calibrated"}}, True,
                        log=logged.append) == []
    assert "no calibration frame" in logged[0]
    cells = qs.summary(rows, qs.normalise_configs({"cal": {"suite_psf": "calibrated"}}))
    assert cells[-1].count("of 1") == 2


def test_quick_scene_through_the_api_has_every_column(tmp_path):
    import quality_suite as qs

    logged = []
    rows = qs.run_suite({"tv0": {"tv_noise_ratio": 0}}, scenes=["beads"], quick=True, mip_dir=tmp_path,
                        log=logged.append)
    assert [(r["config"], r["setting"]) for r in rows] == [(c, s) for c in ("defaults", "tv0") for s in qs.SETTINGS]
    assert len(logged) == len(rows)
    for r in rows:
        assert set(qs.COLUMNS) <= set(r)
        for k in ("recall", "false_maxima", "false_per_10", "f1", "nrmse", "energy_near", "residual", "seconds"):
            assert np.isfinite(r[k]), (k, r)
        assert 0 <= r["recall"] <= 1 and 0 <= r["energy_near"] <= 1 and r["residual"] < 1
        assert r["n_beads"] == 15
    by = {(r["config"], r["setting"]): r for r in rows}
    assert by["defaults", "50"]["iterations"] == 50 and by["defaults", "200"]["iterations"] == 200
    assert by["defaults", "converged"]["stop"] in ("converged", "max_iter")
    assert (tmp_path / "quality_beads.png").stat().st_size > 10000
    # reuse: the 'defaults' row taken from another run equals the 'defaults' run itself (the stopping rule does
    # not change the iterates; if the solver ever makes it, run the suite with --no-reuse)
    own = qs.run_suite({}, scenes=["beads"], quick=True, reuse=False, log=lambda s: None)
    d = {r["setting"]: r for r in own}["defaults"]
    assert not d["reused"] and by["defaults", "defaults"]["reused"]
    assert (d["iterations"], d["stop"]) == (by["defaults", "defaults"]["iterations"], by["defaults", "defaults"]["stop"])
    for k in ("recall", "false_maxima", "nrmse", "energy_near", "residual"):
        assert d[k] == pytest.approx(by["defaults", "defaults"][k], rel=1e-6), k
    text = qs.write_doc(tmp_path / "q.md", rows, qs.normalise_configs({"tv0": {"tv_noise_ratio": 0}}), "cmd", 1.0,
                        True, 2, [])
    assert "| beads |" in text and qs.HAND_MARK in text
    # the hand-written part survives a rewrite
    (tmp_path / "q.md").write_text(text + "my notes\n")
    assert "my notes" in qs.write_doc(tmp_path / "q.md", rows, qs.normalise_configs({}), "cmd", 1.0, True, 2, [])


def test_random_scenes_draw_every_range_reproducibly():
    """tools/random_scenes.py's frames: the same seed draws the same frames, another seed others; over 200 draws
    every background kind, blur, depth offset and bead count occurs, and levels and photons stay in their ranges
    (photons log-uniform: about half below their geometric mean sqrt(200 x 5000) = 1000)."""
    import random_scenes as rs

    a, b = rs.draw(57, 200), rs.draw(57, 200)
    assert a == b and rs.draw(58, 5) != a[:5]
    assert {s.background for s in a} == set(rs.BACKGROUNDS)
    assert {s.mismatch.blur for s in a} == set(rs.BLURS) and {s.mismatch.dz for s in a} == set(rs.DEPTHS)
    assert {s.n_beads for s in a} == set(rs.BEADS)
    assert all(0.0 <= s.bg_level <= 0.2 and 200.0 <= s.photons <= 5000.0 for s in a)
    assert 0.35 < np.mean([s.photons < 1000.0 for s in a]) < 0.65
    assert len({s.seed for s in a}) > 150          # the scenes' own seeds differ: 200 different frames

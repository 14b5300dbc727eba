"""Attenuation by a scattering sample (cm2cl.solver.attenuation): each plane's PSF scaled by its ballistic
fraction exp(-d / l_s), so that the volume holds the emitters' brightness before the sample dimmed them."""

import numpy as np
import pytest

import cm2cl
from cm2cl.analysis import quality as Q
from cm2cl.errors import InputError
from cm2cl.solver.attenuation import ballistic_fractions

DEPTHS = np.array([-100.0, 0.0, 100.0, 200.0, 300.0, 400.0])
LS = 200.0
PHOTONS = 3000.0


def test_ballistic_fractions_are_exp_of_the_depth_below_the_surface():
    # written from the definition: the shallowest plane is the surface unless one is given; above it, 1
    np.testing.assert_allclose(ballistic_fractions(DEPTHS, LS), np.exp(-(DEPTHS + 100.0) / LS), rtol=1e-15)
    a = ballistic_fractions(DEPTHS, LS, surface_um=50.0)
    np.testing.assert_allclose(a, [1, 1, np.exp(-0.25), np.exp(-0.75), np.exp(-1.25), np.exp(-1.75)], rtol=1e-15)


def _scene(seed=3):
    """Beads of equal brightness, two per plane, imaged through a sample that attenuates plane i by a_i."""
    nz, shape = len(DEPTHS), (64, 64)
    psf = Q.array_psf(nz, shape)
    rng = np.random.default_rng(seed)
    beads = Q.place_beads(2 * nz, nz, shape, seed, planes=tuple(np.repeat(np.arange(nz), 2)), margin=12)
    truth = Q.bead_volume(beads, np.ones(len(beads)), nz, shape)
    a = ballistic_fractions(DEPTHS, LS)
    y = Q.object_image(psf * a[:, None, None], truth)
    y = rng.poisson(np.maximum(y, 0) / y.max() * PHOTONS) / PHOTONS * y.max()
    return psf, y, beads


def _peaks(vol, beads):
    return np.array([vol[int(z), int(r) - 2:int(r) + 3, int(c) - 2:int(c) + 3].sum() for z, r, c in beads])


def test_attenuation_is_the_psf_scaled_plane_by_plane_and_restores_deep_emitters(rt):
    """The option is the solve with the stack scaled by a_i (bit for bit); beads 300-400 um deep, dimmed 5-7x by
    the sample, come back as bright as the shallow ones (within 15%), where without it they read dimmed."""
    psf, y, beads = _scene()
    kw = dict(max_iter=300, depths_um=DEPTHS)
    rec = cm2cl.reconstruct(y, psf, scattering_length_um=LS, **kw)
    a = ballistic_fractions(DEPTHS, LS)
    np.testing.assert_array_equal(rec.volume, cm2cl.reconstruct(y, psf * a[:, None, None], **kw).volume)
    assert rec.info["attenuation"]["ballistic_fraction"] == pytest.approx(list(a))
    plain = cm2cl.reconstruct(y, psf, **kw)
    # planes 2, 3 lie 300 and 400 um below the surface (a = 0.22, 0.14); planes 0, 1 at 0 and 100 um. (The
    # last two planes, the stack's end, lose 30-60% of a bead with or without the option: not attenuation.)
    deep, shallow = (beads[:, 0] >= 2) & (beads[:, 0] <= 3), beads[:, 0] <= 1
    with_att, without = _peaks(rec.volume, beads), _peaks(plain.volume, beads)
    ratio_with = with_att[deep].mean() / with_att[shallow].mean()
    ratio_without = without[deep].mean() / without[shallow].mean()
    assert 0.85 < ratio_with < 1.15, ratio_with        # measured 0.95
    assert ratio_without < 0.45, ratio_without         # measured 0.32: (0.22 + 0.14) / (1 + 0.61) = 0.22 expected


def test_attenuation_refuses_what_it_cannot_do(rt):
    psf, y, _ = _scene()
    with pytest.raises(InputError, match="depths"):
        cm2cl.reconstruct(y, psf, scattering_length_um=LS)
    with pytest.raises(InputError, match="surface_um: only with a scattering length"):
        cm2cl.reconstruct(y, psf, surface_um=0.0, depths_um=DEPTHS)
    with pytest.raises(InputError, match="scattering_length_um"):
        cm2cl.reconstruct(y, psf, scattering_length_um=-5.0, depths_um=DEPTHS)


def test_series_and_cli_take_the_attenuation(rt, tmp_path):
    """A series solves every frame with the attenuated model (each frame equals the single-frame solve), a
    series without depths is refused before its store exists, and the command line's flag reaches the record."""
    import json

    import zarr

    from cm2cl import io
    from cm2cl.cli import main

    psf, y, _ = _scene()
    kw = dict(max_iter=30, tol=0.0, scattering_length_um=LS)
    frames = np.stack([y, 0.9 * y])
    io.write_tiff(tmp_path / "psf.ome.tif", psf.astype(np.float32), voxel_size_um=(100.0, 2.0, 2.0),
                  depths_um=DEPTHS)
    s = cm2cl.reconstruct_series(frames, tmp_path / "psf.ome.tif", tmp_path / "s.ome.zarr", **kw)
    assert s.computed == 2
    vol = np.asarray(zarr.open_group(str(tmp_path / "s.ome.zarr"), mode="r")["0"])
    # the defaults refine the PSF on frame 0 (psf_refine='common', attenuated like every frame) and keep it in
    # the clear-medium units beside the store; frame 1 is the single-frame solve with that stack
    h, _ = io.read_tiff(tmp_path / "s.psf.ome.tif")
    assert h.shape == psf.shape and not np.allclose(h, psf.astype(np.float32))
    one = cm2cl.reconstruct(frames[1], h, depths_um=DEPTHS, psf_refine=0, **kw).volume
    np.testing.assert_allclose(vol[1], one, rtol=1e-5, atol=1e-5 * one.max())
    with pytest.raises(InputError, match="depths"):
        cm2cl.reconstruct_series(frames, psf, tmp_path / "n.ome.zarr", **kw)
    assert not (tmp_path / "n.ome.zarr").exists()
    import tifffile

    tifffile.imwrite(tmp_path / "meas.tif", y.astype(np.float32))
    out = tmp_path / "v.ome.tif"
    assert main(["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.ome.tif"), "-o", str(out),
                 "--max-iter", "20", "--quiet", "--scattering-length-um", str(LS), "--surface-um", "0"]) == 0
    info = json.loads((tmp_path / "v.cm2cl.json").read_text())["info"]
    assert info["attenuation"]["surface_um"] == 0.0
    assert info["attenuation"]["ballistic_fraction"] == pytest.approx(list(ballistic_fractions(DEPTHS, LS, 0.0)))


def test_tiles_solve_with_the_attenuated_stack(rt):
    """Lateral tiles: the option is the tiled solve of the stack scaled by a_i (same bits), with the depths
    given; without them it is refused."""
    from cm2cl.jobs.tiles import reconstruct_tiled

    nz, shape = len(DEPTHS), (64, 64)
    yy, xx = np.mgrid[:64, :64]
    psf = np.stack([np.exp(-((yy - 32) ** 2 + (xx - 32) ** 2) / (2 * (1 + 0.3 * i) ** 2)) for i in range(nz)])
    x = np.zeros((nz,) + shape)
    x[np.arange(nz), 10 + 7 * np.arange(nz), 12 + 6 * np.arange(nz)] = 1.0
    y = Q.object_image(psf, x)
    a = ballistic_fractions(DEPTHS, LS)
    got, _ = reconstruct_tiled(y, psf, (32, 32), max_iter=10, depths_um=DEPTHS, scattering_length_um=LS)
    want, _ = reconstruct_tiled(y, psf * a[:, None, None], (32, 32), max_iter=10, depths_um=DEPTHS)
    np.testing.assert_array_equal(got, want)
    with pytest.raises(InputError, match="depths"):
        reconstruct_tiled(y, psf, (32, 32), max_iter=10, scattering_length_um=LS)


# --- scattering_length_um='auto': l_s estimated from the answer (cm2cl.analysis.attenuation) ---------------------

def _blob_volume(ls, seed=0, nz=12, per_plane=30, spread=(0.5, 1.5), depths=None, trend=None):
    """A volume of 3 x 3 Gaussian blobs, ``per_plane`` in each plane with brightness uniform in ``spread``,
    plane i dimmed by exp(-d_i / ls) (ls None: not at all) or by ``trend`` (nz,), and a little noise."""
    rng = np.random.default_rng(seed)
    depths = np.arange(nz) * 100.0 if depths is None else depths
    shape = (96, 96)
    beads = Q.place_beads(per_plane * nz, nz, shape, seed, planes=tuple(np.repeat(np.arange(nz), per_plane)),
                          margin=4, min_lateral=5.0, min_axial=1)
    amp = rng.uniform(*spread, len(beads))
    vol = Q.bead_volume(beads, amp, nz, shape)
    f = np.ones(nz) if ls is None else np.exp(-(depths - depths.min()) / ls)
    if trend is not None:
        f = f * trend
    vol *= f[:, None, None]
    return vol + np.abs(rng.normal(0.0, 0.002, vol.shape)), depths


def test_the_estimate_reads_the_decay_of_the_emitters_light_with_depth():
    """Blobs of brightness spread 3x (0.5-1.5), dimmed with depth by exp(-d / l_s): the estimate is within 10% of
    l_s for l_s 300 and 800 um over 1.1 mm (the last planes' dimmest blobs fall below the detector's 10% of
    the peak; the rounds on the brightened volume bring them back into the medians), its interval holds l_s,
    and it is applied."""
    from cm2cl.analysis.attenuation import estimate_scattering_length

    for ls in (300.0, 800.0):
        vol, z = _blob_volume(ls)
        est = estimate_scattering_length(vol, z)
        assert est["scattering_length_um"] == pytest.approx(ls, rel=0.10), (ls, est)
        lo, hi = est["rate_interval_per_um"]
        assert lo <= 1.0 / ls <= hi, (ls, est)
        assert est["planes"] == 8 and est["reason"] is None     # the planes but two at each end
    # one round (no brightening) reads the decay from the brightest deep blobs only: less than there is
    vol, z = _blob_volume(300.0)
    one = estimate_scattering_length(vol, z, rounds=1)
    assert one["scattering_length_um"] > 1.1 * 300.0, one


def test_the_estimate_applies_nothing_where_the_light_does_not_fall():
    """No decay, light that rises with depth, a fall of 5% over the stack (what a point's flux varies by without
    scattering) and too few emitters: no l_s, and the reason says why."""
    from cm2cl.analysis.attenuation import estimate_scattering_length

    vol, z = _blob_volume(None)
    assert estimate_scattering_length(vol, z)["scattering_length_um"] is None
    vol, z = _blob_volume(None, trend=np.linspace(1.0, 2.0, 12))
    est = estimate_scattering_length(vol, z)
    assert est["scattering_length_um"] is None and "does not fall" in est["reason"], est
    vol, z = _blob_volume(-1100.0 / np.log(0.95))
    est = estimate_scattering_length(vol, z)
    assert est["scattering_length_um"] is None and "less than 0.1" in est["reason"], est
    vol, z = _blob_volume(300.0, per_plane=3)
    est = estimate_scattering_length(vol, z)
    assert est["scattering_length_um"] is None and "fewer than 3 inner planes" in est["reason"], est
    with pytest.raises(InputError, match="depths_um: 11 depths for 12 planes"):
        estimate_scattering_length(vol, z[:-1])


def _auto_scene(ls, seed=5):
    """Eight beads in each of 10 planes 100 um apart, imaged through a sample of scattering length ``ls``
    (None: clear), 10000 photons at the brightest pixel."""
    nz, shape, photons = 10, (96, 96), 10000.0
    depths = np.arange(nz) * 100.0
    psf = Q.array_psf(nz, shape)
    rng = np.random.default_rng(seed)
    beads = Q.place_beads(8 * nz, nz, shape, seed, planes=tuple(np.repeat(np.arange(nz), 8)), margin=10,
                          min_axial=1)
    truth = Q.bead_volume(beads, rng.uniform(0.7, 1.0, len(beads)), nz, shape)
    a = np.ones(nz) if ls is None else ballistic_fractions(depths, ls)
    y = Q.object_image(psf * a[:, None, None], truth)
    y = rng.poisson(np.maximum(y, 0) / y.max() * photons) / photons * y.max()
    return psf, y, depths, beads


def test_auto_is_the_solve_with_the_estimated_length(rt):
    """'auto' on a frame through a sample of l_s = 500 um: an estimate is applied, the answer is bit for bit the
    solve given that estimate (and its surface), and beads 400-600 um deep (0.30-0.45 of their light) come back
    near the shallow ones' brightness; a clear sample's frame gets no attenuation and the plain solve's answer.
    On this small stack the estimate reads l_s short (measured 343 um; seeds 6, 7: 291, 371): the
    reconstruction recovers a smaller share of the faintest, deepest beads' light than of the bright ones'
    (docs/paper_scenes.md, "The scattering length estimated")."""
    psf, y, depths, beads = _auto_scene(500.0)
    kw = dict(depths_um=depths)
    rec = cm2cl.reconstruct(y, psf, scattering_length_um="auto", **kw)
    att = rec.info["attenuation"]
    ls = att["scattering_length_um"]
    assert ls is not None and 250.0 < ls < 600.0, att["estimate"]
    assert att["estimate"]["first_solve_iterations"] > 0
    given = cm2cl.reconstruct(y, psf, scattering_length_um=ls, surface_um=att["surface_um"], **kw)
    np.testing.assert_array_equal(rec.volume, given.volume)
    assert att["ballistic_fraction"] == pytest.approx(given.info["attenuation"]["ballistic_fraction"])
    plain = cm2cl.reconstruct(y, psf, **kw)
    deep, shallow = (beads[:, 0] >= 4) & (beads[:, 0] <= 6), beads[:, 0] <= 2
    with_auto, without = _peaks(rec.volume, beads), _peaks(plain.volume, beads)
    ratio_auto = with_auto[deep].mean() / with_auto[shallow].mean()
    ratio_plain = without[deep].mean() / without[shallow].mean()
    assert 0.8 < ratio_auto < 1.5, ratio_auto       # measured 1.25 (the estimate short: brightened a little too much)
    assert ratio_plain < 0.6, ratio_plain           # measured 0.35
    psf, y, depths, _ = _auto_scene(None)
    rec = cm2cl.reconstruct(y, psf, scattering_length_um="auto", **kw)
    att = rec.info["attenuation"]
    assert att["scattering_length_um"] is None and att["ballistic_fraction"] == [1.0] * 10, att["estimate"]
    np.testing.assert_array_equal(rec.volume, cm2cl.reconstruct(y, psf, **kw).volume)


def test_a_series_takes_frame_0s_estimate_and_reads_it_back(rt, tmp_path, capsys, monkeypatch):
    """A series with 'auto' estimates l_s once, on frame 0, as a single frame's 'auto' does (the same number),
    solves every frame with it (frame 1 equals the single-frame solve given the number), keeps it in the store's
    record, and a resumed job reads it back without solving frame 0 again; the command line says what frame 0
    gave. Without depths it is refused before a store exists."""
    import tifffile

    from cm2cl import io
    from cm2cl.cli import main
    from cm2cl.jobs.store import read_record

    psf, y, depths, _ = _auto_scene(500.0)
    kw = dict(depths_um=depths, psf_refine=0, max_iter=150)
    frames = np.stack([y, 0.9 * y])
    out = tmp_path / "s.ome.zarr"
    s = cm2cl.reconstruct_series(frames, psf, out, scattering_length_um="auto", **kw)
    assert s.computed == 2
    att = read_record(out)["attenuation"]
    one = cm2cl.reconstruct(y, psf, scattering_length_um="auto", **kw).info["attenuation"]
    assert att["scattering_length_um"] is not None
    assert att["scattering_length_um"] == pytest.approx(one["scattering_length_um"], rel=1e-12)
    import zarr

    vol = np.asarray(zarr.open_group(str(out), mode="r")["0"])
    want = cm2cl.reconstruct(frames[1], psf, scattering_length_um=att["scattering_length_um"],
                             surface_um=att["surface_um"], **kw).volume
    np.testing.assert_array_equal(vol[1], want)

    def no_solve(*a, **k):
        raise AssertionError("frame 0 solved again on a resume")

    from cm2cl.solver import api

    monkeypatch.setattr(api, "ADMMSolver", no_solve)   # every solve of cm2cl.reconstruct builds one
    assert cm2cl.reconstruct_series(frames, psf, out, scattering_length_um="auto", **kw).skipped == 2
    monkeypatch.undo()
    with pytest.raises(InputError, match="scattering_length_um: needs the planes' depths"):
        cm2cl.reconstruct_series(frames, psf, tmp_path / "n.ome.zarr", scattering_length_um="auto")
    assert not (tmp_path / "n.ome.zarr").exists()
    with pytest.raises(InputError, match="scattering_length_um: needs the planes' depths"):
        cm2cl.reconstruct(y, psf, scattering_length_um="auto")
    with pytest.raises(InputError, match="scattering_length_um"):
        cm2cl.reconstruct(y, psf, scattering_length_um="estimate", depths_um=depths)
    io.write_tiff(tmp_path / "psf.ome.tif", psf.astype(np.float32), voxel_size_um=(100.0, 2.0, 2.0),
                  depths_um=depths)
    tifffile.imwrite(tmp_path / "frames.tif", frames.astype(np.float32))
    assert main(["reconstruct", str(tmp_path / "frames.tif"), "--psf", str(tmp_path / "psf.ome.tif"), "-o",
                 str(tmp_path / "c.ome.zarr"), "--scattering-length-um", "auto", "--psf-refine", "0",
                 "--max-iter", "150"]) == 0
    err = capsys.readouterr().err
    ls = read_record(tmp_path / "c.ome.zarr")["attenuation"]["scattering_length_um"]
    assert f"frame 0: scattering length estimated {ls:.0f} um" in err


def test_auto_on_the_command_line_and_in_tiles(rt, tmp_path, capsys):
    """`--scattering-length-um auto` reaches the record (the estimate and what it read) and the report's line;
    lateral tiles estimate from the whole stitched volume and equal the tiled solve given that estimate."""
    import json

    import tifffile

    from cm2cl import io
    from cm2cl.cli import main
    from cm2cl.jobs.tiles import reconstruct_tiled

    psf, y, depths, _ = _auto_scene(500.0)
    io.write_tiff(tmp_path / "psf.ome.tif", psf.astype(np.float32), voxel_size_um=(100.0, 2.0, 2.0),
                  depths_um=depths)
    tifffile.imwrite(tmp_path / "meas.tif", y.astype(np.float32))
    out = tmp_path / "v.ome.tif"
    assert main(["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.ome.tif"), "-o", str(out),
                 "--scattering-length-um", "auto"]) == 0
    info = json.loads((tmp_path / "v.cm2cl.json").read_text())["info"]
    ls = info["attenuation"]["scattering_length_um"]
    assert ls is not None and info["attenuation"]["estimate"]["emitters"] > 0
    assert f"scattering length estimated {ls:.0f} um" in capsys.readouterr().out
    got, tinfo = reconstruct_tiled(y, psf, (48, 48), max_iter=40, depths_um=depths, scattering_length_um="auto")
    est = tinfo["attenuation"]
    assert est["estimate"]["first_solve_iterations"] == 4 * 40   # four tiles of the clear-medium solve
    assert est["scattering_length_um"] is not None, est["estimate"]   # measured 377 um
    want, _ = reconstruct_tiled(y, psf, (48, 48), max_iter=40, depths_um=depths,
                                scattering_length_um=est["scattering_length_um"], surface_um=est["surface_um"])
    np.testing.assert_array_equal(got, want)


def test_cli_analyze_scattering(tmp_path, capsys):
    """`cm2cl analyze scattering` on a volume of blobs dimmed with depth (l_s 300 um, a reconstruction's OME-TIFF
    with its depths): the estimate of the Python function, the table's fitted line through the planes' medians,
    the figure; a volume without depths is refused in one line, with no output."""
    import csv
    import json

    from cm2cl import io
    from cm2cl.analysis.attenuation import estimate_scattering_length
    from cm2cl.cli import main

    vol, z = _blob_volume(300.0)
    io.write_tiff(tmp_path / "vol.ome.tif", vol.astype(np.float32), voxel_size_um=(100.0, 5.0, 5.0), depths_um=z)
    out = tmp_path / "sc"
    assert main(["analyze", "scattering", str(tmp_path / "vol.ome.tif"), "-o", str(out)]) == 0
    want = estimate_scattering_length(vol.astype(np.float32), z)["scattering_length_um"]
    assert f"scattering length {want:.0f} um" in capsys.readouterr().out
    rec = json.loads((out / "analysis.json").read_text())
    assert rec["scattering_length_um"] == pytest.approx(want) and rec["scattering_length_um"] == pytest.approx(300, rel=0.1)
    with open(out / "scattering.csv") as f:
        table = list(csv.reader(f))
    assert table[0] == ["plane", "depth_um", "emitters", "median_log_flux", "fitted_log_flux"] and len(table) == 9
    fitted = np.array([float(r[4]) for r in table[1:]])
    np.testing.assert_allclose(np.diff(fitted) / 100.0, -1.0 / want, rtol=1e-9)   # the line, slope -1 / l_s
    assert (out / "scattering.png").stat().st_size > 1000 and rec["solved_with_scattering_length_um"] is None
    # a reconstruction solved with an attenuation already: the line says the fall is what is left in it
    io.write_tiff(tmp_path / "att.ome.tif", vol.astype(np.float32), voxel_size_um=(100.0, 5.0, 5.0), depths_um=z,
                  extra={"info": {"attenuation": {"scattering_length_um": 965.0}}})
    assert main(["analyze", "scattering", str(tmp_path / "att.ome.tif"), "-o", str(tmp_path / "sc2")]) == 0
    assert "solved with a scattering length of 965 um already" in capsys.readouterr().out
    import tifffile

    tifffile.imwrite(tmp_path / "bare.tif", vol.astype(np.float32))
    assert main(["analyze", "scattering", str(tmp_path / "bare.tif"), "-o", str(tmp_path / "x")]) != 0
    err = capsys.readouterr().err
    assert "no depths in um" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "x").exists()


def test_the_estimate_says_why_a_stack_cannot_have_one():
    from cm2cl.analysis.attenuation import estimate_scattering_length

    vol, z = _blob_volume(300.0, nz=6)
    assert estimate_scattering_length(vol, z)["reason"] == "6 planes: it needs 7 (the 2 at each end are left out)"
    vol, z = _blob_volume(300.0)
    assert estimate_scattering_length(vol, z, surface_um=5000.0)["reason"] == "no plane below the surface"
    assert estimate_scattering_length(0 * vol, z)["reason"] == "an empty volume"

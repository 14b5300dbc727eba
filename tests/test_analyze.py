"""cm2cl analyze (issue 25): PCC curves per view configuration of a PSF stack and 3D Gaussian sizes of the
particles of a volume, against closed forms, and the command's outputs."""

import csv
import json

import numpy as np
import pytest

from cm2cl import io
from cm2cl.analysis import quality as Q
from cm2cl.analysis.particles import (FWHM_PER_SIGMA, SIGMA_MIN_VOX, fit_particle, measure_particle, particle_table,
                                      summary)
from cm2cl.analysis.views import lenslet_grid, pcc_curves, view_configurations
from cm2cl.cli import main


def _spot_stack(z, c_um=50.0, s0=1.5, n=96):
    """One centred Gaussian spot whose sigma grows as s0 (1 + |z| / c)."""
    yy, xx = np.mgrid[:n, :n] - n // 2
    return np.array([np.exp(-(yy ** 2 + xx ** 2) / (2 * (s0 * (1 + abs(zi) / c_um)) ** 2)) for zi in z])


def test_pcc_width_of_a_blurring_spot_is_the_closed_form():
    """Two centred 2D Gaussians of sigmas s0 and s have PCC 2 s0 s / (s0^2 + s^2), which is 0.8 at s = 2 s0:
    with s = s0 (1 + |z| / c) the width at PCC 0.8 is 2c (the window's mean subtraction moves it < 2%)."""
    z = np.arange(-100.0, 100.1, 2.5)
    r = pcc_curves(_spot_stack(z), z)
    assert list(r["curves"]) == ["1x1"] and r["ref_index"] == 40
    assert r["widths_um"]["1x1"] == pytest.approx(100.0, rel=0.02)
    s0, s = 1.5, 1.5 * (1 + np.abs(z) / 50.0)
    np.testing.assert_allclose(r["curves"]["1x1"], 2 * s0 * s / (s0 ** 2 + s ** 2), atol=0.02)


def test_array_psf_views_lose_correlation_faster_with_more_lenslets():
    """The CM2-like 3 x 3 stack (views spreading apart with depth): the grid is found in the stack, the
    configurations are 3x3, 2x3, 2x2 and the central lenslet, and more views decorrelate sooner."""
    psf = Q.array_psf(24, (128, 128))
    grid = lenslet_grid(psf)
    assert [len(r) for r in grid["rows"]] == [3, 3, 3] and [len(c) for c in grid["cols"]] == [3, 3, 3]
    assert grid["axis"] == grid["rows"][1][1]
    conf = view_configurations(grid)
    assert {k: len(v) for k, v in conf.items()} == {"3x3": 9, "2x3": 6, "2x2": 4, "1": 1}
    z = np.arange(24) * 10.0
    w = pcc_curves(psf, z, ref_index=12)["widths_um"]
    assert w["3x3"] is not None and w["2x3"] is not None and w["2x2"] is not None
    assert w["3x3"] < w["2x3"] <= w["2x2"] and (w["1"] is None or w["1"] > w["2x2"]), w


def test_particle_fwhm_of_known_gaussians():
    rng = np.random.default_rng(1)
    shape, sz, sr = (20, 64, 64), 2.0, 1.5
    zz, yy, xx = np.meshgrid(*(np.arange(n, dtype=float) for n in shape), indexing="ij")
    centres = [(6.3, 15.2, 20.7), (12.8, 40.4, 45.1), (9.5, 50.0, 14.6)]
    vol = sum(a * np.exp(-0.5 * (((zz - c[0]) / sz) ** 2 + ((yy - c[1]) ** 2 + (xx - c[2]) ** 2) / sr ** 2))
              for a, c in zip((1.0, 0.7, 0.5), centres))
    vol = vol + 0.002 * rng.standard_normal(shape)
    rows = particle_table(vol, (10.0, 2.0, 2.0), threshold=0.3)
    assert len(rows) == 3 and all(r["ok"] for r in rows)
    for r in rows:
        assert r["fwhm_lateral_um"] == pytest.approx(FWHM_PER_SIGMA * sr * 2.0, rel=0.03)
        assert r["fwhm_axial_um"] == pytest.approx(FWHM_PER_SIGMA * sz * 10.0, rel=0.03)
    got = sorted((r["z"], r["y"], r["x"]) for r in rows)
    np.testing.assert_allclose(got, sorted(centres), atol=0.05)
    s = summary(rows, key=lambda r: "left" if r["x"] < 32 else "right")
    assert s["all"]["n_fit"] == 3 and s["regions"]["left"]["n"] == 2 and s["regions"]["right"]["n"] == 1


def test_a_one_voxel_particle_fits_at_the_floor():
    """A particle one voxel wide (a spike on a flat floor) fits at the narrowest Gaussian, SIGMA_MIN_VOX in
    every axis: the width docs/paper_comparison.md reads as "reconstructed into one voxel". A particle of
    sigma 0.6 voxel is resolved above it."""
    vol = np.full((9, 15, 15), 0.01)
    vol[4, 7, 7] = 1.0
    f = fit_particle(vol, (4, 7, 7))
    assert f["sigma_lateral_vox"] == pytest.approx(SIGMA_MIN_VOX, abs=1e-3)
    assert f["sigma_axial_vox"] == pytest.approx(SIGMA_MIN_VOX, abs=1e-3)
    assert f["lateral_at_floor"] and f["axial_at_floor"]
    zz, yy, xx = np.meshgrid(*(np.arange(n, dtype=float) for n in vol.shape), indexing="ij")
    g = np.exp(-0.5 * ((zz - 4) ** 2 + (yy - 7) ** 2 + (xx - 7) ** 2) / 0.6 ** 2)
    fg = fit_particle(g, (4, 7, 7))
    assert fg["sigma_lateral_vox"] == pytest.approx(0.6, rel=0.02)
    assert not fg["lateral_at_floor"] and not fg["axial_at_floor"]
    # one voxel wide laterally, resolved in depth (sigma 1.5 planes): only the lateral width is a bound
    ax = 0.01 + np.where((yy == 7) & (xx == 7), np.exp(-0.5 * ((zz - 4) / 1.5) ** 2), 0.0)
    fa = fit_particle(ax, (4, 7, 7))
    assert fa["lateral_at_floor"] and not fa["axial_at_floor"] and fa["sigma_axial_vox"] == pytest.approx(1.5, rel=0.05)
    s = summary([measure_particle(ax, (4, 7, 7)), measure_particle(g, (4, 7, 7))])["all"]
    assert (s["n_fit"], s["n_lateral_at_floor"], s["n_axial_at_floor"]) == (2, 1, 0)
    assert not s["lateral_median_at_floor"]   # one of two: the median lies above the floor
    s = summary([measure_particle(ax, (4, 7, 7))] * 2 + [measure_particle(g, (4, 7, 7))])["all"]
    assert s["lateral_median_at_floor"] and not s["axial_median_at_floor"]
    assert s["fwhm_lateral_um"]["median"] == pytest.approx(FWHM_PER_SIGMA * SIGMA_MIN_VOX, rel=0.01)


def test_cli_analyze_pcc_and_particles(tmp_path, capsys):
    z = np.arange(-100.0, 100.1, 5.0)
    io.write_tiff(tmp_path / "psf.ome.tif", _spot_stack(z).astype(np.float32), voxel_size_um=(5.0, 2.0, 2.0),
                  depths_um=z)
    assert main(["analyze", "pcc", str(tmp_path / "psf.ome.tif"), "-o", str(tmp_path / "pcc")]) == 0
    out = capsys.readouterr().out
    rec = json.loads((tmp_path / "pcc" / "analysis.json").read_text())
    assert rec["widths"]["1x1"] == pytest.approx(100.0, rel=0.02) and "1x1 " in out
    with open(tmp_path / "pcc" / "pcc.csv") as f:
        table = list(csv.reader(f))
    assert table[0] == ["z_um", "pcc_1x1"] and len(table) == 1 + z.size and float(table[21][1]) == pytest.approx(1.0)
    assert (tmp_path / "pcc" / "pcc.png").stat().st_size > 1000 and rec["figure"] == "pcc.png"
    assert main(["analyze", "pcc", str(tmp_path / "psf.ome.tif"), "-o", str(tmp_path / "pcc"), "--ref-z", "50"]) == 0
    assert json.loads((tmp_path / "pcc" / "analysis.json").read_text())["reference_depth"] == 50.0
    # particles: a volume with its voxel size
    vol = np.zeros((12, 40, 40))
    zz, yy, xx = np.meshgrid(*(np.arange(n, dtype=float) for n in vol.shape), indexing="ij")
    vol += np.exp(-0.5 * (((zz - 5.2) / 1.5) ** 2 + ((yy - 20.3) ** 2 + (xx - 18.6) ** 2) / 1.2 ** 2))
    io.write_tiff(tmp_path / "vol.ome.tif", vol.astype(np.float32), voxel_size_um=(20.0, 3.0, 3.0))
    assert main(["analyze", "particles", str(tmp_path / "vol.ome.tif"), "-o", str(tmp_path / "p")]) == 0
    rec = json.loads((tmp_path / "p" / "analysis.json").read_text())
    assert rec["summary"]["all"]["n_fit"] == 1
    assert rec["summary"]["all"]["fwhm_axial_um"]["median"] == pytest.approx(FWHM_PER_SIGMA * 1.5 * 20.0, rel=0.03)
    assert rec["summary"]["all"]["n_lateral_at_floor"] == 0 and "floor" not in capsys.readouterr().out
    # a particle in one voxel laterally: its lateral width is flagged as the fit's floor in the table and the line
    spike = np.full_like(vol, 1e-3)
    spike[:, 20, 18] += np.exp(-0.5 * ((np.arange(12) - 5.0) / 1.5) ** 2)
    io.write_tiff(tmp_path / "spike.ome.tif", spike.astype(np.float32), voxel_size_um=(20.0, 3.0, 3.0))
    assert main(["analyze", "particles", str(tmp_path / "spike.ome.tif"), "-o", str(tmp_path / "ps")]) == 0
    out = capsys.readouterr().out
    assert "at the fit's floor (0.71 voxel" in out and "1 lateral of 1" in out and "axial of" not in out, out
    with open(tmp_path / "ps" / "particles.csv") as f:
        table = list(csv.DictReader(f))
    assert len(table) == 1 and table[0]["lateral_at_floor"] == "True" and table[0]["axial_at_floor"] == "False"
    assert float(table[0]["fwhm_lateral_um"]) == pytest.approx(FWHM_PER_SIGMA * SIGMA_MIN_VOX * 3.0, rel=0.01)
    # refused in one line before any output: bad level, no scale, a 2D input
    io.write_tiff(tmp_path / "px.ome.tif", vol.astype(np.float32))
    io.write_tiff(tmp_path / "flat.ome.tif", vol[0].astype(np.float32))
    for argv, msg in ((["pcc", str(tmp_path / "psf.ome.tif"), "--level", "2"], "--level"),
                      (["particles", str(tmp_path / "px.ome.tif")], "no voxel size in um"),
                      (["pcc", str(tmp_path / "flat.ome.tif")], "expected a 3D stack")):
        assert main(["analyze", *argv, "-o", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err
        assert msg in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "bad").exists()


def test_particles_all_of_separated_ones_and_none_in_pure_noise():
    rng = np.random.default_rng(3)
    noise = rng.standard_normal((16, 96, 96))
    assert particle_table(noise, (10.0, 2.0, 2.0)) == []
    zz, yy, xx = np.meshgrid(*(np.arange(n, dtype=float) for n in noise.shape), indexing="ij")
    centres = [(4, 15, 15), (8, 15, 60), (12, 70, 30), (5, 75, 80), (10, 45, 45)]
    vol = 0.05 * noise + sum(np.exp(-0.5 * (((zz - c[0]) / 1.5) ** 2 + ((yy - c[1]) ** 2 + (xx - c[2]) ** 2) / 1.2 ** 2))
                             for c in centres)
    rows = particle_table(vol, (10.0, 2.0, 2.0))
    assert len(rows) == 5 and sorted((round(r["z"]), round(r["y"]), round(r["x"])) for r in rows) == sorted(centres)


def test_pcc_is_one_at_the_reference_and_shift_invariant():
    """Every curve is 1 at the reference plane; moving the PSF on the sensor changes nothing where the
    window keeps its size (the whole array's, the single lenslet's) and the registration moves nothing out of
    it (the stack padded with zeros)."""
    psf = np.pad(Q.array_psf(16, (128, 128)), ((0, 0), (32, 32), (32, 32)))
    z = np.arange(16) * 10.0
    a = pcc_curves(psf, z, ref_index=8)
    b = pcc_curves(np.roll(psf, (3, -5), axis=(1, 2)), z, ref_index=8)
    for k in a["curves"]:
        assert a["curves"][k][8] == pytest.approx(1.0)
    for k in ("3x3", "1"):
        np.testing.assert_allclose(b["curves"][k], a["curves"][k], atol=1e-9)


def test_sbr_of_known_levels_and_the_command(tmp_path, capsys):
    """Background B, particles of A + B: each patch's SBR is (A + B) / B; the command writes the map."""
    from cm2cl.analysis.metrics import local_sbr, particle_mask

    rng = np.random.default_rng(0)
    img = 100.0 + rng.standard_normal((240, 240))
    yy, xx = np.mgrid[:240, :240]
    for cy in range(20, 240, 40):
        for cx in range(20, 240, 40):
            img[(yy - cy) ** 2 + (xx - cx) ** 2 <= 9] += 50.0
    mask = particle_mask(img, 80)
    sbr_map, mean = local_sbr(img, mask, 80)
    assert sbr_map.shape == (3, 3) and mean == pytest.approx(1.5, rel=0.01)
    io.write_tiff(tmp_path / "raw.ome.tif", img.astype(np.float32), voxel_size_um=(5.0, 5.0))
    assert main(["analyze", "sbr", str(tmp_path / "raw.ome.tif"), "-o", str(tmp_path / "s"), "--patch-um", "400"]) == 0
    rec = json.loads((tmp_path / "s" / "analysis.json").read_text())
    assert rec["patch_px"] == 80 and rec["mean_sbr"] == pytest.approx(1.5, rel=0.01)
    with open(tmp_path / "s" / "sbr.csv") as f:
        assert len(list(csv.reader(f))) == 1 + 9
    capsys.readouterr()
    # a patch the image cannot hold, or a negative one, is named by its option in one line, before any output
    for flag, value, msg in (("--patch-um", "-3", "--patch-um: must be a positive number, got -3"),
                             ("--patch-um", "2000", "--patch-um: a patch of 2000 um (5 um pixels) is 400 px; it must "
                                                    "be 2 px to the image's 240 px"),
                             ("--patch-px", "1", "--patch-px: a patch of 1 px is 1 px")):
        out = tmp_path / f"bad{value}"
        assert main(["analyze", "sbr", str(tmp_path / "raw.ome.tif"), "-o", str(out), flag, value]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0], err
        assert not out.exists()


def _particle_volume(centres, shape=(30, 80, 80), sz=1.5, sr=1.2, amps=None, noise=0.002, seed=3):
    rng = np.random.default_rng(seed)
    zz, yy, xx = np.meshgrid(*(np.arange(n, dtype=float) for n in shape), indexing="ij")
    amps = amps or [1.0] * len(centres)
    vol = sum(a * np.exp(-0.5 * (((zz - c[0]) / sz) ** 2 + ((yy - c[1]) ** 2 + (xx - c[2]) ** 2) / sr ** 2))
              for a, c in zip(amps, centres))
    return vol + noise * rng.standard_normal(shape)


def test_depth_range_per_patch_is_the_spread_of_centres_plus_the_elongation():
    """Voxels 20 um deep and 10 um wide, patches of 400 um = 40 px: patch (0, 0) holds particles at planes 5,
    12 and 20 (range 300 um + elongation), patch (1, 1) planes 8 and 10 (40 um + elongation), patch (0, 1) one
    particle (the elongation alone); with the default elongation the particles' own median axial FWHM."""
    from cm2cl.analysis.particles import depth_range

    centres = [(5, 10, 12), (12, 25, 30), (20, 15, 20), (8, 50, 55), (10, 60, 70), (14, 12, 60)]
    vs = (20.0, 10.0, 10.0)
    rows = particle_table(_particle_volume(centres), vs, threshold=0.3)
    assert len(rows) == 6
    r = depth_range(rows, (800.0, 800.0), 400.0, elongation_um=372.0)
    got = {(p["patch_row"], p["patch_col"]): p for p in r["patches"]}
    assert set(got) == {(0, 0), (1, 1), (0, 1)} and r["patches_total"] == 4
    assert got[(0, 0)]["range_um"] == pytest.approx(300 + 372, abs=2) and got[(0, 0)]["particles"] == 3
    assert got[(1, 1)]["range_um"] == pytest.approx(40 + 372, abs=2)
    assert got[(0, 1)]["range_um"] == pytest.approx(372)
    v = [672, 412, 372]
    assert r["mean_um"] == pytest.approx(np.mean(v), abs=2) and r["std_um"] == pytest.approx(np.std(v, ddof=1), abs=2)
    two = depth_range(rows, (800.0, 800.0), 400.0, elongation_um=0.0, min_particles=2)
    assert len(two["patches"]) == 2 and two["mean_um"] == pytest.approx(170, abs=2)
    own = depth_range(rows, (800.0, 800.0), 400.0)
    assert own["elongation_um"] == pytest.approx(FWHM_PER_SIGMA * 1.5 * 20.0, rel=0.05)
    assert own["elongation_from"].startswith("median") and not own["elongation_at_floor"]
    assert r["elongation_at_floor"] is False   # a given elongation is the user's
    # particles one plane deep (spikes in z, resolved laterally): the median axial width is the fit's floor, a bound
    zz, yy, xx = np.meshgrid(*(np.arange(n, dtype=float) for n in (30, 80, 80)), indexing="ij")
    flat = sum(np.where(zz == c[0], np.exp(-0.5 * ((yy - c[1]) ** 2 + (xx - c[2]) ** 2) / 1.2 ** 2), 0.0)
               for c in centres) + 1e-3
    thin = particle_table(flat, vs, threshold=0.3)
    assert len(thin) == 6 and all(t["axial_at_floor"] and not t["lateral_at_floor"] for t in thin)
    floor = depth_range(thin, (800.0, 800.0), 400.0)
    assert floor["elongation_at_floor"] and floor["elongation_um"] == pytest.approx(FWHM_PER_SIGMA * SIGMA_MIN_VOX * 20,
                                                                                    rel=0.01)


def test_cli_analyze_depth_range(tmp_path, capsys):
    centres = [(5, 10, 12), (12, 25, 30), (20, 15, 20), (8, 50, 55), (10, 60, 70)]
    io.write_tiff(tmp_path / "vol.ome.tif", _particle_volume(centres).astype(np.float32),
                  voxel_size_um=(20.0, 10.0, 10.0))
    out = tmp_path / "dr"
    assert main(["analyze", "depth-range", str(tmp_path / "vol.ome.tif"), "-o", str(out), "--patch-um", "400",
                 "--elongation-um", "372", "--threshold", "0.3"]) == 0
    said = capsys.readouterr().out
    assert "depth range 542 +- 184 um over 2 of 4 patches" in said and "floor" not in said
    rec = json.loads((out / "analysis.json").read_text())
    assert rec["mean_um"] == pytest.approx(542, abs=2) and rec["particles"] == 5
    with open(out / "depth_range.csv") as f:
        table = list(csv.reader(f))
    assert table[0][:2] == ["patch_row", "patch_col"] and len(table) == 3
    assert (out / "depth_range.png").stat().st_size > 1000
    # particles one plane deep, the elongation their own: the line says it is the fit's floor
    flat = np.full((30, 80, 80), 1e-3, np.float32)
    for z, y, x in centres:
        flat[z, y - 1:y + 2, x - 1:x + 2] += 1.0
    io.write_tiff(tmp_path / "flat.ome.tif", flat, voxel_size_um=(20.0, 10.0, 10.0))
    assert main(["analyze", "depth-range", str(tmp_path / "flat.ome.tif"), "-o", str(tmp_path / "fl"),
                 "--patch-um", "400", "--threshold", "0.3"]) == 0
    assert "elongation 14 um: the fit's floor, the median particle one plane deep, a bound" in capsys.readouterr().out
    assert json.loads((tmp_path / "fl" / "analysis.json").read_text())["elongation_at_floor"] is True
    for bad, msg in ((["--patch-um", "2000"], "larger than the volume's field"), (["--patch-um", "-5"], "--patch-um"),
                     (["--elongation-um", "nan"], "--elongation-um"), (["--min-particles", "0"], "--min-particles")):
        assert main(["analyze", "depth-range", str(tmp_path / "vol.ome.tif"), "-o", str(tmp_path / "x")] + bad) != 0
        err = capsys.readouterr().err
        assert msg in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "x").exists()

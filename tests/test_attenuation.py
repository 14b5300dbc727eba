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

"""The camera's noise model (cm2cl.io.camera): parameters given or fitted to the frame, the data term's
inverse-variance weights, and bad parameters refused before the solve."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

import cm2cl
from cm2cl.errors import InputError
from cm2cl.io.camera import Camera, camera_weights, estimate_camera, parse_camera, variance_weights
from test_admm import bead_problem


def _frame(rng, gain, read_noise, offset=0.0, shape=(160, 200)):
    """A smooth photon image (50 .. 2000 photons) with point-like foci, Poisson counts, Gaussian read
    noise, in ADU."""
    sig = gaussian_filter(rng.random(shape), 8)
    sig = 50 + 1950 * (sig - sig.min()) / np.ptp(sig)
    pts = np.zeros(shape)
    pts[rng.integers(0, shape[0], 30), rng.integers(0, shape[1], 30)] = 3000
    sig += gaussian_filter(pts, 1.5)
    return gain * (rng.poisson(sig) + read_noise * rng.standard_normal(shape)) + offset


@pytest.mark.parametrize("gain", [0.5, 2.0, 5.0])
def test_gain_is_fitted_from_one_frame(gain):
    """The mean-variance fit recovers the gain within 10% (seen: 1-7% high, the foci's structure)."""
    cam = estimate_camera(_frame(np.random.default_rng(int(gain * 10)), gain, 2.0))
    assert cam.gain == pytest.approx(gain, rel=0.1) and cam.source == "estimated"


def test_weights_are_the_inverse_variance():
    y = np.full((20, 20), 100.0)
    y[5:10, 5:10] = 1000.0
    w = variance_weights(y, Camera(gain=2.0, offset=0.0, read_noise=3.0))
    var_dark, var_bright = 2.0 * 100 + 36.0, 2.0 * 1000 + 36.0
    assert w[0, 0] / w[7, 7] == pytest.approx(var_bright / var_dark, rel=1e-9)   # away from the edges of the smoothing
    assert np.median(w) == pytest.approx(1.0)


@pytest.mark.parametrize("spec,message", [
    ("gain=-1", "gain must be > 0"), ("gain=nan", "finite"), ("gain=2,read-noise=-1", ">= 0"),
    ("offset=3", "gain .* is needed"), ("gain=2,shutter=1", "unknown shutter"), ("gain:2", "expected 'gain=G"),
    ("gain=abc", "not a number"), ({"gain": 1, "colour": 2}, "unknown colour")])
def test_bad_camera_parameters_are_refused(spec, message):
    with pytest.raises(InputError, match=message):
        parse_camera(spec)


def test_offset_above_the_median_is_refused():
    y = np.full((16, 16), 100.0)
    with pytest.raises(InputError, match="above the frame's median"):
        camera_weights(y, "gain=2,offset=150")
    out, w, rec = camera_weights(y + 0.0, {"gain": 2, "offset": 50, "read_noise": 1})
    assert np.all(out == 50.0) and rec == {"gain": 2.0, "offset": 50.0, "read_noise": 1.0, "source": "given"}


def test_reconstruct_with_a_camera_records_it_and_weighs_the_data(rt):
    psf, _, y = bead_problem(2)
    y = 1000 * y / y.max() + 20.0
    kw = dict(l1=1e-3, tv=1e-3, max_iter=20, tol=0, padded_shape=(64, 80))
    a = cm2cl.reconstruct(y, psf, camera="gain=2,read-noise=1.5", **kw)
    b = cm2cl.reconstruct(y, psf, **kw)
    assert a.info["camera"]["gain"] == 2.0 and b.info["camera"] is None
    assert np.linalg.norm(a.volume - b.volume) > 1e-3 * np.linalg.norm(b.volume)   # the weights matter


def test_cli_refuses_bad_camera_before_any_work(tmp_path, capsys):
    import tifffile

    from cm2cl.cli import main

    psf, _, y = bead_problem(2)
    tifffile.imwrite(tmp_path / "m.tif", y.astype(np.float32))
    tifffile.imwrite(tmp_path / "p.tif", psf.astype(np.float32), photometric="minisblack")
    out = tmp_path / "v.ome.tif"
    assert main(["reconstruct", str(tmp_path / "m.tif"), "--psf", str(tmp_path / "p.tif"), "-o", str(out),
                 "--camera", "gain=0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "camera" in err[0] and "gain must be > 0" in err[0] and not out.exists()

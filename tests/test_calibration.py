"""PSF calibration (issue 12 item 1): registration of scan planes to 0.1 px, drift per mm, the prepared
stack from a simulated raw scan, the real DiffuserCam 3D PSF's corner background, bad input."""

from pathlib import Path

import numpy as np
import pytest
import tifffile

from cm2cl import simulate
from cm2cl.analysis.registration import fourier_shift, measure_shift, scan_drift
from cm2cl.cli import main
from cm2cl.errors import InputError
from cm2cl.io.calibration import prepare_psf_stack
from cm2cl.simulate.render import render_psf_stack

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "diffusercam-3d"


def _optics():
    scene = simulate.load_scene("demo_beads")
    return scene.optics


def _fine_scan(z):
    return render_psf_stack(_optics(), np.asarray(z, float), {})


def test_registration_recovers_integer_and_subpixel_shifts():
    planes = _fine_scan([-100.0, 0.0, 150.0])
    for p in planes:
        for s in [(3.0, -2.0), (0.37, -1.62), (-4.25, 0.8), (0.05, 0.0)]:
            got = measure_shift(p, fourier_shift(p, s))
            assert np.all(np.abs(got - np.array(s)) <= 0.1), (s, got)


def test_linear_drift_of_a_scan_is_measured_per_mm():
    """Planes every 10 um over 300 um with a drift of (12, -7) px per mm: the fitted line within 0.1 px."""
    z = np.arange(-150.0, 151.0, 10.0)
    planes = _fine_scan(z)
    per_mm = np.array([12.0, -7.0])
    drifted = np.stack([fourier_shift(p, per_mm * zz / 1000.0) for p, zz in zip(planes, z)])
    d = scan_drift(drifted, z)
    truth = np.outer(z - z[0], per_mm / 1000.0)
    assert np.abs(d["fit"] - truth).max() <= 0.1
    assert np.allclose(d["per_mm"], per_mm, atol=0.5)


def test_prepared_stack_from_a_raw_scan_reconstructs_like_the_ideal_stack(rt):
    """A raw scan (dark offset 100, Poisson and read noise, a drift of (8, 5) px/mm, 10 um steps) prepared
    with axial binning 5 (8 planes of 50 um): the drift is recovered, and emitters imaged through the
    ideal binned stack are found by a reconstruction with the prepared stack as with the ideal one (all of
    them within 1 px laterally), and each prepared plane correlates with its ideal plane (PCC > 0.9). The stacks themselves differ by the
    noise and by resampling the sharp foci (Fourier shifts of near-single-pixel spots)."""
    import cm2cl
    from cm2cl import reference as ref
    from cm2cl.analysis import find_emitters

    z = np.arange(-200.0, 200.0, 10.0)
    ideal = _fine_scan(z)
    rng = np.random.default_rng(3)
    per_mm = np.array([8.0, 5.0])
    raw = []
    for p, zz in zip(ideal, z):
        q = np.maximum(fourier_shift(p / p.sum() * 2e5, per_mm * (zz - z[0]) / 1000.0), 0)
        raw.append(rng.poisson(q) + 100 + rng.normal(0, 2, q.shape))
    raw = np.round(np.stack(raw)).clip(0, 65535).astype(np.uint16)
    stack, depths, rec = prepare_psf_stack(raw, z, axial_bin=5, lateral_bin=2)
    reg = next(s for s in rec["steps"] if s["step"] == "registration")
    assert np.allclose(reg["drift_px_per_mm"], per_mm, atol=0.5)
    dark = next(s for s in rec["steps"] if s["step"] == "dark level")
    assert 99 <= dark["level_min"] <= dark["level_max"] <= 101
    from cm2cl.io.prepare import bin_image

    want = bin_image((ideal / ideal.reshape(len(z), -1).sum(1)[:, None, None]).reshape(8, 5, *ideal.shape[1:]).sum(1), 2)
    assert stack.shape == want.shape and np.allclose(depths, z.reshape(8, 5).mean(1))
    M = want.shape[1:]
    P = tuple(2 * m for m in M)
    x = np.zeros((8,) + P)
    truth = [(1, 30, 40), (3, 60, 100), (6, 90, 70), (4, 40, 130)]
    oy, ox = (P[0] - M[0]) // 2, (P[1] - M[1]) // 2
    for k, r, c in truth:
        x[k, oy + r, ox + c] = 1.0
    y = ref.forward(want, x, P)
    for h in (want, stack):
        rec_ = cm2cl.reconstruct(y, h, max_iter=150)
        found = find_emitters(rec_.volume, threshold=0.3)["index"]
        for k, r, c in truth:      # each emitter found laterally within 1 px (depth is coarse at 50 um planes
            lat = np.abs(found[:, 1:] - np.array([r, c])).max(axis=1)   # for these optics, ideal stack or not)
            assert lat.min() <= 1.0, (k, r, c, found[:6])
    pcc = [np.corrcoef(a.ravel(), b.ravel())[0, 1] for a, b in zip(stack, want)]
    assert min(pcc) > 0.9, pcc


@pytest.mark.skipif(not DATA.exists(), reason="../shared/data/diffusercam-3d not present")
def test_diffusercam_psf_corner_background_is_removed():
    files = sorted((DATA / "psf").glob("psf*.tiff"))[:6]
    raw = np.stack([tifffile.imread(f) for f in files]).astype(np.float64)
    stack, _, rec = prepare_psf_stack(raw, np.arange(len(raw)) * 10.0, register=False, noise_floor=0)
    readme = []
    for p in raw:
        c = np.concatenate([p[:20, :20].ravel(), p[:20, -20:].ravel(), p[-20:, :20].ravel(), p[-20:, -20:].ravel()])
        q = np.maximum(p - np.median(c), 0.0)
        readme.append(q / q.sum())
    readme = np.stack(readme)
    assert np.linalg.norm(stack - readme) <= 1e-12 * np.linalg.norm(readme)
    assert rec["steps"][0]["level_max"] > 0                       # there was a background to remove
    assert np.median(stack[:, :20, :20]) <= 1e-4 * stack.max()          # the corners read ~0


def test_bad_scans_are_refused(tmp_path, capsys):
    with pytest.raises(InputError, match="outside the scan"):
        prepare_psf_stack(np.ones((3, 8, 8)), [0, 10, 20], z_range=(0, 50))
    with pytest.raises(InputError, match="3 planes but 2 z positions"):
        prepare_psf_stack(np.ones((3, 8, 8)), [0, 10])
    tifffile.imwrite(tmp_path / "a.tif", np.ones((8, 8), np.uint16))
    tifffile.imwrite(tmp_path / "b.tif", np.ones((9, 8), np.uint16))
    out = tmp_path / "psf.ome.tif"
    code = main(["prepare-psf", str(tmp_path / "a.tif"), str(tmp_path / "b.tif"), "--z-start", "0", "--z-step",
                 "10", "-o", str(out)])
    assert code == 2 and "differs from the first frame" in capsys.readouterr().err and not out.exists()


def test_cli_writes_a_stack_reconstruct_takes_with_its_scale(rt, tmp_path, capsys):
    from cm2cl import io

    z = np.arange(0.0, 100.0, 10.0)
    raw = (_fine_scan(z - 50) * 3e4 + 100).astype(np.uint16)
    tifffile.imwrite(tmp_path / "scan.tif", raw, photometric="minisblack")
    out = tmp_path / "psf.ome.tif"
    assert main(["prepare-psf", str(tmp_path / "scan.tif"), "--z-start", "0", "--z-step", "10", "--axial-bin", "2",
                 "--object-pixel-um", "4.2", "-o", str(out)]) == 0
    assert "5 planes" in capsys.readouterr().out
    stack, meta = io.read_tiff(out)
    assert stack.shape[0] == 5 and meta["voxel_size_um"] == (20.0, 4.2, 4.2)
    assert meta["depths_um"] == [5.0, 25.0, 45.0, 65.0, 85.0]
    assert (tmp_path / "psf.cm2cl.json").exists()


@pytest.mark.skipif(not DATA.exists(), reason="../shared/data/diffusercam-3d not present")
def test_diffusercam_measurement_saturation_is_reported():
    """The real DiffuserCam 3D image has pixels at 65535 (its README): they are counted and located."""
    from cm2cl.analysis import check_pixels

    img = tifffile.imread(DATA / "image.tiff")
    rep = check_pixels(img)
    assert rep["saturated"]["level"] == 65535.0
    assert rep["saturated"]["count"] == int((img == 65535).sum()) > 0
    r, c = rep["saturated"]["first"][0]
    assert img[r, c] == 65535


def test_corners_that_are_not_dark_are_warned_with_their_level(caplog):
    planes = np.full((3, 64, 64), 50.0)
    planes[:, 28:36, 28:36] += 200.0                 # the spot; the corners hold 50 = 20% of the peak
    with caplog.at_level("WARNING", logger="cm2cl"):
        _, _, rec = prepare_psf_stack(planes, [0, 10, 20], register=False, noise_floor=0)
    assert rec["warnings"] and "are not dark" in rec["warnings"][0] and "median up to 50" in rec["warnings"][0]
    assert "are not dark" in caplog.text


@pytest.mark.skipif(not DATA.exists(), reason="../shared/data/diffusercam-3d not present")
def test_diffusercam_3d_end_to_end_through_the_command_line(rt, tmp_path, capsys):
    """Issue 12: the real scan's planes through `cm2cl prepare-psf` (corner background off, binned 4x to the
    working pixel), then `cm2cl reconstruct` of the raw image (its saturated pixel reported, the PSF taken
    as already binned). The target is tilted in depth, so the light's lateral centroid moves with depth:
    seen 45.8 px in the first quarter of the planes against 43.5 in the last (bin 4; 94 -> 81 at bin 2,
    187 -> 171 at full size)."""
    from cm2cl import io

    psf = tmp_path / "psf.ome.tif"
    assert main(["prepare-psf", str(DATA / "psf" / "psf*.tiff"), "--z-start", "0", "--z-step", "1",
                 "--no-register", "--noise-floor", "0", "--bin", "4", "-o", str(psf)]) == 0
    assert "44 planes of 67 x 80" in capsys.readouterr().out
    vol = tmp_path / "vol.ome.tif"
    assert main(["reconstruct", str(DATA / "image.tiff"), "--psf", str(psf), "--offset", "100", "--bin", "4",
                 "-o", str(vol), "--quiet"]) == 0
    cap = capsys.readouterr()
    assert "already on the 4x binned grid" in cap.err and "1 saturated pixel(s)" in cap.out
    v, _ = io.read_tiff(vol)
    assert v.shape == (44, 67, 80)
    xs = np.arange(v.shape[2])
    cx = (v.sum(axis=1) * xs).sum(axis=1) / np.maximum(v.sum(axis=(1, 2)), 1e-30)
    assert cx[:11].mean() - cx[-11:].mean() > 1.5, cx

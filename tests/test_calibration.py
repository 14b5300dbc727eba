"""PSF calibration (issue 12 items 1 and 4): sub-pixel registration of scan planes, the drift per mm, the
prepared stack from a simulated raw scan against the ideal one, the real DiffuserCam 3D PSF's corner
background, the sensor-fit rule, bad input.

Shifted planes are rendered by the optics model with the pinhole moved laterally (the foci move by
-m x / pixel), not by the shifting code under test."""

import json
from pathlib import Path

import numpy as np
import pytest
import tifffile

from cm2cl import io
from cm2cl.analysis.registration import measure_shift, scan_drift, shift_image
from cm2cl.cli import main
from cm2cl.errors import InputError
from cm2cl.io.calibration import prepare_psf_stack
from cm2cl.io.prepare import fit_lateral
from cm2cl.optics.psf import array_psf
from cm2cl.simulate import load_scene

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "diffusercam-3d"


def _optics(binning=4, shape=(400, 400)):
    """The demo's optics on a finer pixel (8.8 um at binning 4 by default), cropped."""
    return load_scene("demo_beads").optics.replace(binning=binning, sensor_shape=shape)


def _plane(optics, z_um, dy, dx):
    """The PSF at depth z of a pinhole placed so that its image moves by (dy, dx) pixels."""
    p_mm = optics.pixel_size_um / 1000.0
    m = float(optics.magnification(z_um))
    return array_psf(optics, float(z_um), -dx * p_mm / m, -dy * p_mm / m, dtype=np.float64)


def _scan(optics, z, per_mm):
    """A drifting scan: the pinhole's image moves by per_mm px per mm of z (through the axis at z = 0)."""
    return np.stack([_plane(optics, zz, *(np.asarray(per_mm) * zz / 1000.0)) for zz in z])


def test_registration_recovers_integer_and_subpixel_shifts():
    """Within 0.1 px, in focus and 300 um out of focus, for whole, fractional and mixed shifts, on 4.4-um
    pixels (2x binning), where the in-focus foci are about a pixel wide (pixel locking: up to 0.085 px in
    focus; on 8.8-um pixels the foci are narrower than a pixel and the error reaches 0.15 px)."""
    o = _optics(2, (800, 800))
    for z in (-300.0, 0.0, 300.0):
        ref = _plane(o, z, 0.0, 0.0)
        for s in [(3.0, -2.0), (12.0, 7.0), (0.37, -1.62), (-4.25, 0.8), (0.05, 0.0), (0.5, -0.5)]:
            got = measure_shift(ref, _plane(o, z, *s))
            assert np.abs(got - np.array(s)).max() <= 0.1, (z, s, got)


def test_linear_drift_of_a_scan_is_measured_per_mm():
    """41 planes every 25 um over 1 mm drifting by (7, -3) px per mm: the fitted line within 0.1 px at
    every plane and the slope within 0.1 px/mm, with and without noise. (In focus the foci are narrower
    than these 8.8-um pixels and lock to them; a scan of only +-200 um, all near focus, gives the slope to
    0.2 px/mm; a calibration scan spans the depth of field, 2.5 mm in the paper.)"""
    o = _optics(4, (360, 360))
    z = np.arange(-500.0, 501.0, 25.0)
    per_mm = np.array([7.0, -3.0])
    planes = _scan(o, z, per_mm)
    rng = np.random.default_rng(5)
    noisy = rng.poisson(planes * 1e5) + rng.normal(0.0, 2.0, planes.shape)
    for scan in (planes, noisy):
        d = scan_drift(iter(scan), z)
        assert np.abs(d["fit"] - np.outer(z, per_mm / 1000.0)).max() <= 0.1
        assert np.abs(d["per_mm"] - per_mm).max() <= 0.1, d["per_mm"]
        assert d["residual_px"] < 0.1


def test_shift_image_is_zero_filled_and_matches_scipy():
    """Away from the edges both methods equal scipy's (periodic Fourier shift; order-1 spline); what leaves
    the frame does not come back on the other side."""
    from scipy import ndimage

    rng = np.random.default_rng(0)
    a = np.zeros((40, 50))
    a[10:30, 12:38] = ndimage.gaussian_filter(rng.random((20, 26)), 2.0)
    s = (1.3, -2.6)
    ref = np.real(np.fft.ifftn(ndimage.fourier_shift(np.fft.fftn(a), s)))
    got = shift_image(a, s, "fourier")
    assert np.abs(got - ref)[5:-5, 5:-5].max() < 0.05 * a.max()     # equal up to the edge ringing
    assert np.allclose(shift_image(a, s, "bilinear"), ndimage.shift(a, s, order=1, mode="constant"))
    edge = np.zeros((20, 20))
    edge[8, 18] = 1.0
    for method in ("fourier", "bilinear"):
        moved = shift_image(edge, (0.0, 3.0), method)
        assert np.abs(moved[:, :10]).max() < 1e-12, method


def test_fit_lateral_pads_or_crops_around_the_axis():
    a = np.zeros((2, 5, 7))
    a[:, 2, 3] = 1.0                                    # the centre pixel (5 // 2, 7 // 2)
    a[:, 0, 0] = 0.5
    out, info = fit_lateral(a, (9, 8))
    assert out.shape == (2, 9, 8) and out[0, 4, 4] == 1.0 and out[0, 2, 1] == 0.5
    assert info["offset"] == [2, 1] and "4 rows of zeros added" in info["message"]
    out, info = fit_lateral(a, (3, 3))                 # cropped: the corner pixel's light is cut
    assert out[0, 1, 1] == 1.0 and info["light_cut"] == pytest.approx(0.5 / 1.5)
    assert "cropped" in info["message"] and "33.33% of its light cut off" in info["message"]
    out, info = fit_lateral(a, (5, 7), axis=(0, 0))     # a given axis moves to the centre
    assert out[0, 2, 3] == 0.5 and info["message"] is not None
    same, info = fit_lateral(a, (5, 7))
    assert info["message"] is None and np.array_equal(same, a)
    with pytest.raises(InputError, match=r"psf: optical axis \(9, 1\) \(row, col\) is outside its 5 x 7"):
        fit_lateral(a, (5, 7), axis=(9, 1))
    for bad in ("ab", 5, [float("nan"), 3]):            # a PSF record's axis_pixel of the wrong type (issue 27)
        with pytest.raises(InputError, match="is not a \\(row, col\\) pair of finite numbers"):
            fit_lateral(a, (5, 7), axis=bad)


def test_prepared_stack_from_a_raw_scan_reconstructs_like_the_ideal_stack():
    """The demo's bead scene (12 beads, 5 planes of 250 um) on its 8x binned sensor cropped to 192 x 256,
    reconstructed with its ideal PSF stack (each plane's PSF at the plane's depth) and with one prepared
    from a raw scan of the same optics: 125 planes every 10 um over +-620 um, cropped to 176 x 240,
    drifting by (6, -4) px/mm, 2e5 photons a plane, Poisson and read noise, dark level 100, 16 bit;
    prepared with axial binning 25 (sums over the reconstruction's planes) and padding to the sensor.
    Margins: recall and precision at most one bead below the ideal stack's, lateral RMS error at most 0.25
    voxel above, axial at most 0.5 plane above (a sum over 250 um is not the PSF at the plane's centre;
    measured: recall 0.92 both, lateral 5.2 vs 6.2 um, axial 68 vs 41 um). Each prepared plane is within
    0.1 px of the ideal one (the drift was taken out)."""
    import cm2cl
    from cm2cl.analysis import score_beads
    from cm2cl.simulate import simulate_scene

    scene = {k: v for k, v in load_scene("demo_beads").as_dict().items() if k != "source"}
    scene["optics"]["sensor_shape"] = [192, 256]
    sim = simulate_scene(scene)
    o = _optics(8, (176, 240))
    z = np.arange(-620.0, 621.0, 10.0)
    per_mm = np.array([6.0, -4.0])
    rng = np.random.default_rng(11)
    raw = rng.poisson(_scan(o, z, per_mm) * 2e5) + 100.0 + rng.normal(0.0, 2.0, (len(z), 176, 240))
    raw = np.round(raw).clip(0, 65535).astype(np.uint16)
    stack, depths, rec = prepare_psf_stack(raw, z, axial_bin=25, sensor_shape=(192, 256))
    assert stack.shape == sim.psf.shape and np.allclose(depths, sim.depths_um)
    reg = next(s for s in rec["steps"] if s["step"] == "registration")
    assert np.abs(np.array(reg["drift_px_per_mm"]) - per_mm).max() <= 0.1
    dark = next(s for s in rec["steps"] if s["step"] == "dark level")
    assert 99.0 <= dark["level_min"] <= dark["level_max"] <= 101.0
    assert "warnings" not in rec and "fitted to 192 x 256" in rec["notes"][0]
    for ideal_plane, plane in zip(sim.psf, stack):
        assert np.abs(measure_shift(ideal_plane, plane)).max() <= 0.1
    scores = []
    for h in (sim.psf, stack):
        r = cm2cl.reconstruct(sim.measurement, h, max_iter=60)
        scores.append(score_beads(r.volume, sim))
    ideal, prep = scores
    n = ideal["n_true"]
    dxy, dz = sim.voxel_size_um[1], sim.voxel_size_um[0]
    assert ideal["recall"] >= 0.8                                    # the comparison is meaningful
    assert prep["recall"] >= ideal["recall"] - 1.0 / n and prep["precision"] >= ideal["precision"] - 1.0 / n
    assert prep["lateral_rms_um"] <= ideal["lateral_rms_um"] + 0.25 * dxy
    assert prep["axial_rms_um"] <= ideal["axial_rms_um"] + 0.5 * dz


@pytest.mark.skipif(not DATA.exists(), reason="../shared/data/diffusercam-3d not present")
def test_diffusercam_psf_corner_background_is_removed(tmp_path, capsys):
    """All 44 real planes through the CLI with the README's recipe (per-plane median of the four 20 x 20
    corners subtracted, clipped at 0, unit sum: --noise-floor 0 --no-register): equal to the recipe in
    float64 up to the float32 output (1e-6 of the peak); half of every plane's corner pixels read 0 and
    their share of the plane's light falls to under 0.55 of the raw one (measured 0.45 to 0.50: what is
    left is the noise above the median, which the recipe keeps)."""
    files = sorted((DATA / "psf").glob("psf*.tiff"))
    out = tmp_path / "psf.ome.tif"
    assert main(["prepare-psf", str(DATA / "psf"), "--z-start", "0", "--z-step", "10", "--noise-floor", "0",
                 "--no-register", "-o", str(out)]) == 0
    cap = capsys.readouterr()
    assert cap.err == "" and "44 planes of 270 x 320" in cap.out
    stack, meta = io.read_tiff(out)
    raw = np.stack([tifffile.imread(f) for f in files]).astype(np.float64)

    def corners(p):
        return np.concatenate([p[:20, :20].ravel(), p[:20, -20:].ravel(), p[-20:, :20].ravel(), p[-20:, -20:].ravel()])

    recipe = []
    for p in raw:
        q = np.maximum(p - np.median(corners(p)), 0.0)
        recipe.append(q / q.sum())
    recipe = np.stack(recipe)
    assert np.abs(stack - recipe).max() <= 1e-6 * recipe.max()
    for p, q in zip(raw, stack):
        assert np.mean(corners(q) == 0.0) >= 0.49                  # those at or under the median
        assert corners(q).mean() / q.sum() < 0.55 * corners(p).mean() / p.sum()
    record = json.loads((tmp_path / "psf.cm2cl.json").read_text())
    assert record["steps"][1]["level_min"] > 0 and record["output"] == "psf.ome.tif"
    assert meta["depths_um"] == [10.0 * i for i in range(44)]


def _write_scan(path, planes, depths=None):
    if depths is None:
        tifffile.imwrite(path, planes, photometric="minisblack")
    else:
        io.write_tiff(path, planes, depths_um=depths)
    return path


def test_cli_stack_with_metadata_depths_is_taken_by_reconstruct_with_its_scale(rt, tmp_path, capsys):
    """A scan whose OME planes carry z (no --z-start/--z-step), 3 planes summed, binned 2 x 2,
    --object-pixel-um: the stack has the voxel size and depths; cm2cl reconstruct takes a measurement
    larger than the (cropped) stack, pads the PSF around its axis, says so, and labels the volume with the
    PSF's scale and depths."""
    o = _optics(8, (120, 150))
    z = np.arange(-45.0, 46.0, 10.0)[:9]                    # 9 planes, 3 output planes at -35, -5, 25 um
    raw = (_scan(o, z, (0.0, 0.0)) * 3e4 + 100).astype(np.uint16)
    scan = _write_scan(tmp_path / "scan.ome.tif", raw, depths=z)
    out = tmp_path / "psf.ome.tif"
    assert main(["prepare-psf", str(scan), "--axial-bin", "3", "--bin", "2", "--object-pixel-um", "42.24",
                 "-o", str(out)]) == 0
    assert "3 planes of 60 x 75" in capsys.readouterr().out
    stack, meta = io.read_tiff(out)
    api, _, _ = prepare_psf_stack(raw, z, axial_bin=3, lateral_bin=2)        # the CLI is the API
    assert stack.shape == (3, 60, 75) and np.abs(stack - api).max() <= 1e-6 * api.max()
    assert meta["voxel_size_um"] == pytest.approx((30.0, 84.48, 84.48))
    assert meta["depths_um"] == pytest.approx([-35.0, -5.0, 25.0])
    assert meta["extra"]["voxel_space"] == io.OBJECT_SPACE and meta["extra"]["axis_pixel"] == [30, 37]
    meas = tmp_path / "meas.tif"
    tifffile.imwrite(meas, (np.random.default_rng(0).random((65, 80)) * 100).astype(np.float32))
    vol = tmp_path / "vol.ome.tif"
    assert main(["reconstruct", str(meas), "--psf", str(out), "-o", str(vol), "--max-iter", "3", "--quiet"]) == 0
    said = capsys.readouterr().err          # a note on stderr
    assert "60 x 75 pixels fitted to 65 x 80 (5 rows of zeros added, 5 columns of zeros added)" in said
    v, vmeta = io.read_tiff(vol)
    assert v.shape == (3, 65, 80) and vmeta["voxel_size_um"] == pytest.approx((30.0, 84.48, 84.48))
    assert vmeta["depths_um"] == pytest.approx([-35.0, -5.0, 25.0])
    assert "fitted to 65 x 80" in json.loads((tmp_path / "vol.cm2cl.json").read_text())["info"]["psf_fit"]


def test_api_options_and_refusals():
    o = _optics(8, (60, 60))
    z = np.arange(0.0, 100.0, 10.0)
    brightness = 1.0 + np.arange(10) / 10.0                  # the source brightens during the scan
    planes = _scan(o, z, (0.0, 0.0)) * 1e4 * brightness[:, None, None] + 50.0
    st, d, rec = prepare_psf_stack(planes, z, dz_um=50.0, register=False, normalise="stack",
                                   dark=("region", (0, 5, 0, 60)))
    sums = st.reshape(2, -1).sum(1)                           # relative throughput kept: 6.0 / 8.5
    assert st.shape == (2, 60, 60) and np.allclose(d, [20.0, 70.0]) and sums == pytest.approx([6.0 / 8.5, 1.0], rel=1e-3)
    st2, d2, _ = prepare_psf_stack(planes[::-1], z[::-1], dz_um=50.0, register=False, normalise="stack",
                                   dark=("region", (0, 5, 0, 60)))
    assert np.allclose(d2, d) and np.allclose(st2, st)          # a scan towards the lens: same stack
    one, _, _ = prepare_psf_stack(planes, z, register=False, dark=50.0, noise_floor=0)
    two, _, _ = prepare_psf_stack(planes, z, register=False, dark=50.0, noise_floor=0, lateral_bin=2)
    assert two.shape == (10, 30, 30) and np.allclose(two, io.bin_image(one, 2))   # sums of 2 x 2, unit sum
    st3, d3, rec3 = prepare_psf_stack(planes, z, z_range=(20, 60), axial_bin=2, register=False, dark=50.0)
    assert np.allclose(d3, [25.0, 45.0]) and rec3["steps"][0]["planes_dropped_for_binning"] == 1
    for kw, msg in [({"z_range": (0, 150)}, r"scan: depth range \[0, 150\] um is outside the scan's \[0, 90\] um"),
                    ({"dz_um": 25.0}, "dz: 25 um is not a whole multiple of the scan step 10 um"),
                    ({"dz_um": -10.0}, "dz: must be a positive number of um, got -10"),
                    ({"axial_bin": 11}, "10 plane.s. in the depth range cannot be binned by 11"),
                    ({"dark": np.zeros((5, 5))}, r"the dark frame's shape \(5, 5\) differs from the planes' \(60, 60\)"),
                    ({"dark": ("region", (0, 70, 0, 5))}, "dark region rows 0:70, columns 0:5 is empty or outside"),
                    ({"sensor_shape": (0, 10)}, "sensor shape"),
                    ({"lateral_bin": 200}, r"lateral bin: 200 is larger than the 60 x 60 planes"),
                    ({"shift_method": "cubic"}, "shift method: unknown 'cubic'")]:
        with pytest.raises(InputError, match=msg):
            prepare_psf_stack(planes, z, **kw)
    with pytest.raises(InputError, match="10 planes but 2 z positions"):
        prepare_psf_stack(planes, [0, 10])
    mixed = [planes[0], planes[1][:50]]
    with pytest.raises(InputError, match=r"scan: plane 1 has shape \(50, 60\), plane 0 \(60, 60\)"):
        prepare_psf_stack(mixed, [0, 10])


def _run(argv, capsys):
    code = main(argv)
    cap = capsys.readouterr()
    return code, cap.out, cap.err.strip().splitlines()


def test_bad_scans_are_refused_in_one_line_and_write_nothing(tmp_path, capsys):
    o = _optics(8, (40, 40))
    planes = (_scan(o, np.arange(0.0, 50.0, 10.0), (0.0, 0.0)) * 1e4 + 100).astype(np.uint16)
    good = _write_scan(tmp_path / "good.tif", planes)
    shapes = tmp_path / "shapes"
    shapes.mkdir()
    tifffile.imwrite(shapes / "a.tif", planes[0])
    tifffile.imwrite(shapes / "b.tif", planes[1][:30])
    (tmp_path / "empty").mkdir()
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "readme.txt").write_text("not an image")
    (tmp_path / "fake.tif").write_text("not a TIFF either")
    tifffile.imwrite(tmp_path / "dark_small.tif", np.zeros((30, 30), np.uint16))
    zs = ["--z-start", "0", "--z-step", "10"]
    cases = [
        ([str(shapes)] + zs, f"scan '{shapes / 'b.tif'}' (frame 1 of the series, page 0 of the file): shape (30, 40) differs from the first frame's"),
        ([str(good), "--z-range", "0", "100"] + zs, "depth range [0, 100] um is outside the scan's [0, 40] um"),
        ([str(tmp_path / "empty")] + zs, f"scan '{tmp_path / 'empty'}': the folder holds no .tif/.tiff file"),
        ([str(tmp_path / "notes")] + zs, f"scan '{tmp_path / 'notes'}': the folder holds no .tif/.tiff file"),
        ([str(tmp_path / "fake.tif")] + zs, f"scan '{tmp_path / 'fake.tif'}': not a readable TIFF"),
        ([str(good), "--dark", str(tmp_path / "dark_small.tif")] + zs, "differs from the scan's planes (40, 40)"),
        ([str(good)], "its files carry no z position per plane (OME Plane PositionZ); give --z-start and --z-step"),
        ([str(good), "--z-start", "0"], "--z-start/--z-step: give both"),
        ([str(good), "--axis", "3"] + zs, "--axis: expected ROW,COL or 'centroid'"),
        ([str(good), "--dark", "region:0:5"] + zs, "--dark: expected region:R0:R1,C0:C1"),
    ]
    for argv, msg in cases:
        out = tmp_path / "psf.ome.tif"
        before = sorted(p.name for p in tmp_path.iterdir())
        code, _, err = _run(["prepare-psf"] + argv + ["-o", str(out)], capsys)
        assert code == 2 and len(err) == 1 and err[0].startswith("cm2cl: error:") and msg in err[0], (argv, err)
        assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_a_dark_region_that_is_not_dark_and_ignored_files_are_warned_about(tmp_path, capsys):
    """A region inside a blurred spot (peak 1000 over a dark level of 100): one warning line with the level
    measured (and the stack is still written); a folder's non-TIFF file: a warning naming it."""
    rng = np.random.default_rng(2)
    r, c = np.indices((40, 40))
    spot = 1000.0 * np.exp(-((r - 20) ** 2 + (c - 20) ** 2) / (2 * 6.0 ** 2))
    planes = np.round(100 + spot + rng.normal(0, 2, (5, 40, 40))).astype(np.uint16)
    folder = tmp_path / "scan"
    folder.mkdir()
    for i, p in enumerate(planes):
        tifffile.imwrite(folder / f"z{i:02d}.tif", p)
    (folder / "stage.log").write_text("positions")
    out = tmp_path / "psf.ome.tif"
    code, said, err = _run(["prepare-psf", str(folder), "--z-start", "0", "--z-step", "10", "--dark",
                            "region:15:25,15:25", "-o", str(out)], capsys)
    assert code == 0 and out.exists() and len(err) == 2, err
    assert err[0].startswith(f"cm2cl: warning: scan '{folder}': the dark level (median of rows 15:25, columns "
                             "15:25 of each plane) is not dark in 5 of 5 planes: up to ")
    level = float(err[0].split("up to ")[1].split(" ")[0])
    assert abs(level - np.median(100 + spot[15:25, 15:25])) < 5   # the spot's light (892), not the dark 100
    assert "1 file(s) that are not TIFFs were not read: stage.log" in err[1]
    code, said, err = _run(["prepare-psf", str(folder), "--z-start", "0", "--z-step", "10", "--dark", "corners:8",
                            "-o", str(tmp_path / "psf2.ome.tif")], capsys)
    assert code == 0 and len(err) == 1                                      # 8 x 8 corners are dark
    assert 99.0 <= float(said.split("dark level ")[1].split(";")[0]) <= 102.0

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

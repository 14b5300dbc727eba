"""The CM2 simulator: scenes, objects, effects (each doing what it claims, and only when named),
the shift-invariant path being the project's forward operator, outputs, CLI, and bad input."""

import argparse
import json
import math

import numpy as np
import pytest
from scipy import ndimage

import cm2cl.simulate as sim
from cm2cl.simulate import pipeline
from cm2cl import reference
from cm2cl.analysis import local_sbr, signal_mask
from cm2cl.errors import InputError
from cm2cl.io import read_tiff, write_tiff
from cm2cl.optics import CM2Optics
from cm2cl.simulate import effects as fx
from cm2cl.simulate import objects as ob
from cm2cl.cli.simulate import register


def scene(objects, effects=(), *, size=(2.0, 2.0, 0.5), dz=250.0, binning=8, render=None, **extra):
    d = {"name": "t", "optics": {"binning": binning},
         "volume": {"size_mm": list(size), "dz_um": dz},
         "objects": list(objects), "effects": list(effects),
         "output": {"measurement_dtype": "float32"}}
    if render:
        d["render"] = render
    d.update(extra)
    return d


def bead(x_um=0.0, y_um=0.0, z_um=0.0, d=10.0, brightness=2.0e4):
    return {"type": "beads", "diameter_um": d, "positions_um": [[x_um, y_um, z_um]], "brightness": brightness}


def count_foci(img, rel=0.1):
    m = ndimage.binary_dilation(img > rel * img.max(), iterations=2)
    return ndimage.label(m)[1]


def padded_volume(result):
    """The ground truth embedded in the forward model's padded grid."""
    py, px = result.record["render"]["padded_shape"]
    my, mx = result.ground_truth.shape[1:]
    x = np.zeros((result.ground_truth.shape[0], py, px))
    oy, ox = (py - my) // 2, (px - mx) // 2
    x[:, oy:oy + my, ox:ox + mx] = result.ground_truth
    return x, (py, px)


# ---------------------------------------------------------------------------------------------
# built-in scenes, determinism
# ---------------------------------------------------------------------------------------------

def test_builtin_scenes_are_valid():
    names = sim.builtin_scenes()
    for n in ("demo_beads", "fig3_beads", "fig4_fibres", "fig5_scattering", "fig2_target", "vessels"):
        assert n in names
        s = sim.load_scene(n)
        assert s.description and s.depths_um.size >= 1
    s = sim.load_scene("fig3_beads")
    assert s.box.size_mm == (5.7, 6.0) and s.box.z_range_um == (-500.0, 500.0)
    assert [e["name"] for e in sim.load_scene("fig5_scattering").effects] == ["background", "scattering", "noise"]


def test_demo_scene_is_deterministic_per_seed():
    a = sim.simulate_scene("demo_beads", seed=11)
    b = sim.simulate_scene("demo_beads", seed=11)
    c = sim.simulate_scene("demo_beads", seed=12)
    assert a.measurement.dtype == np.uint16             # 8-bit pixels summed over 8 x 8 binning
    assert np.array_equal(a.measurement, b.measurement)
    assert np.array_equal(a.ground_truth, b.ground_truth)
    assert not np.array_equal(a.measurement, c.measurement)
    assert a.record["render"]["path"] == "shift_invariant"
    assert a.ground_truth.shape == (5, 243, 324) and a.psf.shape == (5, 243, 324)
    assert len(a.emitters["x_um"]) == 12
    assert a.ground_truth.sum() == pytest.approx(12 * 3.0e5, rel=1e-5)   # every bead inside the window


# ---------------------------------------------------------------------------------------------
# the shift-invariant path is the forward operator
# ---------------------------------------------------------------------------------------------

def test_shift_invariant_path_is_the_forward_operator():
    """The noise-free simulated image equals y = C sum_i h_i (*) x_i applied to the saved ground
    truth with the saved PSF: by the float64 reference and by the device ForwardModel."""
    beads = {"type": "beads", "diameter_um": 30.0, "count": 10, "brightness": 1e4,
             "region_size_mm": [1.5, 1.5]}
    r = sim.simulate_scene(scene([beads], size=(2.0, 2.0, 0.5), dz=125.0), seed=5)
    assert r.record["render"]["path"] == "shift_invariant"
    x, padded = padded_volume(r)
    assert x.sum() == pytest.approx(10 * 1e4, rel=1e-5)          # nothing outside the window
    y_ref = reference.forward(r.psf, x, padded)
    rel = np.linalg.norm(r.expected - y_ref) / np.linalg.norm(y_ref)
    assert rel < 1e-5
    if r.record["render"]["backend"] == "opencl":
        from cm2cl.solver.forward import ForwardModel
        y_dev = ForwardModel(r.psf, padded_shape=padded).forward(x.astype(np.float32))
        assert np.linalg.norm(r.expected - y_dev) / np.linalg.norm(y_ref) < 1e-6
    # and the numpy backend gives the same image
    r2 = sim.simulate_scene(scene([beads], size=(2.0, 2.0, 0.5), dz=125.0, render={"backend": "numpy"}), seed=5)
    assert r2.record["render"]["backend"] == "numpy"
    assert np.linalg.norm(r2.expected - y_ref) / np.linalg.norm(y_ref) < 1e-12


def test_per_emitter_path_agrees_with_the_shift_invariant_path():
    """Beads on grid nodes and planes: per-emitter PSFs (exact positions) give the same image as
    the slice-wise convolution, so the shift-variant machinery is consistent with the operator."""
    o = CM2Optics(binning=8)
    pos = []
    for z, (kr, kc) in zip((-250.0, 0.0, 250.0), ((3, -5), (-7, 2), (0, 9))):
        m = float(o.magnification(z))
        pos.append([-kc * 17.6 / m, -kr * 17.6 / m, z])
    objs = [{"type": "beads", "diameter_um": 0.5, "positions_um": pos, "brightness": 1e4}]
    a = sim.simulate_scene(scene(objs), seed=0)
    b = sim.simulate_scene(scene(objs, render={"mode": "emitters"}), seed=0)
    assert a.record["render"]["path"] == "shift_invariant" and b.record["render"]["path"] == "emitters"
    assert np.abs(a.expected - b.expected).max() < 1e-3 * a.expected.max()


def test_grid_path_reduces_to_the_operator_where_nothing_varies():
    """Truncation named but the object sits where no view is cut: the local-convolution grid
    (bilinear partition of unity) reproduces the shift-invariant image."""
    tgt = {"type": "target", "groups": [3, 4], "tilt_deg": 20.0, "brightness_per_um2": 1.0}
    a = sim.simulate_scene(scene([tgt], dz=125.0), seed=0)
    b = sim.simulate_scene(scene([tgt], [{"name": "truncation"}], dz=125.0, render={"grid_mm": 1.0}), seed=0)
    assert b.record["render"]["path"] == "grid" and b.record["render"]["kernels_used"] > 4
    assert np.linalg.norm(a.expected - b.expected) / np.linalg.norm(a.expected) < 1e-5


# ---------------------------------------------------------------------------------------------
# effects do what they claim
# ---------------------------------------------------------------------------------------------

NOISE = {k: v["default"] for k, v in fx.EFFECTS["noise"]["params"].items()}


@pytest.mark.parametrize("binning", [1, 4])
def test_noise_statistics_poisson_plus_read_noise(binning):
    rng = np.random.default_rng(0)
    o = CM2Optics(binning=binning)
    mu = 50.0
    img, info = fx.noise(np.full((400, 500), mu), o, rng, **{**NOISE, "bit_depth": 0})
    assert img.dtype == np.float32
    var = mu + binning ** 2 * 6.62 ** 2
    assert img.mean() == pytest.approx(mu, abs=4 * math.sqrt(var / img.size))
    assert img.var() == pytest.approx(var, rel=0.02)


def test_noise_quantisation_and_full_well():
    rng = np.random.default_rng(1)
    o = CM2Optics()
    mu = 2000.0
    dn, info = fx.noise(np.full((400, 500), mu), o, rng, **NOISE)
    gain = 6620.0 / 255
    assert dn.dtype == np.uint8 and info["gain_e_per_dn"] == pytest.approx(gain)
    assert dn.mean() == pytest.approx(mu / gain, abs=0.02)
    assert dn.var() == pytest.approx((mu + 6.62 ** 2) / gain ** 2 + 1 / 12, rel=0.03)
    sat, info = fx.noise(np.full((10, 10), 1e5), o, rng, **NOISE)
    assert np.all(sat == 255) and info["saturated_pixels"] == 100
    binned, info = fx.noise(np.full((10, 10), 1e5), CM2Optics(binning=8), rng, **NOISE)
    assert binned.dtype == np.uint16 and binned.max() <= 64 * 255


def test_background_lowers_sbr_most_where_views_overlap():
    beads = {"type": "beads", "diameter_um": 10.0, "count": 15, "brightness": 2e4, "min_separation_um": 300.0,
             "region_size_mm": [4.0, 4.0]}
    # a sample wider than 2 l/l0 D = 6.8 mm, so that all nine views overlap at the centre
    base = scene([beads], size=(10.0, 8.0, 0.5), dz=250.0)
    clean = sim.simulate_scene(base, seed=2).expected
    mask = signal_mask(clean, 0.2, patch_px=24)
    sbrs = []
    for f in (0.25, 1.0, 4.0):
        img = sim.simulate_scene({**base, "effects": [{"name": "background", "fraction": f}]}, seed=2).expected
        sbrs.append(local_sbr(img, mask, 24)[1])
    assert sbrs[0] > sbrs[1] > sbrs[2] > 1.0
    # the background alone: the central field sees all 9 overlapping views, the outer field fewer
    bg = sim.simulate_scene({**base, "effects": [{"name": "background", "fraction": 4.0}]}, seed=2).expected - clean
    cy, cx = 121, 162
    d = int(round(CM2Optics(binning=8).foci_separation_px(0)))
    assert bg[cy, cx] > 1.3 * bg[cy, cx + int(1.5 * d)]


def test_truncation_drops_views_at_the_field_edge():
    """Views across the field (paper Fig. 2C): 3x3 centre, 2x3 edge, 2x2 corner from the finite
    sensor; the ~21 deg angular cutoff removes more far off axis."""
    cases = [((0, 0), 9, 9), ((0, 2500), 6, 6), ((4000, 2500), 4, 4), ((5000, 0), 6, 3)]
    for (x, y), n_plain, n_trunc in cases:
        plain = sim.simulate_scene(scene([bead(x, y)], size=(12.0, 10.0, 0.0)), seed=0)
        assert count_foci(plain.expected) == n_plain, (x, y)
        for mode in ("emitters", "grid"):
            cut = sim.simulate_scene(scene([bead(x, y)], [{"name": "truncation"}], size=(12.0, 10.0, 0.0),
                                render={"mode": mode}), seed=0)
            assert cut.record["render"]["path"] == mode
            assert count_foci(cut.expected) == n_trunc, (x, y, mode)
            assert cut.expected.sum() == pytest.approx(plain.expected.sum() * n_trunc / n_plain, rel=0.01)


def test_scattering_attenuates_ballistic_light_with_depth():
    ls = 300.0
    top = -500.0                           # top of the 1-mm box
    ratios = []
    for z in (-250.0, 0.0, 250.0, 500.0):
        base = scene([bead(0, 0, z)], size=(2.0, 2.0, 1.0), dz=250.0)
        clear = sim.simulate_scene(base, seed=0).expected
        no_halo = sim.simulate_scene({**base, "effects": [{"name": "scattering", "ls_um": ls, "halo_fraction": 0.0}]},
                          seed=0).expected
        halo = sim.simulate_scene({**base, "effects": [{"name": "scattering", "ls_um": ls}]}, seed=0).expected
        e = math.exp(-(z - top) / ls)
        assert no_halo.sum() / clear.sum() == pytest.approx(e, rel=1e-4)
        assert halo.sum() / clear.sum() == pytest.approx(1.0, abs=0.02)       # scattered, not lost
        assert halo.max() / clear.max() < e + 0.1                             # but spread out
        ratios.append(no_halo.sum() / clear.sum())
    assert np.all(np.diff(ratios) < 0)


def test_vignetting_follows_cos4():
    base = scene([bead(3000, 0, 0)], size=(8.0, 2.0, 0.0))
    plain = sim.simulate_scene(base, seed=0).expected
    vig = sim.simulate_scene({**base, "effects": [{"name": "vignetting"}]}, seed=0).expected
    assert vig.sum() / plain.sum() == pytest.approx(math.cos(math.atan(3.0 / 12.0)) ** 4, rel=1e-3)


def test_aberration_blurs_off_axis_views():
    """Field aberrations (they grow with the field angle) spread an off-axis bead's light: the image's
    effective lit area (sum I)^2 / sum I^2 grows by more than 1.8x at 3.5 mm off axis and by at most 25%
    on axis, with the light conserved. (The area rather than the peak: a spot of about a pixel has a peak
    that depends on where it falls within its pixel.)"""
    area = lambda a: float(a.sum()) ** 2 / float(np.sum(np.square(a, dtype=np.float64)))   # noqa: E731
    for x, lo, hi in ((0.0, 0.8, 1.25), (3500.0, 1.8, 10.0)):
        base = scene([bead(x, 0, 0)], size=(8.0, 2.0, 0.0), binning=4)
        base["optics"]["sensor_shape"] = [700, 900]      # wider than the chip: keep every view
        plain = sim.simulate_scene(base, seed=0).expected
        ab = sim.simulate_scene({**base, "effects": [{"name": "aberration"}]}, seed=0)
        assert ab.record["render"]["path"] == "emitters"
        assert ab.expected.sum() == pytest.approx(plain.sum(), rel=0.01)
        assert lo < area(ab.expected) / area(plain) < hi, x


def test_unnamed_effects_never_run(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("an effect that the scene did not name was run")
    real = {"truncation": fx.truncation, "render_emitters": pipeline.render_emitters}
    for name in fx.EFFECTS:
        monkeypatch.setattr(fx, name, boom)
    monkeypatch.setattr(pipeline, "render_grid", boom)
    monkeypatch.setattr(pipeline, "render_emitters", boom)
    r = sim.simulate_scene(scene([bead()]), seed=0)
    assert r.record["effects_applied"] == [] and r.measurement.dtype == np.float32
    assert sorted(r.record["effects_not_named"]) == sorted(fx.EFFECTS)
    # naming one effect runs that one only
    monkeypatch.setattr(fx, "noise", lambda img, optics, rng, **p: (img.astype(np.float32) + 1.0, {"ran": True}))
    r = sim.simulate_scene(scene([bead()], [{"name": "noise"}]), seed=0)
    assert [e["name"] for e in r.record["effects_applied"]] == ["noise"]
    assert r.record["effects_applied"][0]["info"] == {"ran": True}
    # shift-variant effects take a shift-variant path, never the fast one
    monkeypatch.setattr(fx, "truncation", real["truncation"])
    monkeypatch.setattr(pipeline, "render_emitters", real["render_emitters"])
    monkeypatch.setattr(pipeline, "render_shift_invariant", boom)
    r = sim.simulate_scene(scene([bead()], [{"name": "truncation"}]), seed=0)
    assert r.record["render"]["path"] == "emitters"
    assert [e["name"] for e in r.record["effects_applied"]] == ["truncation"]


def test_z_oversampling_keeps_energy_and_ground_truth_planes():
    beads = {"type": "beads", "diameter_um": 10.0, "count": 6, "brightness": 1e4, "region_size_mm": [1.0, 1.0]}
    a = sim.simulate_scene(scene([beads]), seed=3)
    b = sim.simulate_scene(scene([beads], render={"z_oversample": 3}), seed=3)
    assert b.ground_truth.shape == a.ground_truth.shape
    assert b.ground_truth.sum() == pytest.approx(a.ground_truth.sum(), rel=1e-5)
    assert b.expected.sum() == pytest.approx(a.expected.sum(), rel=1e-3)
    assert not np.allclose(a.expected, b.expected)          # finer depth sampling changes the image


# ---------------------------------------------------------------------------------------------
# objects
# ---------------------------------------------------------------------------------------------

def test_objects_follow_their_geometry():
    box = ob.Box((0.0, 0.0), (4.0, 3.0), (-500.0, 500.0))
    rng = np.random.default_rng(0)
    spec = {k: v.get("default") for k, v in ob.OBJECTS["fibres"]["params"].items()}
    spec.update(count=5, surface_depth_um=600.0)
    f = ob.fibres(spec, box, rng, 5.0)
    assert len(f) > 0
    assert np.abs(f.xyz_um[:, 0]).max() <= 2000 + 7.5 and np.abs(f.xyz_um[:, 1]).max() <= 1500 + 7.5
    surf = ob.surface_z(spec, box, f.xyz_um[:, 0], f.xyz_um[:, 1])
    # on the surface: centre line 7.5 um (a radius) above it, the tube within a radius (+ slope) of that
    assert np.abs(f.xyz_um[:, 2] - surf - 7.5).max() < 12.0
    assert abs(np.mean(f.xyz_um[:, 2] - surf - 7.5)) < 1.0
    # brightness per length: in a huge region (a 2-mm fibre is almost never clipped at its edge)
    big = ob.Box((0.0, 0.0), (1000.0, 1000.0), (-500.0, 500.0))
    unclipped = ob.fibres(spec, big, np.random.default_rng(1), 5.0)
    assert unclipped.weight.sum() == pytest.approx(5 * 2.0 * 2.0e5, rel=0.01)
    t = ob.target({"groups": [4, 5], "tilt_deg": 30.0, "tilt_axis": "x", "center_mm": None,
                   "center_z_um": None, "brightness_per_um2": 1.0}, box, rng, 5.0)
    slope = np.polyfit(t.xyz_um[:, 1], t.xyz_um[:, 2], 1)[0]
    assert slope == pytest.approx(math.tan(math.radians(30.0)), rel=1e-6)
    b = ob.beads({"diameter_um": 10.0, "count": 40, "density_per_mm3": None, "positions_um": None,
                  "min_separation_um": 200.0, "brightness": 1.0, "brightness_cv": 0.0}, box, rng)
    from scipy.spatial.distance import pdist
    assert len(b) == 40 and pdist(b.xyz_um).min() >= 200.0 and box.contains(b.xyz_um).all()
    v = ob.vessels({k: p.get("default") for k, p in ob.OBJECTS["vessels"]["params"].items()}, box, rng, 10.0)
    assert len(v) > 0 and box.contains(v.xyz_um, tol_um=60.0).all()


# ---------------------------------------------------------------------------------------------
# outputs, io, CLI
# ---------------------------------------------------------------------------------------------

def napari_points_csv(path):
    """Points as napari's builtin CSV reader gives them (napari_builtins/io/_read.py: ``read_csv``,
    ``_guess_layer_type_from_column_names``, ``_points_csv_to_layerdata``): the header names the
    columns; 'points' when 'axis-0' and 'axis-1' are among them (and not the shapes set); the
    ``axis-*`` columns, in file order, are the coordinates; the other columns, except a first one
    named 'index', become properties."""
    import csv
    with open(path, newline="") as f:
        reader = csv.reader(f, delimiter=",")
        names = next(reader)
        table = np.array(list(reader))
    assert not {"index", "shape-type", "vertex-index", "axis-0", "axis-1"} <= set(names)
    assert {"axis-0", "axis-1"} <= set(names), f"napari would not read {names} as points"
    axes = np.array([n.startswith("axis-") for n in names])
    data = table[:, axes].astype(float)
    props = {n: table[:, i].astype(float) for i, n in enumerate(names)
             if not axes[i] and not (i == 0 and n == "index")}
    return data, props


def test_simulate_writes_tiffs_with_geometry_and_a_record(tmp_path):
    from test_io import ome_scale, resolution_um
    out = tmp_path / "demo"
    rec = sim.simulate("demo_beads", out, seed=3)
    names = sorted(p.name for p in out.iterdir())
    assert names == ["emitters.csv", "ground_truth.ome.tif", "measurement.ome.tif", "psf.ome.tif",
                     "simulation.json"]
    obj = 17.6 * 12 / 5                  # object-space voxel: sensor pixel / magnification (l0 / l)
    depths = [-500, -250, 0, 250, 500]
    # scale as Fiji (OME via Bio-Formats; resolution tags) reads it, not through cm2cl's reader
    meas, _ = read_tiff(out / "measurement.ome.tif")
    assert meas.dtype == np.uint16 and resolution_um(out / "measurement.ome.tif") == pytest.approx((17.6, 17.6))
    for name in ("psf.ome.tif", "ground_truth.ome.tif"):
        sizes, z = ome_scale(out / name)
        assert sizes == pytest.approx((250.0, obj, obj)) and z == pytest.approx(depths), name
        assert resolution_um(out / name) == pytest.approx((obj, obj), rel=1e-6), name
    psf, pm = read_tiff(out / "psf.ome.tif")
    assert psf.shape == (5, 243, 324) and pm["extra"]["voxel_space"] == "object"
    gt, gm = read_tiff(out / "ground_truth.ome.tif")
    assert gm["extra"]["kind"] == "ground_truth"
    saved = json.loads((out / "simulation.json").read_text())
    assert saved["seed"] == 3 and saved == rec
    assert saved["psf"]["voxel_size_um"] == pytest.approx([250.0, obj, obj]) and saved["psf"]["depths_um"] == depths
    assert [e["name"] for e in saved["effects_applied"]] == ["noise"]
    # emitters.csv as napari reads it: points at the beads' voxels of the ground truth, physical columns kept
    pts, props = napari_points_csv(out / "emitters.csv")
    assert pts.shape == (12, 3) and set(props) == {"x_um", "y_um", "z_um", "brightness", "diameter_um"}
    idx = np.round(pts).astype(int)
    assert (gt[idx[:, 0], idx[:, 1], idx[:, 2]] > 0.25 * gt.max()).all()
    assert np.allclose(np.interp(pts[:, 0], np.arange(5), depths), props["z_um"], atol=1e-3 * 250)
    # one frame for volumes, MIPs and emitters: the um columns are napari's world coordinates of the ground
    # truth (index x scale + translate, as its reader places the volume), and the record maps them back to
    # the scene's own object positions (from the optical axis, mirrored, at the depth's magnification)
    from cm2cl.io.napari_reader import read_tiff_layer
    _, gkw, _ = read_tiff_layer(out / "ground_truth.ome.tif")
    world = pts * np.array(gkw["scale"]) + np.array(gkw["translate"])
    assert np.allclose(np.column_stack([props["z_um"], props["y_um"], props["x_um"]]), world, rtol=1e-7, atol=1e-4)
    fr = saved["emitters_frame"]
    k = (fr["l_um"] + props["z_um"]) / fr["l_um"]
    obj = np.column_stack([(fr["x0_um"] - props["x_um"]) * k, (fr["y0_um"] - props["y_um"]) * k, props["z_um"]])
    truth = sim.simulate_scene("demo_beads", seed=3).emitters
    true_xyz = np.column_stack([truth["x_um"], truth["y_um"], truth["z_um"]])
    assert np.allclose(obj, true_xyz, rtol=1e-6, atol=1e-4)
    assert np.array_equal(meas, sim.simulate_scene("demo_beads", seed=3).measurement)
    # a second run into the same directory replaces it
    sim.simulate("demo_beads", out, seed=4)
    assert json.loads((out / "simulation.json").read_text())["seed"] == 4


def test_interrupted_simulation_leaves_no_complete_output(tmp_path, monkeypatch):
    import cm2cl.io.tiff as io
    calls = []

    def failing(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise OSError("disk full")
        return write_tiff(*a, **k)
    monkeypatch.setattr(io, "write_tiff", failing)
    with pytest.raises(InputError, match=r"writing failed \(disk full\); nothing was written$"):
        sim.simulate(scene([bead()]), tmp_path / "out", seed=0)
    assert list(tmp_path.iterdir()) == []


def test_cli_simulate_and_list(tmp_path, capsys):
    parser = argparse.ArgumentParser(prog="cm2cl")
    register(parser.add_subparsers())
    args = parser.parse_args(["simulate", "--list"])
    assert args.func(args) == 0
    assert "demo_beads" in capsys.readouterr().out
    args = parser.parse_args(["simulate", "demo_beads", "-o", str(tmp_path / "o"), "--seed", "1"])
    assert args.func(args) == 0
    assert (tmp_path / "o" / "simulation.json").exists()
    with pytest.raises(InputError, match="-o OUTDIR"):
        args = parser.parse_args(["simulate", "demo_beads"])
        args.func(args)
    with pytest.raises(InputError, match="no built-in scene"):
        args = parser.parse_args(["simulate", "fig9_nothing", "-o", str(tmp_path / "x")])
        args.func(args)


def test_main_cli_turns_bad_scenes_into_exit_code_2(tmp_path, capsys):
    from cm2cl.cli import main
    (tmp_path / "bad.toml").write_text('[volume]\nsize_mm = [1.0, 1.0, 0.0]\n[[objects]]\ntype = "bead"\n')
    assert main(["simulate", str(tmp_path / "bad.toml"), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("cm2cl: error: scene 'bad.toml': objects[0].type: unknown object 'bead' "
                   "(known: beads, fibres, target, vessels)")
    assert not (tmp_path / "o").exists()


# ---------------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------------

GOOD = """
[optics]
binning = 8
[volume]
size_mm = [2.0, 2.0, 0.5]
dz_um = 250.0
[[objects]]
type = "beads"
diameter_um = 10.0
count = 3
"""


@pytest.mark.parametrize("text, message", [
    (GOOD + '[[effects]]\nname = "noise"\n[[effects]]\nname = "background"\n',
     "effects[1].name: 'background' acts on the sample/optics and must come before"),
    (GOOD + '[[effects]]\nname = "vignetting"\n[[effects]]\nname = "background"\n[[effects]]\nname = "blurr"\n',
     "scene 'x.toml': effects[2].name: unknown effect 'blurr' (known: noise, background, scattering, "
     "truncation, aberration, vignetting)"),
    (GOOD.replace('type = "beads"', 'type = "bead"'), "objects[0].type: unknown object 'bead' (known: beads"),
    (GOOD.replace("diameter_um = 10.0", "diameter_um = -5.0"), "objects[0].diameter_um: must be > 0, got -5.0"),
    (GOOD.replace("size_mm = [2.0, 2.0, 0.5]", "size_mm = [2.0, -2.0, 0.5]"), "volume.size_mm[1]: must be >= 0"),
    (GOOD.replace("size_mm = [2.0, 2.0, 0.5]\n", ""), "volume.size_mm: missing (required)"),
    (GOOD.replace("dz_um", "dz_mm"), "volume.dz_mm: unknown key"),
    (GOOD.replace("count = 3", "count = 3\ndensity_per_mm3 = 2.0"), "objects[0]: give exactly one of count"),
    (GOOD.replace("binning = 8", "binning = 0"), "scene 'x.toml': optics.binning: must be >= 1, got 0"),
    (GOOD.replace("binning = 8", "binnig = 8"), "optics.binnig: unknown optics field"),
    (GOOD + '[[effects]]\nname = "scattering"\n', "effects[0].ls_um: missing (required)"),
    (GOOD + '[[effects]]\nname = "noise"\nsigma = 3\n', "effects[0].sigma: unknown key"),
    (GOOD + '[[effects]]\nname = "noise"\n[[effects]]\nname = "noise"\n', "effect 'noise' named twice"),
    (GOOD + '[render]\nmode = "shift_invariant"\n[[effects]]\nname = "truncation"\n',
     "render.mode: 'shift_invariant' cannot model"),
    (GOOD.replace("[[objects]]", "[[objects]]\nwhat = 1"), "objects[0].what: unknown key"),
    (GOOD.replace("binning = 8", "binning = 1").replace("size_mm = [2.0, 2.0, 0.5]", "size_mm = [2.0, 2.0, 9.0]")
     .replace("dz_um = 250.0", "dz_um = 1.0"), "scene 'x.toml': volume: needs ~"),
    ("[volume\n", "scene 'x.toml': not valid TOML"),
    ("a = " + "[" * 5000 + "]" * 5000 + "\n", "scene 'x.toml': nested too deeply to read"),
    (GOOD.replace("[[objects]]\ntype = \"beads\"\ndiameter_um = 10.0\ncount = 3\n", ""), "objects: the scene has no objects"),
])
def test_bad_scenes_raise_one_line_input_errors(tmp_path, text, message):
    p = tmp_path / "x.toml"
    p.write_text(text)
    with pytest.raises(InputError) as info:
        sim.simulate_scene(p, seed=0)
    msg = str(info.value)
    assert message in msg and "\n" not in msg
    assert isinstance(info.value, ValueError)


def test_missing_scene_files():
    with pytest.raises(InputError, match="scene 'nowhere/x.toml': no such file"):
        sim.load_scene("nowhere/x.toml")
    with pytest.raises(InputError, match="built-in: demo_beads"):
        sim.load_scene("no_such_scene")


# ---------------------------------------------------------------------------------------------
# the demo (short run; the full demo uses 200 iterations)
# ---------------------------------------------------------------------------------------------

def test_demo_recovers_the_beads(tmp_path):
    from cm2cl.cli.demo import demo
    s = demo(tmp_path / "demo", max_iter=60, verbose=False)
    assert s["emitters"]["true"] == 12 and s["emitters"]["recall"] >= 0.9
    # lateral errors well under a voxel (42 um), axial well under a plane (250 um)
    assert s["lateral_error_um"]["rms"] < 0.3 * s["voxel_size_um"][1]
    assert s["axial_error_um"]["rms"] < 0.5 * s["voxel_size_um"][0]
    names = sorted(p.name for p in (tmp_path / "demo").iterdir())
    assert names == ["demo.json", "mip_ground_truth.png", "mip_reconstruction.png", "reconstruction.ome.tif",
                     "reconstruction_log.csv", "simulation"]
    vol, _ = read_tiff(tmp_path / "demo" / "reconstruction.ome.tif")
    assert vol.shape == (5, 243, 324)
    # the reconstruction carries the ground truth's object-space scale, as other programs read it
    from test_io import ome_scale
    assert ome_scale(tmp_path / "demo" / "reconstruction.ome.tif") == \
        ome_scale(tmp_path / "demo" / "simulation" / "ground_truth.ome.tif")
    assert ome_scale(tmp_path / "demo" / "reconstruction.ome.tif")[1] == [-500, -250, 0, 250, 500]

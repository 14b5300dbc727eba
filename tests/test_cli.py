"""The command line as a user runs it: outputs complete or absent, one-line errors."""

import io as _io
import json
import sys

import numpy as np
import pytest
import tifffile
from scipy.ndimage import gaussian_filter

from cm2cl import io
from cm2cl.cli import main
from cm2cl.cli.reconstruct import Progress
from cm2cl.errors import InputError
from test_admm import bead_problem
from test_io import ome_scale, resolution_um


def _files(tmp_path):
    psf, _, y = bead_problem(6)
    tifffile.imwrite(tmp_path / "psf.tif", (psf * 1000 + 100).astype(np.uint16), photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", (y * 1000 + 100).astype(np.uint16))
    return tmp_path / "meas.tif", tmp_path / "psf.tif"


def test_reconstruct_writes_volume_and_log(rt, tmp_path, capsys):
    meas, psf = _files(tmp_path)
    out = tmp_path / "vol.tif"
    assert main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(out), "--offset", "100", "--psf-offset", "100",
                 "--max-iter", "40", "--quiet"]) == 0
    vol, meta = io.read_tiff(out)
    assert vol.shape == (4, 32, 40) and vol.dtype == np.float32 and vol.min() >= 0 and vol.max() > 0
    assert meta["extra"]["scaling"]["y_scale"] > 0
    rows = (tmp_path / "vol.cm2cl.log.csv").read_text().splitlines()
    assert rows[0].startswith("iter,objective,data") and len(rows) == 41
    doc = json.loads((tmp_path / "vol.cm2cl.json").read_text())
    assert doc["params"]["max_iter"] == 40 and len(doc["log"]) == 40
    mis = doc["info"]["misfit"]   # the data misfit reached, in the record and the TIFF's metadata
    assert 0 < mis["relative"] < 1 and mis["ratio"] > 0 and mis["pixels"] == 32 * 40
    assert meta["extra"]["info"]["misfit"] == mis
    assert not list(tmp_path.glob("*.partial"))


def test_a_single_frame_with_singleton_axes_is_one_image(rt, tmp_path, capsys):
    """A 5-D TIFF of one frame (TCZYX = 1, 1, 1, My, Mx) reconstructs as its 2D image does (a series reads it so
    too); two frames in it are refused with a pointer to a series output (issue 27)."""
    meas, psf = _files(tmp_path)
    img = tifffile.imread(meas)
    tifffile.imwrite(tmp_path / "five.tif", img[None, None, None], metadata={"axes": "TCZYX"})
    base = ["--psf", str(psf), "--max-iter", "5", "--quiet"]
    assert main(["reconstruct", str(meas), "-o", str(tmp_path / "a.ome.tif"), *base]) == 0
    assert main(["reconstruct", str(tmp_path / "five.tif"), "-o", str(tmp_path / "b.ome.tif"), *base]) == 0
    np.testing.assert_array_equal(io.read_tiff(tmp_path / "a.ome.tif")[0], io.read_tiff(tmp_path / "b.ome.tif")[0])
    tifffile.imwrite(tmp_path / "two.tif", np.stack([img, img])[:, None, None], metadata={"axes": "TCZYX"})
    capsys.readouterr()
    assert main(["reconstruct", str(tmp_path / "two.tif"), "-o", str(tmp_path / "c.ome.tif"), *base]) == 2
    err = capsys.readouterr().err
    assert "(2, 1, 1, 32, 40)" in err and ".ome.zarr" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "c.ome.tif").exists()


def test_reconstruct_bad_input_writes_nothing(rt, tmp_path, capsys):
    meas, psf = _files(tmp_path)
    tifffile.imwrite(tmp_path / "stack.tif", np.ones((2, 32, 40), np.uint16))
    tifffile.imwrite(tmp_path / "small.tif", np.ones((32, 30), np.uint16))
    cases = [
        (["reconstruct", str(tmp_path / "small.tif"), "--psf", str(psf), "--bin", "64"], "smaller than the bin"),
        (["reconstruct", str(tmp_path / "stack.tif"), "--psf", str(psf)], "expected a 2D image, got shape (2, 32, 40)"),
        (["reconstruct", str(meas), "--psf", str(psf), "--tv", "-1"], "tv: must be >= 0, got -1.0"),
        (["reconstruct", str(tmp_path / "nope.tif"), "--psf", str(psf)], "no such file"),
        (["reconstruct", str(meas), "--psf", str(psf), "--offset", "dark"], "--offset: expected"),
        (["reconstruct", str(meas), "--psf", str(psf), "--offset", "nan"], "--offset: expected a finite number"),
        (["reconstruct", str(meas), "--psf", str(psf), "--psf-offset", "inf"], "--psf-offset: expected a finite"),
        (["reconstruct", str(meas), "--psf", str(psf), "--offset", "-5"], "--offset: a dark level is >= 0 ADU"),
        (["reconstruct", str(meas), "--psf", str(psf), "--psf-offset", "-0.5"], "--psf-offset: a dark level is >= 0"),
    ]
    for argv, msg in cases:
        out = tmp_path / "out.tif"
        assert main(argv + ["-o", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0] and err[0].startswith("cm2cl: error:")
        assert not out.exists() and not (tmp_path / "out.cm2cl.log.csv").exists()


def test_reconstruct_labels_the_volume_with_the_ground_truths_object_space_scale(rt, tmp_path, capsys):
    """Defect 1: the volume was labelled with the sensor pixel (17.6 um) while the ground truth's grid is
    42.24 um in object space. Compared as Fiji reads them: OME PhysicalSize* / PositionZ and the TIFF
    resolution tags."""
    import cm2cl.simulate as sim
    sim.simulate("demo_beads", tmp_path / "s", seed=2)
    meas, psf, gt = (tmp_path / "s" / n for n in ("measurement.ome.tif", "psf.ome.tif", "ground_truth.ome.tif"))
    out = tmp_path / "vol.ome.tif"
    # the labels come from the PSF's scale, whatever the solve: no PSF refinement (its rounds cost a minute here)
    assert main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(out), "--max-iter", "2", "--psf-refine", "0",
                 "--quiet"]) == 0
    (dz, dy, dx), depths = ome_scale(gt)
    assert dy == pytest.approx(42.24) and depths == [-500, -250, 0, 250, 500]
    assert ome_scale(out) == ome_scale(gt)
    assert resolution_um(out) == pytest.approx(resolution_um(gt), rel=1e-9)
    assert "voxel 250 x 42.24 x 42.24 um" in capsys.readouterr().out
    assert (tmp_path / "vol.cm2cl.log.csv").exists() and (tmp_path / "vol.cm2cl.json").exists()
    with tifffile.TiffFile(out) as tf:
        assert tf.series[0].dtype == np.float32
    # binning widens the lateral voxel, depths stay; a float64 solve gives a float64 volume
    out2 = tmp_path / "vol2.ome.tif"
    dt = "float64" if rt.caps.fp64 else "float32"
    assert main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(out2), "--max-iter", "1", "--bin", "2",
                 "--dtype", dt, "--psf-refine", "0", "--quiet"]) == 0
    with tifffile.TiffFile(out2) as tf:
        assert tf.series[0].dtype == np.dtype(dt)
    sizes, z = ome_scale(out2)
    assert sizes == pytest.approx((dz, 2 * dy, 2 * dx)) and z == depths
    assert resolution_um(out2) == pytest.approx((2 * dy, 2 * dx), rel=1e-6)


def test_reconstruct_without_an_object_space_psf_labels_pixels_or_the_given_voxel(rt, tmp_path, capsys):
    meas, psf = _files(tmp_path)           # plain TIFFs without scale, like a DiffuserCam PSF
    out = tmp_path / "px.ome.tif"
    assert main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(out), "--offset", "100", "--psf-offset", "100",
                 "--max-iter", "2", "--quiet"]) == 0
    assert ome_scale(out) == ((None, None, None), []) and resolution_um(out) is None
    assert "unit pixel" in capsys.readouterr().out
    # a PSF in um on the sensor (as cm2cl's psf.tif was): not an object-space scale either
    p, _ = io.read_tiff(psf)
    io.write_tiff(tmp_path / "sensor_psf.ome.tif", p, voxel_size_um=(250.0, 17.6, 17.6), depths_um=[0, 1, 2, 3])
    assert main(["reconstruct", str(meas), "--psf", str(tmp_path / "sensor_psf.ome.tif"), "-o", str(out),
                 "--offset", "100", "--psf-offset", "100", "--max-iter", "2", "--quiet"]) == 0
    assert ome_scale(out) == ((None, None, None), [0, 1, 2, 3])
    assert "no object-space voxel size" in capsys.readouterr().out
    # an explicit voxel size of the PSF grid, times --bin laterally
    assert main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(out), "--offset", "100", "--psf-offset", "100",
                 "--max-iter", "2", "--voxel-size", "100", "5", "6", "--bin", "2", "--quiet"]) == 0
    assert ome_scale(out)[0] == pytest.approx((100.0, 10.0, 12.0))
    assert resolution_um(out) == pytest.approx((10.0, 12.0), rel=1e-6)
    assert main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(tmp_path / "bad.ome.tif"),
                 "--voxel-size", "0", "5", "5", "--quiet"]) == 2
    assert "--voxel-size: expected 3 positive finite numbers" in capsys.readouterr().err
    assert not (tmp_path / "bad.ome.tif").exists()


class _Terminal(_io.StringIO):
    def isatty(self):
        return True


def test_progress_is_one_tqdm_bar_on_a_terminal_only(rt, tmp_path, monkeypatch, capsys):
    row = {"iter": 1, "objective": 1.5, "primal": 0.1, "dual": 0.2}
    term = _Terminal()
    bar = Progress(3, quiet=False, stream=term)
    for i in (1, 2, 3):
        bar({**row, "iter": i})
    bar.close()
    text = term.getvalue()
    assert "3/3" in text and "obj=1.5000e+00" in text and "primal=1.00e-01" in text and "dual=2.00e-01" in text
    for quiet, stream in ((True, _Terminal()), (False, _io.StringIO())):
        p = Progress(3, quiet=quiet, stream=stream)
        p(row)
        p.close()
        assert stream.getvalue() == ""
    # through the command: a bar on a terminal, nothing with --quiet
    meas, psf = _files(tmp_path)
    argv = ["reconstruct", str(meas), "--psf", str(psf), "-o", str(tmp_path / "v.ome.tif"), "--offset", "100", "--psf-offset", "100",
            "--max-iter", "3", "--tol", "0", "--psf-refine", "0"]
    term = _Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    assert main(argv) == 0
    assert "ADMM" in term.getvalue() and "3/3" in term.getvalue() and "obj=" in term.getvalue()
    term = _Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    assert main(argv + ["--quiet"]) == 0
    assert term.getvalue() == ""


def test_measurement_offset_is_not_subtracted_from_the_psf(rt, tmp_path, capsys):
    """Issue 8 item 13: --offset 100 was subtracted from the PSF too, emptying its weak planes; the PSF has
    its own --psf-offset."""
    psf, _, y = bead_problem(6)
    tifffile.imwrite(tmp_path / "psf.tif", (psf * 50).astype(np.float32), photometric="minisblack")  # max ~50
    tifffile.imwrite(tmp_path / "meas.tif", (y * 1000 + 100).astype(np.float32))
    out = tmp_path / "v.ome.tif"
    argv = ["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "-o", str(out),
            "--offset", "100", "--max-iter", "3", "--quiet"]
    assert main(argv) == 0
    assert main(argv + ["--psf-offset", "100"]) == 2      # the old behaviour, now asked for explicitly
    assert "all zero" in capsys.readouterr().err


def test_a_psf_of_another_lateral_size_is_centred_on_the_sensor(rt, tmp_path, capsys):
    """Issue 12 item 4: a cropped calibration (PSF smaller than the sensor) is zero-padded, a wider one
    cropped, both centred on the array centre, with a note; the solve equals one with the PSF fitted by
    hand."""
    import cm2cl

    psf, _, y = bead_problem(6)
    tifffile.imwrite(tmp_path / "meas.tif", y.astype(np.float32))
    small = psf[:, 2:-2, 3:-3]                                # 28 x 34 of the 32 x 40 sensor
    tifffile.imwrite(tmp_path / "psf.tif", small.astype(np.float32), photometric="minisblack")
    out = tmp_path / "v.ome.tif"
    assert main(["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "-o", str(out),
                 "--max-iter", "10", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "28 x 34 pixels fitted to 32 x 40 (4 rows of zeros added, 6 columns of zeros added)" in err
    vol, _ = io.read_tiff(out)
    fitted = np.pad(small, ((0, 0), (2, 2), (3, 3))).astype(np.float32)
    ref = cm2cl.reconstruct(y.astype(np.float32), fitted, max_iter=10)
    np.testing.assert_allclose(vol, ref.volume, rtol=1e-5, atol=1e-6 * ref.volume.max())
    wide = np.pad(psf, ((0, 0), (3, 3), (1, 1)))
    tifffile.imwrite(tmp_path / "wide.tif", wide.astype(np.float32), photometric="minisblack")
    assert main(["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "wide.tif"), "-o",
                 str(tmp_path / "w.ome.tif"), "--max-iter", "2", "--quiet"]) == 0
    assert "38 x 42 pixels fitted to 32 x 40 (6 rows cropped, 2 columns cropped)" in capsys.readouterr().err


def test_dry_run_plans_from_the_headers_and_writes_nothing(rt, tmp_path, capsys, monkeypatch):
    from cm2cl.solver.memory import memory_estimate

    meas, psf = _files(tmp_path)
    read = []
    monkeypatch.setattr(io, "read_tiff", lambda p: read.append(p))
    out = tmp_path / "v.ome.tif"
    assert main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(out), "--dry-run"]) == 0
    text = capsys.readouterr().out
    from cm2cl.solver.params import ADMMParams
    from cm2cl.solver.terms import state_counts, terms_for

    est = memory_estimate(4, (64, 80), np.float32, "cl", **state_counts(terms_for(ADMMParams())))
    assert "4 planes x 32 x 40 sensor" in text and "padded 64 x 80" in text
    assert f"{est['total'] / 2**30:.2f} GiB" in text and "fits: run without --dry-run" in text
    assert read == [] and not out.exists()


def test_memory_estimate_bounds_the_solvers_allocations(rt):
    """The plan's device bytes come from the same accounting as the solver's buffers: never below what
    the solver allocates, at most 5% above (FFT libraries' own scratch not included) but for the
    reductions' partial sums, planned for a GPU's work-item per column."""
    from cm2cl.solver.admm import ADMMSolver
    from cm2cl.solver.memory import memory_estimate
    from cm2cl.solver.params import ADMMParams
    from cm2cl.solver.terms import state_counts

    psf, _, _ = bead_problem(7)
    for P in ((64, 80), (72, 96)):
        s = ADMMSolver(psf, ADMMParams(), padded_shape=P)
        counts = state_counts(s.terms)
        est = memory_estimate(4, P, np.float32, s.backend, **counts)["total"]
        # the reductions' partial sums are bounded for a work-item per column (GPUs); a CPU's row layout
        # needs a fraction of that bound, which is a larger share of the smaller state without TV
        partials = 4 * (P[0] * P[1] * 4 // 32 + counts["nslots"] * (P[0] + P[1] + 1) * 4)
        assert s.allocated_bytes <= est <= 1.05 * s.allocated_bytes + partials, (P, s.allocated_bytes, est)


def test_prior_points_turns_tv_off(rt, tmp_path):
    """--prior points: TV off (recorded); an explicit --tv or --l1-plane-power wins."""
    meas, psf = _files(tmp_path)
    # planes blurred unequally (each keeps its light), so their norms ||h_i|| differ and the weights tell the powers
    h = tifffile.imread(psf).astype(np.float64) - 100
    h = np.stack([gaussian_filter(p, s) for p, s in zip(h, (0.0, 0.6, 1.0, 1.5))])
    tifffile.imwrite(psf, (h + 100).round().astype(np.uint16), photometric="minisblack")
    base = ["reconstruct", str(meas), "--psf", str(psf), "--offset", "100", "--psf-offset", "100", "--max-iter", "5",
            "--quiet", "--prior", "points"]
    assert main(base + ["-o", str(tmp_path / "p.ome.tif")]) == 0
    info = json.loads((tmp_path / "p.cm2cl.json").read_text())["info"]
    h = io.read_tiff(psf)[0].astype(np.float64) - 100
    power, light = (h ** 2).sum(axis=(1, 2)), h.sum(axis=(1, 2))   # light: within 1% (the uint16 rounding)
    assert info["tv"] == 0
    np.testing.assert_allclose(info["l1_plane_weights"], light / light.mean(), rtol=1e-5)   # q = 0: the light
    assert main(base + ["-o", str(tmp_path / "q.ome.tif"), "--tv", "0.01"]) == 0
    assert json.loads((tmp_path / "q.cm2cl.json").read_text())["info"]["tv"] == 0.01
    # points-weighted: TV off too, and plane i's l1 weight ~ ||h_i||^2 / sum h_i (mean 1), read back from the record
    assert main(base[:-1] + ["points-weighted", "-o", str(tmp_path / "w.ome.tif")]) == 0
    info = json.loads((tmp_path / "w.cm2cl.json").read_text())["info"]
    assert np.ptp(power) > 0.05 * power.mean()   # the planes differ, so the weights say which power was used
    assert info["tv"] == 0
    np.testing.assert_allclose(info["l1_plane_weights"], (power / light) / (power / light).mean(), rtol=1e-5)
    # --l1-plane-power wins over the prior's: 1 is the weights before stop 49, ~ ||h_i||
    assert main(base + ["-o", str(tmp_path / "n.ome.tif"), "--l1-plane-power", "1"]) == 0
    info = json.loads((tmp_path / "n.cm2cl.json").read_text())["info"]
    assert info["tv"] == 0
    np.testing.assert_allclose(info["l1_plane_weights"], np.sqrt(power) / np.sqrt(power).mean(), rtol=1e-5)


@pytest.mark.parametrize("command", ["devices", "demo", "simulate", "reconstruct", "prepare-psf"])
def test_every_command_prints_its_help(command, capsys):
    """argparse formats help strings with %: a stray one (a '9%' in --lean's help did) breaks --help."""
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    assert "usage: cm2cl " + command in capsys.readouterr().out


def test_help_is_grouped_by_what_a_user_does_with_examples(capsys):
    """Issue 23 item 4: --help in groups (inputs, solver, memory and devices, series, output), every declared
    parameter with a flag among the solver's options, examples in the epilog."""
    from cm2cl.solver.params import parameters

    with pytest.raises(SystemExit):
        main(["reconstruct", "--help"])
    text = capsys.readouterr().out
    heads = ["inputs:", "solver:", "memory and devices:", "series (an OME-Zarr output):", "output:", "examples:"]
    at = [text.index("\n" + h) for h in heads]
    assert at == sorted(at)
    solver = text[at[1]:at[2]]
    flagged = [p for p in parameters() if p.flag]
    assert {p.flag for p in flagged} >= {"--l1", "--tv", "--max-iter", "--tol", "--anisotropic", "--penalty"}
    for p in flagged:
        assert p.flag in solver, p.flag
    words = " ".join(solver.split())   # argparse wraps lines wherever the text falls
    assert "Iteration cap (default: 1000)" in words and "(default: adaptive)" in words
    assert text.count("cm2cl reconstruct ") >= 4      # usage and the examples


def test_library_errors_name_parameters_and_the_command_line_names_its_options(rt, tmp_path, capsys):
    """Library messages begin with the parameter's name (tv:, output '...':, warm_start:); the command line
    says the option the user typed."""
    from cm2cl.cli.main import build_parser
    from cm2cl.cli.options import with_flags
    from cm2cl.jobs import executor_for

    flags = build_parser().parse_args(["reconstruct", "m.tif", "--psf", "p.tif", "-o", "v.tif"]).flags
    assert flags["tv_isotropic"] == "--anisotropic" and flags["max_iter"] == "--max-iter"
    assert with_flags("tv_iters: must be <= 1000, got 5000", flags) == "--tv-iters: must be <= 1000, got 5000"
    assert with_flags("output 'a.zarr': holds another job", flags) == "--output 'a.zarr': holds another job"
    assert with_flags("measurement 'm.tif': no such file", flags) == "measurement 'm.tif': no such file"
    with pytest.raises(InputError, match=r"^warm_start: .*\(no scheduler, one device\)") as exc:
        executor_for([0, 1], None, warm_start=True)
    assert "--" not in str(exc.value)
    meas, psf = _files(tmp_path)
    assert main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(tmp_path / "v.tif"), "--tv-iters", "5000"]) == 2
    assert capsys.readouterr().err.strip() == "cm2cl: error: --tv-iters: must be <= 1000, got 5000"


def test_command_line_modules_form_no_circle_and_share_no_private_names():
    """Issue 23 item 4: cli/reconstruct.py and cli/series.py imported each other's private helpers; now the
    shared preparation is one module, and no function in cli/ is over 80 lines."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "cm2cl"
    graph = {}
    for pkg in ("cli", "jobs"):
        for f in sorted((root / pkg).glob("*.py")):
            tree = ast.parse(f.read_text())
            name = f"{pkg}.{f.stem}"
            graph[name] = set()
            for n in ast.walk(tree):
                if isinstance(n, ast.ImportFrom) and n.level:
                    assert not [a.name for a in n.names if a.name.startswith("_")], (name, n.module)
                    base = pkg if n.level == 1 else ""
                    mods = [n.module] if n.module else [a.name for a in n.names]
                    graph[name] |= {f"{base}.{m}".strip(".") for m in mods}
                if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and pkg == "cli":
                    assert n.end_lineno - n.lineno + 1 <= 80, (name, n.name)
    assert len((root / "cli" / "reconstruct.py").read_text().splitlines()) < 250

    def visit(node, path):
        for nxt in graph.get(node, ()):
            assert nxt not in path, f"import circle {path + [nxt]}"
            visit(nxt, path + [nxt])

    for node in graph:
        visit(node, [node])


def test_dry_run_counts_the_presets_iterations(rt, tmp_path, capsys):
    meas, psf = _files(tmp_path)
    argv = ["reconstruct", str(meas), "--psf", str(psf), "-o", str(tmp_path / "v.ome.tif"), "--dry-run"]
    assert main(argv + ["--preset", "best"]) == 0
    assert "for 3000 iterations" in capsys.readouterr().out
    assert main(argv + ["--preset", "best", "--max-iter", "7"]) == 0
    assert "for 7 iterations" in capsys.readouterr().out
    assert main(argv + ["--scattering-length-um", "auto"]) == 0
    assert "--scattering-length-um auto: up to twice that" in capsys.readouterr().out


def test_a_warning_has_one_cm2cl_prefix_and_v_names_the_module(capsys):
    """Issue 27 nit: warnings read 'cm2cl: WARNING: cm2cl: ...'; at the default level the message follows
    the level, and -v adds the module that logged it."""
    import argparse
    import logging

    from cm2cl.cli.main import _log_handler

    for verbose, want in ((0, "cm2cl: WARNING: frame 1 does not match\n"),
                          (1, "cm2cl: WARNING: cm2cl.jobs.store: frame 1 does not match\n")):
        logger, handler, level = _log_handler(argparse.Namespace(verbose=verbose, log_level=None))
        try:
            logging.getLogger("cm2cl.jobs.store").warning("frame 1 does not match")
        finally:
            logger.removeHandler(handler)
            logger.setLevel(level)
        assert capsys.readouterr().err == want


@pytest.mark.parametrize("delay", [0.15, 0.3])
def test_ctrl_c_while_the_command_starts_is_one_line_and_130(delay):
    """Ctrl-C while the modules load (numpy, OpenCL, the solver: about half a second) or just after: one line,
    exit 130, no import's traceback (issue 27)."""
    import signal
    import subprocess
    import time

    p = subprocess.Popen([sys.executable, "-m", "cm2cl", "devices"], stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True)
    time.sleep(delay)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    # loading numpy, OpenCL and the solver takes far longer than the delay: the signal always finds it running
    assert p.returncode == 130 and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1 and "interrupted" in err

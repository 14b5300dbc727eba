"""Property tests (issue 8): random shapes, dtypes, NaN/Inf placements and parameter values thrown at
cm2cl.reconstruct and the CLI (as options and as TIFF files). Every input is reconstructed (a finite volume
of the right shape) or refused with cm2cl's own error (one line on the command line, exit 2, no output
left); never another exception, a hang (each example has a time limit) or a volume of the wrong shape.
Small on purpose: tiny arrays, few examples, the whole file in well under a minute."""

import contextlib
import signal

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

import cm2cl
from cm2cl import io
from cm2cl.cli import main
from cm2cl.errors import CM2Error

SETTINGS = settings(max_examples=40, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

#: seconds one example may take before it counts as a hang (they take well under one)
HANG_S = 30
DTYPES = ["float32", "float64", "uint8", "uint16", "int16", "int64", "complex64", "bool"]
NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 5),
                    st.sampled_from([0.0, 1e-3, 1e3, 1e300, -1e-3, "1e-3", None, True, 2.0]))


@contextlib.contextmanager
def time_limit(seconds=HANG_S):
    def hang(*_):
        raise TimeoutError(f"no answer within {seconds} s")

    old = signal.signal(signal.SIGALRM, hang)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _one_line_refusal(msg):
    assert msg and "\n" not in msg.strip() and ":" in msg, msg


@st.composite
def problems(draw):
    nz = draw(st.integers(1, 3))
    my, mx = draw(st.integers(1, 12)), draw(st.integers(1, 12))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    dt_y, dt_h = draw(st.sampled_from(DTYPES)), draw(st.sampled_from(DTYPES))
    y = (rng.random((my, mx)) * 100).astype(dt_y)
    psf = (rng.random((nz, my, mx)) * 100).astype(dt_h)
    if draw(st.booleans()) and y.dtype.kind == "f":
        y.flat[draw(st.integers(0, y.size - 1))] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    if draw(st.booleans()) and psf.dtype.kind == "f":
        psf.flat[draw(st.integers(0, psf.size - 1))] = draw(st.sampled_from([np.nan, np.inf]))
    if draw(st.booleans()):          # a measurement of another shape
        y = y[: max(1, my - 1)]
    names = ["l1", "tv", "tol", "mu_v", "tv_axial_weight", "tv_iters", "patience", "max_slab_planes", "padded_shape"]
    kw = {k: draw(NUMBERS) for k in draw(st.sets(st.sampled_from(names), max_size=2))}
    if "padded_shape" in kw:
        kw["padded_shape"] = draw(st.sampled_from([None, (32, 32), (2 * my - 1, 2 * mx), (1, 1), (16, 16, 2),
                                                   (-32, 32), (32.0, 32.5), "ab", kw["padded_shape"]]))
    kw["max_iter"] = draw(st.sampled_from([1, 3, 0, -1, 2.5, 2.0]))
    kw["dtype"] = draw(st.sampled_from([np.float32, np.float64, "float32", "int32"]))
    return y, psf, kw


@SETTINGS
@given(problems())
def test_reconstruct_returns_a_volume_or_refuses_clearly(rt, case):
    y, psf, kw = case
    if np.dtype(kw["dtype"]) == np.float64 and not rt.caps.fp64:
        kw["dtype"] = np.float32
    try:
        with time_limit():
            rec = cm2cl.reconstruct(y, psf, **kw)
    except CM2Error as exc:
        _one_line_refusal(str(exc))
        event("refused")
        return
    event("reconstructed")
    assert rec.volume.shape == psf.shape
    assert np.all(np.isfinite(rec.volume))


def _cli(files, meas, psf, opts, capsys):
    """Run ``cm2cl reconstruct`` on files in ``files``; (exit code, stderr lines, the output path)."""
    out = files / "v.ome.tif"
    for p in files.iterdir():                 # a fresh output place for each example
        if p.name not in ("meas.tif", "psf.tif", "odd.tif"):
            p.unlink()
    try:
        with time_limit():
            code = main(["reconstruct", str(files / meas), "--psf", str(files / psf), "-o", str(out), "--quiet",
                         *opts])
    except SystemExit as exc:                 # argparse's own refusals (not a number, unknown choice)
        code = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    event("reconstructed" if code == 0 else "refused")
    if code != 0:
        errors = [e for e in err if not e.startswith("cm2cl: note:")]      # notes may come first
        assert code == 2 and len(errors) == 1 and errors[0].startswith(("cm2cl: error:", "cm2cl reconstruct: error:")), \
            (code, err)
        assert sorted(p.name for p in files.iterdir() if p.name not in ("meas.tif", "psf.tif", "odd.tif")) == []
    return code, out


@st.composite
def argvs(draw):
    opts = []
    for name, values in [("--l1", ["0.001", "-1", "nan", "x", "1e400"]), ("--tv", ["0", "1e-3", "inf"]),
                         ("--max-iter", ["2", "0", "-3", "1.5"]), ("--offset", ["none", "auto", "3", "nan", "q"]),
                         ("--psf-offset", ["none", "2", "-inf"]), ("--bin", ["1", "2", "3", "0", "100"]),
                         ("--dtype", ["float32", "float64"]), ("--tol", ["0", "-1", "1e-3"]),
                         ("--penalty", ["adaptive", "fixed", "balance"]), ("--tv-iters", ["1", "0", "2000"]),
                         ("--voxel-size", ["1 2 2", "0 1 1", "nan 1 1"]), ("--patience", ["1", "0"])]:
        if draw(st.booleans()):
            opts += [name, *draw(st.sampled_from(values)).split()]
    return opts


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("prop")
    rng = np.random.default_rng(1)
    tifffile.imwrite(d / "psf.tif", (rng.random((2, 10, 12)) * 100).astype(np.uint16), photometric="minisblack")
    tifffile.imwrite(d / "meas.tif", (rng.random((10, 12)) * 100).astype(np.uint16))
    tifffile.imwrite(d / "odd.tif", (rng.random((9, 12)) * 100).astype(np.uint16))
    return d


@SETTINGS
@given(argvs(), st.sampled_from(["meas.tif", "odd.tif"]))
def test_cli_exits_0_with_a_whole_output_or_2_with_one_line(rt, files, capsys, opts, meas):
    code, out = _cli(files, meas, "psf.tif", opts, capsys)
    if code == 0:
        b = int(opts[opts.index("--bin") + 1]) if "--bin" in opts else 1
        vol, _ = io.read_tiff(out)
        assert vol.shape == (2, 10 // b, 12 // b) and np.all(np.isfinite(vol))
        assert (files / "v.cm2cl.json").exists() and (files / "v.cm2cl.log.csv").exists()


FILE_DTYPES = ["uint8", "uint16", "int16", "int32", "float32", "float64", "complex64", "bool"]


@st.composite
def tiff_pairs(draw):
    """A measurement and a PSF stack as TIFF files: random sizes (one-pixel-wide included), dtypes, planes
    (a 2D PSF is one plane), NaN/Inf in either, sometimes of different sensor shapes."""
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    nz, my, mx = draw(st.integers(1, 3)), draw(st.integers(1, 9)), draw(st.integers(1, 9))

    def array(shape, dt):
        a = rng.random(shape) * 200 + 1
        return (a > 100) if dt == "bool" else a.astype(dt)

    y = array((my, mx) if not draw(st.booleans()) else (my, max(1, mx - draw(st.integers(0, 2)))),
              draw(st.sampled_from(FILE_DTYPES)))
    psf = array((nz, my, mx) if nz > 1 or draw(st.booleans()) else (my, mx), draw(st.sampled_from(FILE_DTYPES)))
    for a in (y, psf):
        if a.dtype.kind == "f" and draw(st.booleans()):
            a.flat[draw(st.integers(0, a.size - 1))] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    return y, psf, draw(st.sampled_from([[], ["--bin", "2"], ["--offset", "auto"], ["--dtype", "float64"]]))


@SETTINGS
@given(tiff_pairs())
def test_cli_on_random_files_reconstructs_or_refuses_with_one_line(rt, tmp_path_factory, capsys, case):
    y, psf, opts = case
    if "float64" in opts and not rt.caps.fp64:
        opts = []
    d = tmp_path_factory.mktemp("files")
    tifffile.imwrite(d / "meas.tif", y)
    tifffile.imwrite(d / "psf.tif", psf, photometric="minisblack")
    code, out = _cli(d, "meas.tif", "psf.tif", opts + ["--max-iter", "2"], capsys)
    if code == 0:
        b = 2 if "--bin" in opts else 1
        vol, _ = io.read_tiff(out)
        nz = psf.shape[0] if psf.ndim == 3 else 1
        assert vol.shape == (nz, y.shape[0] // b, y.shape[1] // b) and np.all(np.isfinite(vol))
        assert vol.dtype == (np.float64 if "float64" in opts else np.float32)


# ---- series jobs against one frame (issue 27) ----------------------------------------------------------------

SERIES_OPTIONS = [("--l1", ["0.001", "-1", "nan"]), ("--tv", ["0", "1e-3"]), ("--max-iter", ["3", "0"]),
                  ("--offset", ["none", "auto", "3", "q"]), ("--bin", ["1", "2", "0"]), ("--tol", ["0", "-1"]),
                  ("--background", ["model", "none", "opening:3px", "garbage"]), ("--mask", ["saturated", "bogus"]),
                  ("--saturation", ["50"]), ("--max-memory", ["0.5", "1G", "x"]), ("--stream", ["auto", "never"]),
                  ("--host-memory", ["2G"]), ("--dry-run", []), ("--padded", []), ("--prior", ["points", "nope"]),
                  ("--relaxation", ["1", "1.6", "2.5"]), ("--penalty", ["fixed", "balance"])]


@st.composite
def series_argvs(draw):
    opts = []
    for name, values in SERIES_OPTIONS:
        if draw(st.integers(0, 3)) == 0:      # a few options per example
            opts += [name] + ([draw(st.sampled_from(values))] if values else [])
    return opts + ["--max-iter", "3"] if "--max-iter" not in opts else opts


@pytest.fixture(scope="module")
def series_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("series")
    rng = np.random.default_rng(2)
    frames = (rng.random((3, 10, 12)) * 100).astype(np.uint16)
    tifffile.imwrite(d / "psf.tif", (rng.random((2, 10, 12)) * 100).astype(np.uint16), photometric="minisblack")
    tifffile.imwrite(d / "frames.tif", frames, photometric="minisblack")
    tifffile.imwrite(d / "frame0.tif", frames[0])
    return d


def _run(argv, capsys):
    try:
        with time_limit():
            code = main(argv)
    except SystemExit as exc:
        code = exc.code
    return code, capsys.readouterr().err.strip().splitlines()


@SETTINGS
@given(series_argvs())
def test_series_options_work_as_for_one_frame_or_are_refused_before_any_work(rt, series_files, capsys, opts):
    """A series (-o OUT.ome.zarr) given random options: it refuses every option one frame refuses, and any
    it does not apply, with one line before any work (no store, no bookkeeping left); what it accepts gives
    frame 0 the volume a one-frame run gives (the same solve)."""
    d = series_files
    for p in d.iterdir():
        if p.name not in ("psf.tif", "frames.tif", "frame0.tif"):
            if p.is_dir():
                import shutil
                shutil.rmtree(p)
            else:
                p.unlink()
    # the PSF as given: a series solves frame 0 with the stack its refinement made, a frame alone refines itself
    one, one_err = _run(["reconstruct", str(d / "frame0.tif"), "--psf", str(d / "psf.tif"), "-o", str(d / "v.ome.tif"),
                         "--quiet", "--psf-refine", "0", *opts], capsys)
    many, many_err = _run(["reconstruct", str(d / "frames.tif"), "--psf", str(d / "psf.tif"), "-o",
                           str(d / "s.ome.zarr"), "--quiet", "--psf-refine", "0", *opts], capsys)
    assert many in (0, 2), (many, many_err)
    if one != 0:
        assert many == 2, (opts, one_err)     # nothing one frame refuses is taken by a series
    if many == 2:
        errors = [e for e in many_err if not e.startswith("cm2cl: note:")]
        assert len(errors) == 1 and "error:" in errors[0], many_err
        left = sorted(p.name for p in d.iterdir() if p.name.startswith(("s.", ".s.")))
        assert left == [], left
        event("series refused")
        return
    event("series reconstructed")
    assert one == 0 and "--dry-run" not in opts
    from cm2cl.jobs.store import FrameStore

    store = FrameStore.open_readonly(d / "s.ome.zarr")
    try:
        assert store.missing() == [] and store.n_frames == 3
        vol, _ = io.read_tiff(d / "v.ome.tif")
        np.testing.assert_allclose(store.read(0), vol, rtol=1e-5, atol=1e-6 * float(np.abs(vol).max()))
    finally:
        store.close()


# ---- OME metadata with random values (issue 27) --------------------------------------------------------------

#: valid values and units, and ones that are no numbers, not finite, not positive, out of range, unknown
GOOD_VALUES, BAD_VALUES = ["5", "0.5", "2"], ["0", "-1", "nan", "inf", "1e400", "abc", "", " 2 ", "1,5", "0x10", "1e-300"]
GOOD_UNITS, BAD_UNITS = [None, "&#181;m", "nm", "mm"], ["cm", "pixel", "bogus", ""]


@st.composite
def ome_files(draw):
    """A 2-plane PSF stack whose OME-XML carries random PhysicalSize*, units, Plane TheZ and PositionZ."""
    def attrs(names):
        out = []
        for n in names:
            # mostly present, mostly valid (hypothesis leans to 0: it means present and valid), so that some files
            # read with a scale
            if draw(st.integers(0, 3)) < 3:
                out.append(f'{n}="{draw(st.sampled_from(BAD_VALUES if draw(st.integers(0, 5)) == 5 else GOOD_VALUES))}"')
                unit = draw(st.sampled_from(BAD_UNITS if draw(st.integers(0, 5)) == 5 else GOOD_UNITS))
                if unit is not None:
                    out.append(f'{n}Unit="{unit}"')
        return " ".join(out)

    planes = "".join(f'<Plane TheZ="{draw(st.one_of(st.just(str(z)), st.sampled_from(["x", "-1", "1.5", "7"])))}" '
                     'TheC="0" TheT="0" '
                     f'{attrs(["PositionZ"])}/>' for z in range(2))
    xml = ('<?xml version="1.0" encoding="UTF-8"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06">'
           '<Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="XYZCT" Type="uint16" SizeX="12" SizeY="10" '
           f'SizeZ="2" SizeC="1" SizeT="1" {attrs(["PhysicalSizeX", "PhysicalSizeY", "PhysicalSizeZ"])}>'
           '<Channel ID="Channel:0:0" SamplesPerPixel="1"/><TiffData/>' + planes + '</Pixels></Image></OME>')
    return xml


@settings(SETTINGS, max_examples=150)
@given(ome_files())
def test_random_ome_metadata_reads_as_a_scale_or_refuses_with_one_line(rt, series_files, tmp_path_factory, capsys,
                                                                       xml):
    """Whatever numbers and units the OME-XML carries, reading gives finite positive voxel sizes and finite
    depths (or none), or one line naming the file; a reconstruction with it as the PSF writes its output or
    refuses with one line and leaves nothing."""
    d = tmp_path_factory.mktemp("ome")
    data = (np.random.default_rng(3).random((2, 10, 12)) * 100).astype(np.uint16)
    tifffile.imwrite(d / "psf.ome.tif", data, description=xml, metadata=None, photometric="minisblack")
    try:
        _, meta = io.read_tiff(d / "psf.ome.tif")
    except CM2Error as exc:
        _one_line_refusal(str(exc))
        assert "psf.ome.tif" in str(exc)
        event("read refused")
    else:
        vs = meta.get("voxel_size_um")
        assert vs is None or all(np.isfinite(v) and v > 0 for v in vs), vs
        dep = meta.get("depths_um")
        assert dep is None or all(np.isfinite(v) for v in dep), dep
        event("read with a scale" if vs else "read without a scale")
    out = d / "v.ome.tif"
    code, err = _run(["reconstruct", str(series_files / "frame0.tif"), "--psf", str(d / "psf.ome.tif"), "-o", str(out),
                      "--quiet", "--max-iter", "2"], capsys)
    assert code in (0, 2), (code, err)
    if code == 2:
        errors = [e for e in err if not e.startswith("cm2cl: note:")]
        assert len(errors) == 1 and "error:" in errors[0], err
        assert sorted(p.name for p in d.iterdir()) == ["psf.ome.tif"]
    else:
        vol, vmeta = io.read_tiff(out)
        assert vol.shape == (2, 10, 12) and np.all(np.isfinite(vol))

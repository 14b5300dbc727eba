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

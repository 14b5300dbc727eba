"""Property tests (issue 8): random shapes, dtypes, NaN/Inf placements and parameter values thrown at
cm2cl.reconstruct and the CLI. Every input is reconstructed (finite volume of the right shape) or refused
with cm2cl's own error (one line on the command line, exit 2); never another exception or a hang."""

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import cm2cl
from cm2cl.cli import main
from cm2cl.errors import CM2Error

SETTINGS = settings(max_examples=30, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

DTYPES = ["float32", "float64", "uint8", "uint16", "int16", "int64", "complex64", "bool"]
NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 5),
                    st.sampled_from([0.0, 1e-3, 1e3, 1e300, -1e-3, "1e-3", None]))


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
    kw = {k: draw(NUMBERS) for k in draw(st.sets(st.sampled_from(["l1", "tv", "tol", "mu_v", "tv_axial_weight"]),
                                                 max_size=2))}
    kw["max_iter"] = draw(st.sampled_from([1, 3, 0, -1, 2.5]))
    kw["dtype"] = draw(st.sampled_from([np.float32, np.float64, "float32", "int32"]))
    return y, psf, kw


@SETTINGS
@given(problems())
def test_reconstruct_returns_a_volume_or_refuses_clearly(rt, case):
    y, psf, kw = case
    if np.dtype(kw["dtype"]) == np.float64 and not rt.caps.fp64:
        kw["dtype"] = np.float32
    try:
        rec = cm2cl.reconstruct(y, psf, **kw)
    except CM2Error as exc:
        msg = str(exc)
        assert msg and "\n" not in msg.strip() and ":" in msg, msg
        return
    assert rec.volume.shape == psf.shape
    assert np.all(np.isfinite(rec.volume))


@st.composite
def argvs(draw):
    opts = []
    for name, values in [("--l1", ["0.001", "-1", "nan", "x", "1e400"]), ("--tv", ["0", "1e-3", "inf"]),
                         ("--max-iter", ["2", "0", "-3", "1.5"]), ("--offset", ["none", "auto", "3", "nan", "q"]),
                         ("--psf-offset", ["none", "2", "-inf"]), ("--bin", ["1", "2", "0", "100"]),
                         ("--dtype", ["float32", "float64"]), ("--tol", ["0", "-1", "1e-3"]),
                         ("--penalty", ["adaptive", "fixed", "balance"]), ("--tv-iters", ["1", "0", "2000"]),
                         ("--voxel-size", ["1 2 2", "0 1 1", "nan 1 1"])]:
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
    out = files / "v.ome.tif"
    if out.exists():
        out.unlink()
    try:
        code = main(["reconstruct", str(files / meas), "--psf", str(files / "psf.tif"), "-o", str(out), "--quiet",
                     *opts])
    except SystemExit as exc:        # argparse's own refusals (not a number, unknown choice)
        code = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    if code == 0:
        from cm2cl import io

        vol, _ = io.read_tiff(out)
        assert vol.ndim == 3 and vol.shape[0] == 2 and np.all(np.isfinite(vol))
    else:
        errors = [e for e in err if not e.startswith("cm2cl: note:")]      # notes may come first
        assert code == 2 and len(errors) == 1 and errors[0].startswith(("cm2cl: error:", "cm2cl reconstruct: error:")), \
            (code, err)
        assert not out.exists()

"""The command line as a user runs it: outputs complete or absent, one-line errors."""

import json

import numpy as np
import tifffile

from cm2cl import io
from cm2cl.cli import main
from test_admm import bead_problem


def _files(tmp_path):
    psf, _, y = bead_problem(6)
    tifffile.imwrite(tmp_path / "psf.tif", (psf * 1000 + 100).astype(np.uint16), photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", (y * 1000 + 100).astype(np.uint16))
    return tmp_path / "meas.tif", tmp_path / "psf.tif"


def test_reconstruct_writes_volume_and_log(rt, tmp_path, capsys):
    meas, psf = _files(tmp_path)
    out = tmp_path / "vol.tif"
    assert main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(out), "--offset", "100",
                 "--max-iter", "40", "--quiet"]) == 0
    vol, meta = io.read_tiff(out)
    assert vol.shape == (4, 32, 40) and vol.dtype == np.float32 and vol.min() >= 0 and vol.max() > 0
    assert meta["extra"]["scaling"]["y_scale"] > 0
    rows = (tmp_path / "vol.log.csv").read_text().splitlines()
    assert rows[0].startswith("iter,objective,data") and len(rows) == 41
    doc = json.loads((tmp_path / "vol.json").read_text())
    assert doc["params"]["max_iter"] == 40 and len(doc["log"]) == 40
    assert not list(tmp_path.glob("*.partial"))


def test_reconstruct_bad_input_writes_nothing(rt, tmp_path, capsys):
    meas, psf = _files(tmp_path)
    tifffile.imwrite(tmp_path / "small.tif", np.ones((32, 30), np.uint16))
    cases = [
        (["reconstruct", str(tmp_path / "small.tif"), "--psf", str(psf)], "does not match the PSF"),
        (["reconstruct", str(meas), "--psf", str(psf), "--tv", "-1"], "tv: must be >= 0, got -1.0"),
        (["reconstruct", str(tmp_path / "nope.tif"), "--psf", str(psf)], "no such file"),
        (["reconstruct", str(meas), "--psf", str(psf), "--offset", "dark"], "--offset: expected"),
    ]
    for argv, msg in cases:
        out = tmp_path / "out.tif"
        assert main(argv + ["-o", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0] and err[0].startswith("cm2cl: error:")
        assert not out.exists() and not (tmp_path / "out.log.csv").exists()

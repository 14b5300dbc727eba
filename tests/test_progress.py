"""Progress on stderr (issue 26): timed lines where stderr is not a terminal, a bar closed at the real count
on a terminal, nothing with --quiet, and the cm2cl logger on stderr with -v / --log-level."""

import io

import numpy as np
import pytest
import tifffile

from cm2cl.cli import main
from cm2cl.cli.progress import FrameProgress, Progress


class _Tty(io.StringIO):
    def isatty(self):
        return True


def _row(i):
    return {"iter": i, "objective": 1.0 / i, "primal": 1e-2, "dual": 1e-3}


def test_lines_every_n_seconds_when_not_a_terminal(monkeypatch):
    clock = iter(np.arange(0.0, 1000.0, 10.0))   # each call of the clock: 10 s later
    monkeypatch.setattr("cm2cl.cli.progress.time.perf_counter", lambda: float(next(clock)))
    out = io.StringIO()
    p = Progress(100, quiet=False, stream=out, every=25.0)
    for i in range(1, 11):
        p(_row(i))
    p.close()
    lines = out.getvalue().splitlines()
    # rows at t = 10, 20, ..., 100 s after the start; a line whenever 25 s have passed since the last one
    assert [ln.split(",")[0] for ln in lines] == ["cm2cl: iteration 3/100", "cm2cl: iteration 6/100",
                                                  "cm2cl: iteration 9/100"], lines
    assert "objective 3.3333e-01" in lines[0] and "at most 16 min left" in lines[0], lines[0]
    # a run past its estimate (psf_refine auto's rounds per lenslet) says so, not "at most 0 s left"
    past = io.StringIO()
    p = Progress(5, quiet=False, stream=past, every=25.0)
    for i in range(1, 10):
        p(_row(i))
    lines = past.getvalue().splitlines()
    assert lines[-1].startswith("cm2cl: iteration 9, past the 5 first estimated, objective") and "left" not in \
        lines[-1], lines
    quiet, off = io.StringIO(), io.StringIO()
    for stream, kw in ((quiet, dict(quiet=True, every=1e-9)), (off, dict(quiet=False, every=0))):
        q = FrameProgress(5, stream=stream, **kw)
        for i in range(5):
            q(i, {"iterations": 10, "objective": 0.5})
        q.close()
    assert quiet.getvalue() == "" and off.getvalue() == ""


def test_bar_ends_at_the_real_count_when_the_solve_stops_early():
    out = _Tty()
    p = Progress(200, quiet=False, stream=out)
    for i in range(1, 147):
        p(_row(i))
    p.close()
    last = out.getvalue().replace("\r", "\n").strip().splitlines()[-1]
    assert "146/146" in last and "100%" in last, last


def test_cli_log_level_and_progress_lines(rt, tmp_path, capsys):
    from test_admm import bead_problem

    psf, _, y = bead_problem(6)
    tifffile.imwrite(tmp_path / "psf.tif", psf.astype(np.float32), photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", (y / y.max() * 1000).astype(np.float32))
    base = ["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "--max-iter", "30",
            "--tol", "0", "--psf-refine", "0"]
    assert main(base + ["-o", str(tmp_path / "a.ome.tif"), "-v", "--progress-every", "0"]) == 0
    err = capsys.readouterr().err
    assert "cm2cl: INFO: cm2cl.solver.admm: ADMM on" in err and "iteration " not in err, err
    # capsys' stderr is no terminal: with a tiny interval every row prints a line; at the default level no log
    assert main(base + ["-o", str(tmp_path / "b.ome.tif"), "--progress-every", "1e-9"]) == 0
    err = capsys.readouterr().err
    assert "cm2cl: iteration 30/30" in err and "INFO" not in err, err
    assert main(base + ["-o", str(tmp_path / "c.ome.tif"), "--log-level", "error", "--quiet"]) == 0
    assert capsys.readouterr().err == ""
    with pytest.raises(SystemExit) as info:
        main(base + ["-o", str(tmp_path / "d.ome.tif"), "--progress-every", "-1"])
    assert info.value.code == 2 and "'-1' is not a number of seconds >= 0" in capsys.readouterr().err

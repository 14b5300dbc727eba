"""Outputs and files (issue 8, items 1-4, 6, 7): the output is checked before any work, published as a unit
that never mixes two runs (kill -9 at each publishing step), staged under unique names, locked against a
second run, with sidecars that cannot overwrite other files; volumes the dtype cannot hold are refused;
one-pixel-wide volumes keep their shape."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import tifffile

from cm2cl import io
from cm2cl.cli import main
from cm2cl.io import publish
from test_admm import bead_problem


def _files(tmp_path, scale=1.0):
    psf, _, y = bead_problem(6)
    tifffile.imwrite(tmp_path / "psf.tif", psf.astype(np.float32), photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", (y * scale).astype(np.float32))
    return tmp_path / "meas.tif", tmp_path / "psf.tif"


def _run(tmp_path, out, *extra, scale=1.0):
    meas, psf = _files(tmp_path, scale)
    return main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(out), "--max-iter", "5", "--quiet", *extra])


def _listing(tmp_path):
    return sorted(p.name for p in tmp_path.iterdir() if p.name not in ("meas.tif", "psf.tif"))


def test_output_naming_a_directory_is_refused_before_any_work(rt, tmp_path, capsys):
    (tmp_path / "vol.ome.tif").mkdir()
    assert _run(tmp_path, tmp_path / "vol.ome.tif") == 2
    err = capsys.readouterr().err
    assert "is a directory" in err and len(err.strip().splitlines()) == 1
    assert _listing(tmp_path) == ["vol.ome.tif"] and not any((tmp_path / "vol.ome.tif").iterdir())


def test_unwritable_folder_and_full_disk_are_refused_before_the_solve(rt, tmp_path, capsys, monkeypatch):
    import cm2cl.solver

    calls = []
    monkeypatch.setattr(cm2cl.solver, "reconstruct", lambda *a, **k: calls.append(1))
    real_access = os.access
    monkeypatch.setattr(publish.os, "access", lambda p, m: False if str(p) == str(tmp_path) else real_access(p, m))
    assert _run(tmp_path, tmp_path / "vol.ome.tif") == 2
    assert "is not writable" in capsys.readouterr().err
    monkeypatch.setattr(publish.os, "access", real_access)
    monkeypatch.setattr(publish.shutil, "disk_usage", lambda p: type("U", (), {"free": 1000})())
    assert _run(tmp_path, tmp_path / "vol.ome.tif") == 2
    assert "MiB free" in capsys.readouterr().err
    assert calls == [] and _listing(tmp_path) == []


def test_a_failure_while_writing_leaves_nothing(rt, tmp_path, capsys, monkeypatch):
    def full(path, *a, **k):
        with open(path, "wb") as f:
            f.write(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(io, "write_tiff", full)
    assert _run(tmp_path, tmp_path / "vol.ome.tif") == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and "nothing was written" in err
    assert _listing(tmp_path) == []


def test_sidecars_cannot_overwrite_other_files(rt, tmp_path, capsys):
    (tmp_path / "simulation.json").write_text('{"mine": 1}')
    assert _run(tmp_path, tmp_path / "simulation.tif") == 0
    assert json.loads((tmp_path / "simulation.json").read_text()) == {"mine": 1}
    assert json.loads((tmp_path / "simulation.cm2cl.json").read_text())["output"] == "simulation.tif"
    # another output of the same stem would share the sidecar names: refused, the first one kept
    assert _run(tmp_path, tmp_path / "simulation.ome.tif") == 2
    assert "is not this output's record" in capsys.readouterr().err
    assert not (tmp_path / "simulation.ome.tif").exists()
    assert _run(tmp_path, tmp_path / "simulation.tif") == 0     # the same output again is fine


def test_a_second_run_on_the_same_output_is_refused(rt, tmp_path, capsys):
    with publish.OutputSet(tmp_path / "vol.ome.tif"):
        assert _run(tmp_path, tmp_path / "vol.ome.tif") == 2
        assert "another run is writing it" in capsys.readouterr().err
    assert not (tmp_path / "vol.ome.tif").exists()
    assert _run(tmp_path, tmp_path / "vol.ome.tif") == 0


def test_staging_names_are_unique_per_run(tmp_path):
    a = publish.OutputSet(tmp_path / "v.ome.tif")
    a.close()
    b = publish.OutputSet(tmp_path / "v.ome.tif")
    assert a.staged("volume") != b.staged("volume") and str(os.getpid()) in b.staged("volume").name
    b.close()


@pytest.mark.parametrize("step", publish.STEPS)
def test_killed_while_publishing_never_mixes_two_runs(rt, tmp_path, step):
    """A first run (5 iterations) is complete; a second (7) is killed with SIGKILL at `step`. The target
    then holds the first run whole, or the second run's volume (with or without its sidecars): a sidecar
    always belongs to the volume beside it. The next run cleans the killed run's staged files."""
    meas, psf = _files(tmp_path)
    out = tmp_path / "vol.ome.tif"
    base = [sys.executable, "-m", "cm2cl", "reconstruct", str(meas), "--psf", str(psf), "-o", str(out), "--quiet"]
    assert subprocess.run(base + ["--max-iter", "5"], capture_output=True).returncode == 0
    r = subprocess.run(base + ["--max-iter", "7"], capture_output=True, text=True,
                       env={**os.environ, "CM2CL_FAULT": f"publish.{step}"})
    assert r.returncode == -9, r.stderr
    _, meta = io.read_tiff(out)
    vol_iters = meta["extra"]["params"]["max_iter"]
    assert vol_iters == (5 if step in ("staged", "old_sidecars_removed") else 7)
    rec = tmp_path / "vol.cm2cl.json"
    if rec.exists():
        assert json.loads(rec.read_text())["params"]["max_iter"] == vol_iters
    log = tmp_path / "vol.cm2cl.log.csv"
    if log.exists():
        assert len(log.read_text().splitlines()) == vol_iters + 1
    assert subprocess.run(base + ["--max-iter", "6"], capture_output=True).returncode == 0
    assert _listing(tmp_path) == ["vol.cm2cl.json", "vol.cm2cl.log.csv", "vol.ome.tif"]


def test_a_volume_float32_cannot_hold_is_refused(rt, tmp_path, capsys):
    _files(tmp_path)
    psf, _, y = bead_problem(6)
    tifffile.imwrite(tmp_path / "tiny.tif", y * 1e-300)          # float64 file: representable
    out = tmp_path / "t.ome.tif"
    code = main(["reconstruct", str(tmp_path / "tiny.tif"), "--psf", str(tmp_path / "psf.tif"), "-o", str(out),
                 "--max-iter", "3", "--quiet"])
    assert code == 2 and "below what float32 can hold" in capsys.readouterr().err and not out.exists()
    code = main(["reconstruct", str(tmp_path / "tiny.tif"), "--psf", str(tmp_path / "psf.tif"), "-o", str(out),
                 "--max-iter", "3", "--quiet", "--dtype", "float64"])
    assert code == 0
    vol, _ = io.read_tiff(out)
    assert vol.dtype == np.float64 and np.all(np.isfinite(vol)) and vol.max() > 0


@pytest.mark.parametrize("shape", [(4, 1, 7), (4, 7, 1), (1, 1, 1), (1, 5, 6), (3, 1, 1)])
def test_volumes_with_axes_of_length_one_keep_their_shape(tmp_path, shape):
    a = np.arange(np.prod(shape), dtype=np.float32).reshape(shape)
    io.write_tiff(tmp_path / "v.ome.tif", a, voxel_size_um=(5.0, 2.0, 2.0), depths_um=np.arange(shape[0]) * 5.0)
    b, meta = io.read_tiff(tmp_path / "v.ome.tif")
    assert b.shape == shape and np.array_equal(a, b) and meta["voxel_size_um"] == (5.0, 2.0, 2.0)


def _simulate(out, seed, fault=None):
    env = {**os.environ, **({"CM2CL_FAULT": fault} if fault else {})}
    return subprocess.run([sys.executable, "-m", "cm2cl", "simulate", "demo_beads", "-o", str(out), "--seed",
                           str(seed)], capture_output=True, text=True, env=env)


def test_simulate_replaces_a_previous_result_whole(rt, tmp_path):
    """Killed between moving the old folder aside and moving the new one in: the target is absent (never
    new files beside old ones), and the next run on it first restores the previous complete result."""
    out = tmp_path / "sim"
    assert _simulate(out, 1).returncode == 0
    first = json.loads((out / "simulation.json").read_text())["seed"]
    r = _simulate(out, 2, fault="swap.old_moved_aside")
    assert r.returncode == -9
    assert not out.exists()
    from cm2cl.io.staging import StagedOutput

    with StagedOutput(out, "simulation.json"):
        assert json.loads((out / "simulation.json").read_text())["seed"] == first
    assert [p.name for p in tmp_path.iterdir()] == ["sim"]          # no hidden staging left
    assert _simulate(out, 3).returncode == 0
    assert json.loads((out / "simulation.json").read_text())["seed"] == 3
    assert [p.name for p in tmp_path.iterdir()] == ["sim"]


def test_simulate_refuses_a_folder_that_is_not_its_output(rt, tmp_path):
    out = tmp_path / "data"
    out.mkdir()
    (out / "precious.tif").write_bytes(b"x")
    r = _simulate(out, 1)
    assert r.returncode == 2 and "not a previous output of this command" in r.stderr
    assert [p.name for p in out.iterdir()] == ["precious.tif"]


def test_inputs_are_checked_from_their_headers_before_decoding(rt, tmp_path, capsys, monkeypatch):
    """Issue 8 item 14: a small compressed TIFF that decodes to a huge image was decoded (8 GB, 33 s) before
    "shape does not match"; now shapes and the memory they need come from the headers. (A PSF of another
    lateral size is now padded or cropped (issue 12 item 4), so a wrong shape here is a 3D measurement.)"""
    meas, psf = _files(tmp_path)
    big = tmp_path / "big.tif"
    tifffile.imwrite(big, np.zeros((2, 6000, 3000), np.uint8), compression="zlib")
    assert big.stat().st_size < 1e6
    decoded = []
    real = io.read_tiff
    monkeypatch.setattr(io, "read_tiff", lambda p: decoded.append(p) or real(p))
    out = tmp_path / "v.ome.tif"
    assert main(["reconstruct", str(big), "--psf", str(psf), "-o", str(out), "--quiet"]) == 2
    assert "expected a 2D image, got shape (2, 6000, 3000)" in capsys.readouterr().err
    monkeypatch.setattr("cm2cl.solver.memory.host_available_bytes", lambda: 1000)
    assert main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(out), "--quiet"]) == 2
    assert "of host memory" in capsys.readouterr().err
    assert decoded == [] and not out.exists()
    monkeypatch.setattr("cm2cl.solver.memory.host_available_bytes", lambda: 1 << 40)
    assert main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(out), "--quiet", "--max-iter", "2"]) == 0
    assert len(decoded) == 2                                   # the interception sees real reads


@pytest.mark.parametrize("key, value, msg", [
    ("count", 1e8, "objects; at most .* can be generated"),
    ("diameter_um", 1e9, "is larger than the volume"),
    ("dz_um", 1e-9, "planes; at most 100000"),
])
def test_scenes_beyond_the_machine_are_refused_before_generating(tmp_path, key, value, msg):
    """Issue 8 item 15: count = 1e8, diameter_um = 1e9, dz_um = 1e-9 took 15.8 GB and ended in MemoryError
    or ValueError tracebacks with staging files left; now the scene is refused when it is read."""
    from cm2cl import simulate
    from cm2cl.errors import InputError

    s = simulate.load_scene("demo_beads").as_dict()
    s.pop("source", None)
    if key == "dz_um":
        s["volume"]["dz_um"] = value
    else:
        s["objects"][0][key] = value
    with pytest.raises(InputError, match=msg):
        simulate.simulate_scene(s)


def test_simulate_cli_refuses_a_huge_scene_and_leaves_nothing(tmp_path):
    from pathlib import Path

    import cm2cl.simulate

    text = (Path(cm2cl.simulate.__file__).parent / "scenes" / "demo_beads.toml").read_text()
    assert "count = 12" in text
    (tmp_path / "huge.toml").write_text(text.replace("count = 12", "count = 100000000"))
    r = subprocess.run([sys.executable, "-m", "cm2cl", "simulate", str(tmp_path / "huge.toml"), "-o",
                        str(tmp_path / "sim")], capture_output=True, text=True)
    assert r.returncode == 2 and "can be generated" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["huge.toml"]


def test_simulate_checks_the_disk_before_rendering(tmp_path, monkeypatch):
    from cm2cl import simulate
    from cm2cl.errors import InputError
    from cm2cl.io import staging

    calls = []
    monkeypatch.setattr(simulate.pipeline, "simulate_scene", lambda *a, **k: calls.append(1))
    monkeypatch.setattr(staging.shutil, "disk_usage", lambda p: type("U", (), {"free": 1000})())
    with pytest.raises(InputError, match="MiB free"):
        simulate.simulate("demo_beads", tmp_path / "sim")
    assert calls == [] and not (tmp_path / "sim").exists()

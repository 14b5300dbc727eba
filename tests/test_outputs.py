"""Outputs and files (issue 8, items 1-7, 14, 15): the output is checked before any work and nothing is
created by a refusal; a file and its sidecars are published as one unit (paused and killed with SIGKILL at
each named step: the target holds the previous or the new complete result, never a mix); staging is unique
per run and a second run on the same target is refused; sidecars cannot overwrite other files; output
folders are swapped in whole; volumes the dtype cannot hold are refused; one-pixel-wide volumes keep their
shape; inputs and scenes beyond the machine are refused from their headers."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import tifffile

from cm2cl import io
from cm2cl.cli import main
from cm2cl.errors import InputError
from cm2cl.io import publish, staging
from test_admm import bead_problem

INPUTS = ("meas.tif", "psf.tif")


def _files(tmp_path, scale=1.0):
    psf, _, y = bead_problem(6)
    tifffile.imwrite(tmp_path / "psf.tif", psf.astype(np.float32), photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", (y * scale).astype(np.float32))
    return tmp_path / "meas.tif", tmp_path / "psf.tif"


def _run(tmp_path, out, *extra, scale=1.0):
    meas, psf = _files(tmp_path, scale)
    return main(["reconstruct", str(meas), "--psf", str(psf), "-o", str(out), "--max-iter", "5", "--quiet", *extra])


def _argv(tmp_path, iters, *extra):
    return ["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "-o",
            str(tmp_path / "vol.ome.tif"), "--quiet", "--max-iter", str(iters), *extra]


def _listing(d, skip=INPUTS):
    """Every name in ``d`` (hidden ones too) but the inputs."""
    return sorted(p.name for p in d.iterdir() if p.name not in skip)


def _paused(argv, step):
    """A ``python -m cm2cl`` process stopped (SIGSTOP) at the fault point ``step``."""
    p = subprocess.Popen([sys.executable, "-m", "cm2cl", *argv], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         env={**os.environ, staging.FAULT_ENV: f"{step}:pause"})
    deadline = time.monotonic() + 120
    while True:
        pid, status = os.waitpid(p.pid, os.WUNTRACED | os.WNOHANG)
        if pid:
            break
        if time.monotonic() > deadline:
            p.kill()
            pytest.fail(f"never reached {step}")
        time.sleep(0.02)
    assert os.WIFSTOPPED(status), f"exited before {step}: {p.stderr.read().decode()}"
    return p


def _kill(p):
    p.kill()
    assert p.wait() == -signal.SIGKILL
    p.stderr.close()


def _unit(d):
    """{member: the run (its iteration cap) it belongs to} for the members of vol.ome.tif present."""
    s = {}
    if (d / "vol.ome.tif").exists():
        s["volume"] = io.read_tiff(d / "vol.ome.tif")[1]["extra"]["params"]["max_iter"]
    if (d / "vol.cm2cl.json").exists():
        s["record"] = json.loads((d / "vol.cm2cl.json").read_text())["params"]["max_iter"]
    if (d / "vol.cm2cl.log.csv").exists():
        s["log"] = len((d / "vol.cm2cl.log.csv").read_text().splitlines()) - 1
    return s


# ---- item 1: checked before any work, nothing left by a refusal or a failure ---------------------------

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
    monkeypatch.setattr(staging.os, "access", lambda p, m: False if str(p) == str(tmp_path) else real_access(p, m))
    assert _run(tmp_path, tmp_path / "vol.ome.tif") == 2
    assert "is not writable" in capsys.readouterr().err
    monkeypatch.setattr(staging.os, "access", real_access)
    monkeypatch.setattr(staging.shutil, "disk_usage", lambda p: type("U", (), {"free": 1000})())
    assert _run(tmp_path, tmp_path / "vol.ome.tif") == 2
    assert "MiB free" in capsys.readouterr().err
    assert calls == [] and _listing(tmp_path) == []


def _full_disk(path, *a, **k):
    with open(path, "wb") as f:
        f.write(b"half")
    raise OSError(28, "No space left on device")


def test_a_failure_while_writing_leaves_nothing(rt, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(io, "write_tiff", _full_disk)
    assert _run(tmp_path, tmp_path / "vol.ome.tif") == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and "nothing was written" in err
    assert _listing(tmp_path) == []


def test_missing_output_folders_are_created_and_removed_when_nothing_is_published(rt, tmp_path, capsys, monkeypatch):
    """Issue 26: -o new/sub/vol.ome.tif makes the folders (as simulate and demo do); a run that fails
    removes the folders it made; a file in the way or an unwritable parent is refused before the solve."""
    assert _run(tmp_path, tmp_path / "new" / "sub" / "vol.ome.tif") == 0
    assert sorted(p.name for p in (tmp_path / "new" / "sub").iterdir()) == ["vol.cm2cl.json", "vol.cm2cl.log.csv",
                                                                          "vol.ome.tif"]
    monkeypatch.setattr(io, "write_tiff", _full_disk)
    assert _run(tmp_path, tmp_path / "other" / "deep" / "vol.ome.tif") == 2
    assert "nothing was written" in capsys.readouterr().err and not (tmp_path / "other").exists()
    monkeypatch.undo()
    (tmp_path / "afile").write_text("x")
    assert _run(tmp_path, tmp_path / "afile" / "vol.ome.tif") == 2
    err = capsys.readouterr().err
    assert "is a file, not a folder" in err and len(err.strip().splitlines()) == 1
    real_access = os.access
    monkeypatch.setattr(staging.os, "access", lambda p, m: False if str(p) == str(tmp_path) else real_access(p, m))
    assert _run(tmp_path, tmp_path / "x" / "vol.ome.tif") == 2
    assert "is not writable" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_a_failure_while_writing_keeps_the_previous_result_whole(rt, tmp_path, capsys, monkeypatch):
    assert _run(tmp_path, tmp_path / "vol.ome.tif") == 0
    before = {n: (tmp_path / n).read_bytes() for n in _listing(tmp_path)}
    monkeypatch.setattr(io, "write_tiff", _full_disk)
    assert _run(tmp_path, tmp_path / "vol.ome.tif", "--max-iter", "7") == 2
    assert "nothing was written" in capsys.readouterr().err
    assert {n: (tmp_path / n).read_bytes() for n in _listing(tmp_path)} == before


@pytest.fixture(scope="module")
def sim_result(rt):
    from cm2cl.simulate import simulate_scene

    return simulate_scene("demo_beads", seed=1)


def test_simulate_checks_the_disk_before_rendering_and_creates_no_folder(tmp_path, monkeypatch):
    from cm2cl import simulate

    calls = []
    monkeypatch.setattr(simulate.pipeline, "simulate_scene", lambda *a, **k: calls.append(1))
    monkeypatch.setattr(staging.shutil, "disk_usage", lambda p: type("U", (), {"free": 1000})())
    with pytest.raises(InputError, match="MiB free"):
        simulate.simulate("demo_beads", tmp_path / "a" / "b" / "sim")
    assert calls == [] and _listing(tmp_path) == []


def test_a_simulation_refused_after_the_check_leaves_no_folder(tmp_path, monkeypatch):
    """The parent folders are made for the staging folder and removed again when nothing is published."""
    from cm2cl import simulate

    def refuse(*a, **k):
        assert (tmp_path / "a" / "b").is_dir()         # the lock and the staging live there meanwhile
        raise InputError("scene: refused while rendering")

    monkeypatch.setattr(simulate.pipeline, "simulate_scene", refuse)
    with pytest.raises(InputError, match="refused while rendering"):
        simulate.simulate("demo_beads", tmp_path / "a" / "b" / "sim")
    assert _listing(tmp_path) == []


def test_simulated_files_name_their_scene_and_channel(sim_result, tmp_path):
    """Issue 26: the OME Image is named after the scene and what the file is, the channel carries the
    optics' emission wavelength (viewers showed Image0 and no channel)."""
    import xml.etree.ElementTree as ET

    from cm2cl.simulate import write_simulation

    write_simulation(sim_result, tmp_path / "sim")
    for fname, what in (("measurement.ome.tif", "measurement"), ("psf.ome.tif", "PSF stack"),
                        ("ground_truth.ome.tif", "ground truth")):
        root = ET.fromstring(tifffile.TiffFile(tmp_path / "sim" / fname).ome_metadata)
        ns = {"o": root.tag[1:].split("}")[0]}
        img = root.find("o:Image", ns)
        ch = img.find("o:Pixels/o:Channel", ns)
        assert img.get("Name") == f"demo_beads: {what}" and ch.get("Name") == "fluorescence"
        assert float(ch.get("EmissionWavelength")) == pytest.approx(530.0) and ch.get("EmissionWavelengthUnit") == "nm"


def test_simulate_writing_failure_keeps_the_previous_folder(sim_result, tmp_path, monkeypatch):
    from cm2cl.simulate import pipeline, write_simulation

    out = tmp_path / "sim"
    write_simulation(sim_result, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    monkeypatch.setattr(pipeline, "_write_outputs", lambda result, scene, d: _full_disk(d / "measurement.ome.tif"))
    with pytest.raises(InputError, match=r"writing failed \(No space left on device\); nothing was written, the "
                                         "previous result is kept"):
        write_simulation(sim_result, out)
    assert _listing(tmp_path) == ["sim"] and {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_demo_refuses_a_file_as_its_folder_before_any_work(tmp_path, capsys, monkeypatch):
    import cm2cl.simulate

    calls = []
    monkeypatch.setattr(cm2cl.simulate, "simulate_scene", lambda *a, **k: calls.append(1))
    (tmp_path / "afile").write_text("mine")
    assert main(["demo", "-o", str(tmp_path / "afile")]) == 2
    err = capsys.readouterr()
    assert "exists and is not a directory" in err.err and err.out == "" and calls == []
    assert _listing(tmp_path) == ["afile"] and (tmp_path / "afile").read_text() == "mine"


# ---- items 2 and 3: one unit, fault injection at each step, one run per target ---------------------------

#: what a reader finds while the second run (7 iterations) is paused at each step, the first (5) complete;
#: then, after the next run on the target completed a killed publication, the whole unit of this run
_EXPECTED = {
    "staged": ({"volume": 5, "record": 5, "log": 5}, 5),
    "committed": ({"volume": 5, "record": 5, "log": 5}, 7),
    "old_removed": ({"volume": 5}, 7),
    "volume": ({"volume": 7}, 7),
    "log": ({"volume": 7, "log": 7}, 7),
    "record": ({"volume": 7, "log": 7, "record": 7}, 7),
}


def test_every_publishing_step_is_covered():
    assert tuple(_EXPECTED) == publish.STEPS


@pytest.mark.parametrize("step", publish.STEPS)
def test_killed_while_publishing_never_mixes_two_runs(rt, tmp_path, step):
    """A first run (5 iterations) is complete; a second (7) is paused at ``publish.<step>``, looked at,
    and killed with SIGKILL. At every moment the files present belong to one run; after the next open of
    the target (which completes a publication that was committed) the target holds the first or the
    second run whole, and nothing hidden is left."""
    _files(tmp_path)
    assert main(_argv(tmp_path, 5)) == 0
    p = _paused(_argv(tmp_path, 7), f"publish.{step}")
    seen, after = _EXPECTED[step]
    assert _unit(tmp_path) == seen                      # what a reader sees meanwhile: one run's files
    _kill(p)
    assert _unit(tmp_path) == seen
    with publish.OutputSet(tmp_path / "vol.ome.tif"):   # the next run on the target, before its work
        assert _unit(tmp_path) == {"volume": after, "record": after, "log": after}
    assert _listing(tmp_path) == ["vol.cm2cl.json", "vol.cm2cl.log.csv", "vol.ome.tif"]
    assert json.loads((tmp_path / "vol.cm2cl.json").read_text())["files"] == [
        "vol.ome.tif", "vol.cm2cl.json", "vol.cm2cl.log.csv"]


def test_a_second_run_on_the_same_output_is_refused_while_the_first_finishes(rt, tmp_path, capsys):
    """Two runs, two processes: the second is refused (one line, nothing written) while the first holds
    the target; the first then publishes its own result."""
    _files(tmp_path)
    first = _paused(_argv(tmp_path, 7), "publish.staged")
    assert main(_argv(tmp_path, 5)) == 2
    assert "another run is writing it" in capsys.readouterr().err
    first.send_signal(signal.SIGCONT)
    assert first.wait(timeout=60) == 0
    first.stderr.close()
    assert _unit(tmp_path) == {"volume": 7, "record": 7, "log": 7}
    assert _listing(tmp_path) == ["vol.cm2cl.json", "vol.cm2cl.log.csv", "vol.ome.tif"]
    assert main(_argv(tmp_path, 5)) == 0                # and the target is free again


def test_staging_names_are_unique_per_run(tmp_path):
    with publish.OutputSet(tmp_path / "v.ome.tif") as a:
        first = {k: a.staged(k) for k in ("volume", "record", "log")}
    with publish.OutputSet(tmp_path / "v.ome.tif") as b:
        assert all(b.staged(k) != first[k] and f".{os.getpid()}-" in b.staged(k).name for k in first)
    assert _listing(tmp_path) == []                     # the lock file goes with the run


def test_a_lock_file_replaced_under_a_waiting_run_is_taken_again(tmp_path):
    """The holder removes its lock file when done: a run that opened the old file before that must not
    believe it holds the lock while a third run locks the new file."""
    path = tmp_path / ".x.cm2cl-lock"
    real_lock, calls = staging._lock_nonblocking, []

    def lock(fd):
        real_lock(fd)
        if not calls:              # between this run's open and its check, the holder leaves, another comes
            calls.append(1)
            path.unlink()
            calls.append(staging.exclusive_lock(path, "taken"))

    staging._lock_nonblocking = lock
    try:
        with pytest.raises(InputError, match="^busy$"):
            staging.exclusive_lock(path, "busy")
    finally:
        staging._lock_nonblocking = real_lock
    staging.release_lock(calls[1], path)
    assert _listing(tmp_path) == []


# ---- item 4: sidecars -------------------------------------------------------------------------------------

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
    # a user's own OUT.cm2cl.log.csv with no record beside it is not replaced (issue 27)
    (tmp_path / "mine.cm2cl.log.csv").write_text("my notes\n")
    assert _run(tmp_path, tmp_path / "mine.ome.tif") == 2
    assert "mine.cm2cl.log.csv' exists and is not this output's" in capsys.readouterr().err
    assert (tmp_path / "mine.cm2cl.log.csv").read_text() == "my notes\n" and not (tmp_path / "mine.ome.tif").exists()


def test_a_saved_background_is_a_member_of_the_unit_and_overwrites_no_other_file(rt, tmp_path, capsys):
    bg = ["--background", "opening:3px", "--save-background"]
    (tmp_path / "vol.background.ome.tif").write_bytes(b"not cm2cl's")
    assert _run(tmp_path, tmp_path / "vol.ome.tif", *bg) == 2
    assert "vol.background.ome.tif' exists and is not this output's" in capsys.readouterr().err
    assert _listing(tmp_path) == ["vol.background.ome.tif"]
    (tmp_path / "vol.background.ome.tif").unlink()
    assert _run(tmp_path, tmp_path / "vol.ome.tif", *bg) == 0
    assert json.loads((tmp_path / "vol.cm2cl.json").read_text())["files"] == [
        "vol.ome.tif", "vol.cm2cl.json", "vol.cm2cl.log.csv", "vol.background.ome.tif"]
    assert io.read_tiff(tmp_path / "vol.background.ome.tif")[0].shape == (32, 40)
    assert _run(tmp_path, tmp_path / "vol.ome.tif", *bg) == 0           # its own member: replaced
    # a run without a background replaces the whole unit: no background of the previous run stays beside it
    assert _run(tmp_path, tmp_path / "vol.ome.tif") == 0
    assert _listing(tmp_path) == ["vol.cm2cl.json", "vol.cm2cl.log.csv", "vol.ome.tif"]


# ---- item 5: output folders swapped in whole --------------------------------------------------------------

def _simulate_argv(out, seed):
    return ["simulate", "demo_beads", "-o", str(out), "--seed", str(seed)]


def _folder(out):
    """(seed, {name: bytes}) of a complete simulation folder: its record lists exactly the files there."""
    rec = json.loads((out / "simulation.json").read_text())
    assert sorted(p.name for p in out.iterdir()) == sorted([*rec["files"].values(), "simulation.json"])
    return rec["seed"], {p.name: p.read_bytes() for p in out.iterdir() if p.suffix != ".json"}


@pytest.mark.parametrize("step", staging.FOLDER_STEPS)
def test_simulate_replaces_a_previous_result_whole(sim_result, tmp_path, step):
    """Paused and killed at each step of publishing a folder over a previous result: the target holds the
    previous complete result (staged) or the new complete one (swapped), never a mix; the next run removes
    the hidden staging the killed run left."""
    from cm2cl.simulate import write_simulation

    out = tmp_path / "sim"
    write_simulation(sim_result, out)
    before = _folder(out)
    p = _paused(_simulate_argv(out, 2), step)
    now = _folder(out)
    _kill(p)
    assert _folder(out) == now
    if step == "folder.staged":
        assert now == before
    else:
        assert now[0] == 2 and now[1]["measurement.ome.tif"] != before[1]["measurement.ome.tif"]
    assert [n.split("-")[0] for n in _listing(tmp_path)] == [".sim.cm2cl", ".sim.partial", "sim"]  # what it left
    with staging.StagedOutput(out, "simulation.json"):
        pass
    assert _listing(tmp_path) == ["sim"] and _folder(out) == now


def test_simulate_without_an_atomic_exchange_brings_the_previous_result_back(sim_result, tmp_path):
    """Where the filesystem cannot exchange two folders, the previous one is renamed aside first: killed
    there, the target is absent (never mixed), and the next run on it restores the previous result."""
    from cm2cl.simulate import write_simulation

    out = tmp_path / "sim"
    write_simulation(sim_result, out)
    before = _folder(out)
    code = ("import sys; import cm2cl.io.staging as s; s.exchange = lambda a, b: False; "
            "from cm2cl.cli.main import main; sys.exit(main(sys.argv[1:]))")
    p = subprocess.Popen([sys.executable, "-c", code, *_simulate_argv(out, 2)], stderr=subprocess.PIPE,
                         stdout=subprocess.DEVNULL,
                         env={**os.environ, staging.FAULT_ENV: "folder.old_moved_aside"})
    assert p.wait(timeout=120) == -signal.SIGKILL, p.stderr.read()
    p.stderr.close()
    assert not out.exists()
    with staging.StagedOutput(out, "simulation.json"):
        assert _folder(out) == before
    assert _listing(tmp_path) == ["sim"]


def test_a_second_simulation_into_the_same_folder_is_refused(sim_result, tmp_path, capsys, monkeypatch):
    import cm2cl.simulate

    calls = []
    monkeypatch.setattr(cm2cl.simulate.pipeline, "simulate_scene", lambda *a, **k: calls.append(1))
    with staging.StagedOutput(tmp_path / "sim", "simulation.json"):
        assert main(_simulate_argv(tmp_path / "sim", 1)) == 2
        assert "another run is writing it" in capsys.readouterr().err
    assert calls == [] and _listing(tmp_path) == []


def test_simulate_refuses_a_folder_that_is_not_its_output(rt, tmp_path, capsys):
    out = tmp_path / "data"
    out.mkdir()
    (out / "precious.tif").write_bytes(b"x")
    assert main(_simulate_argv(out, 1)) == 2
    assert "not a previous output of this command" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["precious.tif"] and _listing(tmp_path) == ["data"]


# ---- items 6 and 7: what the file holds ------------------------------------------------------------------

@pytest.mark.parametrize("scale, msg", [(1e-300, "below what float32 can hold"), (1e300, "exceed what float32 can hold")])
def test_a_volume_float32_cannot_hold_is_refused_and_float64_written(rt, tmp_path, capsys, scale, msg):
    _files(tmp_path)
    psf, _, y = bead_problem(6)
    tifffile.imwrite(tmp_path / "extreme.tif", y * scale)          # a float64 file: representable
    out = tmp_path / "t.ome.tif"
    argv = ["reconstruct", str(tmp_path / "extreme.tif"), "--psf", str(tmp_path / "psf.tif"), "-o", str(out),
            "--max-iter", "3", "--quiet"]
    assert main(argv) == 2
    assert msg in capsys.readouterr().err and _listing(tmp_path, INPUTS + ("extreme.tif",)) == []
    if not rt.caps.fp64:
        pytest.skip("no fp64 on this device")
    assert main(argv + ["--dtype", "float64"]) == 0
    vol, _ = io.read_tiff(out)
    assert vol.dtype == np.float64 and np.all(np.isfinite(vol)) and 1e-3 < vol.max() / scale < 1e3


@pytest.mark.parametrize("shape", [(4, 1, 7), (4, 7, 1), (1, 1, 1), (1, 5, 6), (3, 1, 1)])
def test_volumes_with_axes_of_length_one_keep_their_shape(tmp_path, shape):
    a = np.arange(np.prod(shape), dtype=np.float32).reshape(shape)
    io.write_tiff(tmp_path / "v.ome.tif", a, voxel_size_um=(5.0, 2.0, 2.0), depths_um=np.arange(shape[0]) * 5.0)
    b, meta = io.read_tiff(tmp_path / "v.ome.tif")
    assert b.shape == shape and np.array_equal(a, b) and meta["voxel_size_um"] == (5.0, 2.0, 2.0)


@pytest.mark.parametrize("sensor, bin_, volume", [((4, 32), 4, (2, 1, 8)), ((1, 32), 1, (2, 1, 32))])
def test_a_one_pixel_wide_reconstruction_reads_back_with_its_shape(rt, tmp_path, sensor, bin_, volume):
    """Item 7 end to end: --bin turns a 4-row sensor into one row, or the sensor has one row (the header
    check took a (1, 32) image for 1D and refused it); the file reads back as (nz, 1, nx)."""
    rng = np.random.default_rng(3)
    tifffile.imwrite(tmp_path / "psf.tif", rng.random((2, *sensor)).astype(np.float32), photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", rng.random(sensor).astype(np.float32))
    out = tmp_path / "v.ome.tif"
    assert main(["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "-o", str(out),
                 "--bin", str(bin_), "--max-iter", "2", "--quiet"]) == 0
    assert io.read_tiff(out)[0].shape == volume


# ---- items 14 and 15: refused from the headers and the scene, before the work -----------------------------

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
    # a CPU device's memory is the host's: the planner refuses first, naming host memory (a GPU: the
    # host check after it)
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

    s = simulate.load_scene("demo_beads").as_dict()
    s.pop("source", None)
    if key == "dz_um":
        s["volume"]["dz_um"] = value
    else:
        s["objects"][0][key] = value
    with pytest.raises(InputError, match=msg):
        simulate.simulate_scene(s)


def test_simulate_cli_refuses_a_huge_scene_and_leaves_nothing(tmp_path, capsys):
    from pathlib import Path

    import cm2cl.simulate

    text = (Path(cm2cl.simulate.__file__).parent / "scenes" / "demo_beads.toml").read_text()
    assert "count = 12" in text
    (tmp_path / "huge.toml").write_text(text.replace("count = 12", "count = 100000000"))
    assert main(["simulate", str(tmp_path / "huge.toml"), "-o", str(tmp_path / "out" / "sim")]) == 2
    err = capsys.readouterr().err
    assert "can be generated" in err and len(err.strip().splitlines()) == 1
    assert _listing(tmp_path) == ["huge.toml"]


@pytest.mark.parametrize("shape", [(1, 32), (32, 1), (1, 1, 32), (2, 1, 32), (1, 4, 5), (3, 4, 5)])
def test_header_shapes_are_the_decoded_shapes(tmp_path, shape):
    """The header check saw (32,) for a one-row image, so a one-row measurement was refused as "not a 2D
    image" and a (2, 1, 32) PSF taken for one plane: peek_tiff now gives read_tiff's shape, plain or OME."""
    a = np.ones(shape, np.float32)
    tifffile.imwrite(tmp_path / "plain.tif", a, photometric="minisblack")
    io.write_tiff(tmp_path / "ome.ome.tif", a)
    for name in ("plain.tif", "ome.ome.tif"):
        assert io.peek_tiff(tmp_path / name) == (shape, np.dtype(np.float32))
        assert io.read_tiff(tmp_path / name)[0].shape == shape


def test_a_second_simulate_on_the_same_folder_is_refused(tmp_path):
    from cm2cl.errors import InputError
    from cm2cl.io.staging import StagedOutput

    with StagedOutput(tmp_path / "sim", "simulation.json"):
        with pytest.raises(InputError, match="another run is writing it"):
            StagedOutput(tmp_path / "sim", "simulation.json")
    with StagedOutput(tmp_path / "sim", "simulation.json"):   # released at the end
        pass
    assert [p.name for p in tmp_path.iterdir()] == []


# ---- found by the property tests --------------------------------------------------------------------------

@pytest.mark.parametrize("case, msg", [
    ("nan_psf", "psf '{d}/psf.tif': contains NaN/Inf values"),
    ("tiny_auto_offset", "measurement '{d}/meas.tif': offset 'auto' averages pixels [5:15, 5:15], which an image "
                         "of shape (4, 4) does not have"),
])
def test_bad_inputs_found_by_the_property_tests_are_refused_in_one_line(rt, tmp_path, capsys, case, msg):
    """A NaN in the PSF reached the hot-pixel check (a ValueError traceback); 'auto' on an image smaller than
    the dark corner averaged nothing and the NaN offset was reported as NaN in the measurement."""
    rng = np.random.default_rng(5)
    y, psf = rng.random((4, 4)).astype(np.float32), rng.random((1, 4, 4)).astype(np.float32)
    extra = []
    if case == "nan_psf":
        psf[0, 1, 2] = np.nan
    else:
        extra = ["--offset", "auto"]
    tifffile.imwrite(tmp_path / "meas.tif", y)
    tifffile.imwrite(tmp_path / "psf.tif", psf, photometric="minisblack")
    assert main(_argv(tmp_path, 2, *extra)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and msg.format(d=tmp_path) in err[0]
    assert _listing(tmp_path) == []

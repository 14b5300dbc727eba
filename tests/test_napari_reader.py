"""The napari reader (issue 26): cm2cl's outputs open at their physical scale and depth offset, and a
simulation's emitters land on its beads in world coordinates; the npe2 manifest validates."""

import importlib
from pathlib import Path

import numpy as np
import pytest

from cm2cl.io.napari_reader import get_reader


@pytest.fixture(scope="module")
def sim_dir(rt, tmp_path_factory):
    from cm2cl.simulate import simulate_scene, write_simulation

    d = tmp_path_factory.mktemp("sim") / "sim"
    write_simulation(simulate_scene("demo_beads", seed=1), d)
    return d


def test_volume_and_emitters_overlay_in_world_coordinates(sim_dir):
    from cm2cl import io

    (data, kw, kind), = get_reader(str(sim_dir / "ground_truth.ome.tif"))(str(sim_dir / "ground_truth.ome.tif"))
    _, meta = io.read_tiff(sim_dir / "ground_truth.ome.tif")
    assert kind == "image" and kw["scale"] == tuple(meta["voxel_size_um"])
    assert kw["translate"] == (meta["depths_um"][0], 0.0, 0.0) and meta["depths_um"][0] != 0.0
    (pts, pkw, pkind), = get_reader(str(sim_dir / "emitters.csv"))(str(sim_dir / "emitters.csv"))
    assert pkind == "points" and pkw["scale"] == kw["scale"] and pkw["translate"] == kw["translate"]
    # world positions of the points, mapped back through the image layer's transform, hit bright voxels
    world = pts * np.array(pkw["scale"]) + np.array(pkw["translate"])
    vox = np.rint((world - np.array(kw["translate"])) / np.array(kw["scale"])).astype(int)
    inside = np.all((vox >= 0) & (vox < np.array(data.shape)), axis=1)
    assert inside.sum() >= 0.8 * len(vox)
    near = [data[max(z - 1, 0):z + 2, max(y - 2, 0):y + 3, max(x - 2, 0):x + 3].max() for z, y, x in vox[inside]]
    assert np.min(near) > 0.2 * data.max(), np.min(near) / data.max()
    assert set(pkw["properties"]) >= {"brightness", "z_um"}


def test_series_store_and_refusals(rt, tmp_path):
    import cm2cl
    from test_jobs import _series

    psf, frames = _series(tmp_path, n=2)
    out = tmp_path / "s.ome.zarr"
    cm2cl.reconstruct_series(frames.astype(float), tmp_path / "psf.ome.tif", out, max_iter=5, tol=0.0,
                             frame_interval_s=0.1, channel="GFP")
    (arr, kw, kind), = get_reader(str(out))(str(out))
    assert kind == "image" and arr.shape[0] == 2 and kw["scale"] == (0.1, 10.0, 2.0, 2.0)
    assert kw["axis_labels"] == ("t", "z", "y", "x") and kw["metadata"]["channel"] == "GFP"
    assert kw["contrast_limits"][1] == pytest.approx(float(np.asarray(arr).max()))
    (tmp_path / "other.csv").write_text("a,b\n1,2\n")
    assert get_reader(str(tmp_path / "other.csv")) is None and get_reader(str(tmp_path / "series.tif")) is None
    assert get_reader(str(tmp_path / "missing.ome.tif")) is None


def test_manifest_validates_and_names_the_reader():
    import npe2   # in the test extra: this test runs wherever the suite does
    import importlib.metadata as md

    path = Path(__import__("cm2cl").__file__).with_name("napari.yaml")
    pm = npe2.PluginManifest.from_file(path)
    (reader,) = pm.contributions.readers
    cmd = {c.id: c for c in pm.contributions.commands}[reader.command]
    mod, _, fn = cmd.python_name.partition(":")
    assert getattr(importlib.import_module(mod), fn) is get_reader
    eps = [e for e in md.entry_points(group="napari.manifest") if e.name == "cm2cl"]
    assert eps and eps[0].value == "cm2cl:napari.yaml"



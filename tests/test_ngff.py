"""The series store as OME-Zarr (issue 26): valid NGFF 0.4 by ome-zarr-models' validated models, "/" chunk
keys, z translated to the first plane's depth, t in seconds when the interval is known, and an omero channel
whose display window covers the volume."""

import json

import numpy as np
import zarr

import cm2cl
from cm2cl import io as cio
from test_admm import bead_problem
from test_jobs import P


def _job(tmp_path, **kw):
    psf, _, _ = bead_problem(7)
    from cm2cl import reference as ref

    frames = []
    for t in range(2):
        _, x, _ = bead_problem(7, emitters=((t, 10 + t, 12), (1, 20, 30 - t)))
        frames.append(ref.forward(psf, x, P) * 1000)
    nz = psf.shape[0]
    cio.write_tiff(tmp_path / "psf.ome.tif", psf.astype(np.float32), voxel_size_um=(25.0, 4.0, 4.0),
                   depths_um=[-500.0 + 25.0 * i for i in range(nz)], extra={"voxel_space": cio.OBJECT_SPACE})
    out = tmp_path / "m.ome.zarr"
    cm2cl.reconstruct_series(np.stack(frames), tmp_path / "psf.ome.tif", out, max_iter=20, tol=0.0, **kw)
    return out


def test_store_is_valid_ngff_with_translation_units_and_omero(rt, tmp_path):
    from ome_zarr_models.v04.image import Image

    out = _job(tmp_path, channel="GCaMP6f", frame_interval_s=0.05)
    image = Image.from_zarr(zarr.open_group(str(out), mode="r"))       # raises on any schema violation
    ms = image.attributes.multiscales[0]
    assert [(a.name, a.unit) for a in ms.axes] == [("t", "second"), ("z", "micrometer"), ("y", "micrometer"),
                                                   ("x", "micrometer")]
    attrs = json.loads((out / ".zattrs").read_text())
    tr = {t["type"]: t for t in attrs["multiscales"][0]["datasets"][0]["coordinateTransformations"]}
    assert tr["scale"]["scale"] == [0.05, 25.0, 4.0, 4.0] and tr["translation"]["translation"] == [0.0, -500.0, 0.0, 0.0]
    assert json.loads((out / "0" / ".zarray").read_text())["dimension_separator"] == "/"
    assert (out / "0" / "1" / "0" / "0" / "0").is_file()
    ch = attrs["omero"]["channels"][0]
    vmax = float(np.asarray(zarr.open_group(str(out), mode="r")["0"]).max())
    assert ch["label"] == "GCaMP6f" and ch["window"]["end"] == vmax and ch["window"]["start"] == 0.0 and vmax > 0


def test_store_without_known_interval_counts_frames(rt, tmp_path):
    from ome_zarr_models.v04.image import Image

    out = _job(tmp_path)
    Image.from_zarr(zarr.open_group(str(out), mode="r"))
    attrs = json.loads((out / ".zattrs").read_text())
    t = attrs["multiscales"][0]["axes"][0]
    assert t == {"name": "t", "type": "time"} and attrs["omero"]["channels"][0]["label"] == "fluorescence"


def test_large_frames_are_chunked_for_viewers_and_done_only_when_whole(tmp_path):
    """A frame of 20 x 300 x 520 is 3 x 2 x 3 chunks of at most 8 x 256 x 256; a frame partly written (a
    run killed inside it) is not done; a done frame one of whose chunks is lost fails its checksum."""
    from cm2cl.jobs.store import FrameStore

    shape = (20, 300, 520)
    rng = np.random.default_rng(0)
    vol = rng.random(shape).astype(np.float32)
    with FrameStore.open(tmp_path / "big.ome.zarr", fingerprint="x", n_frames=2, volume_shape=shape,
                         dtype=np.float32) as store:
        assert store.array.chunks == (1, 8, 256, 256)
        store.write(0, vol, {"iterations": 1})
        store.array[1, :8] = vol[:8]                 # part of frame 1's chunks, no marker
        assert store.missing() == [1] and store.verify() == []
        np.testing.assert_array_equal(store.read(0), vol)
    chunks = [p for p in (tmp_path / "big.ome.zarr" / "0" / "0").rglob("*") if p.is_file()]
    assert len(chunks) == 3 * 2 * 3
    chunks[0].unlink()
    with FrameStore.open(tmp_path / "big.ome.zarr", fingerprint="x", n_frames=2, volume_shape=shape,
                         dtype=np.float32) as store:
        assert store.recomputed == [0] and store.missing() == [0, 1]

"""The series store as OME-Zarr (issue 26): valid NGFF 0.4 by ome-zarr-models' validated models, "/" chunk
keys, z translated to the first plane's depth, t in seconds when the interval is known, and an omero channel
whose display window covers the volume."""

import json

import numpy as np
import pytest
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


def test_pyramid_levels_are_2x_means_validate_and_are_checked(rt, tmp_path):
    """--pyramid 3: levels 1 and 2 are the 2 x 2 means of the level above (NGFF scale x2 and x4, pixel
    centres translated), the store validates, napari's reader gets the levels, a damaged level fails the
    frame's checksum, and a resume asking for other levels is refused."""
    from ome_zarr_models.v04.image import Image

    from cm2cl.errors import InputError
    from cm2cl.io.napari_reader import get_reader
    from cm2cl.jobs.store import FrameStore, downsample, read_record

    out = _job(tmp_path, pyramid=3)
    Image.from_zarr(zarr.open_group(str(out), mode="r"))
    g = zarr.open_group(str(out), mode="r")
    l0, l1, l2 = (np.asarray(g[k]) for k in "012")
    assert l1.shape == (2, l0.shape[1], -(-l0.shape[2] // 2), -(-l0.shape[3] // 2))
    np.testing.assert_allclose(l1[1], downsample(l0[1]), rtol=1e-6)
    np.testing.assert_allclose(l2[0], downsample(downsample(l0[0])), rtol=1e-5)
    assert l1[0, :, 3, 4] == pytest.approx(l0[0, :, 6:8, 8:10].mean(axis=(1, 2)), rel=1e-5)
    ds = json.loads((out / ".zattrs").read_text())["multiscales"][0]["datasets"]
    assert [d["path"] for d in ds] == ["0", "1", "2"]
    s2 = {t["type"]: t for t in ds[2]["coordinateTransformations"]}
    assert s2["scale"]["scale"][2:] == [16.0, 16.0] and s2["translation"]["translation"][2:] == [6.0, 6.0]
    (data, kw, _), = get_reader(str(out))(str(out))
    assert kw["multiscale"] and [a.shape for a in data] == [l0.shape, l1.shape, l2.shape]
    zarr.open_group(str(out), mode="r+")["2"][1] = 0.0       # a coarse level damaged
    store = FrameStore.open_readonly(out)
    assert store.verify() == [1]
    with pytest.raises(InputError, match="holds 3 resolution level"):
        FrameStore.open(out, fingerprint=read_record(out)["fingerprint"], n_frames=2, volume_shape=l0.shape[1:],
                        dtype=np.float32)




def test_ngff_05_store_validates_resumes_and_opens(rt, tmp_path):
    """--ngff 0.5: a Zarr format 3 store with the metadata under "ome" and named dimensions, valid by
    ome-zarr-models' 0.5 models; verify, resume and napari's reader work on it; a resume asking for 0.4
    is refused."""
    from ome_zarr_models.v05.image import Image

    from cm2cl.errors import InputError
    from cm2cl.io.napari_reader import get_reader
    from cm2cl.jobs.store import FrameStore, read_record

    out = _job(tmp_path, ngff="0.5", pyramid=2, channel="GFP")
    Image.from_zarr(zarr.open_group(str(out), mode="r"))
    meta = json.loads((out / "zarr.json").read_text())
    ome = meta["attributes"]["ome"]
    assert ome["version"] == "0.5" and [d["path"] for d in ome["multiscales"][0]["datasets"]] == ["0", "1"]
    assert ome["omero"]["channels"][0]["label"] == "GFP" and ome["omero"]["channels"][0]["window"]["end"] > 0
    assert json.loads((out / "0" / "zarr.json").read_text())["dimension_names"] == ["t", "z", "y", "x"]
    store = FrameStore.open_readonly(out)
    assert store.verify() == [] and sorted(store.done()) == [0, 1]
    (data, kw, _), = get_reader(str(out))(str(out))
    assert kw["multiscale"] and kw["metadata"]["channel"] == "GFP" and kw["scale"][1:] == (25.0, 4.0, 4.0)
    shape = tuple(np.asarray(data[0]).shape[1:])
    with pytest.raises(InputError, match="is OME-Zarr 0.5"):
        FrameStore.open(out, fingerprint=read_record(out)["fingerprint"], n_frames=2, volume_shape=shape,
                        dtype=np.float32, levels=2)
    with FrameStore.open(out, fingerprint=read_record(out)["fingerprint"], n_frames=2, volume_shape=shape,
                         dtype=np.float32, levels=2, ngff="0.5") as again:
        assert again.missing() == []


def test_ome_zarr_py_reads_the_stores_with_their_scale(rt, tmp_path):
    """ome-zarr-py's reader (what napari-ome-zarr uses) opens 0.4 and 0.5 stores: every level, the axes
    with their units, the scales and translation, the channel name."""
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    for ngff in ("0.4", "0.5"):
        (tmp_path / ngff).mkdir()
        out = _job(tmp_path / ngff, ngff=ngff, pyramid=2, channel="GCaMP6f", frame_interval_s=0.5)
        node = list(Reader(parse_url(str(out)))())[0]
        assert [d.shape[:2] for d in node.data] == [(2, node.data[0].shape[1])] * 2
        assert node.data[1].shape[2] == -(-node.data[0].shape[2] // 2)
        md = node.metadata
        assert [a.get("unit") for a in md["axes"]] == ["second", "micrometer", "micrometer", "micrometer"]
        t0 = {t["type"]: t for t in md["coordinateTransformations"][0]}
        assert t0["scale"]["scale"] == [0.5, 25.0, 4.0, 4.0] and t0["translation"]["translation"][1] == -500.0
        assert md["channel_names"] == ["GCaMP6f"]
        np.testing.assert_array_equal(np.asarray(node.data[0]), np.asarray(zarr.open_group(str(out), mode="r")["0"]))

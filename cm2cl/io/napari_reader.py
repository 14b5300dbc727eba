"""napari reader of cm2cl's outputs (the ``napari.manifest`` entry point, ``cm2cl/napari.yaml``): OME-TIFF
volumes and PSF stacks, series' OME-Zarr stores and simulated ``emitters.csv``, each as a layer at its
physical scale (um) and depth offset, so that a reconstruction, its ground truth and the emitters overlay in
world coordinates. napari itself is not imported here: the reader returns napari's layer-data tuples."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

__all__ = ["get_reader", "read_tiff_layer", "read_zarr_layer", "read_emitters_layer"]

TIFF_SUFFIXES = (".ome.tif", ".ome.tiff")


def get_reader(path):
    """The reader of ``path`` (napari's reader hook), or None when it is not a cm2cl output."""
    if isinstance(path, (list, tuple)):
        readers = [get_reader(p) for p in path]
        if not readers or any(r is None for r in readers):
            return None
        return lambda paths: [layer for r, p in zip(readers, paths) for layer in r(p)]
    p = Path(path)
    name = p.name.lower()
    if name.endswith(TIFF_SUFFIXES) and p.is_file():
        return lambda q: [read_tiff_layer(q)]
    if name.endswith(".zarr") and ((p / ".zattrs").is_file() or (p / "zarr.json").is_file()):
        return lambda q: [read_zarr_layer(q)]
    if name.endswith(".csv") and p.is_file() and _is_emitters(p):
        return lambda q: [read_emitters_layer(q)]
    return None


def _scale_translate(meta, ndim: int):
    vs = meta.get("voxel_size_um") if meta.get("unit") == "um" else None
    scale = tuple(float(v) for v in vs)[-ndim:] if vs else (1.0,) * ndim
    translate = [0.0] * ndim
    depths = meta.get("depths_um")
    if vs and ndim == 3 and depths is not None and len(depths):
        translate[0] = float(depths[0])
    return scale, tuple(translate)


def read_tiff_layer(path):
    """(data, kwargs, 'image') of a cm2cl OME-TIFF: ``scale`` the voxel size in um (1 in pixels when it has
    none), ``translate`` the first plane's depth, ``metadata['cm2cl']`` the record's extra."""
    from .tiff import read_tiff

    data, meta = read_tiff(path)
    scale, translate = _scale_translate(meta, data.ndim)
    kw = {"name": Path(path).name.split(".")[0], "scale": scale, "translate": translate,
          "metadata": {"cm2cl": meta.get("extra") or {}, "unit": meta.get("unit"), "path": str(path)}}
    if data.ndim == 3:
        kw["axis_labels"] = ("z", "y", "x")
    return data, kw, "image"


def read_zarr_layer(path):
    """(data, kwargs, 'image') of a series' OME-Zarr store: the (t, z, y, x) array (read lazily, chunk by
    chunk; with a pyramid the list of its levels, ``multiscale``), ``scale`` and ``translate`` from its NGFF
    ``multiscales``, the channel name and contrast window from ``omero``."""
    import zarr

    g = zarr.open_group(str(path), mode="r")
    attrs = dict(g.attrs)
    if isinstance(attrs.get("ome"), dict):       # NGFF 0.5: the metadata under "ome"
        attrs = {**attrs, **attrs["ome"]}
    ms = (attrs.get("multiscales") or [{}])[0]
    datasets = ms.get("datasets") or [{"path": "0"}]
    ds = datasets[0]
    arr = g[ds.get("path", "0")]
    pyramid = [g[d.get("path")] for d in datasets[1:]]
    scale, translate = (1.0,) * arr.ndim, (0.0,) * arr.ndim
    for t in ds.get("coordinateTransformations", []):
        if t.get("type") == "scale":
            scale = tuple(float(v) for v in t["scale"])
        elif t.get("type") == "translation":
            translate = tuple(float(v) for v in t["translation"])
    ch = ((attrs.get("omero") or {}).get("channels") or [{}])[0]
    win = ch.get("window") or {}
    kw = {"name": Path(path).name.split(".")[0], "scale": scale, "translate": translate,
          "axis_labels": tuple(a.get("name", "") for a in ms.get("axes", [])) or None,
          "metadata": {"cm2cl": attrs.get("cm2cl", {}), "channel": ch.get("label"), "path": str(path)}}
    if "start" in win and "end" in win and win["end"] > win["start"]:
        kw["contrast_limits"] = (float(win["start"]), float(win["end"]))
    if pyramid:            # napari's multiscale image: the levels in order, the transform of level 0
        kw["multiscale"] = True
        arr = [arr, *pyramid]
    return arr, {k: v for k, v in kw.items() if v is not None}, "image"


def _is_emitters(path) -> bool:
    try:
        with open(path, newline="") as f:
            head = next(csv.reader(f))
    except (OSError, StopIteration, UnicodeDecodeError, csv.Error):
        return False
    return {"axis-0", "axis-1", "axis-2"} <= set(head)


def read_emitters_layer(path):
    """(data, kwargs, 'points') of a simulation's ``emitters.csv``: the ``axis-0..2`` voxel positions on the
    ground-truth grid, at the scale and depth offset of ``ground_truth.ome.tif`` beside it (so the points sit
    on the beads of any volume on that grid), the other columns as point properties."""
    from .tiff import read_tiff

    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    data = np.array([[float(r[f"axis-{k}"]) for k in range(3)] for r in rows]).reshape(-1, 3)
    props = {k: np.array([float(r[k]) for r in rows]) for k in (rows[0] if rows else {}) if not k.startswith("axis-")}
    scale, translate = (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)
    sibling = Path(path).with_name("ground_truth.ome.tif")
    if sibling.is_file():
        _, meta = read_tiff(sibling)
        scale, translate = _scale_translate(meta, 3)
    kw = {"name": Path(path).stem, "scale": scale, "translate": translate, "properties": props, "size": 3.0,
          "face_color": "transparent", "border_color": "magenta", "metadata": {"path": str(path)}}
    return data, kw, "points"

"""TIFF in and out with voxel sizes (um) and depths in the metadata.

Files are ImageJ hyperstacks where ImageJ can hold the data type (uint8, uint16, float32): the
lateral pixel size goes into the resolution tags, dz into ImageJ's ``spacing``, one label per slice
("z=-500.0 um"), and a JSON record (voxel sizes, depths, extra fields) into ImageJ's ``Info``
property. Other dtypes (float64, int32, ...) are written unchanged as plain TIFF with the same JSON
record as the image description. :func:`read_tiff` reads both, and plain TIFFs from elsewhere.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError
from .staging import jsonable

__all__ = ["write_tiff", "read_tiff"]

_IMAGEJ_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))
_KEY = "cm2cl"


def write_tiff(path, array, voxel_size_um=(1.0, 1.0, 1.0), depths_um=None, extra=None) -> Path:
    """Write a 2D (y, x) or 3D (z, y, x) array as TIFF with its geometry.

    Parameters
    ----------
    path : output file.
    array : numpy array; written with its own dtype (never converted).
    voxel_size_um : (dz, dy, dx) in um; for a 2D image (dy, dx) or (dz, dy, dx) (dz ignored).
    depths_um : optional depth of each z plane (um), e.g. from the nominal working distance.
    extra : optional JSON-serialisable dict stored alongside (e.g. what the data is).
    """
    a = np.asarray(array)
    if a.ndim not in (2, 3) or a.size == 0:
        raise InputError(f"write_tiff '{path}': expected a non-empty 2D or 3D array, got shape {a.shape}")
    vs = [float(v) for v in voxel_size_um]
    if len(vs) not in (2, 3) or (a.ndim == 3 and len(vs) != 3):
        raise InputError(f"write_tiff '{path}': voxel_size_um must be (dz, dy, dx) for a 3D array, got {voxel_size_um!r}")
    if any(not np.isfinite(v) or v <= 0 for v in vs):
        raise InputError(f"write_tiff '{path}': voxel sizes must be positive, got {voxel_size_um!r}")
    vs = vs[-a.ndim:]
    if depths_um is not None:
        depths = [float(d) for d in np.atleast_1d(depths_um)]
        nz = a.shape[0] if a.ndim == 3 else 1
        if len(depths) != nz:
            raise InputError(f"write_tiff '{path}': {len(depths)} depths for {nz} planes")
    else:
        depths = None
    record = {_KEY: __import__("cm2cl").__version__, "shape": list(a.shape), "dtype": str(a.dtype),
              "voxel_size_um": vs, "unit": "um", "depths_um": depths, "extra": jsonable(extra or {})}
    text = json.dumps(record)
    import tifffile

    path = Path(path)
    dy, dx = vs[-2], vs[-1]
    if a.dtype in _IMAGEJ_DTYPES:
        md = {"unit": "um", "axes": "ZYX" if a.ndim == 3 else "YX", "Info": text}
        if a.ndim == 3:
            md["spacing"] = vs[0]
            if depths is not None:
                md["Labels"] = [f"z={d:.6g} um" for d in depths]
        tifffile.imwrite(path, a, imagej=True, resolution=(1.0 / dx, 1.0 / dy), metadata=md)
    else:
        tifffile.imwrite(path, a, description=text, metadata=None, photometric="minisblack",
                         resolution=(1e4 / dx, 1e4 / dy), resolutionunit="CENTIMETER")
    return path


def read_tiff(path):
    """Read a TIFF written by :func:`write_tiff` (or any TIFF).

    Returns (array, meta) where meta holds ``voxel_size_um`` ((dz, dy, dx) for 3D, (dy, dx) for 2D;
    from the cm2cl record, else from ImageJ spacing / resolution tags, else 1.0), ``depths_um``
    (list or None), ``unit`` and ``extra`` (dict).
    """
    import tifffile

    path = Path(path)
    if not path.exists():
        raise InputError(f"'{path}': no such file")
    if path.is_dir():
        raise InputError(f"'{path}': is a directory, expected a TIFF file")
    try:
        with tifffile.TiffFile(path) as tf:
            arr = tf.asarray()
            ij = tf.imagej_metadata or {}
            page = tf.pages[0]
            desc = page.description or ""
            res = page.resolution if hasattr(page, "resolution") else None
            res_unit = page.tags["ResolutionUnit"].value if "ResolutionUnit" in page.tags else None
    except (tifffile.TiffFileError, ValueError, OSError) as exc:
        raise InputError(f"'{path}': not a readable TIFF file ({exc})") from exc
    record = None
    for text in (ij.get("Info"), desc):
        if text:
            try:
                cand = json.loads(text)
            except (TypeError, ValueError):
                continue
            if isinstance(cand, dict) and _KEY in cand:
                record = cand
                break
    if record is not None:
        vs = tuple(float(v) for v in record.get("voxel_size_um", ()))
        meta = {"voxel_size_um": vs, "depths_um": record.get("depths_um"),
                "unit": record.get("unit", "um"), "extra": record.get("extra") or {}}
    else:
        dy = dx = 1.0
        if res and res[0] > 0 and res[1] > 0:
            scale = 1.0
            if not ij:
                scale = {3: 1e4, 2: 2.54e4}.get(int(res_unit) if res_unit is not None else 0, 1.0)
            dx, dy = scale / res[0], scale / res[1]
        dz = float(ij.get("spacing", 1.0))
        vs = (dz, dy, dx) if arr.ndim >= 3 else (dy, dx)
        meta = {"voxel_size_um": vs, "depths_um": None, "unit": ij.get("unit", "um"), "extra": {}}
    return arr, meta

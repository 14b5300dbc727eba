"""TIFF in and out with physical voxel sizes (um) and depths that other programs read.

:func:`write_tiff` writes OME-TIFF (the array keeps its dtype: uint8/16, float32, float64, ...):

- OME-XML ``Pixels PhysicalSizeX/Y/Z`` with ``PhysicalSize*Unit="µm"`` and one ``Plane PositionZ``
  (um) per z plane: read by Fiji (Bio-Formats, which Fiji uses for ``*.ome.tif``), napari's OME
  readers, tifffile and QuPath;
- the TIFF resolution tags (``XResolution``/``YResolution`` in pixels per cm,
  ``ResolutionUnit=CENTIMETER``): the lateral scale for readers that ignore OME, such as ImageJ's own
  TIFF opener (it shows the size in cm);
- a JSON record (voxel sizes, depths, ``extra``) as the OME ``Image Description``.

A volume whose physical scale is not known (``voxel_size_um=None``) is written without
``PhysicalSize*`` and with ``ResolutionUnit=NONE``: readers show it in pixels, never in made-up um.

An OME-TIFF cannot also be an ImageJ hyperstack (both live in the first ImageDescription), so ImageJ's
own opener sees no z spacing; name files ``*.ome.tif`` so that Fiji opens them with Bio-Formats.

:func:`read_tiff` reads these files, the ImageJ hyperstacks cm2cl wrote before, and plain TIFFs.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..errors import InputError
from .staging import jsonable

__all__ = ["write_tiff", "read_tiff", "tiff_stem", "tiff_depths", "OBJECT_SPACE"]

_KEY = "cm2cl"
#: ``extra["voxel_space"]`` of a PSF stack whose voxel size is that of the object-space reconstruction
#: grid (the simulator's psf.ome.tif); ``cm2cl reconstruct`` gives such a scale to the volume
OBJECT_SPACE = "object"
#: lengths OME may use, in um (OME UnitsLength symbols)
_UM_PER = {"µm": 1.0, "um": 1.0, "micron": 1.0, "microns": 1.0, "\u03bcm": 1.0, "nm": 1e-3, "mm": 1e3,
           "cm": 1e4, "m": 1e6}
#: TIFF ResolutionUnit: 2 inch, 3 centimetre
_UM_PER_RESUNIT = {2: 2.54e4, 3: 1e4}


def tiff_stem(path) -> Path:
    """``path`` without its TIFF suffix (``vol.ome.tif`` -> ``vol``, ``vol.tif`` -> ``vol``)."""
    p = Path(path)
    name = p.name
    for suffix in (".ome.tiff", ".ome.tif", ".tiff", ".tif"):
        if name.lower().endswith(suffix):
            return p.with_name(name[: -len(suffix)])
    return p


def _check_geometry(where: str, a, voxel_size_um, depths_um):
    """(dz, dy, dx) or (dy, dx) floats or None, depths list or None; InputError starting with ``where``
    (what is written or read) on bad values."""
    vs = None
    if voxel_size_um is not None:
        try:
            vs = [float(v) for v in voxel_size_um]
        except (TypeError, ValueError):
            raise InputError(f"{where}: voxel_size_um must be numbers (dz, dy, dx), got {voxel_size_um!r}") from None
        if len(vs) not in (2, 3) or (a.ndim == 3 and len(vs) != 3):
            raise InputError(f"{where}: voxel_size_um must be (dz, dy, dx) for a {a.ndim}D array, "
                             f"got {voxel_size_um!r}")
        if any(not np.isfinite(v) or v <= 0 for v in vs):
            raise InputError(f"{where}: voxel sizes must be positive and finite, got {voxel_size_um!r}")
        vs = vs[-a.ndim:]
    depths = None
    if depths_um is not None:
        try:
            depths = [float(d) for d in np.atleast_1d(np.asarray(depths_um, dtype=float))]
        except (TypeError, ValueError):
            raise InputError(f"{where}: depths_um must be numbers, got {depths_um!r}") from None
        nz = a.shape[0] if a.ndim == 3 else 1
        if len(depths) != nz:
            raise InputError(f"{where}: {len(depths)} depths for {nz} planes")
        if not all(np.isfinite(depths)):
            raise InputError(f"{where}: depths_um must be finite")
    return vs, depths


def _record_extra(where: str, record) -> dict:
    """The ``extra`` mapping of a cm2cl record read back (empty when absent)."""
    extra = (record or {}).get("extra") or {}
    if not isinstance(extra, dict):
        raise InputError(f"{where} has extra {type(extra).__name__}, not a mapping")
    return extra


def write_tiff(path, array, voxel_size_um=None, depths_um=None, extra=None, name=None, channel=None,
               emission_nm=None) -> Path:
    """Write a 2D (y, x) or 3D (z, y, x) array as OME-TIFF with its physical geometry.

    Parameters
    ----------
    path : output file (``*.ome.tif`` lets Fiji pick Bio-Formats, which reads the z scale).
    array : numpy array; written with its own dtype (never converted).
    voxel_size_um : (dz, dy, dx) in um (for a 2D image (dy, dx) or (dz, dy, dx), dz unused), or None
        when the physical scale is not known: the file then says pixels.
    depths_um : optional depth of each z plane in um (OME ``Plane PositionZ``).
    extra : optional JSON-serialisable dict stored in the record (what the data is).
    name : the OME Image's name, which viewers show (default: the file's name without .ome.tif).
    channel, emission_nm : the OME Channel's name and emission wavelength in nm (default: no channel name
        or wavelength).
    """
    import tifffile

    a = np.asarray(array)
    if a.ndim not in (2, 3) or a.size == 0:
        raise InputError(f"write_tiff '{path}': expected a non-empty 2D or 3D array, got shape {a.shape}")
    vs, depths = _check_geometry(f"write_tiff '{path}'", a, voxel_size_um, depths_um)
    record = {_KEY: __import__("cm2cl").__version__, "shape": list(a.shape), "dtype": str(a.dtype),
              "voxel_size_um": vs, "unit": "um" if vs else "pixel", "depths_um": depths,
              "extra": jsonable(extra or {})}
    md = {"axes": "ZYX" if a.ndim == 3 else "YX", "Description": json.dumps(record),
          "Name": str(name) if name is not None else tiff_stem(path).name}
    if emission_nm is not None:
        try:
            em = float(emission_nm)
        except (TypeError, ValueError):
            em = float("nan")
        if not (np.isfinite(em) and em > 0):
            raise InputError(f"write_tiff '{path}': emission wavelength {emission_nm!r} nm must be a positive number")
    if channel is not None or emission_nm is not None:
        md["Channel"] = {**({"Name": str(channel)} if channel is not None else {}),
                         **({"EmissionWavelength": em, "EmissionWavelengthUnit": "nm"} if emission_nm is not None
                            else {})}
    if vs is not None:
        md.update(PhysicalSizeX=vs[-1], PhysicalSizeXUnit="µm", PhysicalSizeY=vs[-2], PhysicalSizeYUnit="µm")
        if a.ndim == 3:
            md.update(PhysicalSizeZ=vs[0], PhysicalSizeZUnit="µm")
        resolution, unit = (1e4 / vs[-1], 1e4 / vs[-2]), "CENTIMETER"
    else:
        resolution, unit = (1.0, 1.0), "NONE"
    if depths is not None:
        md["Plane"] = {"PositionZ": depths, "PositionZUnit": ["µm"] * len(depths)}
    path = Path(path)
    tifffile.imwrite(path, a, ome=True, metadata=md, photometric="minisblack", resolution=resolution,
                     resolutionunit=unit)
    return path


def _rational(value) -> float:
    num, den = value if isinstance(value, tuple) else (value, 1)
    return float(num) / float(den) if den else 0.0


class _BadOME(ValueError):
    """OME-XML whose values are not what the schema says (a length or position that is no number)."""


def _num(value, what: str, kind=float):
    """``value`` (an OME attribute) as a finite ``kind``, or _BadOME naming ``what``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise _BadOME(f"{what} is {value!r}, not a number") from None
    if not np.isfinite(v):
        raise _BadOME(f"{what} is {value!r}, not a finite number")
    if kind is int:
        if not v.is_integer():
            raise _BadOME(f"{what} is {value!r}, not an integer")
        try:
            return int(value)             # exact, however long
        except ValueError:
            return int(v)                 # '2.0', '1e3'
    return v


def _geometry(path, ome: str, ndim: int):
    """:func:`_ome_geometry` of a file's OME-XML, unreadable or wrong-typed metadata as one InputError."""
    try:
        return _ome_geometry(ome, ndim)
    except ET.ParseError as exc:
        raise InputError(f"'{path}': its OME-XML is not readable ({exc})") from exc
    except _BadOME as exc:
        raise InputError(f"'{path}': its OME-XML {exc}") from None


def _ome_geometry(xml_text: str, ndim: int):
    """(voxel sizes or None, depths or None, cm2cl record or None) from OME-XML."""
    root = ET.fromstring(xml_text)
    ns = {"ome": root.tag[1:].split("}")[0]} if root.tag.startswith("{") else {}
    q = (lambda t: f"ome:{t}") if ns else (lambda t: t)
    image = root.find(q("Image"), ns)
    if image is None:
        return None, None, None
    pixels = image.find(q("Pixels"), ns)
    record = None
    desc = image.find(q("Description"), ns)
    if desc is not None and desc.text:
        try:
            cand = json.loads(desc.text)
        except ValueError:
            cand = None
        if isinstance(cand, dict) and _KEY in cand:
            record = cand
    if pixels is None:
        return None, None, record

    def length(attr):
        v = pixels.get(attr)
        if v is None:
            return None
        scale = _UM_PER.get(pixels.get(attr + "Unit", "µm"))
        if not scale:
            return None
        um = _num(v, attr) * scale
        if not um > 0:
            raise _BadOME(f"{attr} is {v!r}, not a positive length")
        return um

    depths = None
    planes = pixels.findall(q("Plane"), ns)
    if planes and all(p.get("PositionZ") is not None for p in planes):
        by_z = {}
        for p in planes:
            scale = _UM_PER.get(p.get("PositionZUnit", "reference frame"))
            if scale is None:
                by_z = {}
                break
            by_z.setdefault(_num(p.get("TheZ", 0), "Plane TheZ", int), _num(p.get("PositionZ"), "Plane PositionZ") * scale)
        if by_z and sorted(by_z) == list(range(len(by_z))):
            depths = [by_z[z] for z in range(len(by_z))]
    dx, dy, dz = length("PhysicalSizeX"), length("PhysicalSizeY"), length("PhysicalSizeZ")
    if dz is None and depths is not None and len(depths) > 1 and np.allclose(np.diff(depths), depths[1] - depths[0]):
        dz = abs(depths[1] - depths[0])
    vs = None
    if dx is not None and dy is not None:
        if ndim == 2:
            vs = (dy, dx)
        elif dz is not None:
            vs = (dz, dy, dx)
    return vs, depths, record


def _existing_file(path) -> Path:
    path = Path(path)
    if not path.exists():
        raise InputError(f"'{path}': no such file")
    if path.is_dir():
        raise InputError(f"'{path}': is a directory, expected a TIFF file")
    return path


def _recorded_shape(path, ome: str | None, shape: tuple) -> tuple:
    """The shape :func:`read_tiff` gives an array that tifffile reads as ``shape``: the shape a cm2cl
    record stored in the OME-XML (tifffile drops the axes of length 1 of OME files: one plane, one-pixel
    wide volumes), else ``shape`` itself."""
    if not ome:
        return shape
    record = _geometry(path, ome, len(shape))[2]
    shp = (record or {}).get("shape") or ()
    if shp and not isinstance(shp, list) or not all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in shp):
        raise InputError(f"'{path}': the cm2cl record in its OME-XML has shape {shp!r}, not a list of positive integers")
    stored = tuple(shp)
    return stored if stored and int(np.prod(stored)) == int(np.prod(shape)) else shape


def peek_tiff(path) -> tuple[tuple, np.dtype]:
    """(shape, dtype) of a TIFF's first series from its headers, without decoding any pixel: lets a
    command refuse a wrong or huge input before reading it. The shape is the one :func:`read_tiff`
    returns."""
    import tifffile

    path = _existing_file(path)
    try:
        with tifffile.TiffFile(path) as tf:
            s = tf.series[0]
            shape, dtype = tuple(int(n) for n in s.shape), np.dtype(s.dtype)
            ome = tf.ome_metadata if tf.is_ome else None
    except (tifffile.TiffFileError, ValueError, OSError, IndexError) as exc:
        raise InputError(f"'{path}': not a readable TIFF file ({exc})") from exc
    return _recorded_shape(path, ome, shape), dtype


def tiff_depths(path):
    """The z positions (um) of a multi-plane TIFF's planes from its headers (OME ``Plane PositionZ``), or
    None when it carries none; no pixel is decoded."""
    import tifffile

    path = _existing_file(path)
    try:
        with tifffile.TiffFile(path) as tf:
            ome = tf.ome_metadata if tf.is_ome else None
            ndim = len(tf.series[0].shape)
    except (tifffile.TiffFileError, ValueError, OSError, IndexError) as exc:
        raise InputError(f"'{path}': not a readable TIFF file ({exc})") from exc
    if not ome:
        return None
    return _geometry(path, ome, ndim)[1]


def read_tiff(path, memmap: bool = False):
    """Read a TIFF written by :func:`write_tiff`, an ImageJ hyperstack, or any other TIFF.

    With ``memmap`` the pixels are not read into memory: the array maps the file where its data are
    stored contiguously, else a temporary file tifffile decodes them into (for scans larger than memory).

    Returns (array, meta): ``voxel_size_um`` ((dz, dy, dx) for 3D, (dy, dx) for 2D; None when the file
    carries no physical scale), ``unit`` ('um', or 'pixel' when the scale is not known),
    ``depths_um`` (list or None) and ``extra`` (dict; cm2cl's record, else empty).

    The scale comes from OME ``PhysicalSize*`` and ``Plane PositionZ``, else ImageJ's unit,
    resolution and spacing, else the TIFF resolution tags in cm or inch; a TIFF without any of
    these (or with ``ResolutionUnit=NONE``) is in pixels.
    """
    import tifffile

    path = _existing_file(path)
    try:
        with tifffile.TiffFile(path) as tf:
            arr = tf.asarray(out="memmap") if memmap else tf.asarray()
            ome = tf.ome_metadata if tf.is_ome else None
            ij = tf.imagej_metadata or {}
            page = tf.pages[0]
            desc = page.description or ""
            tags = page.tags
            res = tuple(_rational(tags[k].value) for k in ("XResolution", "YResolution") if k in tags)
            res_unit = int(tags["ResolutionUnit"].value) if "ResolutionUnit" in tags else 2  # TIFF default: inch
    except (tifffile.TiffFileError, ValueError, OSError) as exc:
        raise InputError(f"'{path}': not a readable TIFF file ({exc})") from exc
    if ome:
        arr = arr.reshape(_recorded_shape(path, ome, arr.shape))   # axes of length 1 that tifffile dropped
        vs, depths, record = _geometry(path, ome, arr.ndim)
        extra = _record_extra(f"'{path}': the cm2cl record in its OME-XML", record)
        return arr, {"voxel_size_um": vs, "unit": "um" if vs else "pixel", "depths_um": depths, "extra": extra}
    record = None
    for text in (ij.get("Info"), desc):           # ImageJ hyperstacks written by cm2cl < 0.2
        if text:
            try:
                cand = json.loads(text)
            except (TypeError, ValueError):
                continue
            if isinstance(cand, dict) and _KEY in cand:
                record = cand
                break
    if record is not None:
        where = f"'{path}': its cm2cl record"
        vs, depths = _check_geometry(where, arr, record.get("voxel_size_um") or None, record.get("depths_um"))
        unit = record.get("unit", "um") if vs else "pixel"
        return arr, {"voxel_size_um": tuple(vs) if vs else None, "depths_um": depths, "unit": unit,
                     "extra": _record_extra(where, record)}
    vs = None
    if len(res) == 2 and res[0] > 0 and res[1] > 0:
        if ij:
            scale = _UM_PER.get(str(ij.get("unit", "")).strip())
        else:
            scale = _UM_PER_RESUNIT.get(res_unit)
        if scale:
            dx, dy = scale / res[0], scale / res[1]
            if arr.ndim == 2:
                vs = (dy, dx)
            elif ij:                              # ImageJ omits spacing when it is 1 (its default)
                vs = (float(ij.get("spacing", 1.0)) * scale, dy, dx)
    return arr, {"voxel_size_um": vs, "unit": "um" if vs else "pixel", "depths_um": None, "extra": {}}

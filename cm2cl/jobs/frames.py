"""A time series as a list of 2D frames: one multi-page TIFF (a (T, My, Mx) series), a folder of TIFFs, a
glob, or several of those, in order. Shapes and dtypes come from the TIFF headers, so a series whose
frames differ is refused before any pixel is decoded; frames are decoded one at a time."""

from __future__ import annotations

import glob as _glob
import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError

_TIFF = (".tif", ".tiff")


@dataclass(frozen=True)
class Frame:
    path: str
    index: int          #: index along the file's first axis (0 for a 2D file)
    shape: tuple
    dtype: str


def _expand(source: str, what: str = "measurement") -> list[Path]:
    p = Path(source)
    if any(c in source for c in "*?["):
        files = sorted(Path(f) for f in _glob.glob(source) if f.lower().endswith(_TIFF))
        if not files:
            raise InputError(f"{what} '{source}': the pattern matches no TIFF file")
        return files
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in _TIFF)
        if not files:
            raise InputError(f"{what} '{source}': the folder holds no .tif/.tiff file")
        return files
    if not p.exists():
        raise InputError(f"{what} '{source}': no such file")
    return [p]


def _kept_axes(shape: tuple) -> list[int]:
    """The axes of a file's series that hold frames: all of a 2D or 3D one, the longer than 1 of more
    (a (1, T, 1, My, Mx) TCZYX file is a (T, My, Mx) series)."""
    return [k for k, n in enumerate(shape) if n != 1] if len(shape) > 3 else list(range(len(shape)))


def _frame_key(shape: tuple, index: int) -> tuple:
    """The index into a file's series, of shape ``shape``, of its frame ``index``."""
    kept = _kept_axes(shape)
    time_axis = kept[0] if len(kept) == 3 else None
    return tuple(index if k == time_axis else (slice(None) if k in kept else 0) for k in range(len(shape)))


def _frames_of(path: Path, what: str = "measurement") -> list[Frame]:
    import tifffile

    try:
        with tifffile.TiffFile(path) as t:
            s = t.series[0]
            shape, dtype = tuple(int(n) for n in s.shape), np.dtype(s.dtype)
    except Exception as exc:  # noqa: BLE001 - any unreadable file gets one line
        raise InputError(f"{what} '{path}': not a readable TIFF ({exc})") from exc
    shape = tuple(shape[k] for k in _kept_axes(shape))
    if dtype.kind not in "uif":
        raise InputError(f"{what} '{path}': dtype {dtype} is not numeric")
    if len(shape) == 2:
        return [Frame(str(path), 0, shape, dtype.str)]
    if len(shape) == 3:
        return [Frame(str(path), i, shape[1:], dtype.str) for i in range(shape[0])]
    raise InputError(f"{what} '{path}': expected 2D frames or a (T, My, Mx) series, got shape {shape}")


class FrameSeries:
    """The frames of ``sources`` (files, folders, globs), in order, all of one shape; ``what`` names them in
    errors ('measurement', 'scan')."""

    def __init__(self, sources, what: str = "measurement"):
        sources = [sources] if isinstance(sources, (str, Path)) else list(sources)
        if not sources:
            raise InputError(f"{what}: no frames given")
        self.frames: list[Frame] = []
        for s in sources:
            for f in _expand(str(s), what):
                self.frames.extend(_frames_of(f, what))
        if not self.frames:
            raise InputError(f"{what}: no frames in {', '.join(map(str, sources))}")
        first = self.frames[0]
        for t, f in enumerate(self.frames[1:], start=1):
            if f.shape != first.shape:
                raise InputError(f"{what} '{f.path}' (frame {t} of the series, page {f.index} of the file): shape "
                                 f"{f.shape} differs from the "
                                 f"first frame's {first.shape} ('{first.path}'); one job takes frames of one shape")
        self.shape = first.shape

    def __len__(self) -> int:
        return len(self.frames)

    def read(self, i: int) -> np.ndarray:
        """Frame ``i`` as decoded from its file (its own dtype)."""
        import tifffile
        import zarr

        f = self.frames[i]
        with tifffile.TiffFile(f.path) as t:
            s = t.series[0]
            if len(s.shape) == 2:
                return s.asarray()
            a = zarr.open(s.aszarr(), mode="r")
            return np.asarray(a[_frame_key(tuple(int(n) for n in s.shape), f.index)]).reshape(self.shape)

    def identity(self) -> str:
        """A digest of which frames these are: paths, indices, sizes and modification times (a changed
        file makes a different job)."""
        h = hashlib.sha256()
        for f in self.frames:
            st = Path(f.path).stat()
            h.update(f"{Path(f.path).resolve()}|{f.index}|{st.st_size}|{st.st_mtime_ns}\n".encode())
        return h.hexdigest()


class ArraySeries:
    """Frames held in memory: a (T, My, Mx) array (or a sequence of (My, Mx) arrays), with what a job needs
    of :class:`FrameSeries` (``len``, ``shape``, ``read``, ``identity``, ``frames``)."""

    def __init__(self, frames, what: str = "frames"):
        a = np.asarray(frames)
        if a.ndim != 3 or 0 in a.shape:
            raise InputError(f"{what}: expected a (T, My, Mx) array of frames, got shape {a.shape}")
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise InputError(f"{what}: expected real numbers, got dtype {a.dtype}")
        self.array, self.shape = a, tuple(a.shape[1:])
        self.frames = [Frame(f"<array {what}>", i, self.shape, a.dtype.name) for i in range(a.shape[0])]

    def __len__(self) -> int:
        return self.array.shape[0]

    def read(self, i: int) -> np.ndarray:
        return self.array[i]

    def identity(self) -> str:
        """A digest of the frames' values (other values make a different job)."""
        h = hashlib.sha256(f"{self.array.shape}|{self.array.dtype}".encode())
        for f in self.array:
            h.update(np.ascontiguousarray(f).tobytes())
        return h.hexdigest()

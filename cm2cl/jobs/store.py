"""The output of a job of many frames: an OME-Zarr store (NGFF 0.4, Zarr format 2, readable by napari's
OME-Zarr readers, Fiji's N5/Zarr readers and zarr-python) holding a (T, Z, Y, X) array, one chunk per
frame, with the physical scale in its ``multiscales`` metadata.

Resume: a frame counts as done only when its chunk is wholly written, marked by a file
``.cm2cl-done/NNNNNNNN`` created after the chunk; a run killed at any point leaves at most a chunk without
a marker, which the next run recomputes. Each marker carries the SHA-256 of its frame's volume (hashed
while writing); reopening the store for a resume checks every marked frame against it and recomputes the
frames whose chunk was lost or changed (:meth:`FrameStore.verify`, ``cm2cl verify STORE``). The store records a fingerprint of the job (PSF, parameters,
frames, dtype); a store of another job is refused, never mixed into. One run at a time: a lock file
held for the run's duration refuses a second run on the same store.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np

from ..errors import InputError, JobError
from ..io.publish import check_name_length, exclusive_lock, fault_point, release_lock

#: the job's bookkeeping lives beside the store, outside the zarr hierarchy (zarr warns about anything in it
#: that is no array or group): ``.NAME.cm2cl-done/`` (one marker per finished frame) and ``.NAME.cm2cl-lock``;
#: stores of cm2cl before 0.2 kept the markers inside, as ``NAME/.cm2cl-done``, and are still read
DONE = ".cm2cl-done"
LOCK = ".cm2cl-lock"
log = logging.getLogger("cm2cl")


def done_dir(path) -> Path:
    """The folder of a store's done markers: inside (an older store) when it is there, else beside it."""
    path = Path(path)
    inside = path / DONE
    return inside if inside.is_dir() else path.parent / f".{path.name}{DONE}"


def lock_path(path) -> Path:
    path = Path(path)
    return path.parent / f".{path.name}{LOCK}"


def digest(volume, dtype) -> str:
    """SHA-256 of a volume's bytes as the store holds them (``dtype``, C order)."""
    return hashlib.sha256(np.ascontiguousarray(volume, dtype=np.dtype(dtype)).tobytes()).hexdigest()


def ngff_multiscales(name: str, voxel_size_um, ndim: int = 4, depths_um=None, frame_interval_s=None,
                     levels: int = 1) -> list[dict]:
    """NGFF 0.4 ``multiscales`` for a (t, z, y, x) array and ``levels`` resolution levels (level k is 2^k
    times coarser laterally, its pixel the mean of 2^k x 2^k): micrometre scale when known (unit-less
    pixels otherwise), a translation putting z at the first plane's depth and each level's pixel centres
    where their pixels are (lateral origin: the first pixel's centre, as in the OME-TIFF), and t in seconds
    when the frame interval is known (frames otherwise)."""
    um = {"unit": "micrometer"} if voxel_size_um else {}
    t_axis = {"name": "t", "type": "time", **({"unit": "second"} if frame_interval_s else {})}
    axes = [t_axis] + [{"name": a, "type": "space", **um} for a in "zyx"]
    dz, dy, dx = (float(v) for v in voxel_size_um) if voxel_size_um else (1.0, 1.0, 1.0)
    z0 = float(depths_um[0]) if voxel_size_um and depths_um is not None and len(depths_um) else 0.0
    datasets = []
    for k in range(int(levels)):
        f = float(2 ** k)
        scale = [float(frame_interval_s or 1.0), dz, dy * f, dx * f]
        tr = [0.0, z0, (f - 1) / 2 * dy, (f - 1) / 2 * dx]
        transforms = [{"type": "scale", "scale": scale[-ndim:]}]
        if any(tr):
            transforms.append({"type": "translation", "translation": tr[-ndim:]})
        datasets.append({"path": str(k), "coordinateTransformations": transforms})
    return [{"version": "0.4", "name": name, "axes": axes[-ndim:], "datasets": datasets}]


def _levels_of(meta: dict, path) -> int:
    """The resolution levels a store's record says it holds (1 for stores before pyramids)."""
    v = meta.get("levels", 1)
    if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= 8:
        raise InputError(f"store '{path}': its record says {v!r} resolution levels; not a cm2cl store this "
                         "version can read")
    return v


def _check_window_attrs(attrs: dict, path) -> None:
    """What :meth:`FrameStore._widen_window` reads at close, checked when a store is opened for writing:
    ``cm2cl.display_max`` a finite number >= 0 and the ``omero`` block (under ``ome`` in NGFF 0.5) a mapping
    whose ``channels`` is a list of mappings (else the job would fail after its solve)."""
    def bad(name, value, want):
        text = repr(value)
        raise InputError(f"output '{path}': its attribute {name} is {text[:60]}{'...' if len(text) > 60 else ''}, "
                         f"not {want}; correct it in the store's attributes or choose a new output")

    dm = (attrs.get("cm2cl") or {}).get("display_max")
    if dm is not None and (isinstance(dm, bool) or not isinstance(dm, (int, float)) or not np.isfinite(dm) or dm < 0):
        bad("cm2cl.display_max", dm, "a finite number >= 0")
    where = "ome.omero" if isinstance(attrs.get("ome"), dict) else "omero"
    block = (attrs["ome"] if where == "ome.omero" else attrs).get("omero")
    if block is None:
        return
    if not isinstance(block, dict):
        bad(where, block, "a mapping")
    chans = block.get("channels")
    if chans is not None and not (isinstance(chans, list) and all(isinstance(c, dict) for c in chans)):
        bad(f"{where}.channels", chans, "a list of channel mappings")


def downsample(vol: np.ndarray) -> np.ndarray:
    """A (z, y, x) volume 2x coarser laterally: each pixel the mean of 2 x 2 (an odd last row or column
    averaged with its copy)."""
    v = np.asarray(vol, np.float64)
    if v.shape[1] % 2:
        v = np.concatenate([v, v[:, -1:]], axis=1)
    if v.shape[2] % 2:
        v = np.concatenate([v, v[:, :, -1:]], axis=2)
    return 0.25 * (v[:, 0::2, 0::2] + v[:, 1::2, 0::2] + v[:, 0::2, 1::2] + v[:, 1::2, 1::2])


def level_shape(shape, k: int) -> tuple:
    """(t, z, y, x) of resolution level k of a store of ``shape``."""
    return tuple(shape[:2]) + tuple(-(-int(n) // 2 ** k) for n in shape[2:])


#: the OME-Zarr versions a series store is written in: 0.4 (Zarr format 2, the default: what most readers
#: read today) or 0.5 (Zarr format 3, ome-zarr-py's default)
NGFF_VERSIONS = ("0.4", "0.5")

#: a chunk holds at most this many planes, rows and columns of one frame: a few MB that viewers stream
#: (napari, neuroglancer), where one chunk per frame was ~320 MB at 972 x 1296 x 64
CHUNK_ZYX = (8, 256, 256)


def chunk_shape(shape) -> tuple:
    """Chunks of a (t, z, y, x) store: one frame, at most CHUNK_ZYX of it. A frame is marked done only
    after all its chunks are written, and its checksum covers them all."""
    return (1,) + tuple(min(int(n), c) for n, c in zip(shape[1:], CHUNK_ZYX))


def omero(channel: str, vmax: float = 1.0) -> dict:
    """The NGFF ``omero`` block: one greyscale channel named ``channel``, its display window 0 .. vmax."""
    v = float(vmax) if np.isfinite(vmax) and vmax > 0 else 1.0
    return {"version": "0.4", "rdefs": {"model": "greyscale", "defaultT": 0, "defaultZ": 0},
            "channels": [{"label": str(channel), "color": "FFFFFF", "active": True, "coefficient": 1.0,
                          "family": "linear", "inverted": False,
                          "window": {"min": 0.0, "max": v, "start": 0.0, "end": v}}]}


class FrameStore:
    """An open store of ``n_frames`` volumes of ``volume_shape``; use :meth:`open`."""

    def __init__(self, path: Path, array, lock_fd, levels=()):
        self.path, self.array, self._lock = path, array, lock_fd
        #: the coarser resolution levels' arrays (level 1, 2, ...): written with each frame
        self.levels = list(levels)
        #: the brightest voxel this run wrote (the omero display window is widened to it at close)
        self._vmax = 0.0
        #: frames marked done whose chunk failed its checksum when the store was reopened (now to recompute)
        self.recomputed: list[int] = []
        #: whether this run created the store (a job that fails before its first frame removes it again)
        self.created = False

    @classmethod
    def open(cls, path, *, fingerprint: str, n_frames: int, volume_shape, dtype, voxel_size_um=None,
             depths_um=None, record: dict | None = None, channel: str = "fluorescence",
             frame_interval_s: float | None = None, levels: int = 1, ngff: str = "0.4") -> "FrameStore":
        """Create the store (whole, by a rename: never a half-made store) or reopen it for a resume. Chunks
        are keyed with "/" (NGFF 0.4); ``channel`` names the ``omero`` channel, whose display window follows
        the brightest voxel written; ``frame_interval_s`` gives t its unit (seconds); ``levels`` > 1 adds
        a multiscale pyramid (each level 2x coarser laterally), written with each frame; ``ngff`` '0.4'
        (Zarr format 2) or '0.5' (Zarr format 3, the metadata under ``ome``, named dimensions)."""
        if ngff not in NGFF_VERSIONS:
            raise InputError(f"ngff: {ngff!r}; expected one of {', '.join(NGFF_VERSIONS)}")
        levels = int(levels)
        if not 1 <= levels <= 8:
            raise InputError(f"pyramid: {levels} levels; expected 1 to 8")
        import zarr

        path = Path(path)
        if path.exists() and not path.is_dir():
            raise InputError(f"output '{path}': exists and is not an OME-Zarr folder")
        if not path.parent.is_dir():     # the missing folders are made (checked first: writable, no file in the way)
            from ..io.staging import check_room, make_parents

            check_room(path, "output")
            try:
                make_parents(path.parent)
            except OSError as exc:
                raise InputError(f"output '{path}': cannot create folder '{path.parent}' ({exc.strerror or exc})") from exc
        check_name_length(path, [done_dir(path).name, lock_path(path).name])
        shape = (int(n_frames),) + tuple(int(n) for n in volume_shape)
        created = False
        if not path.exists():
            tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
            shutil.rmtree(tmp, ignore_errors=True)
            try:
                v3 = ngff == "0.5"
                g = zarr.open_group(str(tmp), mode="w", zarr_format=3 if v3 else 2)
                for k in range(levels):
                    ls = level_shape(shape, k)
                    extra = {"dimension_names": ("t", "z", "y", "x")} if v3 else \
                        {"chunk_key_encoding": {"name": "v2", "separator": "/"}}
                    g.create_array(str(k), shape=ls, chunks=chunk_shape(ls), dtype=np.dtype(dtype), fill_value=0,
                                   **extra)
                ms = ngff_multiscales(path.name, voxel_size_um, depths_um=depths_um,
                                      frame_interval_s=frame_interval_s, levels=levels)
                if v3:     # NGFF 0.5: the version once, in the ome block
                    ngff_attrs = {"ome": {"version": "0.5", "omero": omero(channel),
                                          "multiscales": [{k: v for k, v in m.items() if k != "version"} for m in ms]}}
                else:
                    ngff_attrs = {"multiscales": ms, "omero": omero(channel)}
                g.attrs.update({**ngff_attrs,
                                "cm2cl": {"ngff": ngff, "fingerprint": fingerprint, "n_frames": int(n_frames),
                                          "volume_shape": list(shape[1:]), "dtype": np.dtype(dtype).name,
                                          "levels": levels,
                                          "voxel_size_um": list(voxel_size_um) if voxel_size_um else None,
                                          "depths_um": [float(d) for d in depths_um] if depths_um is not None else None,
                                          **(record or {})}})
                book = path.parent / f".{path.name}{DONE}"
                shutil.rmtree(book, ignore_errors=True)    # markers of a store that was deleted: not this one's
                book.mkdir()
                os.rename(tmp, path)
                created = True
            except OSError as exc:
                shutil.rmtree(tmp, ignore_errors=True)
                if not path.exists():
                    raise InputError(f"output '{path}': cannot create the store ({exc.strerror or exc})") from exc
        store = cls._reopen(path, fingerprint, shape, levels, ngff)
        store.created = created
        return store

    @classmethod
    def open_readonly(cls, path) -> "FrameStore":
        """An existing store, to read and verify (no lock taken, nothing changed)."""
        import zarr

        path = Path(path)
        try:
            g = zarr.open_group(str(path), mode="r")
            meta = dict(g.attrs).get("cm2cl")
            arr = g["0"]
        except Exception as exc:  # noqa: BLE001 - not a zarr group at all
            raise InputError(f"store '{path}': not a cm2cl OME-Zarr store ({type(exc).__name__})") from exc
        if not isinstance(meta, dict):
            raise InputError(f"store '{path}': not a cm2cl OME-Zarr store (no cm2cl record)")
        if not done_dir(path).is_dir():
            raise InputError(f"store '{path}': its job record '{done_dir(path).name}' is missing beside it (moved "
                             "without it?); rerunning the job checks and recomputes its frames")
        return cls(path, arr, None, [g[str(k)] for k in range(1, _levels_of(meta, path))])

    @classmethod
    def _reopen(cls, path: Path, fingerprint: str, shape, levels: int = 1, ngff: str = "0.4") -> "FrameStore":
        import zarr

        try:
            g = zarr.open_group(str(path), mode="r+")
            meta = dict(g.attrs).get("cm2cl")
            arr = g["0"] if isinstance(meta, dict) else None
        except PermissionError as exc:
            raise InputError(f"output '{path}': cannot be written ({exc.strerror or exc}); resume it where it can "
                             "be, or choose a new output") from exc
        except Exception as exc:  # noqa: BLE001 - not a zarr group, or its metadata cannot be read
            raise InputError(f"output '{path}': exists and is not a cm2cl OME-Zarr store (its metadata cannot be read: "
                             f"{type(exc).__name__}: {str(exc)[:120]}); not overwritten") from exc
        if not isinstance(meta, dict) or not hasattr(arr, "shape"):
            raise InputError(f"output '{path}': exists and is not a cm2cl OME-Zarr store; not overwritten")
        _check_window_attrs(dict(g.attrs), path)
        if meta.get("fingerprint") != fingerprint:
            raise InputError(f"output '{path}': holds another job (different PSF, parameters or frames); "
                             "refusing to mix results: choose a new output")
        if tuple(arr.shape) != tuple(shape):
            raise InputError(f"output '{path}': holds an array of shape {tuple(arr.shape)}, this job needs {shape}")
        if meta.get("ngff", "0.4") != ngff:
            raise InputError(f"output '{path}': is OME-Zarr {meta.get('ngff', '0.4')}, this job asks for {ngff} "
                             "(--ngff); give the same, or choose a new output")
        held = _levels_of(meta, path)
        if held != levels:
            raise InputError(f"output '{path}': holds {held} resolution level(s), this job asks for {levels} "
                             "(--pyramid); give the same, or choose a new output")
        try:
            coarse = [g[str(k)] for k in range(1, levels)]
        except Exception as exc:  # noqa: BLE001 - a level missing or unreadable
            raise InputError(f"output '{path}': a resolution level of the store cannot be read "
                             f"({type(exc).__name__}); choose a new output") from exc
        try:
            fd = exclusive_lock(lock_path(path), f"output '{path}': another run is writing this store; wait for "
                                                 "it or choose another output")
        except OSError as exc:
            raise InputError(f"output '{path}': its folder cannot be written ({exc.strerror or exc}); resume it "
                             "where it can be, or choose a new output") from exc
        try:
            done_dir(path).mkdir(exist_ok=True)     # a store moved without its markers: every frame computed again
        except OSError as exc:
            release_lock(fd, lock_path(path))
            raise InputError(f"output '{path}': its folder cannot be written ({exc.strerror or exc})") from exc
        store = cls(path, arr, fd, coarse)
        try:
            store._check_writable(levels)
        except InputError:
            release_lock(fd, lock_path(path))
            raise
        for i in store.verify():      # a lost or overwritten chunk: its frame is computed again
            log.warning("output '%s': frame %d does not match its checksum; it is computed again", path, i)
            (done_dir(path) / f"{i:08d}").unlink()
            store.recomputed.append(i)
        return store

    def _check_writable(self, levels: int) -> None:
        """A file made and removed where a run writes (the store's folder for its attributes, each level's
        array folder for its chunks, the job record for its markers): a store that cannot be written (read
        only, immutable) is refused before any frame is solved, not after the first one."""
        for d in [self.path, *(self.path / str(k) for k in range(levels)), done_dir(self.path)]:
            probe = d / f".cm2cl-write-probe.{os.getpid()}"
            try:
                probe.write_bytes(b"")
                probe.unlink()
            except OSError as exc:
                raise InputError(f"output '{self.path}': cannot be written ({exc.strerror or exc}: '{d}'); the "
                                 "frames it holds are kept: resume it where it can be written (the same command), "
                                 "or choose a new output") from exc

    @property
    def n_frames(self) -> int:
        return int(self.array.shape[0])

    def done(self) -> set[int]:
        return {int(p.name) for p in done_dir(self.path).iterdir() if p.name.isdigit()}

    def missing(self) -> list[int]:
        d = self.done()
        return [i for i in range(self.n_frames) if i not in d]

    def verify(self, frames=None) -> list[int]:
        """The frames among ``frames`` (default: every one marked done) whose stored volume does not match
        the checksum in its marker, or cannot be read at all (a chunk deleted reads as zeros, one
        overwritten fails to decode or reads other values). Markers written before checksums were
        recorded are trusted as long as their chunks decode."""
        bad = []
        for i in sorted(self.done() if frames is None else frames):
            try:
                want = self.info(i).get("sha256")
            except (ValueError, OSError, AttributeError):   # a marker that is not the JSON object written
                bad.append(i)
                continue
            try:
                got = digest(self.read(i), self.array.dtype)
                levels = [digest(a[int(i)], a.dtype) for a in self.levels]
            except Exception:  # noqa: BLE001 - any failure to decode the chunk is a bad frame
                bad.append(i)
                continue
            if want is not None and (got != want or (self.levels and levels != self.info(i).get("sha256_levels"))):
                bad.append(i)
        return bad

    def write(self, i: int, volume, info: dict | None = None) -> None:
        """Write frame ``i``'s volume, then mark it done: the marker (carrying ``info``, the frame's
        summary, and the volume's SHA-256, as JSON) is renamed into place only after the whole chunk is
        written."""
        import threading

        vol = np.asarray(volume, self.array.dtype)
        info = {**(info or {}), "sha256": digest(vol, self.array.dtype)}
        try:
            self.array[int(i)] = vol
            coarse = vol
            sums = []
            for a in self.levels:               # the pyramid, level by level, before the frame counts as done
                coarse = downsample(coarse).astype(a.dtype)
                a[int(i)] = coarse
                sums.append(digest(coarse, a.dtype))
            if sums:
                info["sha256_levels"] = sums
            if vol.size:
                self._vmax = max(self._vmax, float(np.nanmax(vol)))
            fault_point(f"after_chunk.{int(i)}")   # tests: kill -9 between chunk and mark
            d = done_dir(self.path)
            tmp = d / f".{int(i):08d}.{os.getpid()}.{threading.get_ident()}"
            tmp.write_text(json.dumps(info))
            os.replace(tmp, d / f"{int(i):08d}")
        except OSError as exc:   # the disk full, the store made read-only during the job, ...
            raise JobError(f"output '{self.path}': frame {int(i)} could not be written ({exc.strerror or exc}); "
                           "the frames finished before it are kept: rerun the same command, where the store can "
                           "be written, to resume") from exc

    def info(self, i: int) -> dict:
        """The summary recorded with frame ``i`` when it was marked done."""
        return json.loads((done_dir(self.path) / f"{int(i):08d}").read_text() or "{}")

    def read(self, i: int) -> np.ndarray:
        """Frame ``i``'s stored volume; a chunk that cannot be decoded is a one-line JobError."""
        try:
            return np.asarray(self.array[int(i)])
        except Exception as exc:  # noqa: BLE001 - the codec's own errors (blosc's RuntimeError, ...)
            raise JobError(f"output '{self.path}': frame {int(i)} cannot be read back ({type(exc).__name__}: "
                           f"{str(exc)[:120]}); rerun the same command to check the store and recompute it") from exc

    def close(self) -> None:
        if self._lock is not None:
            try:
                self._widen_window()
            except OSError as exc:     # the frames are all stored and marked; only the viewers' contrast is stale
                log.warning("output '%s': its display window could not be updated (%s); the frames written are "
                            "complete", self.path, exc.strerror or exc)
            finally:
                release_lock(self._lock, lock_path(self.path))
                self._lock = None

    def _widen_window(self) -> None:
        """The omero window's end raised to the brightest voxel written (viewers open the store at a contrast
        that shows the volume); a store without an omero block (older cm2cl) keeps its metadata."""
        import zarr

        if self._vmax <= 0:
            return
        g = zarr.open_group(str(self.path), mode="r+")
        attrs = dict(g.attrs)
        home = dict(attrs["ome"]) if isinstance(attrs.get("ome"), dict) else None    # NGFF 0.5 keeps it there
        block = (home or attrs).get("omero")
        if not isinstance(block, dict) or not block.get("channels"):
            return
        ch = block["channels"][0]
        meta = dict(g.attrs.get("cm2cl") or {})
        end = max(self._vmax, float(meta.get("display_max") or 0.0))   # over every run on this store
        g.attrs["cm2cl"] = {**meta, "display_max": end}
        if home is not None:
            g.attrs["ome"] = {**home, "omero": omero(ch.get("label", "fluorescence"), end)}
        else:
            g.attrs["omero"] = omero(ch.get("label", "fluorescence"), end)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None and self.created and self._lock is not None and not self.done():
            # the job failed before its first frame (a device that cannot compile, a frame too large for
            # it): the empty store it made is removed, so nothing is left that looks like a job begun
            self._vmax = 0.0
            shutil.rmtree(self.path, ignore_errors=True)
            shutil.rmtree(done_dir(self.path), ignore_errors=True)
        self.close()


def read_record(path) -> dict:
    """The store's cm2cl record (fingerprint, shape, scale, job parameters)."""
    import zarr

    return json.loads(json.dumps(dict(zarr.open_group(str(path), mode="r").attrs)["cm2cl"]))

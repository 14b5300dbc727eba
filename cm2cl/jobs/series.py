"""A series job from Python in one call: :func:`reconstruct_series`, the frames of a time series into one
OME-Zarr store, resumable like ``cm2cl reconstruct FRAMES -o OUT.ome.zarr`` (a rerun of the same call skips
the frames done and recomputes any whose chunk fails its checksum), on the local devices, in order with a
warm start, or on a Dask cluster through a ``distributed.Client``."""

from __future__ import annotations

import numpy as np

from .. import validate
from ..errors import InputError
from ..solver.params import check_keywords
from .executors import executor_for
from .frames import ArraySeries, FrameSeries
from .run import JobSummary, fingerprint, run_series
from .store import FrameStore


def reconstruct_series(frames, psf, output, *, client=None, devices=None, warm_start: bool = False,
                       dtype=np.float32, backend: str = "auto", offset=None, voxel_size_um=None, depths_um=None,
                       padded_shape=None, max_memory=None, stream="auto", lean="auto", progress=None,
                       channel: str = "fluorescence", frame_interval_s: float | None = None, pyramid: int = 1,
                       ngff: str = "0.4", **params) -> JobSummary:
    """Reconstruct every frame of a series into the OME-Zarr store ``output`` (created, or resumed).

    Parameters
    ----------
    frames : paths, a glob, a folder, a :class:`~cm2cl.jobs.FrameSeries`, or a (T, My, Mx) array
        The measurements, read one at a time (files) or held (an array).
    psf : (nz, My, Mx) array or the path of a PSF TIFF
        On the frames' sensor grid; a TIFF's voxel size and depths label the store unless given.
    output : path of the store (``*.ome.zarr``); its folder must exist.
    client : ``distributed.Client`` or scheduler address, optional
        Run the frames as tasks on that Dask cluster (at most two per worker in flight: a long series is
        not read into the client's memory at once); the client is left open.
    devices : list of local devices, optional
        Spread the frames over these OpenCL devices (default: the best one).
    warm_start : bool
        Frame t starts from frame t - 1's volume (in order, one local device).
    offset : None, 'auto' or a number
        Camera offset subtracted from each frame (default None: the frames have none).
    channel, frame_interval_s, pyramid :
        The store's channel name (its ``omero`` block), the time between frames (its t axis in seconds) and
        its resolution levels (1: none coarser; 3: also 2x and 4x coarser laterally).
    ngff : '0.4' (Zarr format 2, default) or '0.5' (Zarr format 3).
    progress : callable, optional
        ``progress(frame_index, info)`` after each frame (info: iterations, converged, objective, seconds).
    padded_shape, max_memory, stream, lean, dtype, backend :
        As :func:`cm2cl.reconstruct`, for every frame.
    **params :
        The solver's parameters, as :func:`cm2cl.reconstruct`. With ``psf_refine`` the PSF is refined on the
        first frame and every frame solved with that stack, kept beside the store as ``OUT.psf.ome.tif``
        (:mod:`cm2cl.jobs.refine`; a resumed job reads it back); with ``psf_refine='auto'`` frame 0's check decides
        whether the lenslets are refined one by one, once for every frame. With ``scattering_length_um='auto'``
        l_s is estimated on frame 0 and every frame solved with it (the store's record keeps it).

    Returns
    -------
    JobSummary
        frames, computed, skipped (already done), converged, iterations, seconds, devices.

    The store is the CLI's (:class:`~cm2cl.jobs.FrameStore`): read it with ``zarr.open(output)['0']``
    or ``FrameStore.open_readonly(output)``; ``cm2cl verify`` checks it.
    """
    prm = check_keywords("reconstruct_series", params)
    if client is not None and (warm_start or devices):
        raise InputError("client: the frames run on the cluster's workers; give client, or devices / warm_start")
    series = frames if isinstance(frames, (FrameSeries, ArraySeries)) else (
        ArraySeries(frames) if isinstance(frames, np.ndarray) else FrameSeries(frames))
    h, vs, d = _psf(psf, voxel_size_um, depths_um)
    if tuple(h.shape[1:]) != tuple(series.shape):
        raise InputError(f"frames: shape {tuple(series.shape)} does not match the PSF's sensor grid "
                         f"{tuple(h.shape[1:])}")
    ex = executor_for(devices or [None], client, warm_start)
    dt = np.dtype(dtype)
    ex.check(dt)
    solver_kw = {"max_memory": max_memory, "stream": stream, "lean": lean}
    if padded_shape is not None:
        solver_kw["padded_shape"] = tuple(int(n) for n in padded_shape)
    prep = {"offset": offset, "bin": 1, "padding": "full", "warm_start": bool(warm_start),
            "padded_shape": solver_kw.get("padded_shape")}
    from ..solver import attenuation
    from ..solver.attenuation import AUTO

    attenuation.check(prm, d, h.shape[0])   # before the store exists
    key = fingerprint(h, prm, series, dt, backend, prep)
    record = {"what": "cm2cl reconstruction series (Python)", "params": prm.as_dict(), "prep": prep,
              "frames": [f"{f.path}[{f.index}]" for f in series.frames[:1000]]}
    from ..io.prepare import prepare

    frame_prep = lambda a: prepare(a, offset=offset, name="frame")  # noqa: E731
    if prm.scattering_length_um == AUTO:   # frame 0's estimate for every frame (read back on a resume)
        from .refine import series_attenuation

        prm, record["attenuation"] = series_attenuation(
            output, key, series, h, frame_prep, prm, voxel_size_um=vs, depths_um=d,
            solve_kw={"dtype": dt, "backend": backend, "device": (devices or [None])[0], **solver_kw})
    with FrameStore.open(output, fingerprint=key, n_frames=len(series), volume_shape=h.shape, dtype=dt,
                         voxel_size_um=vs, depths_um=d, record=record, channel=channel,
                         frame_interval_s=frame_interval_s, levels=pyramid, ngff=ngff) as store:
        from dataclasses import replace

        from ..solver.api import refine_runs
        from ..solver.attenuation import attenuate
        from ..solver.psf_refine import with_reweight

        reweight = None

        # N rounds, or 'auto' / 'common' where they can run: frame 0 decides, once for every frame
        if refine_runs(h, prm.psf_refine, padded_shape, radius=prm.psf_refine_radius):
            from .refine import series_psf

            h, _, reweight = series_psf(output, key, series, h, store, frame_prep, prm, voxel_size_um=vs,
                                        depths_um=d, solve_kw={"dtype": dt, "backend": backend,
                                                               "device": (devices or [None])[0], **solver_kw})
        prm = with_reweight(replace(prm, psf_refine=0), reweight)
        h, _ = attenuate(h, d, prm)   # every frame's model: the stack scaled by its planes' ballistic fractions
        return run_series(series, h, store, params=prm, key=key, executor=ex, dtype=dt, backend=backend,
                          prepare=frame_prep, progress=progress, solver_kw=solver_kw)


def _psf(psf, voxel_size_um, depths_um):
    """(PSF stack float64, voxel size, depths) from an array or a TIFF path (its scale unless given)."""
    vs, d = voxel_size_um, depths_um
    if isinstance(psf, (str, bytes)) or hasattr(psf, "__fspath__"):
        from ..io import read_tiff

        psf, meta = read_tiff(psf)
        if vs is None and meta.get("unit") == "um" and meta.get("voxel_size_um") and len(meta["voxel_size_um"]) == 3:
            vs = meta["voxel_size_um"]
        if d is None:
            d = meta.get("depths_um")
    h = validate.psf_stack(validate.image_array(psf, "psf"), "psf")
    h = np.asarray(h, np.float64)
    from ..solver.api import check_scale

    vs, d = check_scale(vs, d, h.shape[0])
    return h, vs, d


__all__ = ["reconstruct_series"]

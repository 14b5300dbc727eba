"""The PSF a series with ``psf_refine`` solves every frame with: the given stack self-calibrated on the
series' first frame (:mod:`cm2cl.solver.psf_refine`), kept beside the store as ``OUT.psf.ome.tif`` with the
job's fingerprint. A resumed job reads it back, so that every frame of a store is solved with the same
stack; a store with finished frames and no such file (deleted, or another job's) is refused before any
work. With ``psf_refine='auto'`` frame 0's check decides (:func:`cm2cl.reconstruct`): where its views
agree with the PSF no file is made and every frame is solved with the given stack; the check is
deterministic, so a resumed job decides as the first run did. Used by ``cm2cl reconstruct FRAMES -o OUT.ome.zarr --psf-refine N`` and :func:`reconstruct_series`."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ..errors import InputError

log = logging.getLogger(__name__)

__all__ = ["refined_psf_path", "series_psf"]


def refined_psf_path(output) -> Path:
    """``OUT.psf.ome.tif`` beside the store ``OUT.ome.zarr`` (or ``OUT.zarr``)."""
    out = Path(output)
    name = out.name
    for suffix in (".ome.zarr", ".zarr"):
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
            break
    return out.with_name(name + ".psf.ome.tif")


def series_psf(output, key: str, series, h, store, prepare, params, *, solve_kw: dict, voxel_size_um=None,
               depths_um=None, psf_name: str = "psf") -> tuple[np.ndarray, bool]:
    """(the PSF stack the frames are solved with, whether it was read back rather than refined now).

    ``key`` is the job's fingerprint (of the given stack and parameters), ``store`` the open
    :class:`~cm2cl.jobs.FrameStore` (its finished frames decide whether a missing stack may be made again),
    ``prepare`` the frames' preparation, ``params`` the solver's parameters with ``psf_refine`` rounds and
    ``solve_kw`` the rest of :func:`cm2cl.reconstruct`'s keywords for frame 0 (dtype, backend, device,
    layout)."""
    from .. import io
    from ..solver import reconstruct
    from ..solver.api import psf_check

    path = refined_psf_path(output)
    if path.exists():
        psf, meta = io.read_tiff(path)
        if (meta.get("extra") or {}).get("job") == key and psf.shape == tuple(h.shape):
            log.info("the PSF refined on frame 0 is read back from '%s'", path)
            return np.asarray(psf, np.float64), True
    auto = params.psf_refine == "auto"
    if len(store.missing()) < len(series) and not auto:
        _missing(path, output)
    if auto:
        log.info("checking on frame 0 whether the PSF needs refining (psf_refine auto)")
    else:
        log.info("refining the PSF on frame 0 (%s)", "one kernel common to every lenslet"
                 if params.psf_refine == "common" else f"{params.psf_refine} rounds")
    # auto: the check alone where it finds the views in agreement (the frame's own solve is the series')
    # the planes' scale goes with it: an attenuating sample needs their depths (the stack comes back unattenuated)
    rec = (psf_check if auto else reconstruct)(prepare(series.read(0)), h, voxel_size_um=voxel_size_um,
                                               depths_um=depths_um, **solve_kw, **params.as_dict())
    # auto, and frame 0's views agree with the PSF: no file ('common' always writes its stack, the given one
    # where its round had nothing to fit, so that a resumed job reads it back)
    if auto and not rec.info["psf_refine"]["refined"]:
        log.info("psf_refine %s: frame 0 leaves the PSF as given (%s); every frame is solved with it",
                 params.psf_refine, _why(rec.info["psf_refine"]))
        return np.asarray(h, np.float64), False
    if len(store.missing()) < len(series):   # auto decided to refine: the same check decided so before
        _missing(path, output)
    first = series.frames[0] if hasattr(series, "frames") else None
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}.ome.tif")
    try:
        io.write_tiff(tmp, rec.psf, voxel_size_um=voxel_size_um, depths_um=depths_um,
                      extra={"what": "PSF stack self-calibrated on frame 0 of the series (psf_refine), working grid",
                             "job": key, "psf": psf_name, "psf_refine": rec.info["psf_refine"]["rounds"],
                             "frame": f"{first.path}[{first.index}]" if first is not None else "0",
                             "store": str(output)})
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return np.asarray(rec.psf, np.float64), False


def _missing(path, output):
    raise InputError(f"psf_refine: '{path}', the refined PSF stack the finished frames of '{output}' were "
                     "solved with, is missing or belongs to another job; put it back, or reconstruct into a "
                     "new store")


def _why(record: dict) -> str:
    check = record.get("check")
    if check:
        return f"disagreement {check['disagreement']:.3f} <= {check['threshold']:g}"
    if record.get("per_round") and all(r.get("kept") for r in record["per_round"]):
        return "its sparse volume explained too little of the data to fit a kernel"
    return record.get("skipped") or "not checked"

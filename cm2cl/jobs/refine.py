"""The PSF a series with ``psf_refine`` solves every frame with: the given stack self-calibrated on the
series' first frame (:mod:`cm2cl.solver.psf_refine`), kept beside the store as ``OUT.psf.ome.tif`` with the
job's fingerprint. A resumed job reads it back, so that every frame of a store is solved with the same
stack; a store with finished frames and no such file (deleted, or another job's) is refused before any
work. With ``psf_refine='auto'`` frame 0's check decides whether the stack is refined per lenslet or by one
common kernel (:func:`cm2cl.reconstruct`); either way the stack is written. Used by ``cm2cl reconstruct FRAMES -o OUT.ome.zarr --psf-refine N`` and :func:`reconstruct_series`.

Likewise ``scattering_length_um='auto'`` (:func:`series_attenuation`): l_s is estimated once, on frame 0 (as
:func:`cm2cl.reconstruct` estimates it for one frame), every frame is solved with that number, and the store's
record keeps it, so that a resumed job reads it back instead of estimating again."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ..errors import InputError

log = logging.getLogger(__name__)

__all__ = ["refined_psf_path", "series_psf", "series_attenuation"]


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
               depths_um=None, psf_name: str = "psf") -> tuple[np.ndarray, bool, dict | None]:
    """(the PSF stack the frames are solved with, whether it was read back rather than refined now, the
    reweighted l1 of frame 0's final solve that every frame takes as well: ``info['psf_refine']['reweight']``,
    :func:`cm2cl.solver.psf_refine.with_reweight`).

    ``key`` is the job's fingerprint (of the given stack and parameters), ``store`` the open
    :class:`~cm2cl.jobs.FrameStore` (its finished frames decide whether a missing stack may be made again),
    ``prepare`` the frames' preparation, ``params`` the solver's parameters with ``psf_refine`` rounds and
    ``solve_kw`` the rest of :func:`cm2cl.reconstruct`'s keywords for frame 0 (dtype, backend, device,
    layout)."""
    from .. import io
    from ..solver import reconstruct
    from ..solver.psf_refine import describe

    path = refined_psf_path(output)
    if path.exists():
        psf, meta = io.read_tiff(path)
        if (meta.get("extra") or {}).get("job") == key and psf.shape == tuple(h.shape):
            log.info("the PSF refined on frame 0 is read back from '%s'", path)
            return np.asarray(psf, np.float64), True, meta["extra"].get("reweight")
    if len(store.missing()) < len(series):
        _missing(path, output)
    log.info("refining the PSF on frame 0 (%s)", describe(params.psf_refine))
    # the planes' scale goes with it: an attenuating sample needs their depths (the stack comes back unattenuated);
    # the stack is written even where a round had nothing to fit (the given one), so that a resumed job reads it
    rec = reconstruct(prepare(series.read(0)), h, voxel_size_um=voxel_size_um, depths_um=depths_um, **solve_kw,
                      **params.as_dict())
    first = series.frames[0] if hasattr(series, "frames") else None
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}.ome.tif")
    try:
        io.write_tiff(tmp, rec.psf, voxel_size_um=voxel_size_um, depths_um=depths_um,
                      extra={"what": "PSF stack self-calibrated on frame 0 of the series (psf_refine), working grid",
                             "job": key, "psf": psf_name, "psf_refine": rec.info["psf_refine"]["rounds"],
                             "reweight": rec.info["psf_refine"].get("reweight"),
                             "frame": f"{first.path}[{first.index}]" if first is not None else "0",
                             "store": str(output)})
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return np.asarray(rec.psf, np.float64), False, rec.info["psf_refine"].get("reweight")


def _missing(path, output):
    raise InputError(f"psf_refine: '{path}', the refined PSF stack the finished frames of '{output}' were "
                     "solved with, is missing or belongs to another job; put it back, or reconstruct into a "
                     "new store")


def series_attenuation(output, key: str, series, h, prepare, params, *, solve_kw: dict, voxel_size_um=None,
                       depths_um=None) -> tuple:
    """For ``params.scattering_length_um == 'auto'``: (the parameters every frame is solved with, l_s and the
    surface fixed to frame 0's estimate, or no attenuation where it does not apply; the record of the estimate
    for the store). A store of this job (``key``) that records an estimate gives it back without a solve;
    otherwise frame 0 is solved with the clear-medium model (``params`` otherwise, ``solve_kw`` the rest of
    :func:`cm2cl.reconstruct`'s keywords) and l_s estimated from its volume
    (:func:`cm2cl.solver.attenuation.estimate_on`)."""
    from dataclasses import replace

    from ..solver import reconstruct
    from ..solver.attenuation import estimate_on
    from .store import read_record

    record = None
    if Path(output).exists():
        try:
            old = read_record(output)
        except Exception:  # noqa: BLE001 - not a store: opening it says why
            old = {}
        if old.get("fingerprint") == key and isinstance(old.get("attenuation"), dict):
            record = old["attenuation"]
            log.info("the scattering length estimated on frame 0 is read back from '%s'", output)
    if record is None:
        log.info("estimating the scattering length on frame 0")
        call = {"measurement": prepare(series.read(0)), "psf": h, "voxel_size_um": voxel_size_um,
                "depths_um": depths_um, **solve_kw, **params.as_dict()}
        _, record = estimate_on(reconstruct, lambda r: r.volume, depths_um, params, call)
    ls = record["scattering_length_um"]
    return replace(params, scattering_length_um=ls, surface_um=record["surface_um"] if ls is not None else None), \
        record

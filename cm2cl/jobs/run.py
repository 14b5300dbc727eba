"""Run a job of many frames: every frame is an independent reconstruction with the same PSF stack and
parameters. Executors: the local OpenCL devices (one worker thread per device, each with its own solver,
so its PSF spectra are computed once and reused for every frame it takes), or a Dask distributed cluster
(``scheduler='tcp://host:port'``; one solver per worker process, cached across tasks; pin each worker to
a device with ``CM2CL_DEVICE`` in its environment). Results go to a :class:`FrameStore`; frames already
done there are skipped, so the same call resumes a killed job. Each frame starts from zero (no warm
start), so a resumed job gives the same bits as an uninterrupted one on the same device."""

from __future__ import annotations

import hashlib
import json
import queue
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..solver.params import ADMMParams
from .frames import FrameSeries
from .store import FrameStore

#: solvers of this process, by (job fingerprint, device): Dask workers keep theirs between tasks
_SOLVERS: dict = {}
_SOLVERS_LOCK = threading.Lock()


@dataclass
class JobSummary:
    frames: int
    computed: int
    skipped: int
    seconds: float
    devices: list = field(default_factory=list)
    converged: int = 0
    iterations: int = 0
    moved_bytes: int = 0


def fingerprint(psf, params: ADMMParams, series: FrameSeries, dtype, backend: str, prep: dict) -> str:
    h = hashlib.sha256()
    a = np.ascontiguousarray(psf, np.float64)
    h.update(repr(a.shape).encode())
    h.update(a.tobytes())
    h.update(json.dumps({"params": params.as_dict(), "dtype": np.dtype(dtype).name, "backend": backend,
                         "prep": prep}, sort_keys=True, default=str).encode())
    h.update(series.identity().encode())
    return h.hexdigest()


def _solver(key, psf, params, dtype, backend, device, solver_kw):
    from ..solver.admm import ADMMSolver

    with _SOLVERS_LOCK:
        if (key, device) not in _SOLVERS:
            _SOLVERS[(key, device)] = (ADMMSolver(psf, params, dtype=dtype, backend=backend, device=device,
                                                  **(solver_kw or {})), threading.Lock())
        return _SOLVERS[(key, device)]


def solve_frame(key, psf, params_dict, dtype, backend, y, device=None, solver_kw=None, x0=None):
    """One frame on this process's solver for (key, device): (volume, info). Runs on Dask workers too.
    ``solver_kw``: ADMMSolver's layout options (padded_shape, max_memory, stream, lean); ``x0`` a warm start."""
    params = ADMMParams.from_kwargs(**params_dict)
    solver, lock = _solver(key, psf, params, np.dtype(dtype), backend, device, solver_kw)
    with lock:
        t = time.perf_counter()
        rec = solver.solve(y, x0=x0)
    info = {"iterations": rec.iterations, "converged": bool(rec.info["converged"]), "stop": rec.info["stop"],
            "seconds": time.perf_counter() - t, "device": rec.info["device"],
            "objective": rec.log[-1]["objective"], "moved_bytes": rec.info["moved_bytes"]}
    return np.asarray(rec.volume), info


def run_series(series: FrameSeries, psf, store: FrameStore, *, params: ADMMParams, key: str,
               prepare=lambda a: np.asarray(a, np.float64), dtype=np.float32, backend="auto", devices=(None,),
               scheduler=None, progress=None, solver_kw=None, warm_start=False) -> JobSummary:
    """Reconstruct the frames of ``series`` missing from ``store``. ``prepare`` maps a decoded frame to
    the measurement (offset, binning); ``devices`` lists the local devices (index/name/None) to use;
    ``scheduler`` a Dask scheduler address instead. ``progress(i, info)`` is called per finished frame;
    ``solver_kw`` goes to every worker's ADMMSolver (padded_shape, max_memory, stream). ``warm_start``:
    frame t starts from frame t - 1's stored volume (read back from the store, so a resumed job gives
    the same bits); the frames then run in order on one device."""
    todo = store.missing()
    t0 = time.perf_counter()
    summary = JobSummary(frames=len(series), computed=0, skipped=len(series) - len(todo), seconds=0.0)
    pd = params.as_dict()
    write_lock = threading.Lock()

    def finish(i, vol, info):
        with write_lock:
            store.write(i, vol, info)
            summary.computed += 1
            summary.converged += int(info["converged"])
            summary.iterations += int(info["iterations"])
            summary.moved_bytes += int(info.get("moved_bytes", 0))
            if info["device"] not in summary.devices:
                summary.devices.append(info["device"])
        if progress is not None:
            progress(i, info)

    if warm_start:
        if scheduler or len(list(devices)) != 1:
            raise InputError("--warm-start: frame t starts from frame t - 1, so the frames run in order on one "
                             "device (no --scheduler, one --device)")
        dev = list(devices)[0]
        for i in todo:   # ascending: frame i - 1 is in the store before frame i starts (or i == 0)
            x0 = store.read(i - 1) if i > 0 else None
            vol, info = solve_frame(key, psf, pd, np.dtype(dtype).name, backend, prepare(series.read(i)), dev,
                                    solver_kw, x0)
            info["warm"] = x0 is not None
            finish(i, vol, info)
    elif scheduler:
        _run_dask(series, psf, todo, pd, key, prepare, dtype, backend, scheduler, finish, solver_kw)
    else:
        _run_local(series, psf, todo, pd, key, prepare, dtype, backend, list(devices), finish, solver_kw)
    summary.seconds = time.perf_counter() - t0
    return summary


def _run_local(series, psf, todo, pd, key, prepare, dtype, backend, devices, finish, solver_kw):
    q: queue.Queue = queue.Queue()
    for i in todo:
        q.put(i)
    errors: list = []

    def worker(device):
        try:
            while not errors:
                try:
                    i = q.get_nowait()
                except queue.Empty:
                    return
                y = prepare(series.read(i))
                vol, info = solve_frame(key, psf, pd, np.dtype(dtype).name, backend, y, device, solver_kw)
                finish(i, vol, info)
        except BaseException as exc:  # noqa: BLE001 - handed to the caller below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(d,), daemon=True) for d in devices]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]


def _run_dask(series, psf, todo, pd, key, prepare, dtype, backend, address, finish, solver_kw):
    try:
        from distributed import Client, as_completed
    except ImportError as exc:
        raise InputError("--scheduler: needs Dask distributed (pip install 'cm2cl[dask]')") from exc
    try:
        client = Client(address, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise InputError(f"--scheduler '{address}': no Dask scheduler answers there ({exc})") from exc
    try:
        psf_f = client.scatter(np.asarray(psf), broadcast=True)
        futs = {}
        for i in todo:
            y = prepare(series.read(i))
            futs[client.submit(solve_frame, key, psf_f, pd, np.dtype(dtype).name, backend, y,
                               solver_kw=solver_kw, pure=False)] = i
        for fut in as_completed(list(futs)):
            vol, info = fut.result()
            finish(futs[fut], vol, info)
    finally:
        client.close()

"""Run a job of many frames: every frame is a reconstruction with the same PSF stack and parameters, run
by an executor (:mod:`.executors`: in order with a warm start, the local OpenCL devices, or a Dask
cluster). Results go to a :class:`FrameStore`; frames already done there are skipped, so the same call
resumes a killed job, to the same bits."""

from __future__ import annotations

import hashlib
import json
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ..solver.params import ADMMParams
from .executors import Executor, FrameJob, executor_for, solve_frame  # noqa: F401 - solve_frame: its old home
from .frames import FrameSeries
from .store import FrameStore


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

    def add(self, info: dict) -> None:
        """Count one computed frame."""
        self.computed += 1
        self.converged += int(info["converged"])
        self.iterations += int(info["iterations"])
        self.moved_bytes += int(info.get("moved_bytes", 0))
        if info["device"] not in self.devices:
            self.devices.append(info["device"])


def fingerprint(psf, params: ADMMParams, series: FrameSeries, dtype, backend: str, prep: dict) -> str:
    h = hashlib.sha256()
    a = np.ascontiguousarray(psf, np.float64)
    h.update(repr(a.shape).encode())
    h.update(a.tobytes())
    h.update(json.dumps({"params": params.as_dict(), "dtype": np.dtype(dtype).name, "backend": backend,
                         "prep": prep}, sort_keys=True, default=str).encode())
    h.update(series.identity().encode())
    return h.hexdigest()


def run_series(series: FrameSeries, psf, store: FrameStore, *, params: ADMMParams, key: str,
               prepare=lambda a: np.asarray(a, np.float64), dtype=np.float32, backend="auto", devices=(None,),
               scheduler=None, progress=None, solver_kw=None, warm_start=False,
               executor: Executor | None = None) -> JobSummary:
    """Reconstruct the frames of ``series`` missing from ``store``. ``prepare`` maps a decoded frame to
    the measurement (offset, binning); ``executor`` runs them (default :func:`executor_for` ``devices``,
    ``scheduler`` and ``warm_start``: the local devices (index/name/None), a Dask scheduler address, or in
    order on one device, frame t starting from frame t - 1's stored volume). ``progress(i, info)`` is
    called per finished frame; ``solver_kw`` goes to every worker's ADMMSolver (padded_shape, max_memory,
    stream, lean)."""
    executor = executor or executor_for(devices, scheduler, warm_start)
    job = FrameJob(series, np.asarray(psf), params, key, prepare, np.dtype(dtype).name, backend, solver_kw)
    todo = store.missing()
    t0 = time.perf_counter()
    summary = JobSummary(frames=len(series), computed=0, skipped=len(series) - len(todo), seconds=0.0)
    write_lock = threading.Lock()

    def finish(i, vol, info):
        with write_lock:
            store.write(i, vol, info)
            summary.add(info)
        if progress is not None:
            progress(i, info)

    executor.run(job, todo, finish, store)
    summary.seconds = time.perf_counter() - t0
    return summary

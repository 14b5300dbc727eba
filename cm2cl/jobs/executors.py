"""Executors of a job of many frames: they take the frames a store is missing and hand each result to
``finish(i, volume, info)``. :class:`InOrder` runs them one after the other on one device, each frame
starting from the previous one's stored volume (warm start); :class:`LocalDevices` runs one worker thread
per local OpenCL device; :class:`DaskCluster` submits them to a Dask distributed scheduler. Every solver
is built once per (job, device) and reused for every frame it takes (its PSF spectra computed once)."""

from __future__ import annotations

import contextlib
import itertools
import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from ..errors import CM2Error, InputError, JobError
from ..solver.params import ADMMParams
from .frames import FrameSeries

log = logging.getLogger(__name__)

#: solvers of this process, by (job fingerprint, device): Dask workers keep theirs between tasks
_SOLVERS: dict = {}
_SOLVERS_LOCK = threading.Lock()

Finish = Callable[[int, np.ndarray, dict], None]


def _solver(key, psf, params, dtype, backend, device, solver_kw):
    from ..solver.admm import ADMMSolver

    with _SOLVERS_LOCK:
        if (key, device) not in _SOLVERS:
            _SOLVERS[(key, device)] = (ADMMSolver(psf, params, dtype=dtype, backend=backend, device=device,
                                                  **(solver_kw or {})), threading.Lock())
        return _SOLVERS[(key, device)]


class Cancelled(Exception):
    """A frame's solve stopped because the job is stopping (Ctrl-C, SIGTERM, another worker's error)."""


def solve_frame(key, psf, params_dict, dtype, backend, y, device=None, solver_kw=None, x0=None, cancel=None):
    """One frame on this process's solver for (key, device): (volume, info). Runs on Dask workers too.
    ``solver_kw``: ADMMSolver's layout options (padded_shape, max_memory, stream, lean); ``x0`` a warm start;
    ``cancel`` a threading.Event: once set, the solve stops at its next iteration (raises Cancelled)."""
    params = ADMMParams.from_kwargs(**params_dict)
    solver, lock = _solver(key, psf, params, np.dtype(dtype), backend, device, solver_kw)

    def check(row):
        if cancel.is_set():
            raise Cancelled("the job is stopping")

    with lock:
        t = time.perf_counter()
        rec = solver.solve(y, x0=x0, callback=check if cancel is not None else None)
    info = {"iterations": rec.iterations, "converged": bool(rec.info["converged"]), "stop": rec.info["stop"],
            "seconds": time.perf_counter() - t, "device": rec.info["device"],
            "objective": rec.log[-1]["objective"], "moved_bytes": rec.info["moved_bytes"],
            "misfit": rec.info["misfit"]}
    return np.asarray(rec.volume), info


@dataclass(frozen=True)
class FrameJob:
    """What every frame of a job shares: the frames, the PSF stack on the working grid, the parameters,
    how a decoded frame becomes a measurement (``prepare``), and the solver's options."""
    series: FrameSeries
    psf: np.ndarray
    params: ADMMParams
    key: str                         #: the job's fingerprint, which also keys the cached solvers
    prepare: Callable = lambda a: np.asarray(a, np.float64)
    dtype: str = "float32"
    backend: str = "auto"
    solver_kw: dict | None = None    #: ADMMSolver's layout options (padded_shape, max_memory, stream, lean)

    def measurement(self, i: int) -> np.ndarray:
        """Frame ``i`` prepared; a frame that cannot be (NaN, Inf, ...) is named in the error with its file."""
        try:
            return self.prepare(self.series.read(i))
        except InputError as exc:
            f = self.series.frames[i]
            raise InputError(f"frame {i} ('{f.path}', page {f.index}): {exc}") from exc

    def solve(self, i: int, device=None, x0=None, cancel=None):
        """Frame ``i`` on this process's solver for ``device``: (volume, info)."""
        return solve_frame(self.key, self.psf, self.params.as_dict(), self.dtype, self.backend, self.measurement(i),
                           device, self.solver_kw, x0, cancel)


class Executor(Protocol):
    """Runs frames ``todo`` of ``job``, results to ``finish``; ``store`` holds the frames already done."""

    where: str                       #: where the frames run, for the summary ('' when the devices say it)
    devices: list                    #: the local devices it uses (None: the automatic choice)

    def check(self, dtype) -> None:
        """Refuse, before any output exists, what cannot run here (unknown device, no scheduler, no fp64)."""

    def run(self, job: FrameJob, todo: list[int], finish: Finish, store) -> None:
        ...


class InOrder:
    """Warm start: frame t starts from frame t - 1's stored volume, read back from the store (so a resumed
    job gives the same bits as an uninterrupted one); the frames run in order on one device."""

    where = ""

    def __init__(self, device=None):
        self.device, self.devices = device, [device]

    def check(self, dtype) -> None:
        _check_devices([self.device], dtype)

    def run(self, job: FrameJob, todo: list[int], finish: Finish, store) -> None:
        for i in todo:   # ascending: frame i - 1 is in the store before frame i starts (or i == 0)
            x0 = store.read(i - 1) if i > 0 else None
            vol, info = job.solve(i, self.device, x0)
            info["warm"] = x0 is not None
            finish(i, vol, info)


class LocalDevices:
    """One worker thread per local device, each taking the next missing frame; each frame starts from zero,
    so a resumed job gives the same bits as an uninterrupted one on the same device."""

    where = ""

    def __init__(self, devices=(None,)):
        self.devices = list(devices)

    def check(self, dtype) -> None:
        _check_devices(self.devices, dtype)

    def run(self, job: FrameJob, todo: list[int], finish: Finish, store) -> None:
        q: queue.Queue = queue.Queue()
        for i in todo:
            q.put(i)
        errors: list = []
        cancel = threading.Event()

        def worker(device):
            try:
                while not errors and not cancel.is_set():
                    try:
                        i = q.get_nowait()
                    except queue.Empty:
                        return
                    finish(i, *job.solve(i, device, cancel=cancel))
            except Cancelled:
                pass
            except BaseException as exc:  # noqa: BLE001 - handed to the caller below
                errors.append(exc)
                cancel.set()           # the other workers stop at their next iteration

        threads = [threading.Thread(target=worker, args=(d,), daemon=True) for d in self.devices]
        for t in threads:
            t.start()
        try:
            for t in threads:
                t.join()
        except BaseException:
            # Ctrl-C or SIGTERM in the main thread: the workers stop at their next iteration and are waited
            # for, so that no thread is inside the OpenCL runtime when the interpreter exits (it aborted)
            cancel.set()
            for t in threads:
                t.join()
            raise
        if errors:
            raise errors[0]


class DaskCluster:
    """The frames as tasks on a Dask distributed scheduler (``tcp://host:port``): one solver per worker
    process, cached across tasks; pin each worker to a device with ``CM2CL_DEVICE`` in its environment."""

    #: resubmissions of one frame whose data a dying worker took with it (the PSF scattered to it alone)
    RETRIES = 3
    #: frames in flight per worker: enough to keep each busy while the next frame is read and sent, few enough
    #: that a long series is not read and held in the client's memory at once (backpressure)
    IN_FLIGHT_PER_WORKER = 2

    def __init__(self, address):
        """``address``: a scheduler's address (``tcp://host:port``), or a connected ``distributed.Client``
        (which the job uses and leaves open)."""
        self.given = None if isinstance(address, str) else address
        self.address = self.where = (address if self.given is None else
                                     getattr(getattr(address, "scheduler", None), "address", None) or repr(address))
        self.devices = [None]   # the workers' own (CM2CL_DEVICE)

    def client(self, timeout: float = 10.0):
        """A connected client, or a one-line error within ``timeout`` + 5 s: the client's own timeout does not
        cover a port that accepts the connection and never answers the handshake, so the connection is made
        in a thread that is given up on (it is a daemon) when that time has passed."""
        if self.given is not None:
            return self.given
        try:
            from distributed import Client
        except ImportError as exc:
            raise InputError("scheduler: needs Dask distributed (pip install 'cm2cl[dask]')") from exc
        box: dict = {}

        def connect():
            try:
                box["client"] = Client(self.address, timeout=f"{timeout:g}s")
            except BaseException as exc:  # noqa: BLE001 - reported below
                box["error"] = exc

        t = threading.Thread(target=connect, daemon=True, name="cm2cl-dask-connect")
        t.start()
        t.join(timeout + 5.0)
        if t.is_alive():
            raise InputError(f"scheduler '{self.address}': no Dask scheduler answers there (the port accepts "
                             f"connections but nothing replied within {timeout + 5.0:g} s)")
        exc = box.get("error")
        if isinstance(exc, (OSError, TimeoutError, ValueError)):
            raise InputError(f"scheduler '{self.address}': no Dask scheduler answers there ({exc})") from exc
        if exc is not None:
            raise exc
        return box["client"]

    def quiet(self):
        """Dask's own loggers silenced while the job holds a client it made: a lost scheduler or worker made
        distributed.client and distributed.core log tracebacks (some 30 lines) before the job's one line;
        a client given by the caller keeps the caller's logging."""
        return _silenced("distributed") if self.given is None else contextlib.nullcontext()

    def check(self, dtype) -> None:
        with self.quiet():
            c = self.client(5.0)
            if self.given is None:
                c.close()

    def in_flight(self, client) -> int:
        """How many frames are submitted at a time: IN_FLIGHT_PER_WORKER per worker, at least 2."""
        try:
            workers = len(client.scheduler_info().get("workers", {}))
        except Exception:  # noqa: BLE001 - an old or busy scheduler: assume one worker
            workers = 1
        return max(2, self.IN_FLIGHT_PER_WORKER * workers)

    def run(self, job: FrameJob, todo: list[int], finish: Finish, store) -> None:
        with self.quiet():
            self._run(job, todo, finish, store)

    def _run(self, job: FrameJob, todo: list[int], finish: Finish, store) -> None:
        """Submit a bounded number of frames (:meth:`in_flight`), the next one as each finishes: a frame is
        read only when it is sent, so the client holds a few frames, not the series."""
        from distributed import as_completed

        client = self.client()
        finished = []
        try:
            psf = np.asarray(job.psf)
            box = {"psf": client.scatter(psf, broadcast=True)}
            pd = job.params.as_dict()
            pending = iter(todo)
            futs: dict = {}
            tries: dict = {}
            done = as_completed()

            def submit(i):
                f = client.submit(solve_frame, job.key, box["psf"], pd, job.dtype, job.backend, job.measurement(i),
                                  solver_kw=job.solver_kw, pure=False)
                futs[f] = i
                done.add(f)

            for i in itertools.islice(pending, self.in_flight(client)):
                submit(i)
            self.peak_in_flight = len(futs)
            for fut in done:
                i = futs.pop(fut)
                try:
                    result = fut.result()
                except CM2Error:
                    raise                  # the frame's own error (a NaN frame, ...): one line, as locally
                except Exception as exc:  # noqa: BLE001 - the cluster's: lost data, a killed worker, a lost scheduler
                    tries[i] = tries.get(i, 0) + 1
                    if not _lost_data(exc) or tries[i] > self.RETRIES:
                        raise
                    log.warning("Dask: frame %d was cancelled by the cluster (%s: a worker, or the scheduler, gone); "
                                "the PSF is sent again and the frame resubmitted (%d of %d)", i, type(exc).__name__,
                                tries[i], self.RETRIES)
                    box["psf"] = client.scatter(psf, broadcast=True)
                    submit(i)
                    continue
                finish(i, *result)
                finished.append(i)
                nxt = next(pending, None)
                if nxt is not None:
                    submit(nxt)
                    self.peak_in_flight = max(self.peak_in_flight, len(futs))
        except CM2Error:
            raise
        except Exception as exc:  # noqa: BLE001 - reported in one line with how to resume
            raise JobError(f"Dask cluster '{self.address}': the job stopped ({type(exc).__name__}: "
                           f"{_first_line(exc)}); {len(finished)} frames finished in this run are kept in "
                           f"'{getattr(store, 'path', store)}', rerun the same command to resume") from exc
        finally:
            if self.given is None:
                client.close()


@contextlib.contextmanager
def _silenced(prefix: str):
    """Every logger named ``prefix`` or below it disabled, then restored (those made meanwhile stay on)."""
    names = [prefix] + [n for n in list(logging.root.manager.loggerDict) if n.startswith(prefix + ".")]
    loggers = [logging.getLogger(n) for n in names]
    saved = [lg.disabled for lg in loggers]
    for lg in loggers:
        lg.disabled = True
    try:
        yield
    finally:
        for lg, was in zip(loggers, saved):
            lg.disabled = was


def _lost_data(exc) -> bool:
    """Whether a Dask failure is data lost with a worker (the scattered PSF), which a resubmission cures,
    rather than a task that kills its workers (KilledWorker) or a lost scheduler."""
    import asyncio
    import concurrent.futures

    name = type(exc).__name__
    return name in ("FutureCancelledError", "CancelledError") or isinstance(
        exc, (asyncio.CancelledError, concurrent.futures.CancelledError))


def _first_line(exc, limit: int = 300) -> str:
    """The first line of an error's message, cut (at a space, marked '...') when longer than ``limit``."""
    text = str(exc).strip().splitlines()
    line = text[0] if text else ""
    if len(line) <= limit:
        return line
    cut = line.rfind(" ", 0, limit)
    return line[:cut if cut > limit // 2 else limit].rstrip() + " ..."


def executor_for(devices=(None,), scheduler=None, warm_start: bool = False) -> Executor:
    """The executor of a job: in order on one device with ``warm_start``, else on ``scheduler`` (an address
    or a ``distributed.Client``) when given, else on the local ``devices``."""
    devices = list(devices)
    if warm_start:
        if scheduler or len(devices) != 1:
            raise InputError("warm_start: frame t starts from frame t - 1, so the frames run in order on one device "
                             "(no scheduler, one device)")
        return InOrder(devices[0])
    return DaskCluster(scheduler) if scheduler else LocalDevices(devices)


def _check_devices(devices, dtype) -> None:
    """Every device opens (an unknown one fails here), its compiler builds a trivial kernel (a device the
    ``cm2cl devices`` table marks as not compiling fails here, before any output) and, for float64, it
    has fp64."""
    from ..device import compiler_works, get_runtime
    from ..errors import DeviceError

    for d in devices:
        rt = get_runtime(d)
        ok, reason = compiler_works(rt.device)
        if not ok:
            raise DeviceError(f"device '{rt.caps.name}': its OpenCL compiler cannot build kernels ({reason}); "
                              "a device that cannot compile: docs/install.md, 'When you need Debian's "
                              "pocl-opencl-icd'")
        if np.dtype(dtype) == np.float64:
            rt.check_dtype(np.dtype(dtype))

"""The one place that builds OpenCL programs.

Sources are the ``kernels/*.cl`` files, shipped in the wheel as the package
``cm2cl.kernel_src`` (in a source checkout without install, read from ``../kernels``). Each file is
prepended with ``common.cl`` and built lazily, once per (runtime, file, real type, defines),
with ``-D REAL=float|double``; the files of one of the :data:`GROUPS` are built together as one
program. Build failures raise :class:`KernelBuildError` with the file name and the compiler log.
Fast-math options are never used.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from ..errors import KernelBuildError

_SOURCES: dict[str, str] = {}

#: Files built together as one program (a kernel of any of them comes from the group's program): the
#: forward model and the solver use all of them, and PoCL spends a fixed time on every program before it
#: reaches the source, so one program instead of six shortens a cold start (docs/benchmarks.md, "Cold start:
#: what was changed").
GROUPS = (("layout.cl", "fft_conv.cl", "xstep.cl", "splits.cl", "tv.cl", "reduce.cl"),)


def kernel_dir():
    """Folder holding the .cl files: the installed package data, else the source tree."""
    try:
        return resources.files("cm2cl.kernel_src")
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / "kernels"


def source(name: str) -> str:
    """Text of ``kernels/<name>``."""
    if name not in _SOURCES:
        path = kernel_dir() / name
        try:
            _SOURCES[name] = path.read_text(encoding="utf-8")
        except FileNotFoundError as exc:
            raise KernelBuildError(f"kernel source {name!r} not found in {path}") from exc
    return _SOURCES[name]


def build_options(dtype, defines: dict | None = None) -> list[str]:
    dt = np.dtype(dtype)
    if dt == np.float32:
        opts = ["-D", "REAL=float", "-D", "REAL2=float2"]
    elif dt == np.float64:
        opts = ["-D", "REAL=double", "-D", "REAL2=double2", "-D", "REAL_IS_DOUBLE=1"]
    else:
        raise KernelBuildError(f"real type {dt} is not float32 or float64")
    for k, v in sorted((defines or {}).items()):
        opts += ["-D", f"{k}={v}"]
    return opts


def row_width(rt, dtype) -> int:
    """VW of the row kernels (kernels/common.cl): reals per work-item, 32 bytes of them on CPUs (PoCL
    turns a work-item's vectors into SIMD code; 32 bytes, not 64, because PyPI's PoCL before 3.1
    compiles AVX-512 CPUs without AVX-512, see fft_kernels.py), 1 elsewhere (GPUs: neighbouring
    work-items on neighbouring x)."""
    return 32 // np.dtype(dtype).itemsize if rt.caps.kind == "CPU" else 1


def _defines(rt, dtype, defines: dict | None) -> dict:
    """The build's defines: VW for this device unless given."""
    return {"VW": row_width(rt, dtype), **(defines or {})}


def group_of(name: str) -> tuple:
    """The files built in one program with ``kernels/<name>``: its group, or the file alone."""
    return next((g for g in GROUPS if name in g), (name,))


def first_error(log: str) -> str:
    """The build log's first line that says error (else its first non-empty line), trimmed to 200 chars."""
    lines = [ln.strip() for ln in str(log).splitlines() if ln.strip()]
    hit = next((ln for ln in lines if "error" in ln.lower() and not ln.lower().startswith("build on")), None)
    return (hit or (lines[0] if lines else "no build log"))[:200]


def program(rt, name: str, dtype, defines: dict | None = None):
    """The built program holding ``kernels/<name>`` (with the rest of its group) on runtime ``rt``
    (cached on the runtime)."""
    import pyopencl as cl

    opts = build_options(dtype, _defines(rt, dtype, defines))
    files = group_of(name)

    def build():
        text = source("common.cl") + "".join(f'\n#line 1 "{f}"\n' + source(f) for f in files)
        try:
            return cl.Program(rt.context, text).build(options=opts)
        except cl.RuntimeError as exc:  # build failure: pyopencl puts the log in the message
            log = str(exc)
        # raised outside the handler, so neither chained nor in the context: pyopencl's error holds an
        # _ErrorRecord that cannot be pickled, and Dask pickles a worker's error with its cause and context
        summary = (f"OpenCL build of {' + '.join('kernels/' + f for f in files)} failed on '{rt.caps.name}': "
                   f"{first_error(log)}")
        raise KernelBuildError(f"{summary}\n(options {' '.join(opts)})\n{log}", summary=summary, log=log)

    return rt.cached(("program", files, tuple(opts)), build)


def kernel(rt, name: str, kernel_name: str, dtype, defines: dict | None = None):
    """A cached kernel object ``kernel_name`` from ``kernels/<name>``."""
    opts = tuple(build_options(dtype, _defines(rt, dtype, defines)))
    return rt.cached(("kernel", group_of(name), opts, kernel_name),
                     lambda: getattr(program(rt, name, dtype, defines), kernel_name))


def local_memory(nbytes: int):
    """A __local buffer argument of ``nbytes`` bytes."""
    import pyopencl as cl

    return cl.LocalMemory(int(nbytes))


def work_group_size(rt, k, cap: int = 256) -> int:
    """Largest power of two <= the kernel's work-group limit on this device (and <= cap)."""
    import pyopencl as cl

    lim = k.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, rt.device)
    lim = min(int(lim), rt.caps.max_work_group_size, cap)
    n = 1
    while n * 2 <= lim:
        n *= 2
    return n


def launch(rt, k, global_size, *args, cap: int = 64):
    """Run kernel ``k`` over ``global_size`` (1, 2 or 3 dims; the kernel checks its bounds) with a
    local size of (L, 1, 1): L = a power of two within the kernel's work-group limit and ``cap``, because
    PoCL's own choice was slower on the stencil kernels (docs/benchmarks.md, "Measurements behind code choices")."""
    L = work_group_size(rt, k, cap)
    g = [int(s) for s in global_size]
    g[0] = -(-g[0] // L) * L
    local = (L,) + (1,) * (len(g) - 1)
    return k(rt.queue, tuple(g), local, *args)

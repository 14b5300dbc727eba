"""Pick an OpenCL device and record what it can do.

Order of choice: ``CM2CL_DEVICE`` (an index into :func:`list_devices` or a fragment of the
device or platform name), else ``PYOPENCL_CTX`` (pyopencl's own syntax), else the best GPU by
a scoring rule, else the best CPU device (PoCL).  Nothing outside :mod:`cm2cl.device` touches
pyopencl. A :class:`Runtime` (one per device per process) owns every per-device cache: built
programs, kernels, FFT plans and library handles (:meth:`Runtime.cached`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..errors import DeviceError

NO_DEVICE_HELP = (
    "no OpenCL device found. Install an OpenCL driver for your GPU, or the CPU fallback PoCL: "
    "`pip install 'cm2cl[pocl]'` (pocl-binary-distribution) or, on Debian/Ubuntu, "
    "`apt-get install pocl-opencl-icd`."
)


def _cl():
    try:
        import pyopencl as cl
    except ImportError as exc:  # pragma: no cover - pyopencl is a hard dependency
        raise DeviceError(f"pyopencl is not importable ({exc}); `pip install pyopencl`") from exc
    return cl


@dataclass(frozen=True)
class Capabilities:
    """What one OpenCL device can do (sizes in bytes)."""

    index: int
    name: str
    platform: str
    kind: str  # "GPU", "CPU", "ACCELERATOR", "OTHER"
    fp64: bool
    global_mem: int
    max_alloc: int
    max_work_group_size: int
    compute_units: int
    local_mem: int
    opencl_version: str
    platform_version: str = ""
    driver_version: str = ""
    vector_width_float: int = 1   # native SIMD width in float32 / float64 lanes
    vector_width_double: int = 1

    @property
    def implementation(self) -> str:
        """Which OpenCL implementation the device comes from, with its version; for PoCL also where
        it was installed from (the system's package, or PyPI's pocl-binary-distribution)."""
        return implementation_of(self.platform, self.platform_version, self.driver_version)

    @property
    def score(self) -> float:
        """Higher is better: GPUs first, then memory and compute units."""
        kind_rank = {"GPU": 3, "ACCELERATOR": 2, "CPU": 1}.get(self.kind, 0)
        return kind_rank * 1e6 + min(self.global_mem / 2**30, 1e3) * 100 + self.compute_units


def _kind(device) -> str:
    cl = _cl()
    t = device.type
    if t & cl.device_type.GPU:
        return "GPU"
    if t & cl.device_type.ACCELERATOR:
        return "ACCELERATOR"
    if t & cl.device_type.CPU:
        return "CPU"
    return "OTHER"


@lru_cache(maxsize=1)
def _all_devices():
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error:  # e.g. "PLATFORM_NOT_FOUND_KHR" when no ICD is installed
        platforms = []
    out = []
    for p in platforms:
        try:
            out.extend(p.get_devices())
        except cl.Error:
            continue
    return tuple(out)


def capabilities(device, index: int = -1) -> Capabilities:
    return Capabilities(
        index=index,
        name=device.name.strip(),
        platform=device.platform.name.strip(),
        kind=_kind(device),
        fp64=bool(device.double_fp_config),
        global_mem=int(device.global_mem_size),
        max_alloc=int(device.max_mem_alloc_size),
        max_work_group_size=int(device.max_work_group_size),
        compute_units=int(device.max_compute_units),
        local_mem=int(device.local_mem_size),
        opencl_version=device.version.strip(),
        platform_version=device.platform.version.strip(),
        driver_version=device.driver_version.strip(),
        vector_width_float=max(1, int(device.native_vector_width_float)),
        vector_width_double=max(1, int(device.native_vector_width_double)),
    )


def implementation_of(platform: str, platform_version: str, driver_version: str) -> str:
    """'PoCL 3.1+debian (system package)', 'PoCL 3.0-rc2 (PyPI pocl-binary-distribution 3.0)',
    or the platform name and driver version for other vendors."""
    import re

    m = re.search(r"PoCL\s+(\S+)", platform_version)
    if not m:
        return f"{platform} (driver {driver_version})"
    ver = m.group(1)
    try:
        from importlib.metadata import PackageNotFoundError, version
        pypi = version("pocl-binary-distribution")
    except PackageNotFoundError:
        pypi = None
    if re.search(r"debian|ubuntu|fedora|conda", ver, re.I):
        origin = "system package"
    elif pypi and ver.split("-")[0].split("+")[0] == pypi.split("-")[0].split("+")[0].split(".post")[0]:
        origin = f"PyPI pocl-binary-distribution {pypi}"
    else:
        origin = "system or conda install"
    return f"PoCL {ver} ({origin})"


def list_devices() -> list[Capabilities]:
    """Every OpenCL device visible, in a stable order (platform, then device)."""
    return [capabilities(d, i) for i, d in enumerate(_all_devices())]


def _match(spec: str, source: str):
    devices = _all_devices()
    if not devices:
        raise DeviceError(NO_DEVICE_HELP)
    caps = list_devices()
    spec = spec.strip()
    if spec.lstrip("-").isdigit():
        i = int(spec)
        if not 0 <= i < len(devices):
            raise DeviceError(
                f"{source}={spec!r}: device index out of range (0..{len(devices) - 1}); "
                "`cm2cl devices` lists them"
            )
        return devices[i]
    frag = spec.lower()
    hits = [d for d, c in zip(devices, caps)
            if frag in c.name.lower() or frag in c.platform.lower()]
    if not hits:
        names = ", ".join(f"{c.index}: {c.name} ({c.platform})" for c in caps)
        raise DeviceError(f"{source}={spec!r}: no OpenCL device name matches; available: {names}")
    return max(hits, key=lambda d: capabilities(d).score)


def _from_pyopencl_ctx(spec: str):
    """Interpret PYOPENCL_CTX ('platform:device' indices or a name fragment)."""
    cl = _cl()
    platforms = [p for p in cl.get_platforms()]
    parts = spec.split(":")
    try:
        p = platforms[int(parts[0])] if parts[0] else platforms[0]
        devs = p.get_devices()
        return devs[int(parts[1])] if len(parts) > 1 and parts[1] else devs[0]
    except (ValueError, IndexError):
        return _match(spec, "PYOPENCL_CTX")


_PROBE = "__kernel void probe(__global float *a) { a[get_global_id(0)] = 1.0f; }"
_PROBES: dict = {}


def compiler_works(device) -> tuple[bool, str]:
    """Whether the device's OpenCL compiler builds a trivial kernel (cached per device), and why not.

    Some installations list a device whose compiler cannot target the host: PyPI's PoCL 3.0
    (LLVM 14) fails with "unknown target CPU 'generic'" on CPUs its LLVM does not recognise."""
    cl = _cl()
    key = device.int_ptr
    if key not in _PROBES:
        try:
            cl.Program(cl.Context([device]), _PROBE).build()
            _PROBES[key] = (True, "")
        except cl.Error as exc:
            lines = [ln.strip() for ln in str(exc).splitlines() if "error" in ln.lower()]
            _PROBES[key] = (False, (lines[-1] if lines else str(exc).splitlines()[0])[:200])
    return _PROBES[key]


def compiler_report() -> dict:
    """{device index: (compiles, reason)} for every device :func:`list_devices` shows."""
    return {i: compiler_works(d) for i, d in enumerate(_all_devices())}


def select_device(spec: str | int | None = None):
    """Return the pyopencl Device to use.

    ``spec`` (index or name fragment) overrides the environment; ``None`` reads
    ``CM2CL_DEVICE``, then ``PYOPENCL_CTX``, then scores the devices.
    """
    if spec is not None and str(spec).strip() != "":
        return _match(str(spec), "device")
    env = os.environ.get("CM2CL_DEVICE", "").strip()
    if env:
        return _match(env, "CM2CL_DEVICE")
    env = os.environ.get("PYOPENCL_CTX", "").strip()
    if env:
        return _from_pyopencl_ctx(env)
    devices = _all_devices()
    if not devices:
        raise DeviceError(NO_DEVICE_HELP)
    why = []
    for d in sorted(devices, key=lambda d: -capabilities(d).score):
        ok, reason = compiler_works(d)
        if ok:
            return d
        why.append(f"'{d.name.strip()}' ({d.platform.version.strip()[:24]}): {reason}")
    raise DeviceError("no OpenCL device can compile kernels: " + "; ".join(why) + ". "
                      "On Debian/Ubuntu `apt-get install pocl-opencl-icd` gives a working CPU device.")


class Runtime:
    """A context and in-order queue on one device, plus its capabilities.

    One Runtime per device per process (see :func:`get_runtime`); it owns every cache of its
    device (programs, kernels, FFT plans and library handles) through :meth:`cached`.
    """

    def __init__(self, device):
        cl = _cl()
        self.device = device
        self.caps = capabilities(device, _all_devices().index(device) if device in _all_devices() else -1)
        self.context = cl.Context([device])
        self.queue = cl.CommandQueue(self.context)
        self._cache: dict = {}

    def cached(self, key, factory):
        """The object stored under ``key`` (a hashable tuple whose first item names the kind: "program",
        "kernel", "fft", ...), made by ``factory()`` on first use."""
        obj = self._cache.get(key)
        if obj is None:
            obj = factory()
            self._cache[key] = obj
        return obj

    def zeros(self, shape, dtype):
        """A zero-filled device array (pyopencl.array.Array) on this runtime's queue."""
        import pyopencl.array as cla

        return cla.zeros(self.queue, shape, np.dtype(dtype))

    def cached_keys(self, kind: str) -> list:
        """Keys of the cached objects of one kind (for tests and diagnostics)."""
        return [k for k in self._cache if k[0] == kind]

    def check_dtype(self, dtype) -> np.dtype:
        """The real type to compute in; refuse float64 on devices without fp64."""
        dt = np.dtype(dtype)
        if dt not in (np.float32, np.float64):
            raise DeviceError(f"dtype: {dt} is not a supported real type (float32 or float64)")
        if dt == np.float64 and not self.caps.fp64:
            raise DeviceError(
                f"dtype: float64 requested but device '{self.caps.name}' has no fp64 support; "
                "use float32 or another device"
            )
        return dt

    def __repr__(self):
        return f"Runtime({self.caps.name!r} on {self.caps.platform!r})"


_RUNTIMES: dict = {}


def get_runtime(device=None) -> Runtime:
    """The cached Runtime for ``device`` (a Device, index, name fragment, Runtime or None)."""
    if isinstance(device, Runtime):
        return device
    cl = _cl()
    if not isinstance(device, cl.Device):
        device = select_device(device)
    key = device.int_ptr
    if key not in _RUNTIMES:
        _RUNTIMES[key] = Runtime(device)
    return _RUNTIMES[key]


def format_table(caps: list[Capabilities], chosen: int | None = None, compiles=None) -> str:
    """Plain-text table of devices, as printed by ``cm2cl devices``; ``compiles`` maps a device
    index to (ok, reason) from :func:`compiler_works`. Device names are printed whole: users pick a
    device by a fragment of its name (``--device``, ``CM2CL_DEVICE``)."""
    head = ["#", "device", "implementation", "type", "fp64", "global mem", "max buffer", "max wg", "CUs",
            "compiles"]
    rows = []
    for c in caps:
        mark = "*" if chosen is not None and c.index == chosen else " "
        ok = (compiles or {}).get(c.index)
        rows.append([
            f"{mark}{c.index}", c.name, c.implementation[:52], c.kind, "yes" if c.fp64 else "no",
            f"{c.global_mem / 2**30:.1f} GiB", f"{c.max_alloc / 2**30:.2f} GiB",
            str(c.max_work_group_size), str(c.compute_units),
            "?" if ok is None else ("yes" if ok[0] else "NO: " + ok[1][:60]),
        ])
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    line = lambda r: "  ".join(s.ljust(w) for s, w in zip(r, widths)).rstrip()  # noqa: E731
    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(r) for r in rows])

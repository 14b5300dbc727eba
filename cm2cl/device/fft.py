"""Batched 2D FFTs on the device behind one small interface.

Three backends:

* ``cl`` (always available): cm2cl's own kernels (``kernels/fft.cl``, plans in
  :mod:`.fft_kernels`), real-to-complex, 2/3/5/7-smooth sizes (odd ones too; prime factors up to
  13); the spectrum of a (b, py, px) real array is (b, py, px//2 + 1) complex.
* ``vkfft`` (pyvkfft, when importable): real-to-complex, the same sizes and layout as ``cl``.
* ``reikna`` (always available): complex-to-complex, fast on powers of two; the spectrum is
  (b, py, px) complex.  Real input is widened on the device first.

``auto`` picks ``cl`` on CPU devices, where it measured 2.7-3.5x faster than VkFFT (docs/fft.md,
``tools/bench_fft.py``), and ``vkfft`` on other devices when pyvkfft is importable (not measured
here), else ``cl``.

Every kernel downstream is elementwise over the spectrum, so the two layouts need no special
casing: a plane of the spectrum is ``plan.spec_shape[1:]`` (:func:`spectrum_shape`).  Inverse
transforms are normalised (ifft(fft(x)) == x) and may overwrite their input.  No fast-math anywhere.
"""

from __future__ import annotations

import numpy as np

from . import kernels
from ..errors import InputError

BACKENDS = ("cl", "vkfft", "reikna")
#: backends whose spectrum holds only the px//2 + 1 non-negative frequencies of the last axis
HALF_SPECTRUM = ("cl", "vkfft")


def _vkfft_importable() -> bool:
    try:
        import pyvkfft.opencl  # noqa: F401
    except Exception:  # pyvkfft missing, or built without the OpenCL backend
        return False
    return True


def available_backends() -> list[str]:
    return [b for b in BACKENDS if b != "vkfft" or _vkfft_importable()]


def resolve_backend(name: str | None = "auto", rt=None) -> str:
    """'auto' -> ``cl`` on CPU devices (or when ``rt`` is not given), else ``vkfft`` if importable,
    else ``cl`` (the rule and its measurements: docs/fft.md); an explicit name must be available."""
    name = (name or "auto").lower()
    if name == "auto":
        if rt is not None and rt.caps.kind != "CPU" and _vkfft_importable():
            return "vkfft"
        return "cl"
    if name not in BACKENDS:
        raise InputError(f"fft backend: unknown backend {name!r} (known: auto, {', '.join(BACKENDS)})")
    if name == "vkfft" and not _vkfft_importable():
        raise InputError("fft backend: 'vkfft' requested but pyvkfft is not importable "
                         "(pip install 'cm2cl[vkfft]')")
    return name


def _is_smooth(n: int, primes=(2, 3, 5, 7)) -> bool:
    for p in primes:
        while n % p == 0:
            n //= p
    return n == 1


def good_size(n: int, backend: str) -> int:
    """Smallest size >= n on which ``backend`` is fast: a power of two for reikna, else even and
    2/3/5/7-smooth (real-to-complex through the half-length transform)."""
    n = max(int(n), 1)
    if backend == "reikna":
        return 1 << (n - 1).bit_length()
    m = n + (n % 2)
    while not _is_smooth(m):
        m += 2
    return m


def spectrum_shape(real_shape, backend: str) -> tuple:
    """Shape of the spectrum of a (..., py, px) real array: px//2 + 1 in the last axis for the
    half-spectrum backends, px for reikna."""
    *lead, px = (int(s) for s in real_shape)
    return tuple(lead) + ((px // 2 + 1) if backend in HALF_SPECTRUM else px,)


def complex_dtype(dtype) -> np.dtype:
    return np.dtype(np.complex64 if np.dtype(dtype) == np.float32 else np.complex128)


class FFTPlan:
    """Forward and inverse 2D FFT over the last two axes of a (batch, py, px) real array."""

    def __init__(self, rt, shape, batch: int, dtype, backend: str):
        self.rt = rt
        self.dtype = np.dtype(dtype)
        self.cdtype = complex_dtype(dtype)
        self.backend = backend
        py, px = (int(s) for s in shape)
        self.real_shape = (int(batch), py, px)
        self.spec_shape = spectrum_shape(self.real_shape, backend)
        if backend == "cl":
            from .fft_kernels import ClPlan

            self._cl = ClPlan(rt, self.real_shape, self.dtype)
        elif backend == "vkfft":
            from pyvkfft.opencl import VkFFTApp

            self._app = VkFFTApp(self.real_shape, self.dtype, rt.queue, ndim=2, inplace=False,
                                 r2c=True, r2c_odd=bool(px % 2), norm=1)
        elif backend == "reikna":
            from reikna.core import Type
            from reikna.fft import FFT

            self._fft = FFT(Type(self.cdtype, self.spec_shape), axes=(1, 2)).compile(_reikna_thread(rt))
            self._r2c = kernels.kernel(rt, "layout.cl", "real_to_complex", self.dtype)
            self._re = kernels.kernel(rt, "layout.cl", "complex_real_part", self.dtype)
        else:
            raise InputError(f"fft backend: unknown backend {backend!r}")

    @property
    def scratch_bytes(self) -> int:
        """Device bytes the FFT library allocates for this plan besides input and output: VkFFT's
        temporary buffer (pyvkfft's ``tmp_buffer_nbytes``), cm2cl's pass-path scratch; reikna's own
        temporaries are not reported (0)."""
        if self.backend == "cl":
            return int(self._cl.scratch_bytes)
        if self.backend == "vkfft":
            return int(getattr(self._app, "tmp_buffer_nbytes", 0) or 0)
        return 0

    def _check(self, a, shape, dtype, what):
        if tuple(a.shape) != tuple(shape) or a.dtype != dtype:
            raise InputError(f"{what}: expected {shape} {np.dtype(dtype)}, got {a.shape} {a.dtype}")

    def forward(self, src, dst):
        """dst (spectrum) <- FFT(src (real)); src is left intact."""
        self._check(src, self.real_shape, self.dtype, "fft input")
        self._check(dst, self.spec_shape, self.cdtype, "fft output")
        if self.backend == "cl":
            self._cl.forward(src, dst)
        elif self.backend == "vkfft":
            self._app.fft(src, dst)
        else:
            n = np.uint64(src.size)
            kernels.launch(self.rt, self._r2c, (src.size,), dst.data, src.data, n)
            self._fft(dst, dst, inverse=0)
        return dst

    @property
    def fuses_xstep(self) -> bool:
        """Whether :meth:`inverse_xstep` is available: cm2cl's own FFT with its column lines in local
        memory (cm2cl.device.fft_kernels.ClPlan.inverse_xstep)."""
        return self.backend == "cl" and self._cl.fuses_xstep

    def inverse_xstep(self, src, dst, hs, hr, hx, c, mu_v):
        """dst (real) <- IFFT((conj(hs) hr + src - mu_v conj(hs) hx) / c), normalised: the x step's last stage
        fused into the inverse (only where :attr:`fuses_xstep`); hr, hx: one spectrum plane each; src is
        overwritten."""
        self._check(src, self.spec_shape, self.cdtype, "ifft input")
        self._check(hs, self.spec_shape, self.cdtype, "PSF spectra")
        self._check(dst, self.real_shape, self.dtype, "ifft output")
        self._cl.inverse_xstep(src, dst, hs, hr, hx, c, mu_v)
        return dst

    def inverse(self, src, dst):
        """dst (real) <- IFFT(src (spectrum)), normalised; src may be overwritten."""
        self._check(src, self.spec_shape, self.cdtype, "ifft input")
        self._check(dst, self.real_shape, self.dtype, "ifft output")
        if self.backend == "cl":
            self._cl.inverse(src, dst)
        elif self.backend == "vkfft":
            self._app.ifft(src, dst)
        else:
            self._fft(src, src, inverse=1)
            n = np.uint64(dst.size)
            kernels.launch(self.rt, self._re, (dst.size,), dst.data, src.data, n)
        return dst


def _reikna_thread(rt):
    def make():
        from reikna.cluda import ocl_api  # reikna >= 0.9: NumPy 2 compatible, nothing to patch

        return ocl_api().Thread(rt.queue)

    return rt.cached(("reikna_thread",), make)


def get_plan(rt, shape, batch: int, dtype, backend: str = "auto") -> FFTPlan:
    """Cached plan on runtime ``rt`` for (batch, *shape) real arrays of ``dtype``."""
    backend = resolve_backend(backend, rt)
    dtype = rt.check_dtype(dtype)
    key = ("fft", backend, tuple(int(s) for s in shape), int(batch), dtype.str)
    return rt.cached(key, lambda: FFTPlan(rt, shape, batch, dtype, backend))

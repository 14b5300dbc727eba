"""Plans for cm2cl's own FFT kernels (``kernels/fft.cl``): the "cl" backend of :mod:`.fft`.

How the kernels are made: one generic source, specialised per line length by ``-D`` defines that
this module computes (the line length ``FFT_N``, and for each pass its radix ``FFT_R<p>`` and
sub-transform length ``FFT_S<p>``), so every pass is unrolled with constant radix and strides.
One program per (line length, row mode, columns per group, real type), built lazily and cached on
the runtime like every other program.

A 2D real-to-complex transform of (batch, py, px) reals gives (batch, py, px//2 + 1) complex (the
layout of VkFFT and numpy's rfft2):

* rows: even px as the complex transform of px/2 points (x_2i + i x_2i+1) untangled in the same
  kernel; odd px as the complex transform of the line widened to complex;
* columns: in place on the spectrum, ``FFT_C`` neighbouring columns per work-group so that global
  reads and writes are coalesced.

Where a line (or a block of columns) fits in local memory, one kernel does all its passes (one
read and one write of global memory per dimension); otherwise a kernel per radix pass goes
through global memory (needs a scratch buffer of one spectrum).  Radices 8, 4, 2, 9, 3, 5, 7,
11 and 13; other prime factors are refused.  Twiddles are computed in double on the host.
"""

from __future__ import annotations

import re

import numpy as np

from . import kernels
from ..errors import InputError

__all__ = ["RADICES", "factor", "ClPlan"]

#: radices in the order the passes use them; 8 before 4 before 2, 9 before 3: fewer passes (radix 9 and 16
#: measured in docs/benchmarks.md, "Measurements behind code choices")
RADICES = (8, 4, 2, 9, 3, 5, 7, 11, 13)
MAX_PASSES = 12


def factor(n: int, what: str = "fft size") -> list[int]:
    """The radices of the passes of an n-point transform (product n); InputError if n has a prime
    factor above 13."""
    n = int(n)
    if n < 1:
        raise InputError(f"{what}: {n} is not a positive length")
    out, m = [], n
    for r in RADICES:
        while m % r == 0:
            out.append(r)
            m //= r
    if m != 1:
        raise InputError(f"{what}: {n} has the prime factor {_smallest_factor(m)} > 13, which the 'cl' FFT "
                         "backend does not transform; pad to a 2/3/5/7-smooth size (fft.good_size)")
    if len(out) > MAX_PASSES:
        raise InputError(f"{what}: {n} needs {len(out)} radix passes (at most {MAX_PASSES})")
    return out


def _smallest_factor(m: int) -> int:
    p = 2
    while m % p:
        p += 1
    return p


def _line_defines(n: int) -> dict:
    radices = factor(n)
    d = {"FFT_N": n, "FFT_NPASS": len(radices)}
    ns = 1
    for p, r in enumerate(radices):
        d[f"FFT_R{p}"] = r
        d[f"FFT_S{p}"] = ns
        ns *= r
    return d


def _lines_per_item(caps, dtype) -> int:
    """Lines a work-item transforms together on a CPU (SIMD across lines): the largest of 1, 2,
    4, 8 within the device's native vector width of the real type: more lines per work-item were faster
    up to 8 (docs/benchmarks.md, "Measurements behind code choices")."""
    width = caps.vector_width_float if np.dtype(dtype) == np.float32 else caps.vector_width_double
    v = 1
    while v * 2 <= min(_max_lines(caps, dtype), width):
        v *= 2
    return v


#: PoCL before 3.1 (PyPI's pocl-binary-distribution 3.0, LLVM 14) reports this AVX-512 CPU's native
#: widths (16 floats) but compiles without AVX-512 ("AVX vector argument ... without 'avx512f' enabled
#: changes the ABI"): 512-bit vectors of lines made it abort the process ("LLVM ERROR: Do not know how to
#: scalarize this operator's operand!", float32, 8 lines) or lose its kernels (float64, 4 lines:
#: INVALID_KERNEL_NAME). Lines of a work-item then fill at most 256 bits: 4 complex float32, 2 float64.
_OLD_POCL_VECTOR_BYTES = 32


def _max_lines(caps, dtype) -> int:
    """Most lines a work-item may transform together on this device (the vector types' limit)."""
    return _OLD_POCL_VECTOR_BYTES // _cplx_item(dtype) if _old_pocl(caps) else 8


def _old_pocl(caps) -> bool:
    m = re.search(r"PoCL\s+(\d+)\.(\d+)", caps.platform_version or "")
    return bool(m) and (int(m.group(1)), int(m.group(2))) < (3, 1)


def _cplx_item(dtype) -> int:
    return 2 * np.dtype(dtype).itemsize


class ClPlan:
    """Batched 2D real <-> complex FFT of (batch, py, px) with cm2cl's kernels.

    ``local_limit`` (bytes; default the device's local memory) caps the local memory a line
    kernel may use; lines that do not fit go through the pass kernels.  ``group`` = (work-items
    per work-group, work-items per line[, lines per work-item]) wanted for rows and columns alike,
    instead of the per-device choice (both for tests: they run the GPU shapes on a CPU device and
    force the pass path).
    """

    def __init__(self, rt, real_shape, dtype, local_limit: int | None = None, group=None):
        import pyopencl as cl

        self.rt = rt
        self.dtype = np.dtype(dtype)
        self.cdtype = np.dtype(np.complex64 if self.dtype == np.float32 else np.complex128)
        b, py, px = (int(s) for s in real_shape)
        if min(b, py, px) < 1:
            raise InputError(f"fft shape: {real_shape} has an empty axis")
        self.batch, self.py, self.px = b, py, px
        self.half = px % 2 == 0
        self.nrow = px // 2 if self.half else px  # complex length of a row transform
        self.w = px // 2 + 1
        self.spec_shape = (b, py, self.w)
        factor(self.nrow, f"fft size px={px}" + (f" (rows as {self.nrow} complex points)" if self.half else ""))
        factor(py, f"fft size py={py}")
        limit = rt.caps.local_mem if local_limit is None else int(local_limit)
        limit = min(limit, rt.caps.local_mem) - 256  # room for the kernel's own locals
        cpu = rt.caps.kind == "CPU"

        self.tw_row = self._table(self.nrow)
        self.tw_col = self._table(py)
        self.twr = self._table(2 * self.nrow, self.nrow + 1)  # exp(-pi i k / nrow), k <= nrow
        self._scratch = None

        # Work-group shapes: V lines per work-item x C work-items per group x T work-items per line.
        # CPUs: V from the SIMD width (_lines_per_item), C = T = 1, since a CPU work-group runs as one
        # loop and barriers cost more than they share (docs/benchmarks.md, "Measurements behind code
        # choices"). GPUs (not measured): V = 1; rows one line per group and wide T; columns 16 per
        # group (coalesced reads), the rest in T.
        defs = _line_defines(self.nrow) | ({"FFT_HALF": 1} if self.half else {})
        vec = _lines_per_item(rt.caps, self.dtype) if cpu else 1
        row_ct, col_ct = ((1, 1 if cpu else 256, vec), (1 if cpu else 16, 1 if cpu else 256, vec)) \
            if group is None else ((tuple(group) + (1,))[:3], (tuple(group) + (1,))[:3])
        # a forced shape (tests) still keeps to the lines the device's compiler can vectorise
        row_ct, col_ct = ((c, t, min(v, _max_lines(rt.caps, self.dtype))) for c, t, v in (row_ct, col_ct))
        rows = self._line_kernels(defs, ("rows_r2c", "rows_c2r"), *row_ct, limit, 1)
        self.rows_local = rows is not None
        if rows:
            (self._r2c, self._c2r), self.row_c, self.row_t, self.row_v = rows
        cols = self._line_kernels(_line_defines(py), ("cols",), *col_ct, limit, 1 if cpu or self.w < 4 else 4)
        self.cols_local = cols is not None
        if cols:
            (self._k_cols,), self.col_c, self.col_t, self.col_v = cols
            self._col_defs = _line_defines(py) | {"FFT_C": self.col_c, "FFT_VEC": self.col_v}
        self._k_cols_x = None
        if not (self.rows_local and self.cols_local):
            self._pack = {name: kernels.kernel(rt, "fft.cl", name, self.dtype)
                          for name in ("pack_real", "untangle", "tangle", "unpack_real")}
        self._cl = cl

    def _line_kernels(self, defs, names, want_c, want_t, want_v, limit, min_c):
        """Kernels `names` built for lines of defs["FFT_N"] points, each work-item transforming V
        neighbouring lines together, C work-items per work-group: the largest power of two C <=
        want_c (V = want_v, halved down to 1 when nothing fits) whose two local buffers fit in
        `limit` bytes and within the kernels' work-group limit; T = work-items per line (<= want_t,
        <= n/2).  None if no C >= min_c fits (the lines then go through the pass kernels)."""
        n, item = defs["FFT_N"], _cplx_item(self.dtype)
        v = want_v
        while v >= 1:
            c = want_c
            while c >= max(1, min_c):
                if 2 * n * c * v * item <= limit:
                    ks = tuple(kernels.kernel(self.rt, "fft.cl", name, self.dtype,
                                              defs | {"FFT_C": c, "FFT_VEC": v}) for name in names)
                    L = min(kernels.work_group_size(self.rt, k, 256) for k in ks)
                    if L >= c:
                        return ks, c, max(1, min(want_t, L // c, n // 2)), v
                c //= 2
            v //= 2
        return None

    # ---- tables and scratch -------------------------------------------------------------------
    def _table(self, n: int, count: int | None = None):
        """exp(-2 pi i m / n) for m < count (default n), computed in double, cached on the runtime."""
        import pyopencl.array as cla

        count = n if count is None else count

        def make():
            m = np.arange(count, dtype=np.float64)
            return cla.to_device(self.rt.queue, np.exp(-2j * np.pi * m / n).astype(self.cdtype))

        return self.rt.cached(("fft_twiddles", n, count, self.cdtype.str), make)

    @property
    def scratch_bytes(self) -> int:
        """Device bytes this plan allocates besides its tables: none when every line fits in local
        memory, else two buffers of max(row lines, spectrum) complex values for the pass path."""
        if self.rows_local and self.cols_local:
            return 0
        return 2 * self._scratch_len() * self.cdtype.itemsize

    def _scratch_len(self) -> int:
        return max(self.batch * self.py * self.nrow, self.batch * self.py * self.w)

    def _scratch_buffers(self):
        import pyopencl.array as cla

        if self._scratch is None:
            n = self._scratch_len()
            self._scratch = (cla.empty(self.rt.queue, (n,), self.cdtype), cla.empty(self.rt.queue, (n,), self.cdtype))
        return self._scratch

    # ---- passes through global memory ---------------------------------------------------------
    def _pass_kernel(self, name, r):
        return kernels.kernel(self.rt, "fft.cl", name, self.dtype, {"FFT_R": r})

    def _rows_passes(self, a, b, lines):
        """Transform `lines` lines of nrow complex in a (forward); returns the buffer holding them."""
        n, ns = self.nrow, 1
        for r in factor(n):
            k = self._pass_kernel("pass_rows", r)
            kernels.launch(self.rt, k, (n // r, lines), b.data, a.data, np.int32(n), np.int32(ns),
                           self.tw_row.data)
            a, b, ns = b, a, ns * r
        return a

    def _cols(self, spec, inverse: bool):
        """Columns of the spectrum in place (inverse: conjugated in and out, unnormalised)."""
        n = self.py
        if self.cols_local:
            g = (-(-self.w // (self.col_c * self.col_v)) * self.col_c, self.col_t, self.batch)
            self._k_cols(self.rt.queue, g, (self.col_c, self.col_t, 1), spec.data, np.int32(self.w),
                         np.int32(inverse), self.tw_col.data)
            return
        radices = factor(n)
        a, b, ns = spec.data, self._scratch_buffers()[0].data, 1
        for p, r in enumerate(radices):
            k = self._pass_kernel("pass_cols", r)
            first, last = p == 0, p == len(radices) - 1
            kernels.launch(self.rt, k, (self.w, n // r, self.batch), b, a, np.int32(n), np.int32(self.w),
                           np.int32(ns), np.int32(inverse and first), np.int32(inverse and last),
                           self.tw_col.data)
            a, b, ns = b, a, ns * r
        if a is not spec.data:
            self._cl.enqueue_copy(self.rt.queue, spec.data, a, byte_count=spec.nbytes)

    # ---- the transforms -------------------------------------------------------------------------
    @property
    def fuses_xstep(self) -> bool:
        """Whether :meth:`inverse_xstep` runs the x step's last stage inside the column pass (lines in
        local memory); otherwise the solver runs xstep_solve before :meth:`inverse`."""
        return self.cols_local

    def inverse_xstep(self, src, dst, hs, hr, hx, c, mu_v):
        """:meth:`inverse` of X_i = (B_i - mu_v conj(H_i) HX) / c, B_i = conj(H_i) R + T_i, for T = src (batch
        planes, overwritten), H = hs (same shape), R = hr and HX = hx (one spectrum plane each):
        kernels/xstep.cl's xstep_solve, fused into the column pass's loads (one read and one write of the
        spectra fewer)."""
        if not self.fuses_xstep:
            raise ValueError("inverse_xstep needs the column lines in local memory (fuses_xstep)")
        if self._k_cols_x is None:
            self._k_cols_x = kernels.kernel(self.rt, "fft.cl", "cols", self.dtype, self._col_defs | {"FFT_XSTEP": 1})
        R = self.dtype.type
        g = (-(-self.w // (self.col_c * self.col_v)) * self.col_c, self.col_t, self.batch)
        self._k_cols_x(self.rt.queue, g, (self.col_c, self.col_t, 1), src.data, np.int32(self.w), np.int32(1),
                       self.tw_col.data, hs.data, hr.data, hx.data, R(mu_v), R(1.0 / c))
        return self._rows_inverse(src, dst)

    def forward(self, src, dst):
        """dst (batch, py, px//2+1) complex <- 2D FFT of src (batch, py, px) real."""
        lines = self.batch * self.py
        if self.rows_local:
            C, T = self.row_c, self.row_t
            self._r2c(self.rt.queue, (-(-lines // (C * self.row_v)) * C, T), (C, T), dst.data, src.data, self.tw_row.data,
                      self.twr.data, np.int32(lines))
        else:
            a, b = self._scratch_buffers()
            kernels.launch(self.rt, self._pack["pack_real"], (self.nrow, lines), a.data, src.data,
                           np.int32(self.nrow), np.int32(self.half))
            z = self._rows_passes(a, b, lines)
            kernels.launch(self.rt, self._pack["untangle"], (self.w, lines), dst.data, z.data,
                           np.int32(self.nrow), np.int32(self.half), self.twr.data)
        self._cols(dst, False)
        return dst

    def inverse(self, src, dst):
        """dst (batch, py, px) real <- normalised inverse 2D FFT of src (overwritten)."""
        self._cols(src, True)
        return self._rows_inverse(src, dst)

    def _rows_inverse(self, src, dst):
        """The row pass of :meth:`inverse` (columns done)."""
        lines = self.batch * self.py
        scale = self.dtype.type(1.0 / (self.nrow * self.py))
        if self.rows_local:
            C, T = self.row_c, self.row_t
            self._c2r(self.rt.queue, (-(-lines // (C * self.row_v)) * C, T), (C, T), dst.data, src.data, self.tw_row.data,
                      self.twr.data, scale, np.int32(lines))
        else:
            a, b = self._scratch_buffers()
            kernels.launch(self.rt, self._pack["tangle"], (self.nrow, lines), a.data, src.data,
                           np.int32(self.nrow), np.int32(self.half), self.twr.data)
            z = self._rows_passes(a, b, lines)
            kernels.launch(self.rt, self._pack["unpack_real"], (self.nrow, lines), dst.data, z.data,
                           np.int32(self.nrow), np.int32(self.half), scale)
        return dst

"""The CM2 reconstruction (paper Eq. 4) by ADMM on an OpenCL device.

    minimise 1/2 ||C H x - y||^2 + l1 ||x||_1 + tv TV_3D(x)   subject to x >= 0

Splits (DESIGN.md section 3): v = Hx (crop-aware data step), w = x (l1 + non-negativity),
u = x (TV prox by warm-started dual iterations), and the exact x step by Sherman-Morrison per
lateral frequency. Every step is a kernel in ``kernels/``; inside the loop the only transfer
between host and device is one small buffer of reduced scalars per iteration.

The lean state: per voxel the iteration keeps 7 real volumes (x, the previous x or scratch g, s, u and
the TV dual p = (px, py, pz)) and 2 complex ones (the x spectra, the PSF spectra). w, rho and eta are
not stored; every step that needs them derives them exactly (kernels: split_w, split_rho, div_step):

* w split: s = x + rho_old / mu_w, the l1 prox's argument, so that w = max(s - c / mu_w, 0)
  (c = l1 l1w[z]) and rho = rho_old + mu_w (x - w) = min(mu_w s, c). The weight and penalty s was made
  with are :attr:`ADMMSolver.l1_split`; they stay with s when the penalty policy changes mu_w, so rho
  (the unscaled dual) and w are the same before and after the change. (Of the exact one-scalar forms
  this one keeps w = 0 and rho as accurate as explicit storage; mu_w x + rho - c would cost rho its
  accuracy wherever |rho| << c, i.e. in the background.)
* u split: eta = eta_old + mu_u (x - u) with u = z - tau div p, z = x + eta_old / mu_u and
  tau = tv / mu_u gives eta = tv div p (p as the last dual iterations left it; :attr:`ADMMSolver.tv_split`
  is the tv). z is stored in the x spectra's buffer while the TV prox runs (the spectra are not needed
  between the x step's inverse FFT and the next x step).
* x step: its object-domain rhs mu_u u - eta + mu_w w - rho is made by tv_finish, which has u and eta
  at hand, into g (free by then) for the penalties of its iteration; the next x step uses it where they
  still hold (:attr:`ADMMSolver.rhs_for`) and otherwise makes it again (rhs_volume: the first iteration,
  and after the penalty policy changed mu_u or mu_w).

The lean layout (``lean``, :func:`cm2cl.solver.memory.plan_layout`'s choice where the whole state does
not fit): the x spectra are one slab (of LEAN_SLAB_PLANES planes) per part, not a volume, so each plane
holds the 7 real volumes and its PSF spectra only. The x step transforms each slab's rhs (in g) once for
the spectral sum and again for the solve, whose inverse writes the new x over it; the TV prox keeps z in
g (free since the w split) and its residual in the slab of spectra, the slabs visited last first, and
the first residual plane of the slab just visited in the plane ``r_next`` for the dual step of the slab
before it; TV finish reads z from g and writes the rhs over it, element by element. Same iterates, one
more forward FFT per iteration.

The float64 numpy twin is :func:`cm2cl.reference.admm` (tests and tools only).
"""

from __future__ import annotations

import logging

import numpy as np

from .. import validate
from ..device import kernels
from ..device.runtime import get_runtime
from ..device.volume import fill, scale
from ..errors import DeviceError, InputError
from .forward import centered_psf, choose_padded_shape, crop_offsets, min_padded_shape
from ..device.fft import complex_dtype, get_plan, resolve_backend
from .control import Control, ProblemScale
from .params import ADMMParams
from .parts import Part
from .result import Reconstruction
from .memory import fft_scratch_per_plane, memory_estimate, plan_layout

# Slots of the per-iteration reduction buffer, in the order each fused kernel writes them.
(DX2, X2, L1, TV, RW2, SW2, W2, RHO2,          # update_w
 RV2, SV2, DATA2, HX2, V2, XI2,                # update_v
 RU2, SU2, U2, ETA2) = range(18)               # tv_finish
NSLOTS = 18
#: volumes of the state the iteration derives instead of storing (module docstring)
DERIVED = ("w", "rho", "eta")

log = logging.getLogger(__name__)
#: partials per sum of the fused update-and-reduce kernels at most (row kernels, kernels/common.cl:
#: a work-item per VW x of `rows` rows, all planes): enough work-items for a GPU's cores, few enough
#: that reduce_partials' pass stays small next to a volume's. Also the CPUs' cap: with 2^14 the fig3
#: grid (1944 x 2592, 21 planes) took 39 rows per work-item, and a work-item walking 39 rows x 21
#: planes at a plane's stride ran tv_finish at 0.23x the copy rate (519 ms) and update_w at 0.33x
#: (162 ms); with 2^18 (4 rows) 178 and 83 ms, reduce_partials 0.6 -> 5.1 ms (PoCL, 2 cores)
PARTIALS = 2**18
#: elements per work-item of the row kernels at least (where the columns are that long): the partials
#: then take at most 1/32 of the volume they sum (the memory model counts on it)
ROW_ELEMENTS = NSLOTS * 32
#: planes per launch of xstep_accumulate on CPUs (more launches, each continuing the sum: the same
#: additions). A work-item reads each plane's T and H at once, 2 x 16 streams for a 16-plane slab, which
#: is more than this CPU's prefetchers follow: min of 15 alternating launches (PoCL 3.1, 2 cores, float32)
#: over 16 x 540 x 512 4.5 ms in one launch, 1.6 ms in runs of 4 or 6 planes, 1.8 with 8, 2.5 with 2; over
#: 16 x 648 x 864 6.8 ms, 4.6 / 4.2 / 5.2 / 7.4 ms. GPUs (not measured) keep one launch per slab.
ACC_PLANES = 4
#: the row kernels (kernels/common.cl), built with the part's VW
ROW_KERNELS = (("splits.cl", "update_w"), ("splits.cl", "update_v"), ("tv.cl", "tv_finish"), ("tv.cl", "tv_residual"),
               ("tv.cl", "tv_dual_step"), ("tv.cl", "tv_eta"), ("xstep.cl", "rhs_volume"),
               ("xstep.cl", "xstep_accumulate"), ("xstep.cl", "xstep_solve"))

def pixel_weights(weights, shape) -> np.ndarray:
    """The data term's per-pixel weights: ones, or ``weights`` checked (the sensor's shape, finite, >= 0,
    not all zero)."""
    if weights is None:
        return np.ones(shape)
    w = np.asarray(weights, np.float64)
    if w.shape != tuple(shape):
        raise InputError(f"weights: shape {w.shape} does not match the measurement {tuple(shape)}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise InputError("weights: must be finite and >= 0")
    if not np.any(w > 0):
        raise InputError("weights: every pixel is masked")
    return w


def plane_weights(psf_n, power: float) -> np.ndarray:
    """Each plane's weight in the l1 term: ||h_i||^power / mean_j ||h_j||^power (ones for power 0)."""
    norms = np.sqrt(np.sum(np.asarray(psf_n, np.float64).reshape(psf_n.shape[0], -1) ** 2, axis=1))
    c = norms ** float(power)
    return c / np.mean(c)


def _padded_arg(padded_shape) -> tuple[int, int]:
    """``padded_shape`` as two positive integers, or an InputError naming it."""
    try:
        P = tuple(padded_shape)
        ok = len(P) == 2 and all(isinstance(n, (int, np.integer)) and not isinstance(n, bool) and n > 0 for n in P)
    except TypeError:
        ok = False
    if not ok:
        raise InputError(f"padded_shape: expected two positive integers (Py, Px), got {padded_shape!r}")
    return int(P[0]), int(P[1])


class ADMMSolver:
    """Device state of one reconstruction problem (PSF stack + parameters).

    The depth planes are laid out by :func:`cm2cl.solver.memory.plan_layout` over ``devices`` (default:
    ``device`` alone): resident when they fit the memory (``max_memory`` caps each device, for planning
    and tests), else streamed in slabs from host memory (``stream``: 'auto', True or False). Every
    layout computes the same iterates (:mod:`cm2cl.solver.parts`)."""

    def __init__(self, psf, params: ADMMParams, *, dtype=np.float32, backend="auto", device=None,
                 padded_shape=None, max_slab_planes=None, devices=None, max_memory=None, stream="auto",
                 overlap="auto", lean="auto"):
        psf = validate.psf_stack(psf, "psf")
        # a first normalisation in float64 on the host, so that no input scale over- or underflows
        # in float32 on the device: sum_i (sum |h_i|)^2 bounds max_k sum_i |H_i(k)|^2 from above
        self.psf_prescale = 1.0
        psf = np.asarray(psf, np.float64)   # float32 input too: its sums in float64
        if params.normalize:
            self.psf_prescale = 1.0 / np.sqrt(np.sum(np.abs(psf).reshape(psf.shape[0], -1).sum(axis=1) ** 2))
        psf = psf * self.psf_prescale
        self.p = params
        rts = [get_runtime(d) for d in (devices if devices else [device])]
        self.rt = rt = rts[0]
        self.dtype = rt.check_dtype(dtype)
        for other in rts[1:]:
            other.check_dtype(dtype)
        self.backend = resolve_backend(backend, rt)
        for other in rts[1:]:
            if resolve_backend(backend, other) != self.backend:
                raise InputError(f"devices: the FFT backend '{backend}' resolves differently across the devices "
                                 "(their spectra must share one layout); name one backend, e.g. 'cl'")
        sensor = psf.shape[1:]
        P = _padded_arg(padded_shape) if padded_shape is not None else choose_padded_shape(sensor, self.backend)
        if max_slab_planes is not None and (isinstance(max_slab_planes, bool)
                                            or not isinstance(max_slab_planes, (int, np.integer))
                                            or max_slab_planes < 1):
            raise InputError(f"max_slab_planes: expected an integer >= 1 or None, got {max_slab_planes!r}")
        need = min_padded_shape(sensor, psf)
        if any(p < max(n, m) for p, n, m in zip(P, need, sensor)):
            raise InputError(f"padded_shape: {P} is smaller than sensor + PSF support - 1 = {need}")
        self.P, self.M, self.nz = P, tuple(sensor), psf.shape[0]
        scratch = fft_scratch_per_plane(rt, P, self.dtype, self.backend)
        self.layout = plan_layout(self.nz, P, self.dtype, self.backend, rts, max_memory=max_memory,
                                  stream=stream, max_slab_planes=max_slab_planes, scratch_per_plane=scratch,
                                  overlap=overlap, lean=lean)
        self.memory = memory_estimate(self.nz, P, self.dtype, self.backend, scratch,
                                      lean_slab=self.layout[0].slab_planes if self.layout[0].lean else None)
        self.cdtype = complex_dtype(self.dtype)
        spec_plane = get_plan(rt, P, 1, self.dtype, self.backend).spec_shape[1:]
        self.nfreq = int(np.prod(spec_plane))
        self.offsets = crop_offsets(self.M, P)
        oy, ox = self.offsets
        self.crop = (slice(oy, oy + self.M[0]), slice(ox, ox + self.M[1]))
        self.parts = [Part(lp.rt, lp.z0, lp.z1, P, spec_plane, self.dtype, self.cdtype,
                           slab_planes=lp.slab_planes, streamed=lp.streamed, overlap=lp.overlap, lean=lp.lean)
                      for lp in self.layout]
        #: lean layout (the planner's choice, all parts alike): one slab of spectra per part
        self.lean = any(part.lean for part in self.parts)
        names = [("fft_conv.cl", "spectral_power"), ("xstep.cl", "rhs_volume"), ("xstep.cl", "rhs_plane"),
                 ("xstep.cl", "xstep_accumulate"), ("xstep.cl", "xstep_hx"), ("xstep.cl", "xstep_solve"),
                 ("splits.cl", "update_w"), ("splits.cl", "update_v"), ("splits.cl", "split_state"),
                 ("tv.cl", "tv_residual"), ("tv.cl", "tv_dual_step"), ("tv.cl", "tv_finish"), ("tv.cl", "tv_eta"),
                 ("reduce.cl", "reduce_partials")]
        for part in self.parts:
            part.k = {n: kernels.kernel(part.rt, f, n, self.dtype) for f, n in names}
            self._row_layout(part, kernels.row_width(part.rt, self.dtype))
            part.out = part.rt.zeros(NSLOTS, self.dtype)
            part.plan2d = get_plan(part.rt, P, 1, self.dtype, self.backend)

        # PSF spectra (computed on each part's device) and the ||H|| = 1 normalisation from the
        # spectral power sum_i |H_i|^2, summed over the parts in float64.
        nf = np.uint64(self.nfreq)
        for part in self.parts:
            hn2 = part.planes["hn2"]
            for j, n, a in part.slabs(writes=("hs",), scratch=("g",)):
                z = part.z0 + part.bounds[j][0]   # one slab's planes on the padded grid at a time (host memory)
                a["g"].set(centered_psf(psf[z:z + n].astype(self.dtype), P))
                part.plan(n, self.backend).forward(a["g"], a["hs"])
                kernels.launch(part.rt, part.k["spectral_power"], (self.nfreq,), hn2.data, a["hs"].data,
                               np.int32(n), nf, np.int32(j == 0))
        if len(self.parts) > 1:
            total = np.sum([part.planes["hn2"].get().astype(np.float64) for part in self.parts], axis=0)
            for part in self.parts:
                part.planes["hn2"].set(total.astype(self.dtype))
        hmax = float(self.parts[0].planes["hn2"].get().max())
        self.psf_scale = 1.0 / np.sqrt(hmax) if params.normalize else 1.0
        if params.normalize:
            for part in self.parts:
                part.scale("hs", self.psf_scale)
                scale(part.rt, part.planes["hn2"], self.psf_scale**2)
        psf_n = psf * self.psf_scale  # the normalised stack the solver sees (float64, host)
        self.spectral_mean = float(np.sum(psf_n * psf_n))
        self.l1_plane_weights = plane_weights(psf_n, params.l1_plane_power)
        for part in self.parts:
            part.l1w = [part.rt.zeros(b - a, self.dtype) for a, b in part.bounds]
            for (a, b), arr in zip(part.bounds, part.l1w):
                arr.set(self.l1_plane_weights[part.z0 + a:part.z0 + b].astype(self.dtype))
            part.l1w_all = part.rt.zeros(part.z1 - part.z0, self.dtype) if len(part.bounds) > 1 else part.l1w[0]
            part.l1w_all.set(self.l1_plane_weights[part.z0:part.z1].astype(self.dtype))
        self.psf_scale *= self.psf_prescale  # the whole scale from the caller's PSF
        # buffers, plus the FFT libraries' scratch of the plans each part uses
        self.allocated_bytes = sum(part.device_bytes + part.partials.nbytes + part.out.nbytes + part.plan2d.scratch_bytes
                                   + sum(part.plan(n, self.backend).scratch_bytes
                                         for n in {b - a for a, b in part.bounds})
                                   for part in self.parts)
        self.host_bytes = sum(part.host_bytes for part in self.parts)
        #: (l1, mu): the l1 weight and penalty the w split's state s was made with (w = max(s - c/mu, 0),
        #: rho = min(mu s, c), c = l1 l1w[z]); (0, 1) for a state set directly: s = w >= 0, rho = 0
        self.l1_split = (0.0, 1.0)
        #: the TV weight the dual p belongs to: eta = tv_split div p
        self.tv_split = 0.0
        #: run xstep_solve inside the inverse FFT's column pass where the FFT allows it (off: for tests
        #: and benchmarks of the unfused path)
        self.fuse_xstep = True
        #: (mu_u, mu_w, l1, mu_s, tv) when g holds the x step's object-domain rhs that tv_finish made for
        #: them (the next x step then skips rhs_volume), else None
        self.rhs_for = None
        #: let tv_finish make the next x step's rhs (off: for tests of the rhs_volume path)
        self.rhs_in_tv_finish = True

    # ---- launch helpers --------------------------------------------------------------------
    def _ew(self, part, name, n, *args):
        kernels.launch(part.rt, part.k[name], (int(n),), *args)

    def _grid(self, part, name, planes, *args):
        """Launch over a (nx, ny, planes) range: coordinates without divisions."""
        kernels.launch(part.rt, part.k[name], (self.P[1], self.P[0], int(planes)), *args)

    def _row_layout(self, part, vw: int, rows: int | None = None):
        """The row kernels' work on ``part`` (kernels/common.cl): ``vw`` reals per x block (the kernels'
        VW, built in; VW > 1 walks whole rows per work-item, VW = 1 one x per work-item) and ``rows`` rows
        per work-item (by default as few as keep the partials per sum within PARTIALS, and each work-item
        at ROW_ELEMENTS or more over the planes the device holds: a streamed part's slab, a resident
        part's planes, however many slabs they are in), and the partials buffer that layout needs."""
        ny, nx = self.P
        # work-items per row block, and the elements of one row of one plane each takes
        per_row, width = (1, nx) if vw > 1 else (-(-nx // vw), vw)
        # the partials go with the planes the device holds (a streamed slab; a resident part's planes)
        held = part.max_planes if part.streamed else part.z1 - part.z0
        if rows is None:
            rows = min(ny, max(-(-ROW_ELEMENTS // (width * held)), -(-per_row * ny // PARTIALS)))
        part.vw, part.rows, part.row_items = vw, int(rows), per_row
        part.cw = max(vw // 2, 1)   # complex values per work-item of xstep_accumulate, xstep_solve
        part.acc_planes = ACC_PLANES if part.rt.caps.kind == "CPU" else None   # None: a slab per launch
        part.k.update({n: kernels.kernel(part.rt, f, n, self.dtype, {"VW": vw}) for f, n in ROW_KERNELS})
        part.local = kernels.work_group_size(part.rt, part.k["reduce_partials"])
        part.pstride = per_row * -(-ny // part.rows)   # one partial per work-item and sum
        part.partials = part.rt.zeros(NSLOTS * part.pstride, self.dtype)

    def _row_range(self, part, rows: int) -> tuple:
        """Global size of a row kernel launch with ``rows`` rows per work-item: (row blocks) where a
        work-item walks whole rows (VW > 1), else (x blocks, row blocks)."""
        blocks = -(-self.P[0] // rows)
        return (blocks,) if part.vw > 1 else (part.row_items, blocks)

    def _row_grid(self, part, name, *args):
        """Launch a row kernel without sums over a slab (``args``: those before ``rows``), a row
        per work-item (on GPUs, VW = 1: a work-item per element of a plane, walking the planes)."""
        kernels.launch(part.rt, part.k[name], self._row_range(part, 1), *args, np.int32(1))

    def _rows(self, part, name, slot, *args):
        """Launch a fused update + reduction (a row kernel) over a slab; its sums go to the
        partials of slots slot...; ``args``: the kernel's arguments before ``rows``."""
        kernels.launch(part.rt, part.k[name], self._row_range(part, part.rows), *args,
                       np.int32(part.rows), part.partials.data, np.int32(part.pstride), np.int32(slot))

    def _next(self, i, j, name):
        """(array, has_next): the plane after slab j of part i, in part i's memory."""
        part = self.parts[i]
        if j + 1 < len(part.bounds):
            return part.neighbour(name, j, "next")[0], True
        if i + 1 < len(self.parts):
            return part.load_halo("next", self.parts[i + 1].edge_plane(name, "first")), True
        return None, False

    def _prev(self, i, j, name):
        """(array, planes, has_prev): the plane before slab j of part i, in part i's memory."""
        part = self.parts[i]
        if j > 0:
            return (*part.neighbour(name, j, "prev"), True)
        if i > 0:
            return part.load_halo("prev", self.parts[i - 1].edge_plane(name, "last")), 1, True
        return None, 1, False

    def _each_slab(self, reads=(), writes=(), scratch=(), edges=(), reverse=False):
        """Every slab of every part (the last first with ``reverse``): (part index, part, slab index,
        planes, arrays)."""
        order = range(len(self.parts) - 1, -1, -1) if reverse else range(len(self.parts))
        for i in order:
            for j, n, a in self.parts[i].slabs(reads, writes, scratch, edges, reverse):
                yield i, self.parts[i], j, n, a

    def _each_run(self, reads=(), writes=()):
        """Every run of planes the kernels that touch no scratch can take in one launch: a resident
        part whose volumes are one allocation each, all its planes at once (its slabs in one launch:
        separate launches on 2-plane slabs measured ~2x slower for update_w), else each slab as
        :meth:`_each_slab`: (part index, part, first slab, last slab, planes, arrays, l1 plane weights)."""
        for i, part in enumerate(self.parts):
            whole = part.whole(tuple(reads) + tuple(writes))
            if whole is not None:
                yield i, part, 0, len(part.bounds) - 1, part.z1 - part.z0, whole, part.l1w_all
                continue
            for j, n, a in part.slabs(reads, writes):
                yield i, part, j, j, n, a, part.l1w[j]

    def x_step(self, mu_v, mu_u, mu_w):
        """Solve (mu_v H^T H + (mu_u + mu_w) I) x = H^T (mu_v v - xi) + (mu_u u - eta) + (mu_w w - rho)
        exactly, with eta, w and rho derived from the state (p, s; module docstring): the solution goes to
        ``g`` and H x (padded plane) to part 0's ``hx``."""
        R, I = self.dtype.type, np.int32  # noqa: E741
        ny, nx = self.P
        nf = np.uint64(self.nfreq)
        c = mu_u + mu_w
        l1_s, mu_s = self.l1_split
        aw = R(self.p.tv_axial_weight)
        p0 = self.parts[0].planes
        self._ew(self.parts[0], "rhs_plane", ny * nx, p0["r"].data, p0["v"].data, p0["xi"].data, R(mu_v),
                 np.uint64(ny * nx))
        self.parts[0].plan2d.forward(p0["r"], p0["R"])
        if len(self.parts) > 1:
            Rh = p0["R"].get()
            for part in self.parts[1:]:
                part.planes["R"].set(Rh)
        # g already holds the rhs where tv_finish made it for these penalties (rhs_for), else rhs_volume
        ready = self.rhs_for == (mu_u, mu_w, l1_s, mu_s, self.tv_split)
        self.rhs_for = None   # g is the new iterate after this step
        reads = ("g", "hs") if ready else ("u", "s", "px", "py", "pz", "hs")
        for i, part, j, n, a in self._each_slab(reads, ("spec",), () if ready else ("g",)):
            pl = part.planes
            if not ready:
                prev, pn, hp = self._prev(i, j, "pz")
                self._row_grid(part, "rhs_volume", a["g"].data, a["u"].data, a["s"].data, a["px"].data,
                               a["py"].data, a["pz"].data, (prev if hp else a["pz"]).data, I(hp), I(pn),
                               I(self._has_next(i, j)), R(mu_u), R(mu_w), R(self.tv_split), R(l1_s),
                               part.l1w[j].data, R(mu_s), aw, I(n), I(ny), I(nx))
            part.plan(n, self.backend).forward(a["g"], a["spec"])
            run = part.acc_planes or n
            for z0 in range(0, n, run):   # runs of planes (CPUs, ACC_PLANES), each continuing the sum
                self._ew(part, "xstep_accumulate", -(-self.nfreq // part.cw), a["spec"].data, a["hs"].data,
                         pl["R"].data, pl["S"].data, pl["comp"].data, I(z0), I(min(n, z0 + run)), nf,
                         I(j == 0 and z0 == 0))
        if len(self.parts) > 1:   # the spectral sum over all planes, added in float64 (Kahan: sum - comp)
            S = np.sum([p.planes["S"].get().astype(np.complex128) - p.planes["comp"].get() for p in self.parts],
                       axis=0).astype(self.cdtype)
            for part in self.parts:
                part.planes["S"].set(S)
        for part in self.parts:
            self._ew(part, "xstep_hx", self.nfreq, part.planes["S"].data, part.planes["hn2"].data, R(c),
                     R(mu_v), nf)
        for i, part, j, n, a in self._each_slab(("g", "hs") if self.lean else ("spec", "hs"), ("g",), ("spec",)):
            plan = part.plan(n, self.backend)
            if part.lean:   # one slab of spectra: this slab's rhs transformed again (the same values)
                plan.forward(a["g"], a["spec"])
            if plan.fuses_xstep and self.fuse_xstep:
                plan.inverse_xstep(a["spec"], a["g"], a["hs"], part.planes["R"], part.planes["S"], c, mu_v)
                continue
            self._ew(part, "xstep_solve", -(-self.nfreq // part.cw), a["spec"].data, a["hs"].data, part.planes["R"].data,
                     part.planes["S"].data, R(c), R(mu_v), I(n), nf)
            plan.inverse(a["spec"], a["g"])
        self.parts[0].plan2d.inverse(p0["S"], p0["hx"])

    def w_step(self, l1, mu_w):
        """The w split after an x step (x: the new iterate, g: the previous one): the state s from x and
        the w, rho the previous s stands for (its :attr:`l1_split`), now made with (l1, mu_w); the
        objective terms and residuals go to the reduction slots DX2..RHO2."""
        R, I = self.dtype.type, np.int32  # noqa: E741
        ny, nx = self.P
        l1_s, mu_s = self.l1_split
        aw, iso = R(self.p.tv_axial_weight), I(1 if self.p.tv_isotropic else 0)
        for i, part, j0, j1, n, a, l1w in self._each_run(("x", "g", "s"), ("s",)):
            xn, has_next = self._next(i, j1, "x")
            self._rows(part, "update_w", DX2, a["x"].data, (xn if has_next else a["x"]).data,
                      I(has_next), a["g"].data, a["s"].data, R(l1), l1w.data, R(mu_w), R(l1_s), R(mu_s),
                      aw, iso, I(n), I(ny), I(nx))
        self.l1_split = (float(l1), float(mu_w))

    def _fill(self, names, value=0):
        for part in self.parts:
            for n in names:
                if n in part.planes:
                    fill(part.rt, part.planes[n], value)
                else:
                    part.fill(n, value)

    def _gather(self, name) -> np.ndarray:
        return np.concatenate([part.get(name) for part in self.parts], axis=0)

    # ---- state access (tests and tools) ----------------------------------------------------------
    def get_volume(self, name: str) -> np.ndarray:
        """A (nz, Py, Px) volume of the state: one kept ('x', 'g', 's', 'u', 'px', 'py', 'pz') or one the
        iteration derives ('w', 'rho' from s, 'eta' from p; computed on the device as the kernels that use
        them do)."""
        if name not in DERIVED:
            return self._gather(name)
        R, I = self.dtype.type, np.int32  # noqa: E741
        ny, nx = self.P
        l1_s, mu_s = self.l1_split
        out = []
        for i, part, j, n, a in self._each_slab(("s", "px", "py", "pz")):
            t = part.rt.zeros(a["s"].shape, self.dtype)
            if name == "eta":
                prev, pn, hp = self._prev(i, j, "pz")
                self._row_grid(part, "tv_eta", t.data, a["px"].data, a["py"].data, a["pz"].data,
                           (prev if hp else a["pz"]).data, I(hp), I(pn), I(self._has_next(i, j)),
                           R(self.tv_split), R(self.p.tv_axial_weight), I(n), I(ny), I(nx))
            else:
                self._grid(part, "split_state", n, t.data, a["s"].data, I(name == "rho"), R(l1_s),
                           part.l1w[j].data, R(mu_s), I(n), I(ny), I(nx))
            out.append(t.get())
        return np.concatenate(out, axis=0)

    def set_volume(self, name: str, value: np.ndarray) -> None:
        """Set a kept volume (the derived ones follow from s, p, :attr:`l1_split` and :attr:`tv_split`)."""
        if name in DERIVED:
            raise InputError(f"set_volume: {name!r} is derived from the state (s, p), not stored")
        value = np.asarray(value)
        self.rhs_for = None   # the state changed: the next x step makes its rhs from it
        for part in self.parts:
            for j, n, a in part.slabs(writes=(name,)):
                z = part.z0 + part.bounds[j][0]
                a[name].set(np.ascontiguousarray(value[z:z + n], a[name].dtype))

    def get_plane(self, name: str) -> np.ndarray:
        """A padded plane of part 0 ('v', 'xi', 'hx', ...), shape (1, Py, Px)."""
        return self.parts[0].planes[name].get()

    def set_plane(self, name: str, value: np.ndarray) -> None:
        a = self.parts[0].planes[name]
        a.set(np.ascontiguousarray(np.reshape(value, a.shape), a.dtype))

    @property
    def moved_bytes(self) -> int:
        """Bytes copied between host and devices by streamed slabs and halos so far."""
        return sum(part.moved_bytes for part in self.parts)

    # ---- one reconstruction -----------------------------------------------------------------
    def _check_range(self, scale: float, lo: float, hi: float) -> None:
        """Refuse a volume the solve's dtype cannot hold: the normalised iterate (values ``lo``..``hi``)
        times ``scale`` (the caller's units) above the dtype's maximum, or all of it below its smallest
        subnormal (it would read as zeros). Checked with wide margins before the solve, exactly after."""
        if hi <= 0:
            return
        fi = np.finfo(self.dtype)
        if scale * hi > float(fi.max):
            raise InputError(f"volume: values up to {scale * hi:.3g} (measurement / PSF scale) exceed what "
                             f"{self.dtype.name} can hold ({float(fi.max):.3g}); use dtype float64 or rescale the input")
        if scale * lo < float(fi.smallest_subnormal):
            raise InputError(f"volume: values of {scale * lo:.3g} (measurement / PSF scale) are below what "
                             f"{self.dtype.name} can hold ({float(fi.smallest_subnormal):.3g}) and would read as "
                             "zeros; use dtype float64 or rescale the input")

    def _start_volume(self, x0, scale):
        """``x0`` (a volume in the caller's units on the sensor field (nz, My, Mx) or the padded grid) as the
        normalised padded start of x."""
        x0 = validate.real_array(x0, "x0", ndims=(3,))
        if x0.shape == (self.nz,) + self.M:
            full = np.zeros((self.nz,) + self.P)
            full[:, self.crop[0], self.crop[1]] = x0
            x0 = full
        elif x0.shape != (self.nz,) + self.P:
            raise InputError(f"x0: shape {x0.shape} is neither the volume's {(self.nz,) + self.M} nor the padded "
                             f"{(self.nz,) + self.P}")
        if not np.all(np.isfinite(x0)):
            raise InputError("x0: holds NaN or infinite values")
        return np.maximum(np.asarray(x0, np.float64), 0) * scale

    def solve(self, y, callback=None, callback_every=1, weights=None, x0=None) -> Reconstruction:
        """Reconstruct from measurement ``y``; ``weights`` (optional, the sensor's shape, finite, >= 0)
        weigh each pixel in the data term: 0 masks a pixel (saturated, hot), 1 is the default. ``x0``
        (optional, a volume in the caller's units, e.g. the previous frame's) starts x and its splits
        there instead of at zero (a warm start; the duals start at zero)."""
        y = validate.real_array(y, "measurement", ndims=(2,))
        if y.shape != self.M:
            raise InputError(f"measurement: shape {y.shape} does not match the PSF's sensor grid {self.M}")
        wts = pixel_weights(weights, self.M)
        used = y if weights is None else np.where(wts > 0, y, 0.0)
        ymax = float(np.max(np.abs(used)))   # masked pixels do not set the scale
        # an all-zero frame (a dark frame of a series) is legal: its answer is x = 0, reached at once
        y_scale = 1.0 / ymax if self.p.normalize and ymax > 0 else 1.0
        self._check_range(self.psf_scale / y_scale, 1e6, 1e-6)   # refuses only what must fail
        y_n = np.asarray(y, np.float64) * y_scale   # normalised in float64 before the device sees it

        p, R, I = self.p, self.dtype.type, np.int32  # noqa: E741
        ny, nx = self.P
        p0, pl0 = self.parts[0], self.parts[0].planes
        self._fill(("x", "u", "s", "v", "xi", "px", "py", "pz"))
        self.l1_split = (0.0, 1.0)   # s = w >= 0, rho = 0
        self.rhs_for = None
        if x0 is not None:
            start = self._start_volume(x0, y_scale / self.psf_scale)
            for name in ("x", "u", "s"):
                self.set_volume(name, start)
        cty = np.zeros(self.P, self.dtype)
        cty[self.crop] = y_n.astype(self.dtype)
        pl0["cty"].set(cty[None])
        ctl = Control(p, ProblemScale.of(np.where(wts > 0, y_n, 0.0), self.spectral_mean, self.nz), callback,
                      callback_every)
        self.tv_split = ctl.tv   # p = 0: eta = 0
        aw, iso = R(p.tv_axial_weight), I(1 if p.tv_isotropic else 0)
        step = R(p.tv_step)
        # The data split starts at its minimiser for x = 0 (v = C^T y / (C^T C + mu_v)), not at 0, so that
        # the first x step already moves towards the data (a 1-iteration solve is not all zeros).
        cw = np.zeros(self.P)
        cw[self.crop] = wts
        pl0["cw"].set(cw[None].astype(self.dtype))
        v0 = np.zeros(self.P)
        v0[self.crop] = wts * y_n / (wts + ctl.mu_v)
        pl0["v"].set(v0[None].astype(self.dtype))
        grid = lambda a: (a["px"].data, a["py"].data, a["pz"].data)  # noqa: E731
        for it in range(1, p.max_iter + 1):
            mu_v, mu_u, mu_w = ctl.mu_v, ctl.mu_u, ctl.mu_w
            self.x_step(mu_v, mu_u, mu_w)
            for part in self.parts:
                part.swap("x", "g")   # x: new iterate, g: previous one (then scratch)
                fill(part.rt, part.partials)
            # ---- w split (+ objective terms of x)
            self.w_step(ctl.l1, mu_w)
            # ---- v split (the plane lives on part 0)
            self._rows(p0, "update_v", RV2, pl0["v"].data, pl0["xi"].data, pl0["hx"].data,
                      pl0["cty"].data, pl0["cw"].data, R(mu_v), I(ny), I(nx))
            # ---- u split (TV)
            tau = ctl.tv / mu_u
            zn, rn = ("g", "spec") if self.lean else ("spec", "g")   # where z and the TV residual go
            if tau > 0:
                # One visit per slab and TV iteration, the last slab first: its residual needs the previous
                # slab's dual variable before this iteration's step (not yet taken), its dual step the next
                # slab's residual (already computed): the same values as all residuals, then all steps.
                # The first TV iteration stores z = x + eta/mu_u in spec (free until the next x step),
                # the residual goes to g (free since the w split); lean parts: z in g, the residual in
                # their one slab of spec, whose first plane the previous slab's dual step needs next.
                for k in range(p.tv_iters):
                    first = k == 0
                    reads = ("px", "py", "pz") + (("x",) if first else (zn,))
                    writes = ("px", "py", "pz") + ((zn,) if first else ())
                    for i, part, j, n, a in self._each_slab(reads, writes, edges=(rn,), reverse=True):
                        prev, pn, hp = self._prev(i, j, "pz")
                        self._row_grid(part, "tv_residual", a[rn].data, *grid(a), (prev if hp else a["pz"]).data,
                                   I(hp), I(pn), I(self._has_next(i, j)), a["x" if first else zn].data,
                                   a[zn].data, I(first), R(tau), R(1.0 / tau), aw, I(n), I(ny), I(nx))
                        gn, hn = self._next(i, j, rn)
                        self._row_grid(part, "tv_dual_step", *grid(a), a[rn].data, (gn if hn else a[rn]).data,
                                   I(hn), step, aw, iso, I(n), I(ny), I(nx))
                        if part.lean:
                            part.keep_first_plane(a[rn], "r_next")
            # ---- and the next x step's rhs, for the penalties of this iteration (used if they still hold)
            rhs = self.rhs_in_tv_finish
            l1_s, mu_s = self.l1_split
            for i, part, j0, j1, n, a, l1w in self._each_run(("u", "x", "px", "py", "pz") + ((zn,) if tau > 0 else ())
                                                             + (("s",) if rhs else ()), ("u",) + (("g",) if rhs else ())):
                prev, pn, hp = self._prev(i, j0, "pz")
                self._rows(part, "tv_finish", RU2, a["u"].data, a["x"].data,
                          a[zn if tau > 0 else "x"].data, *grid(a), (prev if hp else a["pz"]).data, I(hp), I(pn),
                          I(self._has_next(i, j1)), R(ctl.tv), R(tau), aw, a["g" if rhs else "u"].data,
                          a["s" if rhs else "u"].data, I(rhs),
                          R(mu_u), R(mu_w), R(l1_s), l1w.data, R(mu_s), I(n), I(ny), I(nx))
            self.rhs_for = (mu_u, mu_w, l1_s, mu_s, self.tv_split) if rhs else None
            # ---- the scalars of this iteration: one small read per part, added in float64
            s = np.zeros(NSLOTS)
            for part in self.parts:
                L = part.local
                part.k["reduce_partials"](part.rt.queue, (NSLOTS * L,), (L,), part.partials.data, part.out.data,
                                          I(part.pstride), kernels.local_memory(L * self.dtype.itemsize))
                s += part.out.get().astype(np.float64)
            if not np.all(np.isfinite(s)):
                raise DeviceError(f"iteration {it}: non-finite residuals or objective on the device; "
                                  "the computation diverged")
            if ctl.update(it, data2=s[DATA2], l1=s[L1], tv=s[TV], dx2=s[DX2], x2=s[X2], rv2=s[RV2],
                          dv2=s[SV2], ru2=s[RU2], du2=s[SU2], rw2=s[RW2], dw2=s[SW2], hx2=s[HX2], v2=s[V2],
                          xi2=s[XI2], w2=s[W2], rho2=s[RHO2], u2=s[U2], eta2=s[ETA2]):
                break
        last = ctl.log[-1]
        log.info("ADMM on %s: %d iterations, %s (relative residuals %.2e / %.2e, change %.2e), %.2f s",
                 ", ".join(part.rt.caps.name for part in self.parts), len(ctl.log),
                 "converged" if ctl.converged else "stopped at max_iter",
                 last["primal_rel"], last["dual_rel"], last["rel_change"], last["seconds"])
        vol = np.maximum(self._gather("x"), 0, dtype=self.dtype)
        self._check_range(self.psf_scale / y_scale, float(vol.max()), float(vol.max()))
        for plane in vol:   # scaled in float64, rounded to the solve's dtype; in place, a plane at a time
            plane[...] = plane.astype(np.float64) * (self.psf_scale / y_scale)
        layout = [{"device": part.rt.caps.name, "planes": [part.z0, part.z1], "streamed": part.streamed,
                   "lean": part.lean,
                   "slab_planes": part.max_planes, "overlap": part.overlap} for part in self.parts]
        return Reconstruction(
            volume_padded=vol, crop=self.crop, log=ctl.log,
            scaling={"psf_scale": float(self.psf_scale), "y_scale": float(y_scale)},
            params=p.as_dict(),
            info={"device": self.rt.caps.name, "platform": self.rt.caps.platform, "dtype": self.dtype.name,
                  "backend": self.backend, "padded_shape": self.P,
                  "slabs": sum(len(part.bounds) for part in self.parts), "layout": layout, **ctl.summary(),
                  "l1_plane_weights": [float(c) for c in self.l1_plane_weights],
                  "device_bytes": int(self.allocated_bytes), "host_bytes": int(self.host_bytes),
                  "moved_bytes": int(self.moved_bytes)})

    def _has_next(self, i, j) -> bool:
        return j + 1 < len(self.parts[i].bounds) or i + 1 < len(self.parts)


__all__ = ["ADMMSolver"]

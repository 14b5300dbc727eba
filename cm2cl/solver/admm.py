"""The CM2 reconstruction (paper Eq. 4) by ADMM on OpenCL devices:

    minimise 1/2 ||C H x - y||^2 + l1 ||x||_1 + tv TV_3D(x)   subject to x >= 0

The objective is a set of terms (:mod:`cm2cl.solver.terms`): a data term on the split v = Hx and
regularisers on splits z = x. Each iteration is the exact x step (:mod:`.xstep`), then every term's
prox and dual update, then one small read of the named sums the penalty policy and the stopping rule
need (:mod:`.control`). The default terms run as one fused set on the lean state (the fast path),
any other set term by term. The depth planes live in parts, resident or streamed, on one or more
devices (:mod:`.parts`, :mod:`.walk`); the float64 twin is :func:`cm2cl.reference.admm`."""

from __future__ import annotations

import logging

import numpy as np
from threadpoolctl import threadpool_limits

from .. import validate
from ..device.fft import complex_dtype, get_plan, resolve_backend
from ..device.runtime import get_runtime
from ..device.volume import fill, scale, upload
from ..errors import DeviceError, InputError
from . import xstep
from .control import Control, ProblemScale, data_misfit
from .forward import centered_psf, choose_padded_shape, crop_offsets, min_padded_shape, psf_support
from .launch import Kernels, RowLayout, Slots
from .memory import fft_scratch_per_plane, memory_estimate, plan_layout
from .params import ADMMParams
from .parts import Part
from .result import Reconstruction
from .terms import plane_weights, state_counts, terms_for
from .walk import Walk

log = logging.getLogger(__name__)

#: kernels every solve uses; those after the row kernels take no VW
COMMON_ROW = (("splits.cl", "update_v"), ("tv.cl", "tv_residual"), ("tv.cl", "tv_dual_step"),
              ("xstep.cl", "xstep_accumulate"), ("xstep.cl", "xstep_solve"))
COMMON_PLAIN = (("fft_conv.cl", "spectral_power"), ("xstep.cl", "rhs_plane"), ("xstep.cl", "xstep_hx"),
                ("reduce.cl", "reduce_partials"))
#: the term sets' kernels that are not row kernels (built without the part's VW)
PLAIN = {"split_state"}


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
    """Device state of one reconstruction problem (PSF stack + parameters + terms).

    The depth planes are laid out by :func:`cm2cl.solver.memory.plan_layout` over ``devices`` (default:
    ``device`` alone): resident when they fit the memory (``max_memory`` caps each device), else
    streamed in slabs from host memory (``stream``: 'auto', True or False); every layout computes the
    same iterates. ``terms``: a set from :mod:`cm2cl.solver.terms` (default: the default terms' fused set)."""

    def __init__(self, psf, params: ADMMParams, *, dtype=np.float32, backend="auto", device=None,
                 padded_shape=None, max_slab_planes=None, devices=None, max_memory=None, stream="auto",
                 overlap="auto", lean="auto", terms=None):
        psf = validate.psf_stack(psf, "psf")
        # a first normalisation in float64 on the host, so that no input scale over- or underflows
        # in float32 on the device: sum_i (sum |h_i|)^2 bounds max_k sum_i |H_i(k)|^2 from above. The
        # stack is scaled plane by plane where it is used, never copied whole (a full frame's is gigabytes)
        self.psf_prescale = 1.0
        if params.normalize:
            l1 = np.array([np.abs(np.asarray(h, np.float64)).sum() for h in psf])
            self.psf_prescale = 1.0 / np.sqrt(np.sum(l1 ** 2))
        self.p = params
        self.terms = terms if terms is not None else terms_for(params)
        if not self.terms.fused and lean is True:
            raise InputError("lean: the lean layout keeps the default terms' fused state; these terms need the whole one")
        self.slots = Slots()
        for key, names in self.terms.sums:
            self.slots.add(key, names)
        rts = [get_runtime(d) for d in (devices if devices else [device])]
        self.rt = rts[0]
        self.dtype = self.rt.check_dtype(dtype)
        self.backend = self._backend(backend, rts)
        self.P = self._grid(psf, padded_shape, max_slab_planes)
        self.M, self.nz = tuple(psf.shape[1:]), psf.shape[0]
        self._lay_out(rts, max_memory, stream, max_slab_planes, overlap, lean if self.terms.fused else False)
        self._psf_spectra(psf)
        self.terms.setup(self)
        #: run xstep_solve inside the inverse FFT's column pass where the FFT allows it (off: tests)
        self.fuse_xstep = True

    # ---- setup ----------------------------------------------------------------------------------------
    def _backend(self, backend, rts) -> str:
        for other in rts[1:]:
            other.check_dtype(self.dtype)
        b = resolve_backend(backend, rts[0])
        for other in rts[1:]:
            if resolve_backend(backend, other) != b:
                raise InputError(f"devices: the FFT backend '{backend}' resolves differently across the devices "
                                 "(their spectra must share one layout); name one backend, e.g. 'cl'")
        return b

    def _grid(self, psf, padded_shape, max_slab_planes) -> tuple[int, int]:
        sensor = psf.shape[1:]
        P = _padded_arg(padded_shape) if padded_shape is not None else choose_padded_shape(sensor, self.backend)
        if max_slab_planes is not None and (isinstance(max_slab_planes, bool)
                                            or not isinstance(max_slab_planes, (int, np.integer))
                                            or max_slab_planes < 1):
            raise InputError(f"max_slab_planes: expected an integer >= 1 or None, got {max_slab_planes!r}")
        need = min_padded_shape(sensor, psf)
        if any(p < max(n, m) for p, n, m in zip(P, need, sensor)):
            raise InputError(f"padded_shape: {P} is smaller than sensor + PSF support - 1 = {need}")
        return P

    def _lay_out(self, rts, max_memory, stream, max_slab_planes, overlap, lean) -> None:
        """The parts (planes over devices, :func:`plan_layout`), their kernels and row layouts."""
        P, rt = self.P, self.rt
        counts = state_counts(self.terms)
        scratch = fft_scratch_per_plane(rt, P, self.dtype, self.backend)
        self.layout = plan_layout(self.nz, P, self.dtype, self.backend, rts, max_memory=max_memory,
                                  stream=stream, max_slab_planes=max_slab_planes, scratch_per_plane=scratch,
                                  overlap=overlap, lean=lean, **counts)
        self.memory = memory_estimate(self.nz, P, self.dtype, self.backend, scratch,
                                      lean_slab=self.layout[0].slab_planes if self.layout[0].lean else None, **counts)
        self.cdtype = complex_dtype(self.dtype)
        spec_plane = get_plan(rt, P, 1, self.dtype, self.backend).spec_shape[1:]
        self.nfreq = int(np.prod(spec_plane))
        oy, ox = self.offsets = crop_offsets(self.M, P)
        self.crop = (slice(oy, oy + self.M[0]), slice(ox, ox + self.M[1]))
        self.parts = [Part(lp.rt, lp.z0, lp.z1, P, spec_plane, self.dtype, self.cdtype, slab_planes=lp.slab_planes,
                           streamed=lp.streamed, overlap=lp.overlap, lean=lp.lean, real=self.terms.volumes,
                           planes=self.terms.planes)
                      for lp in self.layout]
        self.walk = Walk(self.parts)
        #: lean layout (the planner's choice, all parts alike): one slab of spectra per part
        self.lean = any(part.lean for part in self.parts)
        for part in self.parts:
            part.kernels = Kernels(part.rt, self.dtype, COMMON_PLAIN + tuple(k for k in self.terms.kernels
                                                                            if k[1] in PLAIN))
            part.out = part.rt.zeros(len(self.slots), self.dtype)
            part.plan2d = get_plan(part.rt, P, 1, self.dtype, self.backend)
            self._row_layout(part, None)

    def _row_layout(self, part, vw: int | None, rows: int | None = None) -> None:
        """The row kernels of ``part`` built with ``vw`` reals per x block (None: the device's width) and
        ``rows`` rows per work-item (None: :meth:`RowLayout.make`'s choice), with their partials."""
        from ..device import kernels

        held = part.max_planes if part.streamed else part.z1 - part.z0
        local = kernels.work_group_size(part.rt, part.k["reduce_partials"])
        part.row = RowLayout.make(part.rt, self.dtype, self.P, held, len(self.slots), local, vw, rows)
        names = COMMON_ROW + tuple(k for k in self.terms.kernels if k[1] not in PLAIN)
        part.kernels.add(Kernels(part.rt, self.dtype, names, {"VW": part.row.vw}))

    def _psf_spectra(self, psf) -> None:
        """Each part's PSF spectra and the ||H|| = 1 normalisation from sum_i |H_i|^2 (over all parts, in
        float64), the l1 plane weights and the buffers' bytes."""
        nf, P, pre = self.nfreq, self.P, self.psf_prescale
        for part in self.parts:
            hn2 = part.planes["hn2"]
            for j, n, a in part.slabs(writes=("hs",), scratch=("g",)):
                z = part.z0 + part.bounds[j][0]   # one plane on the padded grid at a time in host memory
                for k in range(n):
                    h = (np.asarray(psf[z + k], np.float64) * pre).astype(self.dtype)
                    upload(a["g"][k:k + 1], centered_psf(h[None], P))
                part.plan(n, self.backend).forward(a["g"], a["hs"])
                part.kernels("spectral_power", (nf,), hn2=hn2, H=a["hs"], planes=n, nfreq=nf, first=j == 0)
        if len(self.parts) > 1:
            total = np.sum([part.planes["hn2"].get().astype(np.float64) for part in self.parts], axis=0)
            for part in self.parts:
                part.planes["hn2"].set(total.astype(self.dtype))
        hmax = float(self.parts[0].planes["hn2"].get().max())
        self.psf_scale = 1.0 / np.sqrt(hmax) if self.p.normalize else 1.0
        if self.p.normalize:
            for part in self.parts:
                part.scale("hs", self.psf_scale)
                scale(part.rt, part.planes["hn2"], self.psf_scale**2)
        # the normalised stack the solver sees is psf x prescale x psf_scale: its sums from the planes'
        (y0, y1), (x0, x1) = psf_support(psf)   # (scale-free)
        self.psf_support_px = (y1 - y0 + 1, x1 - x0 + 1)
        sq, light = np.zeros(self.nz), np.zeros(self.nz)
        for z, h in enumerate(psf):   # a plane at a time: the stack may be a memory map
            h = np.asarray(h, np.float64)
            sq[z], light[z] = np.sum(np.square(h)), np.sum(h)
        self.spectral_mean = float((pre * self.psf_scale) ** 2 * np.sum(sq))
        self.l1_plane_weights = plane_weights(np.sqrt(sq), self.p.l1_plane_power, light)
        self.psf_scale *= self.psf_prescale  # the whole scale from the caller's PSF
        # buffers, plus the FFT libraries' scratch of the plans each part uses
        self.allocated_bytes = sum(part.device_bytes + part.row.partials.nbytes + part.out.nbytes
                                   + part.plan2d.scratch_bytes
                                   + sum(part.plan(n, self.backend).scratch_bytes for n in {b - a for a, b in part.bounds})
                                   for part in self.parts)
        self.host_bytes = sum(part.host_bytes for part in self.parts)

    # ---- launching ------------------------------------------------------------------------------------
    def row_grid(self, part, name, **kw) -> None:
        """A row kernel without sums over a slab, a row per work-item."""
        part.kernels(name, part.row.range(self.P[0], 1), rows=1, **kw)

    def reduce_rows(self, part, name, key, **kw) -> None:
        """A row kernel that adds its sums into the partials of the slots registered as ``key``."""
        r = part.row
        part.kernels(name, r.range(self.P[0], r.rows), rows=r.rows, partials=r.partials, pstride=r.pstride,
                     slot0=self.slots.first[key], **kw)

    def _sums(self, it) -> dict:
        """The iteration's named sums: one small read per part, added in float64."""
        s = np.zeros(len(self.slots))
        for part in self.parts:
            part.row.reduce(part.kernels, part.out, len(self.slots))
            s += part.out.get().astype(np.float64)
        if not np.all(np.isfinite(s)):
            raise DeviceError(f"iteration {it}: non-finite residuals or objective on the device; "
                              "the computation diverged")
        return self.slots.named(s)

    def x_step(self, mu_v, mu_u, mu_w):
        """The x step for the default splits' penalties (:func:`cm2cl.solver.xstep.x_step`): the solution
        goes to ``g`` and H x (padded plane) to part 0's ``hx``."""
        xstep.x_step(self, {"v": mu_v, "u": mu_u, "w": mu_w})

    def w_step(self, l1, mu_w):
        """The default set's w split after an x step (:meth:`cm2cl.solver.terms.DefaultSet.w_step`)."""
        self.terms.w_step(self, l1, mu_w)

    # ---- the default set's state (tests and tools: :class:`cm2cl.solver.terms.DefaultSet`) ---------------
    l1_split = property(lambda self: self.terms.l1_split, lambda self, v: setattr(self.terms, "l1_split", v))
    tv_split = property(lambda self: self.terms.tv_split, lambda self, v: setattr(self.terms, "tv_split", v))
    rhs_for = property(lambda self: self.terms.rhs_for, lambda self, v: setattr(self.terms, "rhs_for", v))
    rhs_in_tv_finish = property(lambda self: self.terms.rhs_in_tv_finish,
                                lambda self, v: setattr(self.terms, "rhs_in_tv_finish", v))

    # ---- state access (tests and tools) ----------------------------------------------------------
    def get_volume(self, name: str) -> np.ndarray:
        """A (nz, Py, Px) volume of the state: one kept, or one the terms derive (the default set: 'w',
        'rho' from s, 'eta' from p, computed on the device as the kernels that use them do)."""
        derived = self.terms.derived(self, name)
        return self.walk.gather(name) if derived is None else derived

    def set_volume(self, name: str, value: np.ndarray) -> None:
        """Set a kept volume (the default set's derived ones follow from s, p, l1_split and tv_split)."""
        if name not in self.terms.volumes:
            raise InputError(f"set_volume: {name!r} is derived from the state, not stored")
        self.terms.rhs_for = None   # the state changed: the next x step makes its rhs from it
        self.walk.scatter(name, np.asarray(value))

    def get_plane(self, name: str) -> np.ndarray:
        """A padded plane of part 0 ('v', 'xi', 'hx', ...), shape (1, Py, Px)."""
        return self.parts[0].planes[name].get()

    def set_plane(self, name: str, value: np.ndarray) -> None:
        a = self.parts[0].planes[name]
        a.set(np.ascontiguousarray(np.reshape(value, a.shape), a.dtype))

    @property
    def moved_bytes(self) -> int:
        """Bytes copied between host and devices by streamed slabs and halos so far."""
        return self.walk.moved_bytes

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
        there instead of at zero (a warm start: v at H x0, the data term's dual at its gradient there, the
        regularisers' duals at zero)."""
        y_scale = self._measurement(y, weights)
        ctl = self._start(x0, y_scale, callback, callback_every)
        terms = self.terms
        # The host's linear algebra in the loop (the background's fit, small matrices) on one BLAS thread:
        # OpenBLAS's threads spin after each call and take the cores a CPU device computes on (the demo:
        # 300 iterations 5.5 -> 3.7 s; docs/benchmarks.md, "Host BLAS threads in the loop").
        with threadpool_limits(limits=1, user_api="blas"):
            for it in range(1, self.p.max_iter + 1):
                xstep.x_step(self, ctl.x_mu())
                for part in self.parts:
                    part.swap("x", "g")   # x: new iterate, g: previous one (then scratch)
                    fill(part.rt, part.row.partials)
                terms.update(self, ctl)
                if ctl.update(it, **terms.report(self._sums(it))) and not terms.next_round(self):
                    break
                if ctl.converged:   # a new round of the terms (e.g. new l1 weights): wait for it to converge too
                    ctl.converged, ctl.calm, ctl.stop = False, 0, "max_iter"
        return self._result(ctl, y_scale)

    def _measurement(self, y, weights) -> float:
        """Check ``y`` and ``weights``, keep the normalised measurement; returns y's scale."""
        y = validate.real_array(y, "measurement", ndims=(2,))
        if y.shape != self.M:
            raise InputError(f"measurement: shape {y.shape} does not match the PSF's sensor grid {self.M}")
        self.pixel_weights = wts = pixel_weights(weights, self.M)
        used = y if weights is None else np.where(wts > 0, y, 0.0)
        ymax = float(np.max(np.abs(used)))   # masked pixels do not set the scale
        # an all-zero frame (a dark frame of a series) is legal: its answer is x = 0, reached at once
        y_scale = 1.0 / ymax if self.p.normalize and ymax > 0 else 1.0
        self._check_range(self.psf_scale / y_scale, 1e6, 1e-6)   # refuses only what must fail
        self.y_n = np.asarray(y, np.float64) * y_scale   # normalised in float64 before the device sees it
        return y_scale

    def _start(self, x0, y_scale, callback, callback_every) -> Control:
        """Zero the state (or start x and the identity splits at ``x0``, v at H x0 and the data dual at the
        data term's gradient there: :meth:`cm2cl.solver.terms.Term.warm`) and make the iteration's control."""
        terms = self.terms
        self.walk.fill(tuple(n for n in terms.volumes if n != "g") + ("v", "xi"))
        terms.reset()
        self.warm = x0 is not None
        if x0 is not None:
            start = self._start_volume(x0, y_scale / self.psf_scale)
            for name in terms.start_volumes:
                self.set_volume(name, start)
        wts = self.pixel_weights
        ctl = Control(self.p, ProblemScale.of(np.where(wts > 0, self.y_n, 0.0), self.spectral_mean, self.nz,
                                              self.nz * self.P[0] * self.P[1]),
                      callback, callback_every, splits=terms.splits, cold=x0 is None)
        terms.start(self, ctl)
        if x0 is not None:
            # H x0 into part 0's hx by an x step that returns x0 itself: no data penalty (mu_v = 0) and the
            # rhs c x0 that the splits (at x0, duals 0) make, so X = T / c; its result in g is scratch
            xstep.x_step(self, {**ctl.x_mu(), "v": 0.0})
            terms.data.warm(self, ctl)
        return ctl

    def _result(self, ctl, y_scale) -> Reconstruction:
        last = ctl.log[-1]
        log.info("ADMM on %s: %d iterations, %s (relative residuals %.2e / %.2e, change %.2e), %.2f s",
                 ", ".join(part.rt.caps.name for part in self.parts), len(ctl.log),
                 "converged" if ctl.converged else "stopped at max_iter",
                 last["primal_rel"], last["dual_rel"], last["rel_change"], last["seconds"])
        vol = self.walk.gather("x")
        np.maximum(vol, 0, out=vol)   # in place: the result is the one host copy of the volume
        self._check_range(self.psf_scale / y_scale, float(vol.max()), float(vol.max()))
        for plane in vol:   # scaled in float64, rounded to the solve's dtype; in place, a plane at a time
            plane[...] = plane.astype(np.float64) * (self.psf_scale / y_scale)
        bg = getattr(self.terms.data, "fit", None)
        if bg is not None:
            info_bg = {"model": "cubic B-splines >= 0", "knot_spacing_px": bg.spacing, "coefficients": list(bg.shape),
                       "mean": float(bg.plane().mean() / y_scale)}
        # the data misfit the solve reached: the measurement less the model at the last iterate (H x from the last
        # x step, on part 0's plane) and the background, against the residual's own white noise
        model = self.get_plane("hx")[0][self.crop].astype(np.float64)
        if bg is not None:
            model += bg.plane()
        misfit = data_misfit(self.y_n, model, self.pixel_weights)
        misfit.update({k: misfit[k] / y_scale for k in ("rms", "white_rms") if misfit[k] is not None})
        layout = [{"device": part.rt.caps.name, "planes": [part.z0, part.z1], "streamed": part.streamed,
                   "lean": part.lean, "slab_planes": part.max_planes, "overlap": part.overlap} for part in self.parts]
        return Reconstruction(
            volume_padded=vol, crop=self.crop, log=ctl.log,
            background=None if bg is None else bg.plane() / y_scale,
            scaling={"psf_scale": float(self.psf_scale), "y_scale": float(y_scale)},
            params=self.p.as_dict(),
            info={"device": self.rt.caps.name, "platform": self.rt.caps.platform, "dtype": self.dtype.name,
                  "backend": self.backend, "padded_shape": self.P,
                  "slabs": sum(len(part.bounds) for part in self.parts), "layout": layout, **ctl.summary(),
                  "l1_plane_weights": [float(c) for c in self.l1_plane_weights],
                  "device_bytes": int(self.allocated_bytes), "host_bytes": int(self.host_bytes),
                  "moved_bytes": int(self.moved_bytes),
                  "background": {"model": "none"} if bg is None else info_bg, "misfit": misfit})


__all__ = ["ADMMSolver", "pixel_weights"]

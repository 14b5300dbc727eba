"""The CM2 reconstruction (paper Eq. 4) by ADMM on an OpenCL device.

    minimise 1/2 ||C H x - y||^2 + l1 ||x||_1 + tv TV_3D(x)   subject to x >= 0

Splits (DESIGN.md section 3): v = Hx (crop-aware data step), w = x (l1 + non-negativity),
u = x (TV prox by warm-started dual iterations), and the exact x step by Sherman-Morrison per
lateral frequency. Every step is a kernel in ``kernels/``; inside the loop the only transfer
between host and device is one small buffer of reduced scalars per iteration.
The float64 numpy twin is :func:`cm2cl.reference.admm` (tests and tools only).
"""

from __future__ import annotations

import numpy as np

from .. import validate
from ..device import kernels
from ..device.runtime import get_runtime
from ..errors import DeviceError, InputError
from .forward import ForwardModel, choose_padded_shape, min_padded_shape
from ..device.fft import get_plan, resolve_backend
from .control import Control
from .params import ADMMParams
from .result import Reconstruction
from ..device.volume import Volume
from .memory import check_fits

# Slots of the per-iteration reduction buffer.
DX2, X2, L1, TV, RW2, SW2, RV2, SV2, DATA2, RU2, SU2 = range(11)
NSLOTS = 11
#: elements each work-item of a reduction handles (PoCL on 2 cores: 64 beat 16 and 256 by
#: 1.1-1.6x; GPUs keep hundreds of work-groups at this size for a few million voxels)
PER_ITEM = 64

class ADMMSolver:
    """Device state of one reconstruction problem (PSF stack + parameters)."""

    def __init__(self, psf, params: ADMMParams, *, dtype=np.float32, backend="auto", device=None,
                 padded_shape=None, max_slab_planes=None):
        psf = validate.psf_stack(psf, "psf")
        self.p = params
        self.rt = rt = get_runtime(device)
        self.dtype = rt.check_dtype(dtype)
        self.backend = resolve_backend(backend, rt)
        sensor = psf.shape[1:]
        P = tuple(padded_shape) if padded_shape is not None else choose_padded_shape(sensor, self.backend)
        if any(p < n for p, n in zip(P, min_padded_shape(sensor))):
            raise InputError(f"padded_shape: {P} is smaller than 2*sensor-1 = {min_padded_shape(sensor)}")
        self.memory = check_fits(rt, psf.shape[0], P, self.dtype, self.backend)
        self.model = m = ForwardModel(psf, dtype=self.dtype, backend=self.backend, device=rt,
                                      padded_shape=P, max_slab_planes=max_slab_planes)
        self.P, self.M, self.nz = m.padded_shape, m.sensor_shape, m.nz
        k = lambda f, n: kernels.kernel(rt, f, n, self.dtype)  # noqa: E731
        self.k = {n: k(f, n) for f, n in [
            ("fft_conv.cl", "spectral_power"), ("xstep.cl", "rhs_volume"), ("xstep.cl", "rhs_plane"),
            ("xstep.cl", "xstep_accumulate"), ("xstep.cl", "xstep_hx"), ("xstep.cl", "xstep_solve"),
            ("splits.cl", "update_w"), ("splits.cl", "update_v"), ("tv.cl", "tv_residual"),
            ("tv.cl", "tv_dual_step"), ("tv.cl", "tv_finish"), ("reduce.cl", "reduce_partials")]}
        # reductions: each work-item walks contiguous elements on CPUs, interleaved on GPUs
        self.contiguous = np.int32(rt.caps.kind == "CPU")
        self.local = {n: kernels.work_group_size(rt, self.k[n])
                      for n in ("update_w", "update_v", "tv_finish", "reduce_partials")}
        # one partial sum per work-group of the largest launch, per slot
        biggest = max([(z1 - z0) for z0, z1 in m.bounds] + [1]) * int(np.prod(m.padded_shape))
        self.pstride = -(-biggest // (min(self.local.values()) * PER_ITEM))

        # ||H|| = 1 normalisation from the spectral power, computed on the device once.
        self.hn2 = Volume(rt, [(0, 1)], m.spec_plane, self.dtype)
        nf = np.uint64(m.nfreq)
        for first, ((z0, z1), hs) in zip([1] + [0] * len(m.bounds), m.psf_spectra):
            kernels.launch(rt, self.k["spectral_power"], (m.nfreq,), self.hn2.slabs[0].data, hs.data,
                           np.int32(z1 - z0), nf, np.int32(first))
        hmax = float(self.hn2.slabs[0].get().max())
        self.psf_scale = 1.0 / np.sqrt(hmax) if params.normalize else 1.0
        if params.normalize:
            for hs in m.psf_spectra.slabs:
                hs *= self.dtype.type(self.psf_scale)
            self.hn2.slabs[0] *= self.dtype.type(self.psf_scale**2)

        vol = m.new_volume
        self.x, self.g, self.u, self.w, self.eta, self.rho = (vol() for _ in range(6))
        self.pd = [vol() for _ in range(3)]
        self.spec = m.new_spectrum_volume()
        plane = lambda: Volume(rt, [(0, 1)], self.P, self.dtype)  # noqa: E731
        self.v, self.xi, self.hx, self.cty, self.r = (plane() for _ in range(5))
        splane = lambda: Volume(rt, [(0, 1)], m.spec_plane, m.cdtype)  # noqa: E731
        self.R, self.S, self.comp = (splane() for _ in range(3))
        self.partials = rt.zeros(NSLOTS * self.pstride, self.dtype)
        self.out = rt.zeros(NSLOTS, self.dtype)
        self.allocated_bytes = sum(a.nbytes for a in (
            [m.psf_spectra, self.hn2, self.x, self.g, self.u, self.w, self.eta, self.rho, self.spec,
             self.v, self.xi, self.hx, self.cty, self.r, self.R, self.S, self.comp] + self.pd)) \
            + self.partials.nbytes + self.out.nbytes
        self._plan2d = get_plan(rt, self.P, 1, self.dtype, self.backend)

    # ---- launch helpers --------------------------------------------------------------------
    def _ew(self, name, n, *args):
        kernels.launch(self.rt, self.k[name], (int(n),), *args)

    def _grid(self, name, planes, *args):
        """Launch over a (nx, ny, planes) range: coordinates without divisions."""
        kernels.launch(self.rt, self.k[name], (self.P[1], self.P[0], int(planes)), *args)

    def _red(self, name, n, slot, *args):
        """Launch a fused update + reduction over n elements; its sums go to partials[slot...]."""
        L = self.local[name]
        groups = -(-int(n) // (L * PER_ITEM))
        self.k[name](self.rt.queue, (groups * L,), (L,), *args, self.partials.data, np.int32(self.pstride),
                     kernels.local_memory(L * self.dtype.itemsize), np.int32(slot), np.int32(PER_ITEM),
                     self.contiguous)

    def x_step(self, mu_v, mu_u, mu_w):
        """Solve (mu_v H^T H + (mu_u + mu_w) I) x = H^T (mu_v v - xi) + (mu_u u - eta) + (mu_w w - rho)
        exactly: the solution goes to ``self.g`` and H x (padded plane) to ``self.hx``."""
        m, R, I = self.model, self.dtype.type, np.int32  # noqa: E741
        ny, nx = self.P
        nf = np.uint64(m.nfreq)
        bounds = m.bounds
        c = mu_u + mu_w
        for (z0, z1), gs, us, es, ws, rs, ss in zip(bounds, self.g.slabs, self.u.slabs, self.eta.slabs,
                                                    self.w.slabs, self.rho.slabs, self.spec.slabs):
            self._ew("rhs_volume", gs.size, gs.data, us.data, es.data, ws.data, rs.data,
                     R(mu_u), R(mu_w), np.uint64(gs.size))
            m.plan(z1 - z0).forward(gs, ss)
        self._ew("rhs_plane", ny * nx, self.r.slabs[0].data, self.v.slabs[0].data,
                 self.xi.slabs[0].data, R(mu_v), np.uint64(ny * nx))
        self._plan2d.forward(self.r.slabs[0], self.R.slabs[0])
        for j, ((z0, z1), ss, hs) in enumerate(zip(bounds, self.spec.slabs, m.psf_spectra.slabs)):
            self._ew("xstep_accumulate", m.nfreq, ss.data, hs.data, self.R.slabs[0].data,
                     self.S.slabs[0].data, self.comp.slabs[0].data, I(z1 - z0), nf, I(j == 0))
        self._ew("xstep_hx", m.nfreq, self.S.slabs[0].data, self.hn2.slabs[0].data, R(c), R(mu_v), nf)
        for (z0, z1), ss, hs, gs in zip(bounds, self.spec.slabs, m.psf_spectra.slabs, self.g.slabs):
            self._ew("xstep_solve", m.nfreq, ss.data, hs.data, self.S.slabs[0].data, R(c), R(mu_v),
                     I(z1 - z0), nf)
            m.plan(z1 - z0).inverse(ss, gs)
        self._plan2d.inverse(self.S.slabs[0], self.hx.slabs[0])

    # ---- one reconstruction -----------------------------------------------------------------
    def solve(self, y, callback=None, callback_every=1) -> Reconstruction:
        y = validate.real_array(y, "measurement", ndims=(2,))
        if y.shape != self.M:
            raise InputError(f"measurement: shape {y.shape} does not match the PSF's sensor grid {self.M}")
        ymax = float(np.max(y))
        if self.p.normalize and not ymax > 0:
            raise InputError("measurement: has no positive value (check the offset subtraction)")
        y_scale = 1.0 / ymax if self.p.normalize else 1.0

        p, m, rt, q, R = self.p, self.model, self.rt, self.rt.queue, self.dtype.type
        I = np.int32  # noqa: E741
        ny, nx = self.P
        my, mx = self.M
        oy, ox = m.offsets
        for a in [self.x, self.u, self.w, self.eta, self.rho, self.v, self.xi] + self.pd:
            a.fill(0)
        sensor = Volume(rt, [(0, 1)], self.M, self.dtype).set((y * y_scale)[None])
        m.embed_from_sensor(sensor.slabs[0], self.cty.slabs[0])
        bounds = m.bounds
        nslab = len(bounds)
        ctl = Control(p, callback, callback_every)
        aw, iso = R(p.tv_axial_weight), I(1 if p.tv_isotropic else 0)
        step = R(p.tv_step)
        for it in range(1, p.max_iter + 1):
            mu_v, mu_u, mu_w = ctl.mu_v, ctl.mu_u, ctl.mu_w
            self.x_step(mu_v, mu_u, mu_w)
            self.x, self.g = self.g, self.x  # x: new iterate, g: previous one (then scratch)
            self.partials.fill(0)
            # ---- w split (+ objective terms of x)
            for j, ((z0, z1), xs, gs, ws, rs) in enumerate(zip(bounds, self.x.slabs, self.g.slabs,
                                                              self.w.slabs, self.rho.slabs)):
                has_next = j + 1 < nslab
                xn = self.x.slabs[j + 1] if has_next else xs
                self._red("update_w", xs.size, DX2, xs.data, xn.data, I(has_next), gs.data, ws.data,
                          rs.data, R(p.l1), R(mu_w), aw, iso, I(z1 - z0), I(ny), I(nx))
            # ---- v split
            self._red("update_v", ny * nx, RV2, self.v.slabs[0].data, self.xi.slabs[0].data,
                      self.hx.slabs[0].data, self.cty.slabs[0].data, R(mu_v), I(ny), I(nx), I(my), I(mx),
                      I(oy), I(ox))
            # ---- u split (TV)
            tau = p.tv / mu_u
            px_, py_, pz_ = self.pd
            if tau > 0:
                for _ in range(p.tv_iters):
                    for j, (z0, z1) in enumerate(bounds):
                        hp, hn = j > 0, j + 1 < nslab
                        prev = pz_.slabs[j - 1] if hp else pz_.slabs[j]
                        self._grid("tv_residual", z1 - z0, self.g.slabs[j].data,
                                   px_.slabs[j].data, py_.slabs[j].data, pz_.slabs[j].data, prev.data,
                                   I(hp), I(prev.shape[0]), I(hn), self.x.slabs[j].data,
                                   self.eta.slabs[j].data, R(1.0 / mu_u), R(1.0 / tau), aw,
                                   I(z1 - z0), I(ny), I(nx))
                    for j, (z0, z1) in enumerate(bounds):
                        hn = j + 1 < nslab
                        gn = self.g.slabs[j + 1] if hn else self.g.slabs[j]
                        self._grid("tv_dual_step", z1 - z0, px_.slabs[j].data,
                                   py_.slabs[j].data, pz_.slabs[j].data, self.g.slabs[j].data, gn.data,
                                   I(hn), step, aw, iso, I(z1 - z0), I(ny), I(nx))
            for j, (z0, z1) in enumerate(bounds):
                hp, hn = j > 0, j + 1 < nslab
                prev = pz_.slabs[j - 1] if hp else pz_.slabs[j]
                self._red("tv_finish", self.u.slabs[j].size, RU2, self.u.slabs[j].data,
                          self.eta.slabs[j].data, self.x.slabs[j].data, px_.slabs[j].data, py_.slabs[j].data,
                          pz_.slabs[j].data, prev.data, I(hp), I(prev.shape[0]), I(hn), R(mu_u), R(tau), aw,
                          I(z1 - z0), I(ny), I(nx))
            # ---- the scalars of this iteration: one small read
            L = self.local["reduce_partials"]
            self.k["reduce_partials"](q, (NSLOTS * L,), (L,), self.partials.data, self.out.data,
                                      I(self.pstride), kernels.local_memory(L * self.dtype.itemsize))
            s = self.out.get().astype(np.float64)
            if not np.all(np.isfinite(s)):
                raise DeviceError(f"iteration {it}: non-finite residuals or objective on the device; "
                                  "the computation diverged")
            if ctl.update(it, data2=s[DATA2], l1=s[L1], tv=s[TV], dx2=s[DX2], x2=s[X2], rv2=s[RV2],
                          dv2=s[SV2], ru2=s[RU2], du2=s[SU2], rw2=s[RW2], dw2=s[SW2]):
                break
        x = self.x.get()
        vol = np.maximum(x, 0) * (self.psf_scale / y_scale)
        return Reconstruction(
            volume_padded=vol, crop=m.crop, log=ctl.log,
            scaling={"psf_scale": float(self.psf_scale), "y_scale": float(y_scale)},
            params=p.as_dict(),
            info={"device": rt.caps.name, "platform": rt.caps.platform, "dtype": self.dtype.name,
                  "backend": self.backend, "padded_shape": self.P, "slabs": len(bounds), "stop": ctl.stop,
                  "device_bytes": int(self.allocated_bytes)})


def reconstruct(measurement, psf, *, dtype=np.float32, backend="auto", device=None,
                padded_shape=None, max_slab_planes=None, callback=None, callback_every=1,
                voxel_size_um=None, depths_um=None, **params) -> Reconstruction:
    """Reconstruct a 3D volume from one CM2 measurement (paper Eq. 4) on an OpenCL device.

    Parameters
    ----------
    measurement : (My, Mx) float array, camera offset removed.
    psf : (nz, My, Mx) float array, one PSF per depth plane on the same sensor grid.
    dtype : float32 (default) or float64 (devices with fp64 only).
    backend : FFT backend, 'auto', 'cl', 'vkfft' or 'reikna' (see cm2cl.device.fft).
    device : index, name fragment, pyopencl Device or Runtime (default: see cm2cl.device).
    padded_shape : padded grid (Py, Px) >= 2M - 1 (default: the backend's fast size).
    callback : called with the log row every `callback_every` iterations.
    voxel_size_um : optional object-space voxel size (dz, dy, dx) in um, carried to the result.
    depths_um : optional depth of each PSF plane in um, carried to the result.
    **params : fields of :class:`cm2cl.params.ADMMParams` (l1, tv, tv_axial_weight, max_iter, tol, ...).

    Returns
    -------
    Reconstruction with ``.volume`` (nz, My, Mx) on the sensor field of view, ``.volume_padded``,
    ``.log`` and ``.scaling``.
    """
    prm = ADMMParams.from_kwargs(**params)
    psf = validate.psf_stack(psf, "psf")
    y = validate.real_array(measurement, "measurement", ndims=(2,))
    if y.shape != psf.shape[1:]:
        raise InputError(f"measurement: shape {y.shape} does not match the PSF's sensor grid "
                         f"{psf.shape[1:]} (psf shape {psf.shape})")
    solver = ADMMSolver(psf, prm, dtype=dtype, backend=backend, device=device,
                        padded_shape=padded_shape, max_slab_planes=max_slab_planes)
    rec = solver.solve(y, callback=callback, callback_every=callback_every)
    if voxel_size_um is not None:
        vs = tuple(float(v) for v in voxel_size_um)
        if len(vs) != 3 or not all(np.isfinite(v) and v > 0 for v in vs):
            raise InputError(f"voxel_size_um: expected 3 positive numbers (dz, dy, dx), got {voxel_size_um!r}")
        rec.voxel_size_um = vs
    if depths_um is not None:
        d = np.asarray(depths_um, float).ravel()
        if d.size != psf.shape[0] or not np.all(np.isfinite(d)):
            raise InputError(f"depths_um: expected {psf.shape[0]} finite depths, got {np.shape(depths_um)}")
        rec.depths_um = d
    return rec


__all__ = ["ADMMSolver", "reconstruct"]

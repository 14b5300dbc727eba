"""Float64 numpy twins of every device computation, for tests and tools only.

Same conventions as the device code (see cm2cl.forward): PSF centred at (My//2, Mx//2), object on
the padded grid P, circular convolution on P, crop window at ((Py-My)//2, (Px-Mx)//2).
"""

from __future__ import annotations

import numpy as np

from .forward import centered_psf, crop_offsets


def psf_spectra(psf, padded_shape) -> np.ndarray:
    psf = np.asarray(psf, np.float64)
    if psf.ndim == 2:
        psf = psf[None]
    return np.fft.fft2(centered_psf(psf, padded_shape))


def crop(a, sensor_shape):
    oy, ox = crop_offsets(sensor_shape, a.shape[-2:])
    return a[..., oy:oy + sensor_shape[0], ox:ox + sensor_shape[1]]


def embed(y, padded_shape):
    """C^T: zero padded grid with the sensor window filled."""
    out = np.zeros(y.shape[:-2] + tuple(padded_shape), np.float64)
    oy, ox = crop_offsets(y.shape[-2:], padded_shape)
    out[..., oy:oy + y.shape[-2], ox:ox + y.shape[-1]] = y
    return out


def convolve(psf, x, padded_shape) -> np.ndarray:
    """sum_i h_i (*) x_i on the padded grid."""
    Hs = psf_spectra(psf, padded_shape)
    return np.fft.ifft2((Hs * np.fft.fft2(np.asarray(x, np.float64))).sum(axis=0)).real


def forward(psf, x, padded_shape) -> np.ndarray:
    """y = C H x (paper Eq. 3)."""
    psf = np.asarray(psf)
    sensor = psf.shape[-2:]
    return crop(convolve(psf, x, padded_shape), sensor)


def adjoint(psf, y, padded_shape) -> np.ndarray:
    """H^T C^T y."""
    Hs = psf_spectra(psf, padded_shape)
    V = np.fft.fft2(embed(np.asarray(y, np.float64), padded_shape))
    return np.fft.ifft2(np.conj(Hs) * V).real


# ---- 3D total variation (forward differences, Neumann boundary, axial weight) ---------------
def tv_grad(u, axial_weight=1.0):
    """(gx, gy, gz) of a (nz, ny, nx) volume; gz carries the axial weight."""
    gx = np.zeros_like(u)
    gy = np.zeros_like(u)
    gz = np.zeros_like(u)
    gx[:, :, :-1] = u[:, :, 1:] - u[:, :, :-1]
    gy[:, :-1, :] = u[:, 1:, :] - u[:, :-1, :]
    gz[:-1] = axial_weight * (u[1:] - u[:-1])
    return gx, gy, gz


def _bdiff(p, axis):
    """Backward difference with p = 0 past the last index: the negative adjoint of a forward one."""
    a = np.moveaxis(p, axis, 0).copy()
    a[-1] = 0
    out = a.copy()
    out[1:] -= a[:-1]
    return np.moveaxis(out, 0, axis)


def tv_div(px, py, pz, axial_weight=1.0):
    """div = -grad^T."""
    return _bdiff(px, 2) + _bdiff(py, 1) + axial_weight * _bdiff(pz, 0)


def tv_value(u, axial_weight=1.0, isotropic=True) -> float:
    gx, gy, gz = tv_grad(np.asarray(u, np.float64), axial_weight)
    if isotropic:
        return float(np.sqrt(gx**2 + gy**2 + gz**2).sum())
    return float(np.abs(gx).sum() + np.abs(gy).sum() + np.abs(gz).sum())


def tv_dual_step(p, z, tau, step, axial_weight=1.0, isotropic=True):
    """One projected-gradient (Chambolle) step on the dual of prox_{tau TV}(z), in place on p."""
    g = tv_div(*p, axial_weight) - z / tau
    for pk, gk in zip(p, tv_grad(g, axial_weight)):
        pk += step * gk
    if isotropic:
        n = np.maximum(1.0, np.sqrt(p[0] ** 2 + p[1] ** 2 + p[2] ** 2))
        for pk in p:
            pk /= n
    else:
        np.clip(p, -1.0, 1.0, out=p)
    return p


def tv_prox(z, tau, iters, p=None, axial_weight=1.0, isotropic=True):
    """prox_{tau TV}(z) by `iters` dual iterations from the dual p (warm start); returns (u, p)."""
    step = 1.0 / (4.0 * (2.0 + axial_weight**2))
    p = np.zeros((3,) + z.shape, z.dtype) if p is None else p
    for _ in range(iters):
        tv_dual_step(p, z, tau, step, axial_weight, isotropic)
    return z - tau * tv_div(*p, axial_weight), p


# ---- the ADMM solver (same splits, order and control as cm2cl.admm) -----------------------
def normalisation(psf, y, padded_shape):
    """(psf_scale, y_scale): ||H|| = 1 after scaling the PSFs, max(y) = 1 after scaling y."""
    Hs = np.fft.rfft2(centered_psf(np.asarray(psf, np.float64), padded_shape))
    return 1.0 / np.sqrt((np.abs(Hs) ** 2).sum(axis=0).max()), 1.0 / float(np.max(y))


def admm(y, psf, params=None, padded_shape=None, dtype=np.float64, workers=None, callback=None,
         **kw):
    """Float64 (or ``dtype``) numpy ADMM for paper Eq. 4 with the splits of DESIGN.md section 3.

    Same algorithm, order of updates, residuals, balancing and stopping as the device solver.
    ``workers`` is passed to scipy.fft (-1 = all cores). Returns a Reconstruction.
    """
    import scipy.fft as sfft

    from .control import Control
    from .params import ADMMParams
    from .result import Reconstruction

    p = params if params is not None else ADMMParams.from_kwargs(**kw)
    dt = np.dtype(dtype)
    psf = np.asarray(psf, np.float64)
    psf = psf[None] if psf.ndim == 2 else psf
    y = np.asarray(y, np.float64)
    nz = psf.shape[0]
    M = psf.shape[1:]
    P = tuple(padded_shape) if padded_shape is not None else tuple(2 * m for m in M)
    rfft = lambda a: sfft.rfft2(a, workers=workers)  # noqa: E731
    irfft = lambda a: sfft.irfft2(a, s=P, workers=workers)  # noqa: E731

    s_h, s_y = normalisation(psf, y, P) if p.normalize else (1.0, 1.0)
    cdt = np.complex64 if dt == np.float32 else np.complex128
    Hs = (rfft(centered_psf(psf * s_h, P))).astype(cdt)
    hn2 = (np.abs(Hs) ** 2).sum(axis=0).astype(dt)
    ys = (y * s_y).astype(dt)
    mask = embed(np.ones(M), P).astype(dt)
    cty = embed(ys, P).astype(dt)

    x = np.zeros((nz,) + P, dt)
    u, w, eta, rho = (np.zeros_like(x) for _ in range(4))
    pd = np.zeros((3,) + x.shape, dt)
    v = np.zeros(P, dt)
    xi = np.zeros(P, dt)
    ctl = Control(p, callback)
    sq = lambda a: float(np.sum(np.asarray(a, np.float64) ** 2))  # noqa: E731
    for it in range(1, p.max_iter + 1):
        mu_v, mu_u, mu_w = ctl.mu_v, ctl.mu_u, ctl.mu_w
        # x step: (mu_v H^T H + c I) x = H^T (mu_v v - xi) + (mu_u u - eta) + (mu_w w - rho)
        c = mu_u + mu_w
        B = np.conj(Hs) * rfft(mu_v * v - xi)[None] + rfft(mu_u * u - eta + mu_w * w - rho)
        s = (Hs * B).sum(axis=0)
        HX = s / (c + mu_v * hn2)
        x_new = irfft((B - mu_v * np.conj(Hs) * HX[None]) / c).astype(dt)
        hx = irfft(HX).astype(dt)
        dx2 = sq(x_new.astype(np.float64) - x)
        x = x_new
        # w step: l1 + non-negativity
        w_new = np.maximum(x + rho / mu_w - p.l1 / mu_w, 0).astype(dt)
        rho += mu_w * (x - w_new)
        # v step: crop-aware data update
        v_new = ((cty + mu_v * hx + xi) / (mask + mu_v)).astype(dt)
        xi += mu_v * (hx - v_new)
        # u step: TV prox, warm-started dual
        z = x + eta / mu_u
        if p.tv > 0:
            u_new, pd = tv_prox(z, p.tv / mu_u, p.tv_iters, pd, p.tv_axial_weight, p.tv_isotropic)
        else:
            u_new = z
        u_new = u_new.astype(dt)
        eta += mu_u * (x - u_new)
        done = ctl.update(it, data2=sq(crop(hx.astype(np.float64), M) - ys), l1=float(np.abs(x).sum()),
                          tv=tv_value(x, p.tv_axial_weight, p.tv_isotropic), dx2=dx2, x2=sq(x),
                          rv2=sq(hx - v_new), dv2=sq(v_new - v), ru2=sq(x - u_new), du2=sq(u_new - u),
                          rw2=sq(x - w_new), dw2=sq(w_new - w))
        v, u, w = v_new, u_new, w_new
        if done:
            break
    oy, ox = crop_offsets(M, P)
    vol = np.maximum(x, 0) * (s_h / s_y)
    return Reconstruction(volume_padded=vol, crop=(slice(oy, oy + M[0]), slice(ox, ox + M[1])),
                          log=ctl.log, scaling={"psf_scale": s_h, "y_scale": s_y},
                          params=p.as_dict(), info={"device": "numpy", "dtype": dt.name, "stop": ctl.stop,
                                                    "padded_shape": P})


# ---- spatial-domain operators (no FFT), to check Fourier-domain formulas against ---------
def _psf_taps(psf):
    psf = np.asarray(psf, np.float64)
    psf = psf[None] if psf.ndim == 2 else psf
    cy, cx = psf.shape[1] // 2, psf.shape[2] // 2
    return psf, cy, cx


def convolve_spatial(psf, x, padded_shape=None) -> np.ndarray:
    """sum_i h_i (*) x_i by explicit circular shifts on the padded grid (small sizes only)."""
    psf, cy, cx = _psf_taps(psf)
    out = np.zeros(x.shape[1:])
    for i in range(psf.shape[0]):
        for a, b in zip(*np.nonzero(psf[i])):
            out += psf[i, a, b] * np.roll(x[i], (a - cy, b - cx), axis=(0, 1))
    return out


def correlate_spatial(psf, v) -> np.ndarray:
    """The adjoint of convolve_spatial: x_i = h_i correlated with the padded plane v."""
    psf, cy, cx = _psf_taps(psf)
    out = np.zeros((psf.shape[0],) + v.shape)
    for i in range(psf.shape[0]):
        for a, b in zip(*np.nonzero(psf[i])):
            out[i] += psf[i, a, b] * np.roll(v, (cy - a, cx - b), axis=(0, 1))
    return out

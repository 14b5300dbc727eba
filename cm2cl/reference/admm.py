"""Float64 numpy twin of the ADMM reconstruction (paper Eq. 4), same splits and order as the
device solver, sharing only the iteration policy (:mod:`cm2cl.solver.control`)."""

from __future__ import annotations

import numpy as np

from .forward import centered_psf, crop, crop_offsets, embed
from .tv import tv_prox, tv_value


def normalisation(psf, y, padded_shape):
    """(psf_scale, y_scale): ||H|| = 1 after scaling the PSFs, max|y| = 1 after scaling y (1 for y = 0)."""
    Hs = np.fft.rfft2(centered_psf(np.asarray(psf, np.float64), padded_shape))
    ymax = float(np.max(np.abs(y)))
    return 1.0 / np.sqrt((np.abs(Hs) ** 2).sum(axis=0).max()), (1.0 / ymax if ymax > 0 else 1.0)


def admm(y, psf, params=None, padded_shape=None, dtype=np.float64, workers=None, callback=None,
         weights=None, x0=None, state=None, **kw):
    """Float64 (or ``dtype``) numpy ADMM for paper Eq. 4 with the splits of DESIGN.md section 3.

    Same algorithm, order of updates, residuals, balancing and stopping as the device solver.
    ``workers`` is passed to scipy.fft (-1 = all cores). ``x0``: a warm start on the padded grid in the
    volume's units (x, u and w start there, the duals at zero). ``state``: a dict that receives the
    final iterates of the normalised problem (x, u, w, v and the duals rho, eta, xi, the TV dual p as
    px, py, pz). Returns a Reconstruction.
    """
    import scipy.fft as sfft

    from ..solver.control import Control, ProblemScale
    from ..solver.params import ADMMParams
    from ..solver.result import Reconstruction

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

    wts = np.ones(M) if weights is None else np.asarray(weights, np.float64)
    s_h, s_y = normalisation(psf, np.where(wts > 0, y, 0.0), P) if p.normalize else (1.0, 1.0)
    cdt = np.complex64 if dt == np.float32 else np.complex128
    Hs = (rfft(centered_psf(psf * s_h, P))).astype(cdt)
    hn2 = (np.abs(Hs) ** 2).sum(axis=0).astype(dt)
    ys = (y * s_y).astype(dt)
    mask = embed(wts, P).astype(dt)   # each pixel's weight in the data term, 0 outside the sensor
    cty = embed(ys, P).astype(dt)

    x = np.zeros((nz,) + P, dt)
    if x0 is not None:
        x = (np.maximum(np.asarray(x0, np.float64), 0) * (s_y / s_h)).astype(dt)
    u, w = x.copy(), x.copy()
    eta, rho = (np.zeros_like(x) for _ in range(2))
    pd = np.zeros((3,) + x.shape, dt)
    v = np.zeros(P, dt)
    xi = np.zeros(P, dt)
    ctl = Control(p, ProblemScale.of(np.where(wts > 0, y * s_y, 0.0), float(np.sum((psf * s_h) ** 2)), nz),
                  callback)
    l1, tv = ctl.l1, ctl.tv
    # each plane's l1 weight: ||h_i||^q / mean ||h_j||^q of the normalised stack (all ones for q = 0)
    hn = np.sqrt(np.sum((psf * s_h).reshape(nz, -1) ** 2, axis=1)) ** float(p.l1_plane_power)
    lw = (hn / hn.mean())[:, None, None]
    v = (mask * cty / (mask + ctl.mu_v)).astype(dt)  # the data split's minimiser at x = 0: the first x step sees the data
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
        w_new = np.maximum(x + rho / mu_w - l1 * lw / mu_w, 0).astype(dt)
        rho += mu_w * (x - w_new)
        # v step: crop-aware data update
        v_new = ((mask * cty + mu_v * hx + xi) / (mask + mu_v)).astype(dt)
        xi += mu_v * (hx - v_new)
        # u step: TV prox, warm-started dual
        z = x + eta / mu_u
        if tv > 0:
            u_new, pd = tv_prox(z, tv / mu_u, p.tv_iters, pd, p.tv_axial_weight, p.tv_isotropic)
        else:
            u_new = z
        u_new = u_new.astype(dt)
        eta += mu_u * (x - u_new)
        done = ctl.update(it, data2=float(np.sum(wts * (crop(hx.astype(np.float64), M) - ys) ** 2)), l1=float(np.sum(lw * np.abs(x))),
                          tv=tv_value(x, p.tv_axial_weight, p.tv_isotropic), dx2=dx2, x2=sq(x),
                          rv2=sq(hx - v_new), dv2=sq(v_new - v), ru2=sq(x - u_new), du2=sq(u_new - u),
                          rw2=sq(x - w_new), dw2=sq(w_new - w), hx2=sq(hx), v2=sq(v_new), xi2=sq(xi),
                          w2=sq(w_new), rho2=sq(rho), u2=sq(u_new), eta2=sq(eta))
        v, u, w = v_new, u_new, w_new
        if done:
            break
    if state is not None:
        state.update(x=x, u=u, w=w, v=v, rho=rho, eta=eta, xi=xi, px=pd[0], py=pd[1], pz=pd[2])
    oy, ox = crop_offsets(M, P)
    vol = np.maximum(x, 0) * (s_h / s_y)
    return Reconstruction(volume_padded=vol, crop=(slice(oy, oy + M[0]), slice(ox, ox + M[1])),
                          log=ctl.log, scaling={"psf_scale": s_h, "y_scale": s_y},
                          params=p.as_dict(), info={"device": "numpy", "dtype": dt.name, "padded_shape": P,
                                                    **ctl.summary()})

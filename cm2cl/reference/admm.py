"""Float64 numpy twin of the ADMM reconstruction (paper Eq. 4): the same splits as the device solver, each
term with its own state (:mod:`.terms`), sharing only the iteration policy (:mod:`cm2cl.solver.control`)."""

from __future__ import annotations

import numpy as np

from .forward import centered_psf, crop, crop_offsets, embed
from .terms import L1, TV, LeastSquares, LeastSquaresBackground, ReweightedL1, sq, support_extent


def normalisation(psf, y, padded_shape):
    """(psf_scale, y_scale): ||H|| = 1 after scaling the PSFs, max|y| = 1 after scaling y (1 for y = 0)."""
    Hs = np.fft.rfft2(centered_psf(np.asarray(psf, np.float64), padded_shape))
    ymax = float(np.max(np.abs(y)))
    return 1.0 / np.sqrt((np.abs(Hs) ** 2).sum(axis=0).max()), (1.0 / ymax if ymax > 0 else 1.0)


def admm(y, psf, params=None, padded_shape=None, dtype=np.float64, workers=None, callback=None,
         weights=None, x0=None, state=None, **kw):
    """Float64 (or ``dtype``) numpy ADMM for paper Eq. 4: the x step, then each term's update (:mod:`.terms`).

    Same algorithm, order of updates, residuals, balancing and stopping as the device solver.
    ``workers`` is passed to scipy.fft (-1 = all cores). ``x0``: a warm start on the padded grid in the
    volume's units (x, u and w start there with their duals at zero; v at H x0 and the data dual xi at the
    data term's gradient there). ``state``: a dict that receives the
    final iterates of the normalised problem (x, u, w, v and the duals rho, eta, xi, the TV dual p as
    px, py, pz). Returns a Reconstruction.
    """
    import scipy.fft as sfft

    from ..solver.control import Control, ProblemScale, SplitStats
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
    ctl = Control(p, ProblemScale.of(np.where(wts > 0, y * s_y, 0.0), float(np.sum((psf * s_h) ** 2)), nz, nz * P[0] * P[1]),
                  callback, cold=x0 is None)
    # each plane's l1 weight: ||h_i||^q (sum h_i)^(1 - q), over its mean (ones for q = 0 and planes of equal light)
    q = float(p.l1_plane_power)
    flat = psf.reshape(nz, -1)
    light = np.abs(flat.sum(axis=1))
    hn = np.sqrt(np.sum(flat ** 2, axis=1)) ** q * np.maximum(light, 1e-12 * light.max()) ** (1 - q)
    if p.background == "model":   # knots a quarter of the PSF support apart, within [8 px, the sensor]
        spacing = p.background_scale_px or min(max(0.25 * max(support_extent(psf)), 8.0), max(M))
        data = LeastSquaresBackground(cty, mask, ys, wts, M, dt, spacing)
    else:
        data = LeastSquares(cty, mask, ys, wts, M, dt)
    data.start(ctl.mu["v"])
    if x0 is not None:   # v at H x0, the data dual at the data term's gradient there (the regularisers' at 0)
        data.warm(irfft((Hs * rfft(x)).sum(axis=0)).astype(np.float64))
    lw = (hn / hn.mean())[:, None, None]
    l1 = ReweightedL1(x, lw, p.l1_reweight, p.l1_reweight_eps) if p.l1_reweight else L1(x, lw)
    regs = (TV(x, p.tv_iters, p.tv_axial_weight, p.tv_isotropic), l1)
    weight = {"u": ctl.tv, "w": ctl.l1}
    for it in range(1, p.max_iter + 1):
        mu = dict(ctl.mu)
        # x step: (mu_v H^T H + c I) x = H^T (mu_v v - xi) + sum_t (mu_t z_t - dual_t), c = sum_t mu_t over
        # the active splits (TV off: its split u = x_prev would only hold x back)
        mx = {t.split: (mu[t.split] if ctl.active[t.split] else 0.0) for t in regs}
        c = sum(mx.values())
        B = np.conj(Hs) * rfft(data.rhs(mu["v"]))[None] + rfft(sum(t.rhs(mx[t.split]) for t in regs))
        HX = (Hs * B).sum(axis=0) / (c + mu["v"] * hn2)
        x_new = irfft((B - mu["v"] * np.conj(Hs) * HX[None]) / c).astype(dt)
        hx = irfft(HX).astype(dt)
        dx2 = sq(x_new.astype(np.float64) - x)
        x = x_new
        stats, objective = data.update(hx, mu["v"], p.relaxation)
        splits = {"v": SplitStats(**stats)}
        for t in regs:
            st, obj = t.update(x, mu[t.split], weight[t.split], p.relaxation)
            splits[t.split] = SplitStats(**st)
            objective.update(obj)
        if ctl.update(it, dx2=dx2, x2=sq(x), splits=splits, objective=objective, changes=data.changes()):
            if not (p.l1_reweight and l1.next_round(x)):
                break
            ctl.converged, ctl.calm, ctl.stop = False, 0, "max_iter"   # another round of l1 weights
    tv = regs[0]
    if state is not None:
        state.update(x=x, u=tv.u, w=l1.w, v=data.v, rho=l1.rho, eta=tv.eta, xi=data.xi, px=tv.p[0], py=tv.p[1],
                     pz=tv.p[2])
    oy, ox = crop_offsets(M, P)
    vol = np.maximum(x, 0) * (s_h / s_y)
    background = data.b / s_y if p.background == "model" else None
    return Reconstruction(volume_padded=vol, crop=(slice(oy, oy + M[0]), slice(ox, ox + M[1])),
                          log=ctl.log, scaling={"psf_scale": s_h, "y_scale": s_y}, background=background,
                          params=p.as_dict(), info={"device": "numpy", "dtype": dt.name, "padded_shape": P,
                                                    **ctl.summary()})

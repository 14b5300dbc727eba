"""Float64 numpy twins of the objective's terms, each a split of the ADMM with its own state: the
least-squares data term on v = Hx, l1 + non-negativity on w = x, TV on u = x. Each reports the same
squared norms as its device kernels (the penalty policy and the stopping rule read them)."""

from __future__ import annotations

import numpy as np

from .forward import crop
from .tv import tv_prox, tv_value


def sq(a) -> float:
    return float(np.sum(np.asarray(a, np.float64) ** 2))


class LeastSquares:
    """1/2 ||C H x - y||^2_W on v = Hx: v' = (C^T W y + mu a + xi) / (C^T W C + mu), xi += mu (a - v'), with
    a = alpha Hx + (1 - alpha) v the over-relaxed Hx (alpha = 1: plain ADMM)."""

    split, kind = "v", "data"

    def __init__(self, cty, mask, ys, wts, M, dt):
        self.cty, self.mask, self.ys, self.wts, self.M, self.dt = cty, mask, ys, wts, M, dt
        self.xi = np.zeros_like(cty)

    def start(self, mu):
        self.v = (self.mask * self.cty / (self.mask + mu)).astype(self.dt)   # v's minimiser at x = 0

    def warm(self, hx):
        """A warm start at x0 (``hx`` = H x0): v = H x0 and xi the data term's gradient there,
        mask (H x0 - y) with mask = C^T W C (the v step's fixed point for a = v)."""
        self.v = hx.astype(self.dt)
        self.xi = (self.mask * (hx - self.cty)).astype(self.dt)

    def rhs(self, mu):
        return mu * self.v - self.xi

    def update(self, hx, mu, alpha=1.0):
        a = alpha * hx + (1.0 - alpha) * self.v
        v_new = ((self.mask * self.cty + mu * a + self.xi) / (self.mask + mu)).astype(self.dt)
        self.xi += mu * (a - v_new)
        stats = dict(r2=sq(hx - v_new), d2=sq(v_new - self.v), ax2=sq(hx), z2=sq(v_new), dual2=sq(self.xi))
        self.v = v_new
        return stats, {"data": 0.5 * float(np.sum(self.wts * (crop(hx.astype(np.float64), self.M) - self.ys) ** 2))}

    def changes(self):
        """(||z - z_old||^2, ||z||^2) of variables besides the split: the stopping rule waits for them too."""
        return {}


class L1:
    """l1 sum_z c_z |x_z| + i(x >= 0) on w = x: w' = max(a + rho/mu - l1 c/mu, 0), rho += mu (a - w'), with
    a = alpha x + (1 - alpha) w the over-relaxed x."""

    split, kind = "w", "identity"

    def __init__(self, x, plane_weights):
        self.w, self.rho, self.lw = x.copy(), np.zeros_like(x), plane_weights

    def rhs(self, mu):
        return mu * self.w - self.rho

    def update(self, x, mu, weight, alpha=1.0):
        a = alpha * x + (1.0 - alpha) * self.w
        w_new = np.maximum(a + self.rho / mu - weight * self.lw / mu, 0).astype(x.dtype)
        self.rho += mu * (a - w_new)
        stats = dict(r2=sq(x - w_new), d2=sq(w_new - self.w), ax2=sq(x), z2=sq(w_new), dual2=sq(self.rho))
        self.w = w_new
        return stats, {"l1": float(np.sum(self.lw * np.abs(x)))}


class TV:
    """tv TV(x) on u = x: u' = prox_{tv/mu TV}(a + eta/mu) by warm-started dual iterations, eta += mu (a - u'),
    with a = alpha x + (1 - alpha) u the over-relaxed x."""

    split, kind = "u", "identity"

    def __init__(self, x, iters, axial_weight, isotropic):
        self.u, self.eta = x.copy(), np.zeros_like(x)
        self.p = np.zeros((3,) + x.shape, x.dtype)
        self.iters, self.aw, self.iso = iters, axial_weight, isotropic

    def rhs(self, mu):
        return mu * self.u - self.eta

    def update(self, x, mu, weight, alpha=1.0):
        a = alpha * x + (1.0 - alpha) * self.u if weight > 0 else x   # off: an inactive split, u = x
        z = a + self.eta / mu
        if weight > 0:
            u_new, self.p = tv_prox(z, weight / mu, self.iters, self.p, self.aw, self.iso)
        else:
            u_new = z
        u_new = u_new.astype(x.dtype)
        self.eta += mu * (a - u_new)
        stats = dict(r2=sq(x - u_new), d2=sq(u_new - self.u), ax2=sq(x), z2=sq(u_new), dual2=sq(self.eta))
        self.u = u_new
        return stats, {"tv": tv_value(x, self.aw, self.iso)}


def cubic_bspline(t):
    """The uniform cubic B-spline kernel (support |t| < 2, integral 1)."""
    a = np.abs(np.asarray(t, np.float64))
    return np.where(a < 1, (4 - 6 * a**2 + 3 * a**3) / 6, np.where(a < 2, (2 - a) ** 3 / 6, 0.0))


def background_basis(n_pixels: int, spacing: float) -> np.ndarray:
    """(n_pixels, n): cubic B-splines centred at -h, 0, h, ..., (n_pixels - 1) + h, with h the largest
    spacing <= ``spacing`` that divides the pixels' span."""
    m = max(1, int(np.ceil((n_pixels - 1) / spacing)))
    h = max(n_pixels - 1, 1) / m
    centres = (np.arange(m + 3) - 1.0) * h
    spacing = h
    return cubic_bspline((np.arange(n_pixels)[:, None] - centres[None, :]) / spacing)


def support_extent(psf, fraction=1 - 1e-6):
    """The lateral extent (rows, columns) of the PSF stack holding ``fraction`` of its light."""
    h = np.abs(np.asarray(psf, np.float64))
    out = []
    for axis in (2, 1):
        prof = h.sum(axis=(0, axis))
        c = np.cumsum(prof) / prof.sum()
        lo = int(np.searchsorted(c, (1 - fraction) / 2, side="right"))
        hi = min(int(np.searchsorted(c, 1 - (1 - fraction) / 2, side="left")), int(np.flatnonzero(prof)[-1]))
        out.append(hi - max(min(lo, hi), int(np.flatnonzero(prof)[0])) + 1)
    return tuple(out)


class LeastSquaresBackground(LeastSquares):
    """1/2 ||W^(1/2) (C H x + b - y)||^2 with b = B c, c >= 0, on v = Hx: the data step minimises jointly over
    (v, c); c by non-negative least squares on the whole design matrix (the solver uses its normal
    equations), v = (W (y - b) + mu a) / (W + mu) with a = alpha Hx + (1 - alpha) v + xi / mu (over-relaxed)."""

    def __init__(self, cty, mask, ys, wts, M, dt, spacing):
        super().__init__(cty, mask, ys, wts, M, dt)
        from .forward import crop_offsets

        self.B = np.kron(background_basis(M[0], spacing), background_basis(M[1], spacing))
        oy, ox = crop_offsets(M, cty.shape)
        self.sensor = (slice(oy, oy + M[0]), slice(ox, ox + M[1]))
        self.b = np.zeros(M)

    def _fit(self, a_sensor, weights):
        """b = B c, c = argmin_{c >= 0} ||weights^(1/2) (B c - (y - a))|| (NNLS on the whole design matrix)."""
        from scipy.optimize import nnls

        q = np.sqrt(np.asarray(weights, np.float64).ravel())
        c, _ = nnls(q[:, None] * self.B, q * (self.ys.astype(np.float64) - a_sensor).ravel(), maxiter=100 * self.B.shape[1])
        b = (self.B @ c).reshape(self.M)
        self.change = (sq(b - self.b), sq(b))
        self.b = b
        self.target = self.cty.astype(np.float64).copy()
        self.target[self.sensor] -= self.b

    def start(self, mu):
        self.target = self.cty.astype(np.float64)   # b = 0: the first data step fits it
        self.change = (0.0, 0.0)
        super().start(mu)

    def changes(self):
        return {"b": self.change}

    def warm(self, hx):
        """As :meth:`LeastSquares.warm` with b first fitted to y - C H x0 with the pixels' own weights (the
        v step's fit as mu grows): xi = mask (H x0 - (y - b))."""
        self._fit(hx[self.sensor], self.wts)
        self.change = (0.0, 0.0)   # the start's b: the first data step's change is measured from it
        self.v = hx.astype(self.dt)
        self.xi = (self.mask * (hx - self.target)).astype(self.dt)

    def update(self, hx, mu, alpha=1.0):
        hr = alpha * hx + (1.0 - alpha) * self.v
        self._fit((hr + self.xi / mu)[self.sensor], self.wts * mu / (self.wts + mu))
        v_new = ((self.mask * self.target + mu * hr + self.xi) / (self.mask + mu)).astype(self.dt)
        self.xi += mu * (hr - v_new)
        stats = dict(r2=sq(hx - v_new), d2=sq(v_new - self.v), ax2=sq(hx), z2=sq(v_new), dual2=sq(self.xi))
        self.v = v_new
        fit = crop(hx.astype(np.float64), self.M) + self.b - self.ys
        return stats, {"data": 0.5 * float(np.sum(self.wts * fit ** 2))}


class ReweightedL1(L1):
    """L1 with a weight per voxel, renewed to eps / (x + eps) (eps = ``eps_fraction`` x max x) each time the
    solve converges, ``rounds`` times (Candes, Wakin & Boyd 2008)."""

    def __init__(self, x, plane_weights, rounds, eps_fraction):
        super().__init__(x, plane_weights)
        self.plane, self.rounds, self.eps_fraction, self.done = plane_weights, rounds, eps_fraction, 0
        self.voxel = np.ones_like(x)

    def update(self, x, mu, weight, alpha=1.0):
        self.lw = self.plane * self.voxel
        return super().update(x, mu, weight, alpha)

    def next_round(self, x) -> bool:
        xp = np.maximum(x, 0)
        eps = self.eps_fraction * float(xp.max())
        if self.done >= self.rounds or eps <= 0:
            return False
        self.voxel = (eps / (xp + eps)).astype(x.dtype)
        self.done += 1
        return True

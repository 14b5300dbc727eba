"""Iteration control shared by the device ADMM and its float64 twin: the problem's scale (noise level,
spectral spread of H), the default weights and initial penalties taken from it, the log row, penalty
adaptation, and the stopping rule. Both solvers hand it the same squared norms, so penalties and
decisions are equal across them. Pure numpy: no device code.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .params import ADMMParams

#: the noise estimate is floored at this fraction of max(y): below it (e.g. noise-free simulations)
#: the weights would vanish and the problem would lose its regularisation
NOISE_FLOOR = 1e-4
#: absolute floor of the scales of the relative residuals and of the relative change, as a fraction
#: of ||y|| on the normalised problem (any x that fits the data has ||x|| >= ||y|| since ||H|| = 1):
#: an iterate that vanishes (weights far above the data) is judged against the data's scale, not 0
ABS_FRACTION = 1e-3


def noise_sigma(y) -> float:
    """Robust estimate of the white-noise standard deviation of an image: the median absolute deviation
    of y minus the mean of its 4 neighbours (that residual has variance 1.25 sigma^2 for white noise,
    and smooth structure cancels in it), times 1.4826 (MAD -> sigma for a Gaussian)."""
    y = np.asarray(y, np.float64)
    if y.ndim != 2 or min(y.shape) < 3:
        return 0.0
    d = y[1:-1, 1:-1] - 0.25 * (y[:-2, 1:-1] + y[2:, 1:-1] + y[1:-1, :-2] + y[1:-1, 2:])
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(1.25))


@dataclass(frozen=True)
class ProblemScale:
    """What the defaults are derived from, all on the normalised problem (max y = 1, ||H|| = 1)."""

    #: estimated noise standard deviation of the normalised measurement (floored at NOISE_FLOOR)
    noise_sigma: float
    #: mean over frequencies of sum_i |H_i(k)|^2 = sum_i ||h_i||^2 (Parseval); its maximum is 1
    spectral_mean: float
    #: ||y|| of the normalised measurement
    y_norm: float = 1.0
    #: number of depth planes
    planes: int = 1

    @classmethod
    def of(cls, y_normalised, spectral_mean: float, planes: int = 1) -> "ProblemScale":
        """From the normalised measurement (My, Mx), sum_i ||h_i||^2 of the normalised PSF stack and the
        number of planes."""
        y = np.asarray(y_normalised, np.float64)
        return cls(noise_sigma=max(noise_sigma(y), NOISE_FLOOR), spectral_mean=float(spectral_mean),
                   y_norm=float(np.sqrt(np.sum(y * y))), planes=max(int(planes), 1))

    @property
    def noise_x(self) -> float:
        """Noise level in the volume's domain: the standard deviation of the back-projection h_i^T n of
        white sensor noise n (std noise_sigma) at one voxel, sigma ||h_i||, with ||h_i|| the RMS plane
        norm sqrt(spectral_mean / planes). A weight above |h_i^T y| keeps voxel i at 0, so weights meant
        to suppress noise scale with this, not with sigma: for a spread PSF (lensless, many planes)
        ||h_i|| is far below ||H|| = 1, and weights of the order of sigma erase real structure."""
        return self.noise_sigma * float(np.sqrt(self.spectral_mean / self.planes))

    def weights(self, p: ADMMParams) -> tuple[float, float]:
        """(l1, tv): the given weights, or the defaults relative to the volume-domain noise level."""
        l1 = p.l1 if p.l1 is not None else p.l1_noise_ratio * self.noise_x
        tv = p.tv if p.tv is not None else p.tv_noise_ratio * self.noise_x
        return float(l1), float(tv)

    def penalties(self, p: ADMMParams) -> tuple[float, float, float]:
        """Initial (mu_v, mu_u, mu_w): the given ones, or mu_v = 1 (the curvature of the data term on
        the normalised problem) and mu_u = mu_w = spectral_mean * mu_v: the x step then weighs the
        data and the splits equally at a frequency of average power. With mu_u + mu_w near 1 (the old
        default) the splits dominate at every frequency but the strongest, and the solve creeps. The
        adaptation raises penalties that start low quickly and reliably; one that starts far too high
        is corrected less well (measured in docs/accuracy_vs_time.md), so the start errs low."""
        mu_v = p.mu_v if p.mu_v is not None else 1.0
        ratio = float(min(max(self.spectral_mean, 1e-12), 1.0))
        mu_u = p.mu_u if p.mu_u is not None else ratio * mu_v
        mu_w = p.mu_w if p.mu_w is not None else ratio * mu_v
        return float(mu_v), float(mu_u), float(mu_w)


def _ratio(a: float, b: float) -> float:
    """a / b for non-negative a, b, with 0/0 = 1 and x/0 = inf."""
    if b > 0:
        return a / b
    return 1.0 if a == 0 else np.inf


class Control:
    """Penalties (mu_v, mu_u, mu_w), the log, and the decision to stop."""

    def __init__(self, p: ADMMParams, scale: ProblemScale, callback=None, callback_every: int = 1):
        self.p = p
        self.scale = scale
        self.l1, self.tv = scale.weights(p)
        self.mu0 = scale.penalties(p)
        self.mu_v, self.mu_u, self.mu_w = self.mu0
        self.log: list[dict] = []
        self.callback, self.every = callback, max(1, int(callback_every))
        self.calm = 0
        self.stop = "max_iter"
        self.converged = False
        self.t0 = time.perf_counter()

    @property
    def tv_active(self) -> bool:
        """The u = x split carries a term only when the TV weight is positive; otherwise u = x + eta/mu_u
        = x exactly, and its penalty is neither adapted nor part of the stopping rule."""
        return self.tv > 0

    def _adapt(self, it: int, mu: float, mu0: float, r: float, s: float) -> float:
        p = self.p
        if p.penalty == "fixed":
            return mu
        if p.penalty == "balance":
            if r > p.balance_ratio * s:
                mu *= p.balance_factor
            elif s > p.balance_ratio * r:
                mu /= p.balance_factor
        else:
            if it > p.adapt_until or (it > 10 and it % 10):
                return mu
            q = _ratio(r, s)
            if q > p.adapt_ratio or q < 1.0 / p.adapt_ratio:
                step = np.sqrt(q) if np.isfinite(q) else p.adapt_max_step
                mu *= float(np.clip(step, 1.0 / p.adapt_max_step, p.adapt_max_step))
        return float(np.clip(mu, mu0 / p.mu_range, mu0 * p.mu_range))

    def update(self, it, *, data2, l1, tv, dx2, x2, rv2, dv2, ru2, du2, rw2, dw2,
               hx2, v2, xi2, w2, rho2, u2, eta2) -> bool:
        """Record iteration `it` from squared norms (rv2 = ||Hx - v||^2, dv2 = ||v - v_old||^2, ...;
        data2 = ||C Hx - y||^2; hx2, v2, xi2, w2, rho2, u2, eta2: squared norms of the new iterates and
        duals), adapt the penalties, and return True when the run should stop.

        Dual residuals are mu ||z - z_old|| in the space of each split variable z (for v = Hx this
        bounds mu_v ||H^T (v - v_old)|| since ||H|| = 1 after normalisation); relative residuals divide
        the primal one by max(||A x||, ||z||) and the dual one by ||dual variable|| (Boyd et al. 2011,
        section 3.3.1)."""
        p = self.p
        sq = np.sqrt
        r_v, s_v = sq(rv2), self.mu_v * sq(dv2)
        r_u, s_u = sq(ru2), self.mu_u * sq(du2)
        r_w, s_w = sq(rw2), self.mu_w * sq(dw2)
        nx = sq(x2)
        # (for y = 0 the answer is x = 0 and every norm is 0: the smallest positive floor lets 0/floor = 0)
        floor = max(ABS_FRACTION * self.scale.y_norm, np.finfo(np.float64).tiny)
        # dual residuals are in units of mu * (split variable); their scale is the dual variable or,
        # while the duals are still building up from 0, mu times the split variable
        rel = {
            "v": (_ratio(r_v, max(sq(hx2), sq(v2), floor)),
                  _ratio(s_v, max(sq(xi2), self.mu_v * max(sq(v2), floor)))),
            "w": (_ratio(r_w, max(nx, sq(w2), floor)),
                  _ratio(s_w, max(sq(rho2), self.mu_w * max(sq(w2), floor)))),
            "u": ((_ratio(r_u, max(nx, sq(u2), floor)),
                   _ratio(s_u, max(sq(eta2), self.mu_u * max(sq(u2), floor))))
                  if self.tv_active else (0.0, 0.0)),
        }
        rel_change = _ratio(sq(dx2), max(nx, floor))
        primal_rel = max(r for r, _ in rel.values())
        dual_rel = max(s for _, s in rel.values())
        data = 0.5 * data2
        row = dict(objective=data + self.l1 * l1 + self.tv * tv, data=data, l1=l1, tv=tv, rel_change=rel_change,
                   primal=np.sqrt(r_v**2 + r_u**2 + r_w**2), dual=np.sqrt(s_v**2 + s_u**2 + s_w**2),
                   primal_rel=primal_rel, dual_rel=dual_rel,
                   r_v=r_v, s_v=s_v, r_u=r_u, s_u=s_u, r_w=r_w, s_w=s_w,
                   mu_v=self.mu_v, mu_u=self.mu_u, mu_w=self.mu_w, seconds=time.perf_counter() - self.t0)
        row = {"iter": int(it), **{k: float(v) for k, v in row.items()}}
        self.log.append(row)
        if self.callback is not None and (it % self.every == 0 or it == p.max_iter):
            self.callback(row)
        mv, mu, mw = self.mu0
        self.mu_v = self._adapt(it, self.mu_v, mv, r_v, s_v)
        self.mu_w = self._adapt(it, self.mu_w, mw, r_w, s_w)
        if self.tv_active:
            self.mu_u = self._adapt(it, self.mu_u, mu, r_u, s_u)
        ok = primal_rel <= p.tol and dual_rel <= p.tol and rel_change <= p.tol_change
        self.calm = self.calm + 1 if ok else 0
        if self.calm >= p.patience:
            self.stop, self.converged = "converged", True
            return True
        return False

    def summary(self) -> dict:
        """What the result records about the control: why it stopped, and what the defaults came from."""
        return {"stop": self.stop, "converged": self.converged, "l1": self.l1, "tv": self.tv,
                "noise_sigma": self.scale.noise_sigma, "noise_x": self.scale.noise_x, "spectral_mean": self.scale.spectral_mean,
                "initial_penalties": {"mu_v": self.mu0[0], "mu_u": self.mu0[1], "mu_w": self.mu0[2]},
                "penalty_policy": self.p.penalty, "tol": self.p.tol, "tol_change": self.p.tol_change}

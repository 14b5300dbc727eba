"""Iteration control shared by the device ADMM and its float64 twin: the log row, residual
balancing of the penalties, and the stopping rule. Both solvers hand it the same squared norms."""

from __future__ import annotations

import time

import numpy as np

from .params import ADMMParams, balance


class Control:
    """Penalties (mu_v, mu_u, mu_w), the log, and the decision to stop."""

    def __init__(self, p: ADMMParams, callback=None, callback_every: int = 1):
        self.p = p
        self.mu_v, self.mu_u, self.mu_w = p.mu_v, p.mu_u, p.mu_w
        self.log: list[dict] = []
        self.callback, self.every = callback, max(1, int(callback_every))
        self.calm = 0
        self.stop = "max_iter"
        self.t0 = time.perf_counter()

    def update(self, it, *, data2, l1, tv, dx2, x2, rv2, dv2, ru2, du2, rw2, dw2) -> bool:
        """Record iteration `it` from squared norms (rv2 = ||Hx - v||^2, dv2 = ||v - v_old||^2, ...;
        data2 = ||C Hx - y||^2), adapt the penalties, and return True when the run should stop.

        Dual residuals are mu ||z - z_old|| in the space of each split variable z (for v = Hx this
        bounds mu_v ||H^T (v - v_old)|| since ||H|| = 1 after normalisation)."""
        p = self.p
        r_v, s_v = np.sqrt(rv2), self.mu_v * np.sqrt(dv2)
        r_u, s_u = np.sqrt(ru2), self.mu_u * np.sqrt(du2)
        r_w, s_w = np.sqrt(rw2), self.mu_w * np.sqrt(dw2)
        data = 0.5 * data2
        rel = np.sqrt(dx2) / max(np.sqrt(x2), 1e-300)
        row = dict(objective=data + p.l1 * l1 + p.tv * tv, data=data, l1=l1, tv=tv, rel_change=rel,
                   primal=np.sqrt(r_v**2 + r_u**2 + r_w**2), dual=np.sqrt(s_v**2 + s_u**2 + s_w**2),
                   r_v=r_v, s_v=s_v, r_u=r_u, s_u=s_u, r_w=r_w, s_w=s_w,
                   mu_v=self.mu_v, mu_u=self.mu_u, mu_w=self.mu_w, seconds=time.perf_counter() - self.t0)
        row = {"iter": int(it), **{k: float(v) for k, v in row.items()}}
        self.log.append(row)
        if self.callback is not None and (it % self.every == 0 or it == p.max_iter):
            self.callback(row)
        self.mu_v = balance(self.mu_v, r_v, s_v, p)
        self.mu_u = balance(self.mu_u, r_u, s_u, p)
        self.mu_w = balance(self.mu_w, r_w, s_w, p)
        self.calm = self.calm + 1 if rel < p.tol else 0
        if self.calm >= p.patience:
            self.stop = "tol"
            return True
        if p.tol_residual > 0 and max(r_v, s_v, r_u, s_u, r_w, s_w) < p.tol_residual:
            self.stop = "tol_residual"
            return True
        return False

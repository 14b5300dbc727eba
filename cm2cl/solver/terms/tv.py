"""3D total variation tv TV(x) on the split u = x: u = prox_{tau TV}(x + eta/mu_u) by warm-started
projected-gradient iterations on the dual p = (px, py, pz) (kernels/tv.cl), with u and eta stored."""

from __future__ import annotations

from ..control import SplitStats
from .base import IdentityTerm


class TV(IdentityTerm):
    split = "u"
    volumes = ("u", "eta", "z", "px", "py", "pz")
    sums = ("tv", "ru2", "su2", "u2", "eta2")
    rhs_reads = ("u", "eta")

    def active(self, ctl) -> bool:
        return ctl.tv > 0

    def add_rhs(self, s, part, j, n, a, mu, first) -> None:
        ny, nx = s.P
        s.row_grid(part, "combine", out=a["g"], p=a["u"], q=a["eta"], a=mu, b=-1.0, add=not first, planes=n, ny=ny,
                   nx=nx)

    def update(self, s, ctl) -> None:
        p, (ny, nx), mu = s.p, s.P, ctl.mu["u"]
        tau = ctl.tv / mu
        # z = alpha x + (1 - alpha) u + eta / mu: the prox's argument, over-relaxed (TV off: u = x, inactive)
        alpha = p.relaxation if tau > 0 else 1.0
        for i, part, j0, j1, n, a in s.walk.runs(("x", "u", "eta"), ("z",)):
            s.row_grid(part, "combine", out=a["z"], p=a["x"], q=a["u"], a=alpha, b=1.0 - alpha, add=False, planes=n,
                       ny=ny, nx=nx)
            s.row_grid(part, "combine", out=a["z"], p=a["eta"], q=a["eta"], a=1.0 / mu, b=0.0, add=True, planes=n,
                       ny=ny, nx=nx)
        grid = ("px", "py", "pz")
        for _ in range(p.tv_iters if tau > 0 else 0):
            # the last slab first: its residual needs the previous slab's p before this step, its dual
            # step the next slab's residual (already computed), as all residuals and then all steps
            for i, part, j, n, a in s.walk.slabs(grid + ("z",), grid, edges=("g",), reverse=True):
                s.row_grid(part, "tv_residual", g=a["g"], px=a["px"], py=a["py"], pz=a["pz"], x=a["z"], z=a["z"],
                           first=0, u=a["z"], alpha=1.0, tau=tau, inv_tau=1.0 / tau, aw=p.tv_axial_weight, planes=n, ny=ny, nx=nx,
                           **s.walk.neighbours(i, j, j, a, "pz"))
                gn, hn = s.walk.next(i, j, "g")
                s.row_grid(part, "tv_dual_step", px=a["px"], py=a["py"], pz=a["pz"], g=a["g"],
                           g_next=gn if hn else a["g"], has_next=hn, step=p.tv_step, aw=p.tv_axial_weight,
                           iso=p.tv_isotropic, planes=n, ny=ny, nx=nx)
        for i, part, j0, j1, n, a in s.walk.runs(("u", "eta", "x", "z") + grid, ("u", "eta")):
            xn, has_next = s.walk.next(i, j1, "x")
            nb = s.walk.neighbours(i, j0, j1, a, "pz")
            assert nb["has_next"] == has_next
            s.reduce_rows(part, "tv_update", "u", u=a["u"], eta=a["eta"], x=a["x"], x_next=xn if has_next else a["x"],
                          z=a["z"], px=a["px"], py=a["py"], pz=a["pz"], tau=tau, mu=mu, aw=p.tv_axial_weight,
                          iso=p.tv_isotropic, planes=n, ny=ny, nx=nx, **nb)

    def weights(self, ctl) -> dict:
        return {"tv": ctl.tv}

    def stats(self, v: dict) -> SplitStats:
        return SplitStats(v["ru2"], v["su2"], v["x2"], v["u2"], v["eta2"])

    def objective(self, v: dict) -> dict:
        return {"tv": v["tv"]}

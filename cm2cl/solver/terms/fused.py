"""The default objective {least squares, l1 + non-negativity, TV} on the lean state: the fast path.

Per voxel the iteration keeps x, g (the previous x, then scratch), s, u and the TV dual p = (px, py,
pz); w, rho and eta are derived exactly wherever a kernel needs them (kernels/splits.cl, tv.cl):

* w split: s = xr + rho_old / mu_w (xr = alpha x + (1 - alpha) w_old, over-relaxed), so that
  w = max(s - c / mu_w, 0) and rho = min(mu_w s, c) with
  c = l1 l1w[z]; :attr:`DefaultSet.l1_split` holds the (l1, mu_w) s was made with, so w and rho are the
  same before and after the penalty policy changes mu_w.
* u split: eta = tv div p (p as the last dual iterations left it, :attr:`DefaultSet.tv_split` the tv);
  the prox's argument z = x + eta / mu_u lives in the x spectra's buffer while the TV prox runs.
* x step: its rhs mu_u u - eta + mu_w w - rho is made by tv_finish for the penalties of its iteration
  (into g, free by then); the next x step uses it where they still hold (:attr:`DefaultSet.rhs_for`),
  else rhs_volume makes it again.
* lean layout (:func:`cm2cl.solver.memory.plan_layout`): one slab of x spectra per part; the x step
  transforms each slab's rhs twice and the TV prox keeps z in g and its residual in that slab.

Without TV (``tv=False``: the weight is 0 whatever the measurement, the default) the set keeps x, g and
s only: u would equal x and p stay 0, so the u split is reported as the exact split u = x with a zero
dual, and each x step makes its rhs mu_w w - rho from s (3 real volumes per voxel instead of 7, and no
pass over u and p per iteration).

The same iterates as :class:`cm2cl.solver.terms.GenericSet` of the same terms (a test compares them)."""

from __future__ import annotations

import numpy as np

from ..control import SplitStats
from .data import LeastSquares
from .l1 import PlaneWeights

#: volumes of the state the default set derives instead of storing
DERIVED = ("w", "rho", "eta")


class DefaultSet:
    """The three default terms as one set of fused kernels."""

    fused = True
    volumes = ("x", "g", "s", "u", "px", "py", "pz")
    #: the volumes a warm start sets (the split variables start at x, the duals at zero)
    start_volumes = ("x", "u", "s")
    #: (kernel launch, its sums): the reductions of the fused kernels, in slot order
    sums = (("update_w", ("dx2", "x2", "l1", "tv", "rw2", "sw2", "w2", "rho2")),
            ("v", LeastSquares.sums),
            ("tv_finish", ("ru2", "su2", "u2", "eta2")))
    splits = (("v", "data"), ("u", "identity"), ("w", "identity"))
    kernels = (("splits.cl", "update_w"), ("splits.cl", "split_state"), ("tv.cl", "tv_finish"),
               ("tv.cl", "tv_eta"), ("xstep.cl", "rhs_volume"))

    def __init__(self, data=None, tv: bool = True):
        self.data = data if data is not None else LeastSquares()
        #: whether the set has TV (False: its weight is 0 for every measurement; x, g and s only)
        self.has_tv = bool(tv)
        if not self.has_tv:
            self.volumes, self.start_volumes = ("x", "g", "s"), ("x", "s")
            self.sums = DefaultSet.sums[:2]
        self.kernels = DefaultSet.kernels + tuple(k for k in self.data.kernels if k not in DefaultSet.kernels)
        self.planes = self.data.planes
        #: (l1, mu): the l1 weight and penalty s was made with; (0, 1) for a state set directly (s = w)
        self.l1_split = (0.0, 1.0)
        #: the TV weight the dual p belongs to: eta = tv_split div p
        self.tv_split = 0.0
        #: (mu_u, mu_w, l1, mu_s, tv) when g holds the rhs tv_finish made for them, else None
        self.rhs_for = None
        #: let tv_finish make the next x step's rhs (off: tests of the rhs_volume path)
        self.rhs_in_tv_finish = True

    def setup(self, s) -> None:
        self.weights = PlaneWeights(s.parts, s.l1_plane_weights, s.dtype)
        self.data.setup(s)

    def start(self, s, ctl) -> None:
        if not self.has_tv and ctl.tv > 0:
            raise ValueError(f"terms: a TV weight of {ctl.tv:g} for a set without TV")
        self.data.start(s, ctl)
        self.tv_split = ctl.tv   # p = 0: eta = 0

    def reset(self) -> None:
        self.l1_split = (0.0, 1.0)   # s = w >= 0, rho = 0
        self.rhs_for = None

    # ---- the x step's right-hand side ----------------------------------------------------------------
    def c(self, mu: dict) -> float:
        return mu["u"] + mu["w"] if self.has_tv else mu["w"]

    def rhs_ready(self, mu: dict) -> bool:
        """Whether g holds the rhs for these penalties (then the x step only transforms it)."""
        ready = self.rhs_for == (mu["u"], mu["w"], *self.l1_split, self.tv_split)
        self.rhs_for = None   # g is the new iterate after this step
        return ready

    def rhs_reads(self, ready: bool) -> tuple:
        return () if ready else ("u", "s", "px", "py", "pz") if self.has_tv else ("s",)

    def rhs(self, s, i, part, j, n, a, mu: dict) -> None:
        """rhs_volume: t = mu_u u - eta + mu_w w - rho on slab j from the state (s, p); without TV
        t = mu_w w - rho (mu_u = 0 and tv = 0: s stands in for u and p, whose values are not used)."""
        ny, nx = s.P
        l1_s, mu_s = self.l1_split
        if not self.has_tv:
            x = a["s"]
            s.row_grid(part, "rhs_volume", t=a["g"], u=x, s=x, px=x, py=x, pz=x, pz_prev=x, has_prev=0,
                       prev_planes=1, has_next=0, mu_u=0.0, mu_w=mu["w"], tv=0.0, l1_s=l1_s,
                       l1w=self.weights.slab[i][j], mu_s=mu_s, aw=s.p.tv_axial_weight, planes=n, ny=ny, nx=nx)
            return
        s.row_grid(part, "rhs_volume", t=a["g"], u=a["u"], s=a["s"], px=a["px"], py=a["py"], pz=a["pz"],
                   mu_u=mu["u"], mu_w=mu["w"], tv=self.tv_split, l1_s=l1_s, l1w=self.weights.slab[i][j], mu_s=mu_s,
                   aw=s.p.tv_axial_weight, planes=n, ny=ny, nx=nx, **s.walk.neighbours(i, j, j, a, "pz"))

    # ---- the splits after the x step --------------------------------------------------------------
    def update(self, s, ctl) -> None:
        mu = ctl.mu
        self.w_step(s, ctl.l1, mu["w"])
        self.data.update(s, ctl)
        if not self.has_tv:   # the next x step makes its rhs from s
            return
        tau = ctl.tv / mu["u"]
        zn, rn = ("g", "spec") if s.lean else ("spec", "g")   # where z and the TV residual go
        if tau > 0:
            self.tv_prox(s, tau, zn, rn)
        self.tv_finish(s, ctl, tau, zn)

    def w_step(self, s, l1, mu_w) -> None:
        """s' = x + rho/mu_w (rho from s as made with l1_split), with the objective's sums of x."""
        p, (ny, nx) = s.p, s.P
        l1_s, mu_s = self.l1_split
        for i, part, j0, j1, n, a in s.walk.runs(("x", "g", "s"), ("s",)):
            xn, has_next = s.walk.next(i, j1, "x")
            s.reduce_rows(part, "update_w", "update_w", x=a["x"], x_next=xn if has_next else a["x"],
                          has_next=has_next, x_old=a["g"], s=a["s"], l1=l1, l1w=self.weights.of(i, j0, j1),
                          mu_w=mu_w, l1_s=l1_s, mu_s=mu_s, aw=p.tv_axial_weight, iso=p.tv_isotropic,
                          alpha=p.relaxation, planes=n, ny=ny, nx=nx)
        self.l1_split = (float(l1), float(mu_w))

    def tv_prox(self, s, tau, zn, rn) -> None:
        """The dual iterations on p, one visit per slab and iteration, the last slab first (its residual
        needs the previous slab's p before this step, its dual step the next slab's residual): the first
        stores z = x + eta/mu_u in ``zn``; the residual goes to ``rn`` (lean parts: their one slab of
        spectra, whose first plane the previous slab's dual step needs next)."""
        p, (ny, nx) = s.p, s.P
        grid = ("px", "py", "pz")
        relaxed = p.relaxation != 1.0   # the first iteration's z = alpha x + (1 - alpha) u + eta / mu_u
        for k in range(p.tv_iters):
            first = k == 0
            reads = grid + ((("x", "u") if relaxed else ("x",)) if first else (zn,))
            writes = grid + ((zn,) if first else ())
            for i, part, j, n, a in s.walk.slabs(reads, writes, edges=(rn,), reverse=True):
                s.row_grid(part, "tv_residual", g=a[rn], px=a["px"], py=a["py"], pz=a["pz"],
                           x=a["x" if first else zn], z=a[zn], first=first, u=a["u"] if first and relaxed else a[zn],
                           alpha=p.relaxation if first else 1.0, tau=tau, inv_tau=1.0 / tau,
                           aw=p.tv_axial_weight, planes=n, ny=ny, nx=nx, **s.walk.neighbours(i, j, j, a, "pz"))
                gn, hn = s.walk.next(i, j, rn)
                s.row_grid(part, "tv_dual_step", px=a["px"], py=a["py"], pz=a["pz"], g=a[rn],
                           g_next=gn if hn else a[rn], has_next=hn, step=p.tv_step, aw=p.tv_axial_weight,
                           iso=p.tv_isotropic, planes=n, ny=ny, nx=nx)
                if part.lean:
                    part.keep_first_plane(a[rn], "r_next")

    def tv_finish(self, s, ctl, tau, zn) -> None:
        """u' = z - tau div p, and the next x step's rhs for this iteration's penalties (into g)."""
        p, (ny, nx), mu = s.p, s.P, ctl.x_mu()    # the rhs for the next x step's penalties
        rhs = self.rhs_in_tv_finish
        l1_s, mu_s = self.l1_split
        reads = ("u", "x", "px", "py", "pz") + ((zn,) if tau > 0 else ()) + (("s",) if rhs else ())
        for i, part, j0, j1, n, a in s.walk.runs(reads, ("u",) + (("g",) if rhs else ())):
            s.reduce_rows(part, "tv_finish", "tv_finish", u=a["u"], x=a["x"], z=a[zn if tau > 0 else "x"],
                          px=a["px"], py=a["py"], pz=a["pz"], tv=ctl.tv, tau=tau, aw=p.tv_axial_weight,
                          t=a["g" if rhs else "u"], s=a["s" if rhs else "u"], rhs=rhs, mu_u=mu["u"], mu_w=mu["w"],
                          l1_s=l1_s, l1w=self.weights.of(i, j0, j1), mu_s=mu_s, planes=n, ny=ny, nx=nx,
                          **s.walk.neighbours(i, j0, j1, a, "pz"))
        self.rhs_for = (mu["u"], mu["w"], l1_s, mu_s, self.tv_split) if rhs else None

    # ---- what the control reads --------------------------------------------------------------------
    def report(self, v: dict) -> dict:
        # without TV the u split is u = x exactly, its dual 0: no primal residual, u's change is x's
        u = (SplitStats(v["ru2"], v["su2"], v["x2"], v["u2"], v["eta2"]) if self.has_tv
             else SplitStats(0.0, v["dx2"], v["x2"], v["x2"], 0.0))
        return {"dx2": v["dx2"], "x2": v["x2"],
                "splits": {"v": self.data.stats(v), "u": u,
                           "w": SplitStats(v["rw2"], v["sw2"], v["x2"], v["w2"], v["rho2"])},
                "objective": {**self.data.objective(v), "l1": v["l1"], "tv": v["tv"]}, "changes": self.data.changes()}

    def next_round(self, s) -> bool:
        return False

    # ---- state readback ---------------------------------------------------------------------------
    def derived(self, s, name: str):
        """w, rho (from s) or eta (from p), computed on the device as the kernels that use them do."""
        if name not in DERIVED + (() if self.has_tv else ("u",)):
            return None
        if not self.has_tv and name in ("u", "eta"):   # u = x, eta = 0 exactly
            return s.walk.gather("x") if name == "u" else np.zeros((s.nz,) + s.P, s.dtype)
        (ny, nx), out = s.P, []
        l1_s, mu_s = self.l1_split
        for i, part, j, n, a in s.walk.slabs(("s", "px", "py", "pz") if self.has_tv else ("s",)):
            t = part.rt.zeros(a["s"].shape, s.dtype)
            if name == "eta":
                s.row_grid(part, "tv_eta", eta=t, px=a["px"], py=a["py"], pz=a["pz"], tv=self.tv_split,
                           aw=s.p.tv_axial_weight, planes=n, ny=ny, nx=nx, **s.walk.neighbours(i, j, j, a, "pz"))
            else:
                part.kernels("split_state", (nx, ny, n), out=t, s=a["s"], rho=name == "rho", l1_s=l1_s,
                             l1w=self.weights.slab[i][j], mu_s=mu_s, planes=n, ny=ny, nx=nx)
            out.append(t.get())
        return np.concatenate(out, axis=0)

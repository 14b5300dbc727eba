"""The least-squares data term 1/2 ||C H x - y||^2_W on the split v = Hx (crop-aware: C crops the
padded plane to the sensor, W weighs each pixel, 0 for masked ones)."""

from __future__ import annotations

import numpy as np

from ..control import SplitStats
from .base import Term


class LeastSquares(Term):
    split, kind = "v", "data"
    sums = ("rv2", "sv2", "data2", "hx2", "v2", "xi2")

    def start(self, s, ctl) -> None:
        """v starts at its minimiser for x = 0, (C^T W y) / (C^T W C + mu_v), so that the first x step
        already moves towards the data (a 1-iteration solve is not all zeros)."""
        wts, y_n = s.pixel_weights, s.y_n
        pl0 = s.parts[0].planes
        cty = np.zeros(s.P, s.dtype)
        cty[s.crop] = y_n.astype(s.dtype)
        pl0["cty"].set(cty[None])
        cw = np.zeros(s.P)
        cw[s.crop] = wts
        pl0["cw"].set(cw[None].astype(s.dtype))
        v0 = np.zeros(s.P)
        v0[s.crop] = wts * y_n / (wts + ctl.mu["v"])
        pl0["v"].set(v0[None].astype(s.dtype))

    def warm(self, s, ctl) -> None:
        """A warm start consistent with x0: v = H x0 (the whole padded plane) and xi = C^T W (C H x0 - y),
        the data term's gradient there, which is xi at every fixed point of the v step (v = (C^T W y + mu a +
        xi) / (C^T W C + mu) with a = v). With v at its x = 0 minimiser and xi = 0 instead, the first x step
        pulls x back to a fraction of x0: a start at the converged answer came back at 8.6x its objective
        (docs/warm_start.md)."""
        self._warm_planes(s, s.y_n)

    def _warm_planes(self, s, target) -> None:
        """v = H x0 (part 0's ``hx``) and xi = C^T W (C H x0 - target) on part 0's planes."""
        pl0 = s.parts[0].planes
        hx = pl0["hx"].get()[0].astype(np.float64)
        xi = np.zeros(s.P)
        xi[s.crop] = s.pixel_weights * (hx[s.crop] - target)
        pl0["v"].set(hx[None].astype(s.dtype))
        pl0["xi"].set(xi[None].astype(s.dtype))

    def rhs_plane(self, s, mu_v: float) -> None:
        """r = mu_v v - xi on part 0's plane (the x step transforms it)."""
        part, ny, nx = s.parts[0], *s.P
        pl = part.planes
        part.kernels("rhs_plane", (ny * nx,), r=pl["r"], v=pl["v"], xi=pl["xi"], mu_v=mu_v, n=ny * nx)

    def update(self, s, ctl) -> None:
        """v' = (C^T W y + mu_v a + xi) / (C^T W C + mu_v), xi += mu_v (a - v') on part 0's plane, with
        a = alpha Hx + (1 - alpha) v (over-relaxation)."""
        pl, (ny, nx) = s.parts[0].planes, s.P
        s.reduce_rows(s.parts[0], "update_v", "v", v=pl["v"], xi=pl["xi"], hx=pl["hx"], cty=pl["cty"],
                      cw=pl["cw"], mu_v=ctl.mu["v"], alpha=s.p.relaxation, py=ny, px=nx)

    def stats(self, v: dict) -> SplitStats:
        return SplitStats(v["rv2"], v["sv2"], v["hx2"], v["v2"], v["xi2"])

    def objective(self, v: dict) -> dict:
        return {"data": 0.5 * v["data2"]}

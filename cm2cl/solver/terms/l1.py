"""The l1 term with non-negativity, l1 sum_z c_z ||x_z||_1 + i(x >= 0), on the split w = x (c_z: each
plane's weight, :func:`plane_weights`), with w and its dual rho stored."""

from __future__ import annotations

import numpy as np

from ..control import SplitStats
from .base import IdentityTerm


def plane_weights(norms, power: float, light=None) -> np.ndarray:
    """Each plane's weight in the l1 term: c_i = ||h_i||^q (sum h_i)^(1 - q) / mean_j (the same), q = ``power``,
    from the planes' norms ``norms`` and their light ``light`` (sums; any common scales; None: equal light).

    Both factors scale with the plane: scaling plane i of the PSF by a scales c_i by a, so that plane i's
    answer scales by 1 / a and nothing else changes (a stack dimmed with depth, ``scattering_length_um``, is
    the plain problem with each plane's answer brightened). ||h_i|| is what noise back-projected through the
    plane scales with (q = 1), sum h_i what a smooth misfit back-projected through it scales with (q = 0,
    every plane alike where the planes hold the same light)."""
    c = np.asarray(norms, np.float64) ** float(power)
    if light is not None:
        lt = np.abs(np.asarray(light, np.float64))
        c = c * np.maximum(lt, 1e-12 * lt.max()) ** (1.0 - float(power))
    return c / np.mean(c)


class PlaneWeights:
    """Each part's plane weights on its device: per slab, and for all its planes at once."""

    def __init__(self, parts, weights, dtype):
        self.slab, self.whole = [], []
        for part in parts:
            per = [part.rt.zeros(b - a, dtype) for a, b in part.bounds]
            for (a, b), arr in zip(part.bounds, per):
                arr.set(weights[part.z0 + a:part.z0 + b].astype(dtype))
            allw = part.rt.zeros(part.z1 - part.z0, dtype) if len(per) > 1 else per[0]
            allw.set(weights[part.z0:part.z1].astype(dtype))
            self.slab.append(per)
            self.whole.append(allw)

    def of(self, i: int, j0: int, j1: int):
        """The weights of slabs j0..j1 of part i (one slab, or all of them)."""
        return self.slab[i][j0] if j0 == j1 else self.whole[i]


class L1(IdentityTerm):
    split = "w"
    volumes = ("w", "rho")
    sums = ("l1", "rw2", "sw2", "w2", "rho2")
    rhs_reads = ("w", "rho")

    def setup(self, s) -> None:
        self.plane_w = PlaneWeights(s.parts, s.l1_plane_weights, s.dtype)

    def add_rhs(self, s, part, j, n, a, mu, first) -> None:
        ny, nx = s.P
        s.row_grid(part, "combine", out=a["g"], p=a["w"], q=a["rho"], a=mu, b=-1.0, add=not first, planes=n, ny=ny,
                   nx=nx)

    def update(self, s, ctl) -> None:
        ny, nx = s.P
        for i, part, j0, j1, n, a in s.walk.runs(("x",) + self.volumes, ("w", "rho")):
            s.reduce_rows(part, "l1_update", "w", x=a["x"], w=a["w"], rho=a["rho"], l1=ctl.l1,
                          l1w=self.plane_w.of(i, j0, j1), lw=a.get("lw", a["w"]), voxel="lw" in a, mu=ctl.mu["w"],
                          alpha=s.p.relaxation, planes=n, ny=ny, nx=nx)

    def weights(self, ctl) -> dict:
        return {"l1": ctl.l1}

    def stats(self, v: dict) -> SplitStats:
        return SplitStats(v["rw2"], v["sw2"], v["x2"], v["w2"], v["rho2"])

    def objective(self, v: dict) -> dict:
        return {"l1": v["l1"]}


class ReweightedL1(L1):
    """Reweighted l1 (Candes, Wakin & Boyd 2008): after the solve converges, each voxel's weight becomes
    eps / (x + eps), eps = ``eps_fraction`` x max(x), and the solve goes on from where it was (``rounds``
    such rounds): a voxel's shrinkage falls as it grows, so strong emitters keep their light and the weak
    maxima that model mismatch leaves beside them are shrunk away. Per-voxel weights in a volume ``lw``."""

    volumes = ("w", "rho", "lw")

    def __init__(self, rounds: int = 2, eps_fraction: float = 0.1):
        self.rounds, self.eps_fraction = int(rounds), float(eps_fraction)
        self.done = 0

    def start(self, s, ctl) -> None:
        self.done = 0
        s.walk.fill(("lw",), 1.0)

    def next_round(self, s) -> bool:
        if self.done >= self.rounds:
            return False
        x = np.maximum(s.walk.gather("x"), 0)
        eps = self.eps_fraction * float(x.max())
        if eps <= 0:
            return False
        s.walk.scatter("lw", eps / (x + eps))
        self.done += 1
        return True

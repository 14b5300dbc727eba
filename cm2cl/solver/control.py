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
#: the initial data penalty mu_v on the normalised problem (every identity split starts at spectral_mean
#: x mu_v), for the solve to the stopping rule: 0.2 came within 1% of the optimum 2.3-5.8x sooner than the
#: solver of issue 28 on its bead scene, the demo and DiffuserCam 3D binned 4x (not on the 2x-binned grid),
#: the smallest value that reached 0.1% on all eight cases of docs/penalty.md. Its answers lie closer to the
#: optimum; with the PSF refinement's rounds kept at mu_v = 1 (psf_refine.ROUND_PENALTIES) the quality
#: suite passed as many scenes as at 1 and its seeds 11-13 more (docs/iterations.md, stop 50)
DATA_PENALTY = 0.2
#: the largest factor of one adaptive rebalancing (adapt_max_step's default): at mu_v = 0.2 steps of x3
#: overshot mu_w to 81x the spectral mean on DiffuserCam 3D binned 2x (835 iterations to 1%; 545-583 at x1.5)
ADAPT_MAX_STEP = 1.5
#: the first iteration at which the adaptive rule rebalances (adapt_from's default). Before it the residuals are the
#: transient of the cold start (x, the splits and their duals at 0), not the problem's: rebalancing on them raised
#: mu_w x1.5 ten times by iteration 20 on DiffuserCam 3D binned 2x, to 58x its start, and the solve then needed
#: 679 iterations to come within 1% of the optimum; rebalancing from iteration 10, 154 (docs/iterations.md, stop 54)
ADAPT_FROM = 10


def _neighbour_difference(a: np.ndarray) -> np.ndarray:
    """a less the mean of its 4 neighbours, on the interior pixels: 1.25 sigma^2 of variance for white noise of
    sigma, while structure smoother than a pixel cancels in it."""
    return a[1:-1, 1:-1] - 0.25 * (a[:-2, 1:-1] + a[2:, 1:-1] + a[1:-1, :-2] + a[1:-1, 2:])


def noise_sigma(y) -> float:
    """Robust estimate of the white-noise standard deviation of an image: the median absolute deviation
    of y minus the mean of its 4 neighbours (that residual has variance 1.25 sigma^2 for white noise,
    and smooth structure cancels in it), times 1.4826 (MAD -> sigma for a Gaussian)."""
    y = np.asarray(y, np.float64)
    if y.ndim != 2 or min(y.shape) < 3:
        return 0.0
    d = _neighbour_difference(y)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(1.25))


def data_misfit(y, model, weights=None) -> dict:
    """The misfit of a ``model`` image (C H x + b) to the measurement ``y``, over the pixels whose ``weights``
    (the data term's) are > 0, the residual r = y - model scaled by sqrt(weights) (a camera model's variance
    weights standardise it): ``{'relative', 'rms', 'white_rms', 'ratio', 'pixels'}``.

    relative = ||r|| / ||y|| (y weighted alike); rms is r's root mean square; white_rms the RMS its white part
    has, estimated from r less the mean of its 4 neighbours (white noise gives that difference 1.25 sigma^2 of
    variance, whatever its level; structure smoother than a pixel cancels in it), where the 4 neighbours count
    too; ratio = rms / white_rms: 1 where the model explains the frame down to its noise, 2 where the residual
    holds three times more variance than the noise (structure the model, its PSF or its background, does not
    explain). A value is None where it is undefined (no pixels, a zero frame, noise-free data)."""
    w = np.ones(np.shape(y)) if weights is None else np.asarray(weights, np.float64)
    ok = w > 0
    sw = np.sqrt(np.where(ok, w, 0.0))
    y = np.asarray(y, np.float64) * sw
    r = y - np.asarray(model, np.float64) * sw
    out = {"relative": None, "rms": None, "white_rms": None, "ratio": None, "pixels": int(ok.sum())}
    if not ok.any():
        return out
    ny = float(np.linalg.norm(y[ok]))
    out["relative"] = float(np.linalg.norm(r[ok])) / ny if ny > 0 else None
    out["rms"] = float(np.sqrt(np.mean(r[ok] ** 2)))
    if r.ndim == 2 and min(r.shape) >= 3:
        inner = ok[1:-1, 1:-1] & ok[:-2, 1:-1] & ok[2:, 1:-1] & ok[1:-1, :-2] & ok[1:-1, 2:]
        d = _neighbour_difference(r)
        if inner.any():
            out["white_rms"] = float(np.sqrt(np.mean(d[inner] ** 2) / 1.25))
    if out["white_rms"]:
        out["ratio"] = out["rms"] / out["white_rms"]
    return out


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
    #: voxels of the (padded) volume: the universal threshold's N
    voxels: int = 1

    @classmethod
    def of(cls, y_normalised, spectral_mean: float, planes: int = 1, voxels: int | None = None) -> "ProblemScale":
        """From the normalised measurement (My, Mx), sum_i ||h_i||^2 of the normalised PSF stack, the number
        of planes and of voxels (default: planes x the sensor's pixels x 4, the full padding)."""
        y = np.asarray(y_normalised, np.float64)
        n = voxels if voxels is not None else max(int(planes), 1) * 4 * y.size
        return cls(noise_sigma=max(noise_sigma(y), NOISE_FLOOR), spectral_mean=float(spectral_mean),
                   y_norm=float(np.sqrt(np.sum(y * y))), planes=max(int(planes), 1), voxels=max(int(n), 2))

    @property
    def universal_ratio(self) -> float:
        """sqrt(2 ln N): the universal threshold of N voxels in units of the per-voxel noise."""
        return float(np.sqrt(2.0 * np.log(self.voxels)))

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
        ratio = p.l1_noise_ratio if p.l1_noise_ratio is not None else self.universal_ratio
        l1 = (p.l1 if p.l1 is not None else ratio * self.noise_x) * p.l1_scale
        tv = p.tv if p.tv is not None else p.tv_noise_ratio * self.noise_x
        return float(l1), float(tv)

    def penalty(self, p: ADMMParams, name: str, kind: str) -> float:
        """Initial penalty of split ``name``: the given ``mu_<name>``, or for the data split mu_v =
        DATA_PENALTY (0.2; the data term's curvature is 1 on the normalised problem) and for a split z = x
        spectral_mean * mu_v: the x step then weighs the data and the splits equally at a frequency of
        average power (near 1, the splits dominate at every frequency but the strongest and the solve
        creeps). The adaptation raises penalties that start low quickly and reliably, one far too high less
        well (docs/accuracy_vs_time.md), so the start errs low."""
        given = getattr(p, f"mu_{name}", None)
        if given is not None:
            return float(given)
        mu_v = p.mu_v if p.mu_v is not None else DATA_PENALTY
        if kind == "data":
            return float(mu_v)
        return float(min(max(self.spectral_mean, 1e-12), 1.0) * mu_v)


    def penalties(self, p: ADMMParams) -> tuple[float, float, float]:
        """Initial (mu_v, mu_u, mu_w) of the default splits (:meth:`penalty`)."""
        return self.penalty(p, "v", "data"), self.penalty(p, "u", "identity"), self.penalty(p, "w", "identity")


def _ratio(a: float, b: float) -> float:
    """a / b for non-negative a, b, with 0/0 = 1 and x/0 = inf."""
    if b > 0:
        return a / b
    return 1.0 if a == 0 else np.inf


@dataclass(frozen=True)
class SplitStats:
    """One split's squared norms after an iteration (Boyd et al. 2011, sec. 3.3): ``r2`` = ||A x - z||^2
    (primal), ``d2`` = ||z - z_old||^2 (the dual residual is mu times its root), ``ax2`` = ||A x||^2,
    ``z2`` = ||z||^2 and ``dual2`` = ||dual||^2 (the scales of the relative residuals)."""
    r2: float
    d2: float
    ax2: float
    z2: float
    dual2: float


class Control:
    """The splits' penalties (``mu``, by split name), the log, and the decision to stop.

    ``splits``: the split names in log order, each with the name of its initial-penalty parameter's
    kind: 'data' (the v = Hx split) or 'identity' (a split z = x); :meth:`update` takes each split's
    :class:`SplitStats` and the objective's named parts, and ``weights`` weigh those parts (the
    unweighted parts go to the log)."""

    def __init__(self, p: ADMMParams, scale: ProblemScale, callback=None, callback_every: int = 1,
                 splits=(("v", "data"), ("u", "identity"), ("w", "identity")), cold: bool = True):
        self.p = p
        self.scale = scale
        self.l1, self.tv = scale.weights(p)
        self.weights = {"data": 1.0, "l1": self.l1, "tv": self.tv}
        self.mu0 = {name: scale.penalty(p, name, kind) for name, kind in splits}
        #: the largest factor of one rebalancing: the given adapt_max_step, or ADAPT_MAX_STEP
        self.max_step = float(p.adapt_max_step if p.adapt_max_step is not None else ADAPT_MAX_STEP)
        #: the first iteration that rebalances: the given adapt_from, or ADAPT_FROM from a cold start and 1 from a
        #: warm one (``cold=False``: a start at x0, whose first residuals are the problem's, not a transient)
        self.adapt_from = int(p.adapt_from if p.adapt_from is not None else (ADAPT_FROM if cold else 1))
        self.mu = dict(self.mu0)
        #: splits whose term is active: a split z = x without a weight (TV off) carries no term, z = x
        #: + dual / mu = x exactly, and its penalty is neither adapted nor part of the stopping rule
        self.active = {name: True for name, _ in splits}
        self.active["u"] = self.tv > 0
        self.log: list[dict] = []
        self.callback, self.every = callback, max(1, int(callback_every))
        self.calm = 0
        self.stop = "max_iter"
        self.converged = False
        self.t0 = time.perf_counter()

    def x_mu(self) -> dict:
        """The penalties the x step weighs each split with: an inactive identity split (TV off) gets 0, so
        that it is no proximal term mu_u ||x - x_prev||^2 holding x back (u = x_prev there); with it, the
        default solve needed 1.3-1.7x the iterations to come within 1% of the optimum (docs/quality.md)."""
        return {n: (mu if self.active.get(n, True) or n == "v" else 0.0) for n, mu in self.mu.items()}

    # the default splits' penalties by name
    mu_v = property(lambda self: self.mu["v"])
    mu_u = property(lambda self: self.mu["u"])
    mu_w = property(lambda self: self.mu["w"])

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
            if it < self.adapt_from or it > p.adapt_until or (it > 10 and it % 10):
                return mu
            q = _ratio(r, s)
            if q > p.adapt_ratio or q < 1.0 / p.adapt_ratio:
                step = np.sqrt(q) if np.isfinite(q) else self.max_step
                mu *= float(np.clip(step, 1.0 / self.max_step, self.max_step))
        return float(np.clip(mu, mu0 / p.mu_range, mu0 * p.mu_range))

    def _relative(self, name: str, st: SplitStats, r: float, s: float, floor: float) -> tuple[float, float]:
        """(primal, dual) relative residuals of a split: the primal one over max(||Ax||, ||z||), the dual
        one over ||dual|| or, while the duals are still building up from 0, mu ||z||."""
        if not self.active[name]:
            return 0.0, 0.0
        sq, mu = np.sqrt, self.mu[name]
        return (_ratio(r, max(sq(st.ax2), sq(st.z2), floor)),
                _ratio(s, max(sq(st.dual2), mu * max(sq(st.z2), floor))))

    def update(self, it, *, dx2: float, x2: float, splits: dict, objective: dict, changes=None) -> bool:
        """Record iteration `it` from ||x - x_old||^2, ||x||^2, each split's :class:`SplitStats` and the
        objective's parts (unweighted), adapt the penalties, and return True when the run should stop.
        Dual residuals are mu ||z - z_old|| in the space of each split variable z (for v = Hx this bounds
        mu_v ||H^T (v - v_old)|| since ||H|| = 1 after normalisation). ``changes``: (||z - z_old||^2,
        ||z||^2) of further variables (a background), whose relative change must also fall below tol_change."""
        p = self.p
        sq = np.sqrt
        res = {n: (sq(st.r2), self.mu[n] * sq(st.d2)) for n, st in splits.items()}
        # (for y = 0 the answer is x = 0 and every norm is 0: the smallest positive floor lets 0/floor = 0)
        floor = max(ABS_FRACTION * self.scale.y_norm, np.finfo(np.float64).tiny)
        rel = {n: self._relative(n, st, *res[n], floor) for n, st in splits.items()}
        objective_value = 0.0
        for name, value in objective.items():
            objective_value += value if name == "data" else self.weights[name] * value
        row = dict(objective=objective_value, **objective, rel_change=_ratio(sq(dx2), max(sq(x2), floor)),
                   primal=np.sqrt(sum(r**2 for r, _ in res.values())),
                   dual=np.sqrt(sum(s**2 for _, s in res.values())),
                   primal_rel=max(r for r, _ in rel.values()), dual_rel=max(s for _, s in rel.values()))
        for n, (r, s) in res.items():
            row[f"r_{n}"], row[f"s_{n}"] = r, s
        row.update({f"mu_{n}": mu for n, mu in self.mu.items()}, seconds=time.perf_counter() - self.t0)
        for n, (d2, z2) in (changes or {}).items():
            row[f"rel_change_{n}"] = _ratio(sq(d2), max(sq(z2), floor))
        row = {"iter": int(it), **{k: float(v) for k, v in row.items()}}
        self.log.append(row)
        if self.callback is not None and (it % self.every == 0 or it == p.max_iter):
            self.callback(row)
        for n, (r, s) in res.items():
            if self.active[n]:
                self.mu[n] = self._adapt(it, self.mu[n], self.mu0[n], r, s)
        ok = (row["primal_rel"] <= p.tol and row["dual_rel"] <= p.tol and row["rel_change"] <= p.tol_change
              and all(row[f"rel_change_{n}"] <= p.tol_change for n in (changes or {})))
        self.calm = self.calm + 1 if ok else 0
        if self.calm >= p.patience:
            self.stop, self.converged = "converged", True
            return True
        return False

    def summary(self) -> dict:
        """What the result records about the control: why it stopped, and what the defaults came from."""
        p, sc = self.p, self.scale
        rule = ("given" if p.l1 is not None else "noise ratio" if p.l1_noise_ratio is not None
                else "universal threshold sqrt(2 ln N) x noise_x")
        return {"stop": self.stop, "converged": self.converged, "l1": self.l1, "tv": self.tv,
                "l1_rule": {"rule": rule, "voxels": sc.voxels, "ratio": self.l1 / sc.noise_x if sc.noise_x else None,
                            "noise_x": sc.noise_x, "plane_power": p.l1_plane_power},
                "noise_sigma": self.scale.noise_sigma, "noise_x": self.scale.noise_x, "spectral_mean": self.scale.spectral_mean,
                "initial_penalties": {f"mu_{n}": mu for n, mu in self.mu0.items()}, "adapt_max_step": self.max_step,
                "adapt_from": self.adapt_from,
                "penalty_policy": self.p.penalty, "tol": self.p.tol, "tol_change": self.p.tol_change}

"""Parameters of the ADMM reconstruction, shared by the device solver and its float64 twin.

The problem (paper Eq. 4), on the scaled data (see ``normalize``):

    minimise 1/2 ||C H x - y||^2 + l1 ||x||_1 + tv TV_3D(x)   subject to x >= 0

TV_3D(x) = sum sqrt(dx^2 + dy^2 + (axial_weight dz)^2) (isotropic) or
sum |dx| + |dy| + axial_weight |dz| (anisotropic), forward differences, Neumann boundary.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields


from ..errors import InputError
from ..validate import Checker


#: penalty policies: "adaptive" (default: initial penalties from the problem's scale, then residual
#: balancing with steps sqrt(primal/dual) up to ``adapt_max_step`` on large imbalances), "balance" (the
#: CM2 authors' x``balance_factor`` steps), "fixed" (the initial penalties throughout)
PENALTY_POLICIES = ("adaptive", "balance", "fixed")

#: presets on the accuracy-versus-time front (measured in docs/accuracy_vs_time.md, made by
#: tools/accuracy_vs_time.py): overrides of the defaults; "balanced" is the default itself
PRESETS = {
    "fast": {"max_iter": 100, "tol": 3e-3, "tol_change": 3e-3},
    "balanced": {},
    "best": {"max_iter": 1000, "tol": 1e-4, "tol_change": 1e-4},
}


#: priors for kinds of samples (``--prior``): 'points' for point-like emitters (beads, sparse cell
#: bodies): TV off, which spreads a point into a plateau where the PSF blurs it (defocused planes);
#: 'points-weighted': TV off and each plane's l1 weight ~ ||h_i||^2 (l1_plane_power 2), which shrinks a
#: point source alike in every plane and keeps emitters in the planes whose PSF spreads its light.
#: Measured (docs/paper_scenes.md, recall / precision at the end, recall in the near depth third):
#: fig3_beads defaults 0.14 / 1.00 (0.00), points 0.42 / 1.00 (0.03), points-weighted 0.34 / 0.98 (0.00);
#: fig5_scattering defaults 0.35 / 1.00 (0.01), points 0.62 / 0.99 (0.15), points-weighted 0.93 / 0.99
#: (0.87). 'default': l1 and TV at 30 x the noise level, for extended structure
PRIORS = {
    "default": {},
    "points": {"tv_noise_ratio": 0.0},
    "points-weighted": {"tv_noise_ratio": 0.0, "l1_plane_power": 2.0},
}


@dataclass(frozen=True)
class ADMMParams:
    #: weight of the l1 (sparsity) term on the normalised problem; None = ``l1_noise_ratio`` times the
    #: volume-domain noise level (:attr:`cm2cl.solver.control.ProblemScale.noise_x`: the measurement's
    #: estimated noise sigma times the RMS PSF plane norm)
    l1: float | None = None
    #: weight of the 3D total variation term on the normalised problem (0 disables TV); None =
    #: ``tv_noise_ratio`` times the volume-domain noise level
    tv: float | None = None
    #: default weights relative to the volume-domain noise level noise_x = sigma sqrt(sum_i ||h_i||^2 / nz)
    #: (sigma of the measurement scaled to max 1, PSFs to ||H|| = 1). The ratio 30 was chosen on a sweep
    #: (docs/weights.md): on bead scenes it gives about the former sigma-relative weights (noise_x ~
    #: sigma / 15 there), on the real DiffuserCam 3D data (44 spread planes, noise_x = sigma / 800) weights
    #: 25x lower, which show the tilted target the former weights erased. A 10x noisier measurement gets
    #: 10x the weight.
    l1_noise_ratio: float = 30.0
    tv_noise_ratio: float = 30.0
    #: the l1 weight of plane i is l1 * c_i with c_i = ||h_i||^q / mean_j ||h_j||^q (q this power): 0 weighs
    #: every plane alike; 2 shrinks a point source by the same amount in every plane (the shrinkage of an
    #: isolated voxel is l1 c_i / ||h_i||^2), so planes whose PSF spreads its light (small ||h_i||) keep
    #: their emitters (docs/paper_scenes.md)
    l1_plane_power: float = 0.0
    #: TV weight of the axial difference relative to the lateral ones (voxels are not cubic:
    #: dz >> dx makes axial neighbours less alike; a common choice is dx / dz)
    tv_axial_weight: float = 1.0
    #: isotropic (True) or anisotropic (False) TV
    tv_isotropic: bool = True
    #: dual (Chambolle) iterations of the TV prox per outer iteration, warm-started
    tv_iters: int = 2
    #: initial ADMM penalties of the splits v = Hx, u = x (TV), w = x (l1 + non-negativity); None =
    #: from the problem's scale: mu_v = 1 (the data term's curvature on the ||H|| = 1 scale) and
    #: mu_u = mu_w = mu_v mean_k sum_i |H_i(k)|^2, the mean of H^T H's spectrum (its maximum is 1)
    mu_v: float | None = None
    mu_u: float | None = None
    mu_w: float | None = None
    #: how penalties change between iterations (see PENALTY_POLICIES)
    penalty: str = "adaptive"
    #: "balance": multiply/divide a penalty by `balance_factor` when its primal and dual residuals differ
    #: by more than `balance_ratio` (the CM2 authors' 1.1 and 1.5). "adaptive": when a split's primal and
    #: dual residuals differ by more than `adapt_ratio`, multiply its penalty by sqrt(ratio),
    #: bounded by `adapt_max_step`; checked at iterations 1..10, then every 10th, up to `adapt_until`
    #: (then the penalties stay, and ADMM's convergence with fixed penalties holds). The initial penalties
    #: from the problem's scale are near the best fixed ones on the data measured (docs/accuracy_vs_time.md),
    #: so only a large imbalance (a poor start, or user penalties far off) moves them. The ratio 1000 (not
    #: 100): in the first iterations the duals are still building up and r/s reads 100-1000 on a start
    #: that is fine; on the real DiffuserCam 3D data 100 let that transient raise mu_w 700x and the
    #: objective after 200 iterations was 14% higher (docs/weights.md); bead scenes are unchanged.
    balance_factor: float = 1.1
    balance_ratio: float = 1.5
    adapt_ratio: float = 1000.0
    adapt_max_step: float = 3.0
    adapt_until: int = 100
    #: penalties stay within [initial / mu_range, initial * mu_range]
    mu_range: float = 1e4
    #: stop when every active split's relative primal and dual residuals (Boyd et al. 2011, sec. 3.3:
    #: ||r|| <= tol max(||Hx||, ||v||), ||s|| <= tol ||dual||) are below `tol` and the relative change
    #: of x is below `tol_change`, for `patience` consecutive iterations
    tol: float = 1e-3
    tol_change: float = 1e-3
    patience: int = 3
    max_iter: int = 200
    #: scale y by 1/max(y) and the PSFs so that ||H|| = 1; the result is scaled back
    normalize: bool = True

    def __post_init__(self):
        # the checked values replace the given ones: 2.0 iterations become 2, numpy scalars plain numbers
        for name, value in Checker().fields(self, _SPECS).items():
            object.__setattr__(self, name, value)

    @classmethod
    def from_kwargs(cls, **kw) -> "ADMMParams":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(kw) - known)
        if unknown:
            raise InputError(f"unknown parameter(s) {unknown}; known: {sorted(known)}")
        return cls(**kw)

    def as_dict(self) -> dict:
        return asdict(self)

    @property
    def tv_step(self) -> float:
        """Step of the projected-gradient TV dual iteration: 1 / ||div||^2 bound."""
        return 1.0 / (4.0 * (2.0 + self.tv_axial_weight ** 2))


_NONNEG = {"type": "float", "min": 0}
_POS = {"type": "float", "min": 0, "exclusive": True}
_SPECS = {
    "l1": _NONNEG, "tv": _NONNEG, "l1_noise_ratio": _NONNEG, "tv_noise_ratio": _NONNEG,
    "l1_plane_power": {"type": "float", "min": 0, "max": 4},
    "tv_axial_weight": _POS, "tv_isotropic": {"type": "bool"}, "tv_iters": {"type": "int", "min": 1, "max": 1000},
    "mu_v": _POS, "mu_u": _POS, "mu_w": _POS,
    "penalty": {"type": "str", "choices": PENALTY_POLICIES},
    "balance_factor": {"type": "float", "min": 1, "exclusive": True},
    "balance_ratio": {"type": "float", "min": 1},
    "adapt_ratio": {"type": "float", "min": 1},
    "adapt_max_step": {"type": "float", "min": 1, "exclusive": True},
    "adapt_until": {"type": "int", "min": 0},
    "mu_range": {"type": "float", "min": 1},
    "tol": _NONNEG, "tol_change": _NONNEG,
    "patience": {"type": "int", "min": 1}, "max_iter": {"type": "int", "min": 1},
    "normalize": {"type": "bool"},
}

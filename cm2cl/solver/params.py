"""Parameters of the ADMM reconstruction, shared by the device solver and its float64 twin.

The problem (paper Eq. 4), on the scaled data (see ``normalize``):

    minimise 1/2 ||C H x - y||^2 + l1 ||x||_1 + tv TV_3D(x)   subject to x >= 0

TV_3D(x) = sum sqrt(dx^2 + dy^2 + (axial_weight dz)^2) (isotropic) or
sum |dx| + |dy| + axial_weight |dz| (anisotropic), forward differences, Neumann boundary.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np

from ..errors import InputError


@dataclass(frozen=True)
class ADMMParams:
    #: weight of the l1 (sparsity) term, on the normalised problem
    l1: float = 1e-3
    #: weight of the 3D total variation term, on the normalised problem (0 disables TV)
    tv: float = 1e-3
    #: TV weight of the axial difference relative to the lateral ones (voxels are not cubic:
    #: dz >> dx makes axial neighbours less alike; a common choice is dx / dz)
    tv_axial_weight: float = 1.0
    #: isotropic (True) or anisotropic (False) TV
    tv_isotropic: bool = True
    #: dual (Chambolle) iterations of the TV prox per outer iteration, warm-started
    tv_iters: int = 2
    #: initial ADMM penalties of the splits v = Hx, u = x (TV), w = x (l1 + non-negativity)
    mu_v: float = 1.0
    mu_u: float = 1.0
    mu_w: float = 1.0
    #: residual balancing: multiply/divide a penalty by `balance_factor` when its primal and dual
    #: residuals differ by more than `balance_ratio` (the CM2 authors' 1.1 and 1.5); 0 disables
    balance_factor: float = 1.1
    balance_ratio: float = 1.5
    #: stop when ||x_k - x_k-1|| / ||x_k|| < tol for `patience` consecutive iterations
    tol: float = 1e-3
    patience: int = 4
    #: optional: also stop when every split's primal and dual residual are below this
    tol_residual: float = 0.0
    max_iter: int = 200
    #: scale y by 1/max(y) and the PSFs so that ||H|| = 1; the result is scaled back
    normalize: bool = True

    def __post_init__(self):
        for name in ("l1", "tv"):
            _check(name, getattr(self, name), allow_zero=True)
        for name in ("tv_axial_weight", "mu_v", "mu_u", "mu_w"):
            _check(name, getattr(self, name))
        _check("tol", self.tol, allow_zero=True)
        _check("tol_residual", self.tol_residual, allow_zero=True)
        if self.balance_factor != 0:
            if not (np.isfinite(self.balance_factor) and self.balance_factor > 1):
                raise InputError(f"balance_factor: must be > 1 (or 0 to disable), got {self.balance_factor!r}")
            if not (np.isfinite(self.balance_ratio) and self.balance_ratio >= 1):
                raise InputError(f"balance_ratio: must be >= 1, got {self.balance_ratio!r}")
        for name in ("tv_iters", "patience", "max_iter"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < 1:
                raise InputError(f"{name}: must be an integer >= 1, got {v!r}")

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


def _check(name, v, allow_zero=False):
    try:
        f = float(v)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: {v!r} is not a number") from exc
    if not np.isfinite(f) or f < 0 or (f == 0 and not allow_zero):
        raise InputError(f"{name}: must be finite and {'>= 0' if allow_zero else '> 0'}, got {v!r}")


def balance(mu: float, primal: float, dual: float, p: ADMMParams) -> float:
    """Residual balancing of one penalty (Boyd et al. 2011, sec. 3.4.1)."""
    if p.balance_factor == 0:
        return mu
    if primal > p.balance_ratio * dual:
        return mu * p.balance_factor
    if dual > p.balance_ratio * primal:
        return mu / p.balance_factor
    return mu

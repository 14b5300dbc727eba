"""The objective's terms (:mod:`.base`: the protocol) and the two ways the solver runs a set of them:
:class:`GenericSet`, any terms, each updated by its own kernels; :class:`DefaultSet`
(:mod:`.fused`), the default terms on the lean state with fused kernels, the fast path."""

from __future__ import annotations

from .background import LeastSquaresBackground
from .base import IdentityTerm, Term
from .data import LeastSquares
from .fused import DefaultSet
from .l1 import L1, ReweightedL1, plane_weights
from .tv import TV


class GenericSet:
    """A data term and regularisers on identity splits, each with its own state and kernels; the
    solver's loop runs the x step on their rhs and then each term's update."""

    fused = False
    kernels = (("terms.cl", "x_change"), ("terms.cl", "combine"), ("terms.cl", "l1_update"),
               ("terms.cl", "tv_update"))

    def __init__(self, data: Term, regularisers):
        self.data, self.regs = data, tuple(regularisers)
        self.terms = (data,) + self.regs
        names = [t.split for t in self.terms]
        if len(set(names)) != len(names):
            raise ValueError(f"terms: split names must differ, got {names}")
        self.volumes = tuple(dict.fromkeys(("x", "g") + sum((t.volumes for t in self.terms), ())))
        self.sums = (("x_change", ("dx2", "x2")),) + tuple((t.split, t.sums) for t in self.terms)
        self.splits = tuple((t.split, t.kind) for t in self.terms)
        self.kernels = tuple(dict.fromkeys(GenericSet.kernels + sum((t.kernels for t in self.terms), ())))
        self.planes = tuple(dict.fromkeys(sum((t.planes for t in self.terms), ())))
        self.start_volumes = ("x",) + tuple(t.volumes[0] for t in self.regs)
        #: whether a TV term is among the regularisers
        self.has_tv = any(isinstance(t, TV) for t in self.regs)

    def setup(self, s) -> None:
        for t in self.terms:
            t.setup(s)

    def start(self, s, ctl) -> None:
        for t in self.terms:
            ctl.active[t.split] = t.active(ctl)
            ctl.weights.update(t.weights(ctl))
            t.start(s, ctl)

    def reset(self) -> None:
        pass

    def c(self, mu: dict) -> float:
        c = 0.0
        for t in self.regs:
            c += mu[t.split]
        return c

    def rhs_ready(self, mu: dict) -> bool:
        return False

    def rhs_reads(self, ready: bool) -> tuple:
        return tuple(dict.fromkeys(sum((t.rhs_reads for t in self.regs), ())))

    def rhs(self, s, i, part, j, n, a, mu: dict) -> None:
        for k, t in enumerate(self.regs):
            t.add_rhs(s, part, j, n, a, mu[t.split], k == 0)

    def update(self, s, ctl) -> None:
        ny, nx = s.P
        for i, part, j0, j1, n, a in s.walk.runs(("x", "g")):
            s.reduce_rows(part, "x_change", "x_change", x=a["x"], x_old=a["g"], planes=n, ny=ny, nx=nx)
        for t in self.terms:
            t.update(s, ctl)

    def report(self, v: dict) -> dict:
        objective = {}
        for t in self.terms:
            objective.update(t.objective(v))
        changes = {}
        for t in self.terms:
            changes.update(t.changes())
        return {"dx2": v["dx2"], "x2": v["x2"], "splits": {t.split: t.stats(v) for t in self.terms},
                "objective": objective, "changes": changes}

    def next_round(self, s) -> bool:
        return any([t.next_round(s) for t in self.terms])

    def derived(self, s, name: str):
        return None


def data_term(background: str = "none", spacing_px=None) -> Term:
    """The data term: least squares, with a background in the model for ``background='model'``."""
    if background == "model":
        return LeastSquaresBackground(spacing_px)
    if background == "none":
        return LeastSquares()
    raise ValueError(f"background: expected 'model' or 'none', got {background!r}")


def default_terms(fused: bool = True, background: str = "none", spacing_px=None, tv: bool = True):
    """The default objective {data, TV, l1 + non-negativity} with the data term of :func:`data_term`: the
    fused set, or the same terms as a generic set; ``tv=False``: the fused set without TV's state, for a
    TV weight of 0 (:func:`has_tv`)."""
    data = data_term(background, spacing_px)
    return DefaultSet(data, tv) if fused else GenericSet(data, (TV(), L1()) if tv else (L1(),))


def terms_for(params):
    """The terms ``params`` ask for: the fused default set, or with reweighted l1 the generic one."""
    if params.l1_reweight:
        return GenericSet(data_term(params.background, params.background_scale_px),
                          (TV(), ReweightedL1(params.l1_reweight, params.l1_reweight_eps)))
    return default_terms(True, params.background, params.background_scale_px, tv=has_tv(params))


def state_counts(terms) -> dict:
    """What a solve with ``terms`` keeps, in the memory planner's terms (cm2cl.solver.memory.plan_layout):
    its real volumes per voxel, its reduction slots (each reducing launch's sums once) and its padded
    planes of its own."""
    keys, nslots = set(), 0
    for key, names in terms.sums:
        if key not in keys:
            keys.add(key)
            nslots += len(names)
    return {"real_volumes": len(terms.volumes), "nslots": nslots, "planes": len(terms.planes)}


def has_tv(params) -> bool:
    """Whether ``params`` can give TV a weight: not when it is 0, or left to a noise ratio of 0 (the
    default), whatever the measurement."""
    return not (params.tv == 0 or (params.tv is None and params.tv_noise_ratio == 0))


__all__ = ["Term", "IdentityTerm", "LeastSquares", "LeastSquaresBackground", "data_term", "L1", "TV", "GenericSet", "DefaultSet", "default_terms", "terms_for", "has_tv", "state_counts", "ReweightedL1", "plane_weights"]

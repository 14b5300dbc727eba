"""The protocol of the objective's terms. A term owns a split of the ADMM (its name names the
split's penalty ``mu_<split>`` and its log columns): its volumes (for the parts and the memory model),
its named sums, its share of the x step's right-hand side and of its diagonal, its prox and dual
update, and its residuals for the penalty policy and the stopping rule.

The x step solves (mu_v H^T H + c I) x = H^T (mu_v v - xi) + sum_t (mu_t z_t - dual_t) with
c = sum_t mu_t over the identity splits z_t = x: any term of that form plugs in without changing
the x step (cm2cl/solver/xstep.py)."""

from __future__ import annotations

from abc import ABC, abstractmethod

from ..control import SplitStats


class Term(ABC):
    """One split of the objective. ``kind``: 'data' (v = Hx, one per solve) or 'identity' (z = x).
    A term must say how it updates and what its residuals are; the rest has defaults."""

    split: str = ""
    kind: str = "identity"
    #: real volumes on the padded grid it keeps (its split variable, its dual, its own scratch)
    volumes: tuple = ()
    #: names of its sums, in the order its reducing kernel writes them
    sums: tuple = ()
    #: the volumes its share of the x step's right-hand side reads
    rhs_reads: tuple = ()
    #: (file, kernel) of the kernels it launches, and padded planes of its own (on part 0)
    kernels: tuple = ()
    planes: tuple = ()

    def setup(self, s) -> None:
        """Per-part data it needs on the devices (``s``: the solver), once per solver."""

    def start(self, s, ctl) -> None:
        """Its state at the start of a solve (the solver zeroed every volume, x0 set x and z)."""

    def warm(self, s, ctl) -> None:
        """Its state at a warm start, after :meth:`start`: x and the identity splits hold x0 and part 0's
        ``hx`` holds H x0 (the data term sets its split there and its dual where the data term's optimality
        puts it; regularisers keep their duals at 0)."""

    def active(self, ctl) -> bool:
        """Whether its split carries a term (a split without one is neither adapted nor judged)."""
        return True

    def weights(self, ctl) -> dict:
        """The weights of its objective parts, by name (the data term's part counts as it is)."""
        return {}

    @abstractmethod
    def update(self, s, ctl) -> None:
        """Its prox and dual update after the x step (x: the new iterate), adding its sums."""

    @abstractmethod
    def stats(self, v: dict) -> SplitStats:
        """Its split's squared norms from the solve's named sums ``v``."""

    def objective(self, v: dict) -> dict:
        """Its parts of the objective (unweighted), by name."""
        return {}

    def next_round(self, s) -> bool:
        """Called when the iteration has converged: change the term for another warm-started round (a
        reweighted l1's weights) and return True, or return False (the solve stops)."""
        return False

    def changes(self) -> dict:
        """(||z - z_old||^2, ||z||^2) of variables it keeps besides its split (the background's b), by name:
        the stopping rule also waits for their relative change."""
        return {}

    def derived(self, s, name: str):
        """A volume of its state that it does not store (None: not one of its own)."""
        return None


class IdentityTerm(Term):
    """A term on a split z = x: it also adds mu z - dual to the x step's right-hand side."""

    kind = "identity"

    @abstractmethod
    def add_rhs(self, s, part, j: int, n: int, a: dict, mu: float, first: bool) -> None:
        """t (+)= mu z - dual on slab j of ``part`` (``first``: t = ...)."""

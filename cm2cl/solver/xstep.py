"""The exact x step of the ADMM, shared by every set of terms:

    (mu_v H^T H + c I) x = H^T (mu_v v - xi) + t,   t = sum_t (mu_t z_t - dual_t),  c = sum_t mu_t

solved per lateral frequency by Sherman-Morrison: with B_i = conj(H_i) R + T_i (R, T_i the spectra of
mu_v v - xi and of t), HX = sum_i H_i B_i / (c + mu_v sum_i |H_i|^2) and X_i = (B_i - mu_v conj(H_i) HX) / c.
The spectral sum runs over every plane of every part (added in float64 across parts); H x is the
inverse transform of HX (part 0's plane ``hx``)."""

from __future__ import annotations

import numpy as np


def x_step(s, mu: dict) -> None:
    """One x step of solver ``s`` for penalties ``mu`` (by split): the new x goes to ``g``."""
    terms, (ny, nx) = s.terms, s.P
    c, mu_v = terms.c(mu), mu["v"]
    p0 = s.parts[0].planes
    terms.data.rhs_plane(s, mu_v)
    s.parts[0].plan2d.forward(p0["r"], p0["R"])
    if len(s.parts) > 1:
        Rh = p0["R"].get()
        for part in s.parts[1:]:
            part.planes["R"].set(Rh)
    ready = terms.rhs_ready(mu)   # g already holds t (the default set's tv_finish made it)
    reads = ("g", "hs") if ready else terms.rhs_reads(False) + ("hs",)
    for i, part, j, n, a in s.walk.slabs(reads, ("spec",), () if ready else ("g",)):
        if not ready:
            terms.rhs(s, i, part, j, n, a, mu)
        part.plan(n, s.backend).forward(a["g"], a["spec"])
        _accumulate(s, part, j, n, a)
    if len(s.parts) > 1:   # the spectral sum over all planes, added in float64 (Kahan: sum - comp)
        S = np.sum([p.planes["S"].get().astype(np.complex128) - p.planes["comp"].get() for p in s.parts],
                   axis=0).astype(s.cdtype)
        for part in s.parts:
            part.planes["S"].set(S)
    for part in s.parts:
        pl = part.planes
        part.kernels("xstep_hx", (s.nfreq,), S=pl["S"], hn2=pl["hn2"], c=c, mu_v=mu_v, nfreq=s.nfreq)
    _solve(s, c, mu_v)
    s.parts[0].plan2d.inverse(p0["S"], p0["hx"])


def _accumulate(s, part, j, n, a) -> None:
    """S (+)= sum_i H_i B_i over slab j, in runs of planes on CPUs (each continuing the sum)."""
    pl, run = part.planes, part.acc_planes or n
    for z0 in range(0, n, run):
        part.kernels("xstep_accumulate", (-(-s.nfreq // part.row.cw),), T=a["spec"], H=a["hs"], R=pl["R"],
                     S=pl["S"], comp=pl["comp"], p0=z0, p1=min(n, z0 + run), nfreq=s.nfreq, first=j == 0 and z0 == 0)


def _solve(s, c, mu_v) -> None:
    """X_i for every slab and its inverse transform into g (inside the inverse FFT where it fuses)."""
    for i, part, j, n, a in s.walk.slabs(("g", "hs") if s.lean else ("spec", "hs"), ("g",), ("spec",)):
        plan, pl = part.plan(n, s.backend), part.planes
        if part.lean:   # one slab of spectra: this slab's rhs transformed again (the same values)
            plan.forward(a["g"], a["spec"])
        if plan.fuses_xstep and s.fuse_xstep:
            plan.inverse_xstep(a["spec"], a["g"], a["hs"], pl["R"], pl["S"], c, mu_v)
            continue
        part.kernels("xstep_solve", (-(-s.nfreq // part.row.cw),), T=a["spec"], H=a["hs"], R=pl["R"], HX=pl["S"],
                     c=c, mu_v=mu_v, planes=n, nfreq=s.nfreq)
        plan.inverse(a["spec"], a["g"])

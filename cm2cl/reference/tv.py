"""Float64 numpy twin of the 3D total variation: gradient, divergence, value, and its prox by
projected-gradient (Chambolle) dual iterations."""

from __future__ import annotations

import numpy as np


def tv_grad(u, axial_weight=1.0):
    """(gx, gy, gz) of a (nz, ny, nx) volume; gz carries the axial weight."""
    gx = np.zeros_like(u)
    gy = np.zeros_like(u)
    gz = np.zeros_like(u)
    gx[:, :, :-1] = u[:, :, 1:] - u[:, :, :-1]
    gy[:, :-1, :] = u[:, 1:, :] - u[:, :-1, :]
    gz[:-1] = axial_weight * (u[1:] - u[:-1])
    return gx, gy, gz


def _bdiff(p, axis):
    """Backward difference with p = 0 past the last index: the negative adjoint of a forward one."""
    a = np.moveaxis(p, axis, 0).copy()
    a[-1] = 0
    out = a.copy()
    out[1:] -= a[:-1]
    return np.moveaxis(out, 0, axis)


def tv_div(px, py, pz, axial_weight=1.0):
    """div = -grad^T."""
    return _bdiff(px, 2) + _bdiff(py, 1) + axial_weight * _bdiff(pz, 0)


def tv_value(u, axial_weight=1.0, isotropic=True) -> float:
    gx, gy, gz = tv_grad(np.asarray(u, np.float64), axial_weight)
    if isotropic:
        return float(np.sqrt(gx**2 + gy**2 + gz**2).sum())
    return float(np.abs(gx).sum() + np.abs(gy).sum() + np.abs(gz).sum())


def tv_dual_step(p, z, tau, step, axial_weight=1.0, isotropic=True):
    """One projected-gradient (Chambolle) step on the dual of prox_{tau TV}(z), in place on p."""
    g = tv_div(*p, axial_weight) - z / tau
    for pk, gk in zip(p, tv_grad(g, axial_weight)):
        pk += step * gk
    if isotropic:
        n = np.maximum(1.0, np.sqrt(p[0] ** 2 + p[1] ** 2 + p[2] ** 2))
        for pk in p:
            pk /= n
    else:
        np.clip(p, -1.0, 1.0, out=p)
    return p


def tv_prox(z, tau, iters, p=None, axial_weight=1.0, isotropic=True):
    """prox_{tau TV}(z) by `iters` dual iterations from the dual p (warm start); returns (u, p)."""
    step = 1.0 / (4.0 * (2.0 + axial_weight**2))
    p = np.zeros((3,) + z.shape, z.dtype) if p is None else p
    for _ in range(iters):
        tv_dual_step(p, z, tau, step, axial_weight, isotropic)
    return z - tau * tv_div(*p, axial_weight), p

"""The least-squares data term with a background in the model: y = C H x + b, b = B c a smooth,
non-negative 2D field on the sensor (c >= 0 on a coarse grid of cubic B-splines, so that B c >= 0), fitted
jointly with the volume so that haze is not reconstructed as volume.

On the split v = Hx, the data step minimises over (v, c >= 0)

    1/2 ||W^(1/2) (C v + B c - y)||^2 + mu/2 ||v - a||^2,    a = alpha Hx + (1 - alpha) v_prev + xi / mu
(alpha: the over-relaxation, 1 for plain ADMM):

for a given b, v = (W (y - b) + mu a) / (W + mu) on the sensor (the least-squares step with y - b), and
putting it back leaves c = argmin_{c >= 0} ||Q^(1/2) (B c - (y - a))||^2 with Q = W mu / (W + mu), an exact
non-negative least-squares problem in the few coefficients (solved on the host from the sensor plane
y - a, one plane each way per iteration). B = By (x) Bx is separable, so the normal matrix costs a
pass over the plane only when mu changes.

The smoothness scale: knots a quarter of the PSF stack's lateral support apart (at least
MIN_SPACING_PX): a feature narrower than the PSF's footprint (a focus of the array PSF, in or out of
focus) cannot be taken up by b, while haze, which the whole PSF spreads, can."""

from __future__ import annotations

import numpy as np
from scipy.interpolate import BSpline
from scipy.linalg import cho_factor, cho_solve, solve_triangular
from scipy.optimize import nnls

from .data import LeastSquares

#: knots of the background's B-splines at least this many pixels apart
MIN_SPACING_PX = 8.0
#: knots this fraction of the PSF stack's lateral support apart
SUPPORT_FRACTION = 0.25


def knot_spacing(support_px, sensor_shape, given=None) -> float:
    """The background's knot spacing in pixels: ``given``, else SUPPORT_FRACTION x the PSF support's
    larger side, within [MIN_SPACING_PX, the sensor's larger side]."""
    if given is not None:
        return float(given)
    return float(min(max(SUPPORT_FRACTION * max(support_px), MIN_SPACING_PX), max(sensor_shape)))


def spline_basis(n_pixels: int, spacing: float) -> np.ndarray:
    """(n_pixels, n) uniform cubic B-splines with knots at most ``spacing`` apart, spaced so that they span
    the pixels exactly (centred from one spacing before the first pixel to one after the last; no function
    barely touching the sensor, which would leave the fit ill-conditioned): non-negative, and a partition
    of unity over the pixels."""
    m = max(1, int(np.ceil((n_pixels - 1) / spacing)))
    spacing = max(n_pixels - 1, 1) / m
    n = m + 3
    knots = (np.arange(n + 4) - 3.0) * spacing   # basis k spans knots k..k+4: centred at (k - 1) spacing
    p = np.arange(n_pixels, dtype=np.float64)
    return BSpline.design_matrix(p, knots, 3, extrapolate=True).toarray()[:, :n]


class Background:
    """The fit of b = By C Bx^T >= 0 to a plane r with per-pixel weights q (the host's part of the step)."""

    def __init__(self, sensor_shape, spacing: float):
        self.spacing = float(spacing)
        self.By, self.Bx = spline_basis(sensor_shape[0], spacing), spline_basis(sensor_shape[1], spacing)
        self.shape = (self.By.shape[1], self.Bx.shape[1])
        self.c = np.zeros(self.shape)
        self._normal = None

    def normal(self, q):
        """B^T Q B ((ny nx)^2, by the separable structure) and its Cholesky factor, with a ridge of 1e-12 of
        its mean diagonal for coefficients that touch no weighted pixel."""
        By, Bx = self.By, self.Bx
        t = np.einsum("pq,qj,ql->pjl", q, Bx, Bx, optimize=True)          # (My, nx, nx)
        G = np.einsum("pi,pk,pjl->ijkl", By, By, t, optimize=True).reshape(np.prod(self.shape), -1)
        G += 1e-12 * max(np.trace(G) / len(G), 1e-300) * np.eye(len(G))
        L = np.linalg.cholesky(G)
        return G, L

    def fit(self, r, q, key) -> np.ndarray:
        """c = argmin_{c >= 0} ||Q^(1/2) (B c - r)||^2 (``key`` identifies q: its normal matrix is kept);
        returns b = B c on the sensor."""
        if self._normal is None or self._normal[0] != key:
            self._normal = (key, *self.normal(q))
        _, G, L = self._normal
        h = (self.By.T @ (q * r) @ self.Bx).ravel()
        # ||L^T c - L^-1 h||^2 = c^T G c - 2 c^T h + const: the same minimiser
        c, _ = nnls(L.T, solve_triangular(L, h, lower=True), maxiter=50 * len(h))
        self.c = c.reshape(self.shape)
        return self.plane()

    def plane(self) -> np.ndarray:
        return self.By @ self.c @ self.Bx.T

    def reset(self) -> None:
        """b = 0, and no normal matrix kept: the next fit's weights may be new (a new solve)."""
        self.c[...] = 0.0
        self._normal = None


class LeastSquaresBackground(LeastSquares):
    """1/2 ||W^(1/2) (C H x + b - y)||^2 with b = B c >= 0 estimated jointly (module docstring)."""

    kernels = (("terms.cl", "combine"),)
    planes = ("ytb",)

    def __init__(self, spacing_px=None):
        self.given_spacing = spacing_px
        self.fit = None
        self._b = None
        self._q = self._t = None

    def setup(self, s) -> None:
        self.fit = Background(s.M, knot_spacing(s.psf_support_px, s.M, self.given_spacing))
        self._q = self._t = None

    def _weights(self, s, mu):
        """Q = W mu / (W + mu), kept while mu stays (it changes only when the penalty policy moves it)."""
        if self._q is None or self._q[0] != mu:
            w = s.pixel_weights
            self._q = (mu, w * mu / (w + mu))
        return self._q[1]

    def _set_target(self, s, b) -> None:
        """The plane C^T (y - b) that the least-squares step fits (its 'cty'), through one host plane kept
        for the solve (zero off the sensor)."""
        if self._t is None or self._t.shape != (1,) + tuple(s.P) or self._t.dtype != s.dtype:
            self._t = np.zeros((1,) + tuple(s.P), s.dtype)
        self._t[0][s.crop] = s.y_n - b
        s.parts[0].planes["ytb"].set(self._t)

    def start(self, s, ctl) -> None:
        """b = 0 at the start (v = W y / (W + mu)); the first data step fits b beside the first H x. (Fitting b
        to y at x = 0 gives b the smooth part of the beads' light too, which the volume then takes back
        slowly: 513 against 324 iterations to the stopping rule on DiffuserCam 3D binned 4x, 11 planes.) A warm
        start thus depends on the stored x0 alone, and a resumed job gives the same bits."""
        super().start(s, ctl)
        self._q = None   # a new solve may bring new pixel weights (Q and B^T Q B follow them)
        self._change = (0.0, 0.0)
        self.fit.reset()
        self._b = self.fit.plane()
        self._set_target(s, self._b)

    def warm(self, s, ctl) -> None:
        """A warm start consistent with x0 (:meth:`LeastSquares.warm`): b fitted to y - C H x0 with the
        pixels' weights W (what the v step's fit tends to as mu grows), then v = H x0 and
        xi = C^T W (C H x0 + b - y)."""
        self._q = None
        hx = s.parts[0].planes["hx"].get()[0][s.crop].astype(np.float64)
        self._b = self.fit.fit(s.y_n - hx, s.pixel_weights, "warm")
        self._set_target(s, self._b)
        self._warm_planes(s, s.y_n - self._b)

    def update(self, s, ctl) -> None:
        mu = ctl.mu["v"]
        part, (ny, nx) = s.parts[0], s.P
        pl = part.planes
        alpha = s.p.relaxation   # a = alpha Hx + (1 - alpha) v + xi / mu: the over-relaxed Hx
        s.row_grid(part, "combine", out=pl["r"], p=pl["hx"], q=pl["v"], a=alpha, b=1.0 - alpha, add=False, planes=1,
                   ny=ny, nx=nx)
        s.row_grid(part, "combine", out=pl["r"], p=pl["xi"], q=pl["xi"], a=1.0 / mu, b=0.0, add=True, planes=1,
                   ny=ny, nx=nx)
        a = pl["r"].get()[0][s.crop].astype(np.float64)
        b = self.fit.fit(s.y_n - a, self._weights(s, mu), mu)
        self._change = (float(np.sum((b - self._b) ** 2)), float(np.sum(b * b)))
        self._b = b
        self._set_target(s, b)
        s.reduce_rows(part, "update_v", "v", v=pl["v"], xi=pl["xi"], hx=pl["hx"], cty=pl["ytb"], cw=pl["cw"],
                      mu_v=mu, alpha=alpha, py=ny, px=nx)

    def changes(self) -> dict:
        return {"b": self._change}

    def background(self, s) -> np.ndarray:
        """b on the sensor, normalised units."""
        return self._b

"""Lateral tiles (approximate): a frame reconstructed as tiles of the sensor, each solved on its tile plus
a halo of measurement around it, the tiles' volumes feathered into one. For data whose PSF support is
small against the field (binned data, other lensless systems) and whose volume does not fit otherwise.

Why it works: a voxel's light lands within the PSF's support around it, so a tile's voxels are seen whole
in a window reaching that far beyond the tile (the halo); the tile's solve is cm2cl's usual one (the
window is the crop of an unknown larger scene, so light from outside the window is explained by voxels
outside it, not forced into the tile). It is approximate: voxels near the window's edge see only part of
their light, which is why only the tile (feathered a little into the halo) is kept.

Consistency: every tile solves the same normalised problem as the whole frame would. The measurement is
scaled by the whole frame's maximum and the PSF to ||H|| = 1 once, the weights (l1, TV) come from the
whole frame's noise estimate (``ProblemScale`` of the whole measurement), and the tiles solve with
``normalize=False`` and these absolute weights; a tile with its own maximum and noise estimate would get
other weights, and seams. The volume is scaled back to the caller's units.

Refusal (:func:`plan_tiles`): a halo smaller than the PSF's reach from its optical axis (the views' spread)
would lose views of the tile's edge voxels; a window smaller than the PSF's support could not hold it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from ..errors import InputError

__all__ = ["TilePlan", "plan_tiles", "reconstruct_tiled", "operator_norm"]


@dataclass(frozen=True)
class TilePlan:
    sensor: tuple          #: (My, Mx)
    tile: tuple            #: (ty, tx) tile size in pixels
    halo: tuple            #: (hy, hx) measurement around each tile
    reach: tuple           #: (ry, rx) the PSF's reach from its optical axis (support, 1 - 1e-6 of the light)
    feather: tuple         #: (fy, fx) half-width of the blend across each tile border
    tiles: list            #: [((r0, r1), (c0, c1)), ...] tiles of the sensor
    windows: list          #: the measurement window of each tile (tile + halo, clipped to the sensor)

    def describe(self) -> str:
        return (f"{len(self.tiles)} tiles of {self.tile[0]} x {self.tile[1]} px with a halo of {self.halo[0]} x "
                f"{self.halo[1]} px (PSF reach {self.reach[0]} x {self.reach[1]} px from its axis), windows up to "
                f"{max(w[0][1] - w[0][0] for w in self.windows)} x {max(w[1][1] - w[1][0] for w in self.windows)} px")


def _reach(psf) -> tuple[int, int]:
    """How far the PSF stack's light (all but 1e-6) reaches from its optical axis (the sensor centre
    M // 2, cm2cl's convention), per lateral axis."""
    from ..solver.forward import psf_support

    h = np.asarray(psf)
    M = h.shape[-2:]
    out = []
    for (a, b), m in zip(psf_support(h), M):
        out.append(int(max(m // 2 - a, b - m // 2, 0)))
    return out[0], out[1]


def _ranges(n: int, size: int) -> list[tuple[int, int]]:
    k = max(1, int(np.ceil(n / size)))
    edges = np.linspace(0, n, k + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


#: more than one tile whose window (tile + halo) covers this fraction of the field or more is refused: each
#: tile would solve about the whole frame (a PSF that spans the field), at the tiles' count times the work
WINDOW_MAX_FRACTION = 0.9


def plan_tiles(sensor, psf, tile, halo=None) -> TilePlan:
    """Tiles of about ``tile`` = (ty, tx) pixels covering ``sensor`` (equal sizes, at most ``tile``), each
    with a measurement window reaching ``halo`` (default: the PSF's reach) beyond it; refused when a window
    is smaller than the PSF's spread or covers nearly the whole field (:data:`WINDOW_MAX_FRACTION`)."""
    try:
        ty, tx = (int(t) for t in tile)
    except (TypeError, ValueError):
        raise InputError(f"tile: expected two positive integers (ty, tx), got {tile!r}") from None
    if ty < 1 or tx < 1:
        raise InputError(f"tile: expected two positive integers (ty, tx), got {tile!r}")
    My, Mx = (int(s) for s in sensor)
    ry, rx = _reach(psf)
    if halo is None:
        hy, hx = ry, rx
    else:
        hy, hx = ((int(halo), int(halo)) if np.isscalar(halo) else (int(h) for h in halo))
        if hy < ry or hx < rx:
            raise InputError(f"halo: {hy} x {hx} px is smaller than the PSF's reach from its axis ({ry} x {rx} px): "
                             "the views of a tile's edge voxels would fall outside its window; use a halo of at least "
                             f"{ry} x {rx} px")
    tiles = [(r, c) for r in _ranges(My, ty) for c in _ranges(Mx, tx)]
    windows = [((max(0, r0 - hy), min(My, r1 + hy)), (max(0, c0 - hx), min(Mx, c1 + hx))) for (r0, r1), (c0, c1) in tiles]
    small = [w for w in windows if (w[0][1] - w[0][0]) < 2 * ry + 1 or (w[1][1] - w[1][0]) < 2 * rx + 1]
    if small:
        (a, b), (c, d) = small[0]
        raise InputError(f"tile: a window of {b - a} x {d - c} px (tile + halo) is smaller than the PSF's spread "
                         f"({2 * ry + 1} x {2 * rx + 1} px): views would be lost; use tiles of at least "
                         f"{ry + 1} x {rx + 1} px or no tiles")
    big = max(windows, key=lambda w: (w[0][1] - w[0][0]) * (w[1][1] - w[1][0]))
    (a, b), (c, d) = big
    if len(tiles) > 1 and (b - a) * (d - c) >= WINDOW_MAX_FRACTION * My * Mx:
        raise InputError(f"tile: a window of {b - a} x {d - c} px (tile + a halo of {hy} x {hx} px; the PSF reaches "
                         f"{ry} x {rx} px from its axis) covers nearly all of the {My} x {Mx} px field: the "
                         f"{len(tiles)} tiles would each solve about the whole frame, saving no memory; run without "
                         "tiles")
    fy, fx = max(1, min(hy, ty) // 4), max(1, min(hx, tx) // 4)
    return TilePlan((My, Mx), (ty, tx), (hy, hx), (ry, rx), (fy, fx), tiles, windows)


def _ramp(n0, n1, lo, hi, f, edge_lo, edge_hi):
    """Weights over [lo, hi) for a tile [n0, n1) blended over +-f across its borders (1 at sensor edges)."""
    idx = np.arange(lo, hi) + 0.5
    w = np.ones(hi - lo)
    if not edge_lo:
        w *= np.clip((idx - (n0 - f)) / (2 * f), 0, 1)
    if not edge_hi:
        w *= np.clip(((n1 + f) - idx) / (2 * f), 0, 1)
    return w


def tile_weights(plan: TilePlan):
    """Per tile: (region ((r0, r1), (c0, c1)) within its window, separable weights); they sum to 1 over
    the sensor."""
    My, Mx = plan.sensor
    fy, fx = plan.feather
    out = []
    for ((r0, r1), (c0, c1)), ((wr0, wr1), (wc0, wc1)) in zip(plan.tiles, plan.windows):
        a, b = max(wr0, r0 - fy), min(wr1, r1 + fy)
        c, d = max(wc0, c0 - fx), min(wc1, c1 + fx)
        wy = _ramp(r0, r1, a, b, fy, r0 == 0, r1 == My)
        wx = _ramp(c0, c1, c, d, fx, c0 == 0, c1 == Mx)
        out.append((((a, b), (c, d)), np.outer(wy, wx)))
    return out


def operator_norm(h: np.ndarray) -> float:
    """||H|| of the whole frame's forward model, sqrt(max_f sum_i |H_i(f)|^2) (what the solver divides
    by). A non-negative stack peaks at f = 0, where it is sum_i (sum h_i)^2; a stack with negative values
    (offset subtracted) is transformed plane by plane on the whole frame's 2M - 1 grid (float64, host)."""
    if h.min() >= 0:
        return float(np.sqrt(np.sum(h.reshape(h.shape[0], -1).sum(axis=1) ** 2)))
    import scipy.fft as sfft

    grid = tuple(sfft.next_fast_len(2 * m - 1, real=True) for m in h.shape[1:])
    power = np.zeros((grid[0], grid[1] // 2 + 1))
    for plane in h:
        power += np.abs(sfft.rfft2(plane, grid)) ** 2
    return float(np.sqrt(power.max()))


def reconstruct_tiled(measurement, psf, tile, halo=None, *, progress=None, **kw):
    """Reconstruct ``measurement`` (My, Mx) with ``psf`` (nz, My, Mx) as lateral tiles (see the module's
    doc). ``kw`` are :func:`cm2cl.reconstruct`'s (weights l1 / tv / *_noise_ratio / l1_plane_power,
    iterations, device, dtype, ...). Returns (volume (nz, My, Mx) in the caller's units, info); info['misfit']
    lists each tile's data misfit (:func:`cm2cl.solver.control.data_misfit`, over the tile's window)."""
    from .. import validate
    from ..solver.api import reconstruct
    from ..solver.control import ProblemScale
    from ..solver.params import ADMMParams

    psf = validate.psf_stack(validate.image_array(psf, "psf"), "psf")
    y = validate.real_array(validate.image_array(measurement, "measurement", ndims=(2,)), "measurement", ndims=(2,))
    if y.shape != psf.shape[1:]:
        raise InputError(f"measurement: shape {y.shape} does not match the PSF's sensor grid {psf.shape[1:]}")
    for bad in ("normalize", "padded_shape", "padding", "x0"):
        if bad in kw:
            raise InputError(f"{bad}: not available with lateral tiles")
    from ..solver.psf_refine import explicit_rounds

    if explicit_rounds(kw.get("psf_refine")):
        raise InputError("psf_refine: not available with lateral tiles (the PSF is refined on the whole frame)")
    # 'auto' and 'common' do not refine tiles: a tile's few views would each decide for themselves
    kw = {**kw, "psf_refine": 0}
    from ..solver.attenuation import AUTO, attenuate, solve_estimated

    names = {f.name for f in fields(ADMMParams)}
    p = ADMMParams.from_kwargs(**{k: v for k, v in kw.items() if k in names})
    psf, att = attenuate(psf, kw.get("depths_um"), p)   # the whole stack once; the tiles solve with it as given
    if p.scattering_length_um == AUTO:   # l_s from the whole stitched volume of a clear-medium solve
        call = dict(measurement=y, psf=psf, tile=tile, halo=halo, progress=progress, **kw)
        (vol, info), record = solve_estimated(reconstruct_tiled, lambda r: r[0],
                                              kw.get("depths_um"), p, call)
        return vol, {**info, "attenuation": record}
    kw = {**kw, "scattering_length_um": None, "surface_um": None}
    plan = plan_tiles(y.shape, psf, tile, halo)
    # the whole frame's normalisation and weights (module doc)
    h = np.asarray(psf, np.float64)
    sh = 1.0 / operator_norm(h)
    ymax = float(np.max(np.abs(y)))
    sy = 1.0 / ymax if ymax > 0 else 1.0
    scale = ProblemScale.of(np.asarray(y, np.float64) * sy, float(np.sum((h * sh) ** 2)), h.shape[0])
    l1, tv = scale.weights(p)
    solve_kw = {k: v for k, v in kw.items() if k not in ("l1", "tv", "l1_noise_ratio", "tv_noise_ratio")}
    nz, (My, Mx) = h.shape[0], y.shape
    out = np.zeros((nz, My, Mx))
    total = np.zeros((My, Mx))
    iterations, converged, misfits = [], [], []
    for k, ((((a, b), (c, d)), wgt), ((wr0, wr1), (wc0, wc1))) in enumerate(zip(tile_weights(plan), plan.windows)):
        Wy, Wx = wr1 - wr0, wc1 - wc0
        py0, px0 = My // 2 - Wy // 2, Mx // 2 - Wx // 2     # the PSF around its axis on the window's grid
        ht = h[:, max(py0, 0):py0 + Wy, max(px0, 0):px0 + Wx] * sh
        ht = np.pad(ht, ((0, 0), (max(-py0, 0), Wy - ht.shape[1] - max(-py0, 0)),
                         (max(-px0, 0), Wx - ht.shape[2] - max(-px0, 0))))
        rec = reconstruct(np.asarray(y[wr0:wr1, wc0:wc1], np.float64) * sy, ht, normalize=False, l1=l1, tv=tv,
                          **solve_kw)
        vol = rec.volume.astype(np.float64) * (sh / sy)     # back to the caller's units
        out[:, a:b, c:d] += wgt[None] * vol[:, a - wr0:b - wr0, c - wc0:d - wc0]
        total[a:b, c:d] += wgt
        iterations.append(rec.iterations)
        converged.append(bool(rec.info["converged"]))
        misfits.append({key: val / sy if key in ("rms", "white_rms") and val is not None else val   # caller's units
                        for key, val in rec.info["misfit"].items()})
        if progress is not None:
            progress(k + 1, len(plan.tiles), rec)
    if not np.allclose(total, 1.0):
        raise RuntimeError("tile weights do not sum to 1 (a bug)")
    info = {"tiles": len(plan.tiles), "tile": list(plan.tile), "halo": list(plan.halo), "reach": list(plan.reach),
            "feather": list(plan.feather), "l1": l1, "tv": tv, "iterations": iterations, "converged": converged,
            "noise_x": scale.noise_x, "noise_sigma": scale.noise_sigma, "misfit": misfits}
    if att is not None:
        info["attenuation"] = att
    return np.maximum(out, 0).astype(np.dtype(kw.get("dtype", np.float32))), info

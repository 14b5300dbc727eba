"""The lateral shift variance of an array PSF (paper Fig. 2C and Fig. S4C): a point source scanned over a
lateral grid at one depth gives one PSF per grid position; each is registered onto the on-axis PSF by the
cross-correlation peak and compared with it by the PCC (Eq. 5), over the whole sensor (the map of Fig. 2C)
and over the central lenslet's focus alone (Fig. S4C, where only the lenslet's own aberrations count).
The foci that each PSF holds (its "views") divide the field into the paper's regions: all R x C foci
("central"), (R-1) x C or R x (C-1) ("outer"), (R-1) x (C-1) ("corner"), any other count ("other").

Registration. The foci of every lenslet move together as the point moves (at one depth the array's image
is shifted, not sheared), so a PSF's shift is a linear function of its grid position. Where a PSF has lost
foci, its cross-correlation with the full array has several near-equal peaks (the remaining foci fit any
same-sized block of the reference), so the shift is first fitted, as a plane over the grid, to the
positions that hold every focus (their peak is unique), and every PSF is then registered within half a
foci separation of that prediction."""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from ..errors import InputError
from .metrics import _shift_zero, pcc, register_shift

__all__ = ["FOCI_LEVEL", "FOCI_ENERGY", "CENTRAL_PCC_LEVEL", "foci", "count_foci", "region_names",
           "lateral_pcc_map", "region_summary", "high_pcc_diameter_mm"]

#: pixels above this fraction of the image's peak form the foci (after merging their nearby pieces)
FOCI_LEVEL = 0.02
#: a piece counts as a focus when it holds at least this fraction of the brightest focus's light
#: (a focus cut in half by the sensor's edge or the pixels' angular cutoff still counts; a sliver does not)
FOCI_ENERGY = 0.25
#: the paper's level for the central lenslet's map (Fig. S4C: "PCC > 0.7" over a 7-mm-diameter region)
CENTRAL_PCC_LEVEL = 0.7
#: dilation (px) that merges the pieces of one aberrated focus
_MERGE_PX = 3


def _image(img, name="psf") -> np.ndarray:
    a = np.asarray(img, np.float64)
    if a.ndim != 2 or a.size == 0:
        raise InputError(f"{name}: expected a 2D image, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise InputError(f"{name}: contains NaN or Inf")
    return a


def foci(img, level: float = FOCI_LEVEL, energy: float = FOCI_ENERGY) -> dict:
    """The foci of one PSF image: ``centroids`` (k, 2) in px (row, col), ``energies`` (k,) and ``labels``
    (the image's pixels labelled 1..k by focus, 0 elsewhere), brightest first. Pieces above ``level`` of the
    peak are merged over a few pixels; those with less than ``energy`` of the brightest one's light are
    dropped."""
    a = _image(img)
    peak = float(a.max())
    if peak <= 0:
        return {"centroids": np.zeros((0, 2)), "energies": np.zeros(0), "labels": np.zeros(a.shape, np.int32)}
    mask = ndimage.binary_dilation(a > level * peak, iterations=_MERGE_PX)
    lab, n = ndimage.label(mask)
    idx = np.arange(1, n + 1)
    e = np.asarray(ndimage.sum_labels(np.clip(a, 0, None), lab, idx), float)
    keep = np.flatnonzero(e >= energy * e.max())
    keep = keep[np.argsort(-e[keep])]
    cents = np.array(ndimage.center_of_mass(np.clip(a, 0, None), lab, idx[keep])).reshape(-1, 2)
    relabel = np.zeros(n + 1, np.int32)
    relabel[idx[keep]] = np.arange(1, keep.size + 1)
    return {"centroids": cents, "energies": e[keep], "labels": relabel[lab]}


def count_foci(img, level: float = FOCI_LEVEL, energy: float = FOCI_ENERGY) -> int:
    """How many foci (views) a PSF image holds (:func:`foci`)."""
    return int(foci(img, level, energy)["energies"].size)


def _array_shape(cents) -> tuple:
    """(R, C): the rows and columns of foci of the on-axis PSF (centroids grouped where they line up)."""
    from .views import _groups

    if len(cents) == 0:
        return 0, 0
    return len(_groups(cents[:, 0])), len(_groups(cents[:, 1]))


def region_names(views, rows: int, cols: int) -> np.ndarray:
    """The paper's region of each grid position from its number of foci, for an R x C array."""
    v = np.asarray(views)
    out = np.full(v.shape, "other", dtype=object)
    names = {rows * cols: "central"}
    for k, name in (((rows - 1) * cols, "outer"), (rows * (cols - 1), "outer"), ((rows - 1) * (cols - 1), "corner")):
        if k > 0 and k not in names:
            names[k] = name
    for k, name in names.items():
        out[v == k] = name
    return out


def _positions(ny, nx, x_mm, y_mm):
    xs = np.arange(nx, dtype=float) if x_mm is None else np.asarray(x_mm, float)
    ys = np.arange(ny, dtype=float) if y_mm is None else np.asarray(y_mm, float)
    if xs.shape != (nx,) or ys.shape != (ny,):
        raise InputError(f"grid positions: {ys.size} y and {xs.size} x positions for a {ny} x {nx} grid")
    if not (np.isfinite(xs).all() and np.isfinite(ys).all()):
        raise InputError("grid positions: not finite")
    return xs, ys


def lateral_pcc_map(grid, x_mm=None, y_mm=None, ref=None, central: bool = True, progress=None) -> dict:
    """PCC of each PSF of a lateral grid with the on-axis one (paper Fig. 2C), and of its central lenslet's
    focus alone (Fig. S4C).

    Parameters
    ----------
    grid : (ny, nx, My, Mx) PSFs, or anything indexed as ``grid[i, j]`` (one 2D PSF) with a ``shape`` of
        that form (e.g. a lazy reader of a large scan).
    x_mm, y_mm : the grid's positions (nx and ny values, mm from the optical axis); default: indices.
    ref : (i, j) of the on-axis PSF; default: the position nearest (0, 0) mm (the grid's middle without
        positions).
    central : also compute the central lenslet's map.

    Returns ``pcc`` (ny, nx), ``pcc_central`` (ny, nx; NaN where that focus is off the sensor or absent),
    ``views`` (ny, nx foci per PSF), ``regions`` (ny, nx names, :func:`region_names`), ``shifts`` (ny, nx, 2:
    the registration, px), ``array`` (R, C) and ``ref`` (i, j), with ``x_mm`` and ``y_mm``."""
    shape = tuple(int(n) for n in getattr(grid, "shape", ()))
    if len(shape) != 4 or min(shape) < 1:
        raise InputError(f"lateral PSF grid: expected (ny, nx, My, Mx) PSFs, got shape {shape}")
    ny, nx = shape[:2]
    xs, ys = _positions(ny, nx, x_mm, y_mm)
    if ref is None:
        ref = (int(np.argmin(np.abs(ys))), int(np.argmin(np.abs(xs)))) if x_mm is not None and y_mm is not None \
            else (ny // 2, nx // 2)
    ri, rj = int(ref[0]), int(ref[1])
    if not (0 <= ri < ny and 0 <= rj < nx):
        raise InputError(f"reference position {ref} outside the {ny} x {nx} grid")
    reference = _image(grid[ri, rj], f"PSF ({ri}, {rj})")
    if reference.max() <= 0:
        raise InputError(f"the on-axis PSF ({ri}, {rj}) holds no light")
    f0 = foci(reference)
    full = int(f0["energies"].size)
    R, C = _array_shape(f0["centroids"])
    cents = f0["centroids"]
    sep = float(min(np.hypot(*(cents[a] - cents[b])) for a in range(full) for b in range(a))) if full > 1 else None
    views = np.zeros((ny, nx), np.int32)
    brightest = np.zeros((ny, nx))
    images = {}

    def psf(i, j):
        if (i, j) not in images:
            images.clear()
            images[(i, j)] = _image(grid[i, j], f"PSF ({i}, {j})")
        return images[(i, j)]

    # pass 1: the foci of every PSF; the unique registrations of those that hold them all
    fit_at, fit_shift = [], []
    for i in range(ny):
        for j in range(nx):
            f = foci(psf(i, j))
            views[i, j] = f["energies"].size
            brightest[i, j] = f["energies"].max() if f["energies"].size else 0.0
            if views[i, j] == full and psf(i, j).max() > 0:
                fit_at.append((ys[i], xs[j]))
                fit_shift.append(register_shift(reference, psf(i, j)))
            if progress is not None:
                progress(0.5 * (i * nx + j + 1) / (ny * nx))
    model = None
    if len(fit_at) >= 3 and sep is not None:
        A = np.column_stack([np.ones(len(fit_at)), np.asarray(fit_at)])
        if np.linalg.matrix_rank(A) == 3:
            model = np.linalg.lstsq(A, np.asarray(fit_shift, float), rcond=None)[0]      # (3, 2)
    out_pcc = np.full((ny, nx), np.nan)
    out_central = np.full((ny, nx), np.nan)
    shifts = np.zeros((ny, nx, 2), np.int64)
    window = None
    if central and full > 0:
        axis = np.array(reference.shape, float) // 2
        k = int(np.argmin(np.hypot(*(cents - axis).T)))
        half = int(math.floor(sep / 2)) if sep is not None else max(reference.shape) // 2
        cy, cx = (int(round(v)) for v in cents[k])
        window = (slice(max(0, cy - half), min(reference.shape[0], cy + half + 1)),
                  slice(max(0, cx - half), min(reference.shape[1], cx + half + 1)))
    # pass 2: register within half a foci separation of the fitted shift, then the PCCs
    for i in range(ny):
        for j in range(nx):
            img = psf(i, j)
            if img.max() <= 0:
                continue
            if model is not None:
                guess = np.rint(model[0] + model[1] * ys[i] + model[2] * xs[j]).astype(int)
                pre = _shift_zero(img, int(guess[0]), int(guess[1]))
                if pre.max() > 0:
                    d = register_shift(reference, pre, max_shift=int(sep // 2))
                    s = (int(guess[0]) + d[0], int(guess[1]) + d[1])
                else:
                    s = register_shift(reference, img)
            else:
                s = register_shift(reference, img)
            shifts[i, j] = s
            aligned = _shift_zero(img, *s)
            if aligned.std() > 0:
                out_pcc[i, j] = pcc(reference, aligned, register=False)
            if window is not None:
                a, b = reference[window], aligned[window]
                if b.std() > 0 and b.clip(0, None).sum() >= FOCI_ENERGY * brightest[i, j]:
                    out_central[i, j] = pcc(a, b, register=True, max_shift=max(1, min(a.shape) // 4))
            if progress is not None:
                progress(0.5 + 0.5 * (i * nx + j + 1) / (ny * nx))
    return {"pcc": out_pcc, "pcc_central": out_central if central else None, "views": views,
            "regions": region_names(views, R, C), "shifts": shifts, "array": (R, C), "ref": (ri, rj),
            "x_mm": xs, "y_mm": ys, "window": None if window is None else
            (window[0].start, window[0].stop, window[1].start, window[1].stop)}


def region_summary(m: dict) -> dict:
    """{region: {"positions", "pcc_mean", "pcc_min", "pcc_central_mean"}} over the regions present."""
    out = {}
    for name in ("central", "outer", "corner", "other"):
        sel = m["regions"] == name
        if not sel.any():
            continue
        p = m["pcc"][sel]
        p = p[np.isfinite(p)]
        row = {"positions": int(sel.sum()), "pcc_mean": float(p.mean()) if p.size else None,
               "pcc_min": float(p.min()) if p.size else None}
        if m.get("pcc_central") is not None:
            c = m["pcc_central"][sel]
            c = c[np.isfinite(c)]
            row["pcc_central_mean"] = float(c.mean()) if c.size else None
        out[name] = row
    return out


def high_pcc_diameter_mm(m: dict, level: float = CENTRAL_PCC_LEVEL) -> float | None:
    """Diameter (in the grid's position units) of the disc whose area equals that of the connected region
    around the on-axis position where the central lenslet's PCC exceeds ``level`` (the paper: a 7-mm
    diameter above 0.7, Fig. S4C); None without the central map."""
    c = m.get("pcc_central")
    if c is None:
        return None
    above = np.nan_to_num(c, nan=-1.0) > level
    lab, _ = ndimage.label(above)
    k = lab[m["ref"]]
    if k == 0:
        return 0.0
    xs, ys = m["x_mm"], m["y_mm"]
    dx = float(np.mean(np.abs(np.diff(xs)))) if xs.size > 1 else 1.0
    dy = float(np.mean(np.abs(np.diff(ys)))) if ys.size > 1 else 1.0
    area = float((lab == k).sum()) * dx * dy
    return 2.0 * math.sqrt(area / math.pi)

"""Fluorescent objects of a scene, as emitters in object space.

Every generator takes the validated object table, the scene's volume box and a numpy Generator
and returns a :class:`Beads` (spheres, kept as such so that renderers can treat them exactly) or a
:class:`PointCloud` (extended objects sampled densely; each sample carries photo-electrons).
Positions are (x, y, z) in um: x, y from the optical axis, z from the nominal working distance
(positive = farther from the MLA, i.e. deeper into a sample seen from above).

Brightness is in photo-electrons collected by all views of an on-axis, unattenuated emitter (the
PSF of the whole array sums to 1): per bead, per mm of fibre, per um^2 of target, per um^3 of vessel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Box", "Beads", "PointCloud", "OBJECTS", "generate", "bead_subpoints"]


@dataclass(frozen=True)
class Box:
    """Axis-aligned sample volume: centre and size, lateral in mm, depth in um."""
    center_mm: tuple        # (x, y)
    size_mm: tuple          # (x, y)
    z_range_um: tuple       # (z_min, z_max), z_min = top (closest to the MLA)

    def contains(self, xyz_um, tol_um: float = 1e-6) -> np.ndarray:
        p = np.asarray(xyz_um, float).reshape(-1, 3)
        cx, cy = (1000.0 * c for c in self.center_mm)
        hx, hy = (500.0 * s for s in self.size_mm)
        return ((np.abs(p[:, 0] - cx) <= hx + tol_um) & (np.abs(p[:, 1] - cy) <= hy + tol_um)
                & (p[:, 2] >= self.z_range_um[0] - tol_um) & (p[:, 2] <= self.z_range_um[1] + tol_um))

    def uniform(self, rng, n) -> np.ndarray:
        cx, cy = (1000.0 * c for c in self.center_mm)
        hx, hy = (500.0 * s for s in self.size_mm)
        u = rng.random((n, 3))
        return np.stack([cx + (2 * u[:, 0] - 1) * hx, cy + (2 * u[:, 1] - 1) * hy,
                         self.z_range_um[0] + u[:, 2] * (self.z_range_um[1] - self.z_range_um[0])], axis=1)

    @property
    def volume_mm3(self) -> float:
        return self.size_mm[0] * self.size_mm[1] * (self.z_range_um[1] - self.z_range_um[0]) / 1000.0


@dataclass
class Beads:
    """Uniform fluorescent spheres."""
    xyz_um: np.ndarray          # (n, 3)
    brightness: np.ndarray      # (n,) photo-electrons per bead
    diameter_um: np.ndarray     # (n,)
    kind: str = "beads"

    def __len__(self):
        return len(self.brightness)


@dataclass
class PointCloud:
    """Dense samples of an extended object."""
    xyz_um: np.ndarray          # (n, 3)
    weight: np.ndarray          # (n,) photo-electrons per sample
    kind: str = "points"

    def __len__(self):
        return len(self.weight)


def _brightness(rng, n, mean, cv):
    if cv <= 0:
        return np.full(n, float(mean))
    k = 1.0 / cv ** 2          # gamma with the given mean and coefficient of variation
    return rng.gamma(k, mean / k, n)


def _region(spec, box: Box) -> Box:
    """An object's own region (optional ``region_center_mm`` / ``region_size_mm`` / ``region_z_um``)
    or the scene box."""
    return Box(tuple(spec.get("region_center_mm") or box.center_mm),
               tuple(spec.get("region_size_mm") or box.size_mm),
               tuple(spec.get("region_z_um") or box.z_range_um))


# --------------------------------------------------------------------------------------------
# beads
# --------------------------------------------------------------------------------------------

def beads(spec: dict, box: Box, rng: np.random.Generator) -> Beads:
    """Beads of ``diameter_um`` at explicit ``positions_um`` or at random (``count`` or
    ``density_per_mm3``) in the region, optionally at least ``min_separation_um`` apart."""
    region = _region(spec, box)
    d = float(spec["diameter_um"])
    if spec.get("positions_um") is not None:
        xyz = np.asarray(spec["positions_um"], float).reshape(-1, 3)
    else:
        if spec.get("count") is not None:
            n = int(spec["count"])
        else:
            n = int(rng.poisson(float(spec["density_per_mm3"]) * region.volume_mm3))
        sep = float(spec.get("min_separation_um") or 0.0)
        if sep <= 0:
            xyz = region.uniform(rng, n)
        else:
            from scipy.spatial import cKDTree
            kept = np.zeros((0, 3))
            for _ in range(50):
                if len(kept) >= n:
                    break
                cand = region.uniform(rng, 4 * (n - len(kept)) + 8)
                for c in cand:
                    if len(kept) >= n:
                        break
                    if len(kept) == 0 or cKDTree(kept).query(c)[0] >= sep:
                        kept = np.vstack([kept, c])
            xyz = kept[:n]
    n = len(xyz)
    return Beads(xyz, _brightness(rng, n, spec["brightness"], spec.get("brightness_cv", 0.0)),
                 np.full(n, d))


def bead_subpoints(diameter_um: float, spacing_um: float) -> np.ndarray:
    """(k, 3) offsets (um) of a lattice filling a sphere, for rasterising a bead whose size matters
    on the grid; a single point when the bead is smaller than ``spacing_um``."""
    n = int(math.ceil(diameter_um / max(spacing_um, 1e-9)))
    if n <= 1:
        return np.zeros((1, 3))
    step = diameter_um / n
    g = (np.arange(n) - (n - 1) / 2.0) * step
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = (pts ** 2).sum(axis=1) <= (diameter_um / 2.0) ** 2
    return pts[inside] if inside.any() else np.zeros((1, 3))


# --------------------------------------------------------------------------------------------
# surfaces (for fibres)
# --------------------------------------------------------------------------------------------

def surface_z(spec: dict, region: Box, x_um, y_um) -> np.ndarray:
    """Depth (um) of the object's supporting surface at (x, y): ``plane`` at ``surface_z_um`` (default
    the region top) or a ``cortex``-like dome: top at the centre, falling by ``surface_depth_um`` at
    the region's edge, with a midline groove of ``groove_um`` along y."""
    kind = spec.get("surface", "cortex")
    top = spec.get("surface_z_um")
    top = region.z_range_um[0] if top is None else float(top)
    x = np.asarray(x_um, float) - 1000.0 * region.center_mm[0]
    y = np.asarray(y_um, float) - 1000.0 * region.center_mm[1]
    if kind == "plane":
        return np.full(np.broadcast(x, y).shape, top)
    ax, ay = (500.0 * s for s in region.size_mm)
    r2 = np.minimum((x / ax) ** 2 + (y / ay) ** 2, 1.0)
    depth = float(spec.get("surface_depth_um", 0.8 * (region.z_range_um[1] - region.z_range_um[0])))
    groove = float(spec.get("groove_um", 0.0))
    w = 0.04 * 1000.0 * region.size_mm[0]
    return top + depth * r2 + groove * np.exp(-x ** 2 / (2 * w * w))


def _cross_section(diameter_um, spacing_um):
    """(k, 2) offsets filling a disc (a tube's cross-section)."""
    n = int(math.ceil(diameter_um / max(spacing_um, 1e-9)))
    if n <= 1:
        return np.zeros((1, 2))
    g = (np.arange(n) - (n - 1) / 2.0) * diameter_um / n
    pts = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    keep = (pts ** 2).sum(axis=1) <= (diameter_um / 2.0) ** 2
    return pts[keep] if keep.any() else np.zeros((1, 2))


def _tube(path_xyz, diameter_um, spacing_um, weight_per_um):
    """Samples filling a tube around a polyline sampled every ``spacing_um``."""
    p = np.asarray(path_xyz, float)
    if len(p) < 2:
        return np.zeros((0, 3)), np.zeros(0)
    t = np.gradient(p, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    ref = np.where(np.abs(t[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    n1 = np.cross(t, ref)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    n2 = np.cross(t, n1)
    cs = _cross_section(diameter_um, spacing_um)
    pts = p[:, None, :] + cs[None, :, 0, None] * n1[:, None, :] + cs[None, :, 1, None] * n2[:, None, :]
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    ds = np.concatenate([[seg[0] / 2], (seg[:-1] + seg[1:]) / 2, [seg[-1] / 2]])
    w = (ds * weight_per_um / len(cs))[:, None] * np.ones(len(cs))[None, :]
    return pts.reshape(-1, 3), w.ravel()


# --------------------------------------------------------------------------------------------
# fibres on a curved surface (paper Fig. 4)
# --------------------------------------------------------------------------------------------

def fibres(spec: dict, box: Box, rng: np.random.Generator, spacing_um: float) -> PointCloud:
    """``count`` fibres of ``length_mm`` and ``diameter_um``, worm-like in-plane paths of persistence
    ``persistence_mm``, lying on the scene surface (see :func:`surface_z`)."""
    region = _region(spec, box)
    n = int(spec["count"])
    L = 1000.0 * float(spec["length_mm"])
    lp = 1000.0 * float(spec["persistence_mm"])
    d = float(spec["diameter_um"])
    ds = max(min(spacing_um, d), 0.5)
    steps = max(2, int(math.ceil(L / ds)) + 1)
    cx, cy = (1000.0 * c for c in region.center_mm)
    hx, hy = (500.0 * s for s in region.size_mm)
    pts, wts = [], []
    for _ in range(n):
        start = np.array([cx + (2 * rng.random() - 1) * hx, cy + (2 * rng.random() - 1) * hy])
        theta = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0, math.sqrt(ds / lp), steps))
        xy = start + np.cumsum(ds * np.stack([np.cos(theta), np.sin(theta)], axis=1), axis=0)
        inside = (np.abs(xy[:, 0] - cx) <= hx) & (np.abs(xy[:, 1] - cy) <= hy)
        # the parts of the path inside the region (a fibre leaving and re-entering is two pieces)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], inside.astype(np.int8), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            if b - a < 2:
                continue
            seg = xy[a:b]
            z = surface_z(spec, region, seg[:, 0], seg[:, 1]) + d / 2.0
            p, w = _tube(np.column_stack([seg, z]), d, spacing_um, float(spec["brightness_per_mm"]) / 1000.0)
            pts.append(p)
            wts.append(w)
    if not pts:
        return PointCloud(np.zeros((0, 3)), np.zeros(0), "fibres")
    return PointCloud(np.vstack(pts), np.concatenate(wts), "fibres")


# --------------------------------------------------------------------------------------------
# tilted resolution target (paper Fig. 2E-G)
# --------------------------------------------------------------------------------------------

def _usaf_bars(groups):
    """Rectangles (x0, y0, w, h) in um of a USAF-1951-like layout: each element is three horizontal
    and three vertical bars of line width 1000 / (2 * 2^(g + (e-1)/6)) um, groups side by side."""
    rects = []
    x = 0.0
    for g in range(groups[0], groups[1] + 1):
        y = 0.0
        col_w = 0.0
        for e in range(1, 7):
            w = 1000.0 / (2.0 * 2.0 ** (g + (e - 1) / 6.0))
            for k in range(3):                  # horizontal bars: length 5w along x
                rects.append((x, y + 2 * k * w, 5 * w, w))
            for k in range(3):                  # vertical bars
                rects.append((x + 7 * w + 2 * k * w, y, w, 5 * w))
            col_w = max(col_w, 12 * w)
            y += 7 * w
        x += col_w + 1000.0 / (2.0 * 2.0 ** g)
    r = np.array(rects)
    # centre the layout on the origin
    r[:, 0] -= (r[:, 0] + r[:, 2]).max() / 2
    r[:, 1] -= (r[:, 1] + r[:, 3]).max() / 2
    return r


def target(spec: dict, box: Box, rng: np.random.Generator, spacing_um: float) -> PointCloud:
    """A USAF-like resolution target (groups ``groups[0]..groups[1]``) tilted by ``tilt_deg`` about
    the x (or y) axis through ``center_mm`` / ``center_z_um``."""
    rects = _usaf_bars(tuple(int(g) for g in spec["groups"]))
    pts = []
    wts = []
    bright = float(spec["brightness_per_um2"])
    for x0, y0, w, h in rects:
        s = min(spacing_um, w / 2.0)
        nx = max(1, int(math.ceil(w / s)))
        ny = max(1, int(math.ceil(h / s)))
        gx = x0 + (np.arange(nx) + 0.5) * w / nx
        gy = y0 + (np.arange(ny) + 0.5) * h / ny
        xx, yy = np.meshgrid(gx, gy, indexing="xy")
        pts.append(np.column_stack([xx.ravel(), yy.ravel()]))
        wts.append(np.full(xx.size, bright * w * h / xx.size))
    uv = np.vstack(pts)
    w = np.concatenate(wts)
    t = math.radians(float(spec["tilt_deg"]))
    c = spec.get("center_mm") or box.center_mm
    cz = spec.get("center_z_um")
    cz = 0.5 * (box.z_range_um[0] + box.z_range_um[1]) if cz is None else float(cz)
    if spec.get("tilt_axis", "x") == "x":       # rotate about x: depth varies along y
        xyz = np.column_stack([uv[:, 0], uv[:, 1] * math.cos(t), uv[:, 1] * math.sin(t)])
    else:
        xyz = np.column_stack([uv[:, 0] * math.cos(t), uv[:, 1], uv[:, 0] * math.sin(t)])
    xyz += np.array([1000.0 * c[0], 1000.0 * c[1], cz])
    return PointCloud(xyz, w, "target")


# --------------------------------------------------------------------------------------------
# vessel-like trees
# --------------------------------------------------------------------------------------------

def vessels(spec: dict, box: Box, rng: np.random.Generator, spacing_um: float) -> PointCloud:
    """Branching trees (``roots`` of ``generations``): each segment splits in two at
    +-``branch_angle_deg``, lengths x ``length_ratio`` and diameters x ``diameter_ratio`` per
    generation; filled lumen of ``brightness_per_um3``. Roots start near the region's top."""
    region = _region(spec, box)
    ang = math.radians(float(spec["branch_angle_deg"]))
    bright = float(spec["brightness_per_um3"])
    pts, wts = [], []
    cx, cy = (1000.0 * c for c in region.center_mm)
    hx, hy = (500.0 * s for s in region.size_mm)
    z0, z1 = region.z_range_um

    def inside(p):
        return abs(p[0] - cx) <= hx and abs(p[1] - cy) <= hy and z0 <= p[2] <= z1

    stack = []
    for _ in range(int(spec["roots"])):
        start = np.array([cx + (2 * rng.random() - 1) * hx, cy + (2 * rng.random() - 1) * hy,
                          z0 + 0.1 * (z1 - z0) * rng.random()])
        phi = rng.uniform(0, 2 * np.pi)
        direction = np.array([math.cos(phi), math.sin(phi), 0.6])
        stack.append((start, direction / np.linalg.norm(direction), 0, 1000.0 * float(spec["segment_mm"]),
                      float(spec["root_diameter_um"])))
    while stack:
        start, direction, gen, length, diam = stack.pop()
        n = max(2, int(math.ceil(length / max(min(spacing_um, diam), 0.5))) + 1)
        wobble = np.cumsum(rng.normal(0, 0.05, (n, 3)), axis=0)
        path = start + np.outer(np.linspace(0, length, n), direction) + wobble * length / n
        ok = np.array([inside(p) for p in path])
        if not ok.all():
            path = path[:int(np.argmin(ok))]      # up to the first sample outside the region
        if len(path) >= 2:
            p, w = _tube(path, diam, spacing_um, bright * math.pi * diam ** 2 / 4.0)
            pts.append(p)
            wts.append(w)
        if len(path) < n or gen + 1 >= int(spec["generations"]):
            continue
        # two children in a random plane containing the parent direction
        r = rng.normal(size=3)
        perp = np.cross(direction, r)
        perp /= np.linalg.norm(perp)
        for sgn in (1.0, -1.0):
            child = math.cos(ang) * direction + sgn * math.sin(ang) * perp
            child[2] = abs(child[2]) * 0.5 + 0.1     # keep going down, gently
            stack.append((path[-1], child / np.linalg.norm(child), gen + 1,
                          length * float(spec["length_ratio"]), diam * float(spec["diameter_ratio"])))
    if not pts:
        return PointCloud(np.zeros((0, 3)), np.zeros(0), "vessels")
    return PointCloud(np.vstack(pts), np.concatenate(wts), "vessels")


# --------------------------------------------------------------------------------------------
# registry: parameters (type, default, constraint) used by scene validation
# --------------------------------------------------------------------------------------------

_REGION = {
    "region_center_mm": {"type": "vec2", "default": None},
    "region_size_mm": {"type": "vec2", "default": None, "min": 0, "exclusive": True},
    "region_z_um": {"type": "vec2", "default": None},
}

OBJECTS = {
    "beads": {
        "func": beads,
        "params": {
            "diameter_um": {"type": "float", "required": True, "min": 0, "exclusive": True},
            "count": {"type": "int", "default": None, "min": 0},
            "density_per_mm3": {"type": "float", "default": None, "min": 0},
            "positions_um": {"type": "points3", "default": None},
            "min_separation_um": {"type": "float", "default": 0.0, "min": 0},
            "brightness": {"type": "float", "default": 2.0e4, "min": 0},
            "brightness_cv": {"type": "float", "default": 0.0, "min": 0},
            **_REGION,
        },
        "one_of": ("count", "density_per_mm3", "positions_um"),
    },
    "fibres": {
        "func": fibres,
        "params": {
            "count": {"type": "int", "required": True, "min": 0},
            "length_mm": {"type": "float", "default": 2.0, "min": 0, "exclusive": True},
            "diameter_um": {"type": "float", "default": 15.0, "min": 0, "exclusive": True},
            "persistence_mm": {"type": "float", "default": 1.0, "min": 0, "exclusive": True},
            "brightness_per_mm": {"type": "float", "default": 2.0e5, "min": 0},
            "surface": {"type": "str", "default": "cortex", "choices": ("cortex", "plane")},
            "surface_z_um": {"type": "float", "default": None},
            "surface_depth_um": {"type": "float", "default": None, "min": 0},
            "groove_um": {"type": "float", "default": 0.0, "min": 0},
            **_REGION,
        },
    },
    "target": {
        "func": target,
        "params": {
            "groups": {"type": "intpair", "default": [3, 7]},
            "tilt_deg": {"type": "float", "default": 20.0, "min": -89, "max": 89},
            "tilt_axis": {"type": "str", "default": "x", "choices": ("x", "y")},
            "center_mm": {"type": "vec2", "default": None},
            "center_z_um": {"type": "float", "default": None},
            "brightness_per_um2": {"type": "float", "default": 20.0, "min": 0},
        },
    },
    "vessels": {
        "func": vessels,
        "params": {
            "roots": {"type": "int", "default": 3, "min": 0},
            "generations": {"type": "int", "default": 5, "min": 1},
            "segment_mm": {"type": "float", "default": 1.0, "min": 0, "exclusive": True},
            "root_diameter_um": {"type": "float", "default": 60.0, "min": 0, "exclusive": True},
            "length_ratio": {"type": "float", "default": 0.75, "min": 0, "exclusive": True},
            "diameter_ratio": {"type": "float", "default": 0.79, "min": 0, "exclusive": True},
            "branch_angle_deg": {"type": "float", "default": 35.0, "min": 0, "max": 90},
            "brightness_per_um3": {"type": "float", "default": 0.05, "min": 0},
            **_REGION,
        },
    },
}


def generate(spec: dict, box: Box, rng: np.random.Generator, spacing_um: float):
    """Build one validated object table (``spec['type']``) into Beads or a PointCloud; extended
    objects are sampled every ``spacing_um`` (or finer where they are thinner)."""
    kind = spec["type"]
    func = OBJECTS[kind]["func"]
    if kind == "beads":
        return func(spec, box, rng)
    return func(spec, box, rng, spacing_um)

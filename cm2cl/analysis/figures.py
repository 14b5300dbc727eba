"""Figures: content regions and depth-colour-coded orthogonal MIPs (PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["content_region", "mip_png", "scale_bar_um"]


def content_region(volume, margin: int = 10, rel: float = 0.05) -> tuple:
    """(row slice, col slice) bounding the voxels of a (nz, ny, nx) volume above ``rel`` x its
    maximum, grown by ``margin`` pixels (the whole plane if it is empty)."""
    vol = np.asarray(volume)
    proj = vol.max(axis=0)
    top = float(proj.max()) if proj.size else 0.0
    if top <= 0:
        return slice(0, proj.shape[0]), slice(0, proj.shape[1])
    r, c = np.nonzero(proj > rel * top)
    return (slice(max(r.min() - margin, 0), min(r.max() + margin + 1, proj.shape[0])),
            slice(max(c.min() - margin, 0), min(c.max() + margin + 1, proj.shape[1])))


def mip_png(volume, path, voxel_size_um=None, depths_um=None, title: str | None = None,
            cmap: str = "turbo", gamma: float = 1.0, dpi: int = 120, region=None) -> Path:
    """Save orthogonal maximum-intensity projections (XY, XZ, YZ) of a (nz, ny, nx) volume as a
    PNG with depth colour-coding (hue = depth of the maximum, brightness = its value ** gamma).
    ``region`` = (row slice, col slice) shows only part of the field (see :func:`content_region`);
    axes are in um from the volume's first pixel when ``voxel_size_um`` (dz, dy, dx) is given, with a scale
    bar under the XZ panel (:func:`scale_bar_um`), else in pixels and planes (a volume without a physical scale
    is never labelled in um, nor given a bar). The PNG's text chunks record the axes' units
    (``cm2cl:axes``) and the bar's length (``cm2cl:scale_bar_um``) for readers and tests.

    matplotlib is imported here only (``pip install 'cm2cl[plot]'``)."""
    try:
        from matplotlib.figure import Figure
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib import colormaps
        from matplotlib.colors import Normalize
        from matplotlib.cm import ScalarMappable
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise InputError("mip_png: matplotlib is not installed (pip install 'cm2cl[plot]')") from exc
    vol = np.asarray(volume, dtype=np.float64)
    if vol.ndim != 3 or vol.size == 0:
        raise InputError(f"mip_png: expected a (nz, ny, nx) volume, got shape {vol.shape}")
    if voxel_size_um is None:
        if depths_um is not None:
            raise InputError("mip_png: depths_um needs voxel_size_um (the lateral scale)")
        dz, dy, dx = 1.0, 1.0, 1.0
        lat, ax_unit = "px", "plane"
    else:
        dz, dy, dx = (float(v) for v in voxel_size_um)
        lat = ax_unit = "um"
    y0 = x0 = 0.0
    if region is not None:
        rs, cs = region
        y0 = (rs.start or 0) * dy
        x0 = (cs.start or 0) * dx
        vol = vol[:, rs, cs]
        if vol.size == 0:
            raise InputError(f"mip_png: region {region} is empty")
    nz, ny, nx = vol.shape
    depths = np.arange(nz) * dz if depths_um is None else np.asarray(depths_um, dtype=float)
    if depths.shape != (nz,):
        raise InputError(f"mip_png: depths_um has {depths.size} entries for {nz} planes")
    vmax = float(vol.max())
    scale = 1.0 / vmax if vmax > 0 else 1.0
    colours = colormaps[cmap](np.linspace(0.0, 1.0, nz) if nz > 1 else np.array([0.5]))[:, :3]

    def coloured(values, index):
        v = np.clip(values * scale, 0.0, 1.0) ** gamma
        return colours[index] * v[..., None]

    xy = coloured(vol.max(axis=0), vol.argmax(axis=0))
    xz = coloured(vol.max(axis=1), np.broadcast_to(np.arange(nz)[:, None], (nz, nx)))
    yz = coloured(vol.max(axis=2).T, np.broadcast_to(np.arange(nz)[None, :], (ny, nz)))

    zlen = max(nz * dz, 1e-9)
    w_xy, h_xy, w_z = nx * dx, ny * dy, zlen
    zscale = max(1.0, 0.25 * max(w_xy, h_xy) / zlen)      # stretch thin stacks so they stay visible
    fig = Figure(figsize=(8, 8 * (h_xy + w_z * zscale) / (w_xy + w_z * zscale)), dpi=dpi)
    FigureCanvasAgg(fig)
    W = w_xy + w_z * zscale
    H = h_xy + w_z * zscale
    m = 0.1
    fx = (1 - 2 * m) / W
    fy = (1 - 2 * m) / H
    ax_xy = fig.add_axes([m, m + w_z * zscale * fy, w_xy * fx, h_xy * fy])
    ax_yz = fig.add_axes([m + w_xy * fx, m + w_z * zscale * fy, w_z * zscale * fx, h_xy * fy])
    ax_xz = fig.add_axes([m, m, w_xy * fx, w_z * zscale * fy])
    z0, z1 = depths[0] - dz / 2, depths[-1] + dz / 2
    ax_xy.imshow(xy, extent=(x0, x0 + w_xy, y0 + h_xy, y0), aspect="auto", interpolation="nearest")
    ax_yz.imshow(yz, extent=(z0, z1, y0 + h_xy, y0), aspect="auto", interpolation="nearest")
    ax_xz.imshow(xz, extent=(x0, x0 + w_xy, z1, z0), aspect="auto", interpolation="nearest")
    ax_xy.set_xticks([]); ax_xy.set_ylabel(f"y ({lat})")
    ax_yz.set_yticks([]); ax_yz.set_xlabel(f"z ({ax_unit})"); ax_yz.xaxis.set_label_position("top")
    ax_yz.xaxis.tick_top()
    ax_xz.set_xlabel(f"x ({lat})"); ax_xz.set_ylabel(f"z ({ax_unit})")
    for ax in (ax_xy, ax_yz, ax_xz):
        ax.set_facecolor("black")
    if nz > 1:
        cax = fig.add_axes([m + w_xy * fx + 0.01, m, 0.02, w_z * zscale * fy * 0.9])
        sm = ScalarMappable(norm=Normalize(depths[0], depths[-1]), cmap=cmap)
        fig.colorbar(sm, cax=cax, label="depth (um)" if ax_unit == "um" else "plane")
    meta = {"cm2cl:axes": f"x ({lat}), y ({lat}), z ({ax_unit})"}
    if lat == "um":
        bar = scale_bar_um(w_xy)
        _draw_scale_bar(ax_xz, bar, x0, w_xy)
        meta["cm2cl:scale_bar_um"] = f"{bar:g}"
    if title:
        fig.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, facecolor="white", metadata=meta)
    return path


def scale_bar_um(width_um: float) -> float:
    """A round scale-bar length (1, 2 or 5 x 10^k um) near a fifth of ``width_um``."""
    target = max(float(width_um), 1e-12) / 5.0
    k = 10.0 ** np.floor(np.log10(target))
    return float(max(m * k for m in (1.0, 2.0, 5.0) if m * k <= target))


def _draw_scale_bar(ax, length_um, x0, w):
    """A black bar of ``length_um`` under the right end of the XZ panel, at the height of its x label (in the
    figure's margin: the panels keep only the data), drawn on the panel's x scale, its label to its left."""
    from matplotlib.transforms import blended_transform_factory, offset_copy

    tr = offset_copy(blended_transform_factory(ax.transData, ax.transAxes), fig=ax.figure, y=-24, units="points")
    xb = x0 + w - length_um
    ax.plot([xb, x0 + w], [0.0, 0.0], color="black", linewidth=3, solid_capstyle="butt", transform=tr, clip_on=False)
    label = f"{length_um / 1000:g} mm" if length_um >= 1000 else f"{length_um:g} um"
    ax.text(xb - 0.01 * w, 0.0, label, color="black", ha="right", va="center", fontsize=9, transform=tr,
            clip_on=False)

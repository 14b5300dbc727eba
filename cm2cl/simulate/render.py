"""Image formation: object-space emitters -> expected photo-electrons on the sensor.

Three paths, chosen by the pipeline from the effects a scene names:

* :func:`render_shift_invariant` -- the slice-wise shift-invariant model of the paper (Eq. 3):
  y = C sum_i h_i (*) x_i with the on-axis PSF stack, the object on the padded grid, run by
  :class:`cm2cl.solver.ForwardModel` on the OpenCL device or by this module's own float64
  real-FFT convolution (:func:`convolve_numpy`). One FFT convolution per plane.
* :func:`render_grid` -- shift-variant, for any object: PSFs computed on a lateral grid of field
  points (with truncation / aberrations), each re-centred to the on-axis foci positions, and blended
  with bilinear weights (local convolution model, Nagy & O'Leary): y = C sum_i sum_g k_ig (*) (w_g x_i).
* :func:`render_emitters` -- shift-variant and exact for bead scenes: every bead gets its own array
  PSF at its true (x, y, z), with its size as a sphere transfer function.

The object grid ("render grid") is sensor-referred: plane i at depth z_i, pixel (r, c) of the padded
grid stands for the object point whose central-lens image falls on that pixel, i.e. the image is
inverted and demagnified by l0 / l(z) -- exactly the coordinates of the forward model's x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..optics import CM2Optics, array_psf, axial_psf_stack
from .objects import Beads, Box, PointCloud, bead_subpoints

__all__ = ["RenderGrid", "Sample", "padded_shape_for", "estimate_bytes", "render_backend", "forward",
           "convolve_numpy", "render_shift_invariant", "render_grid", "render_emitters", "render_psf_stack"]


# --------------------------------------------------------------------------------------------
# grid and sample
# --------------------------------------------------------------------------------------------

@dataclass
class RenderGrid:
    """Sensor-referred object grid: depth planes ``depths_um`` (uniform spacing ``dz_um``) on the
    padded grid ``padded_shape`` around the sensor window."""
    optics: CM2Optics
    depths_um: np.ndarray
    dz_um: float
    padded_shape: tuple

    @property
    def offsets(self) -> tuple:
        my, mx = self.optics.shape
        return ((self.padded_shape[0] - my) // 2, (self.padded_shape[1] - mx) // 2)

    @property
    def axis_px(self) -> tuple:
        """Padded-grid pixel (row, col) of the optical axis."""
        oy, ox = self.offsets
        cy, cx = self.optics.center_px
        return (oy + cy, ox + cx)

    @property
    def shape(self) -> tuple:
        return (len(self.depths_um),) + tuple(self.padded_shape)

    @property
    def crop(self) -> tuple:
        oy, ox = self.offsets
        my, mx = self.optics.shape
        return (slice(oy, oy + my), slice(ox, ox + mx))

    def field_axes_mm(self, j):
        """Object positions (x_mm over columns, y_mm over rows) of plane j's grid."""
        m = float(self.optics.magnification(self.depths_um[j]))
        p_mm = self.optics.pixel_size_um / 1000.0
        ar, ac = self.axis_px
        x = -(np.arange(self.padded_shape[1]) - ac) * p_mm / m
        y = -(np.arange(self.padded_shape[0]) - ar) * p_mm / m
        return x, y

    def to_grid(self, xyz_um):
        """Fractional (plane, row, col) of object points (x, y, z) in um."""
        p = np.asarray(xyz_um, float).reshape(-1, 3)
        m = self.optics.magnification(p[:, 2])
        ar, ac = self.axis_px
        pix = self.optics.pixel_size_um
        t = (p[:, 2] - self.depths_um[0]) / self.dz_um
        return t, ar - p[:, 1] * m / pix, ac - p[:, 0] * m / pix

    def splat(self, vol, xyz_um, weight) -> int:
        """Add weighted points into ``vol`` (this grid's shape) with trilinear weights; points more
        than half a plane beyond the first/last plane or off the padded grid are dropped. Returns
        the number of dropped points."""
        t, r, c = self.to_grid(xyz_um)
        w = np.asarray(weight, float)
        nz, py, px = vol.shape
        keep = (t >= -0.5) & (t <= nz - 0.5) & (r >= 0) & (r <= py - 1) & (c >= 0) & (c <= px - 1)
        dropped = int((~keep).sum())
        t, r, c, w = t[keep], r[keep], c[keep], w[keep]
        if w.size == 0:
            return dropped
        t = np.clip(t, 0.0, nz - 1)
        parts = []
        for v, n in ((t, nz), (r, py), (c, px)):
            i0 = np.clip(np.floor(v).astype(np.int64), 0, max(n - 2, 0))
            f = v - i0
            if n == 1:
                parts.append(((i0, np.ones_like(f)),))
            else:
                parts.append(((i0, 1.0 - f), (i0 + 1, f)))
        for it, wt in parts[0]:
            for ir, wr in parts[1]:
                for ic, wc in parts[2]:
                    np.add.at(vol, (it, ir, ic), (w * wt * wr * wc).astype(vol.dtype))
        return dropped


@dataclass
class Sample:
    """What the sample emits, as the object-stage effects see and change it."""
    box: Box
    volume: np.ndarray | None = None        # (nr, Py, Px) float32 on the render grid
    beads: Beads | None = None              # for per-emitter rendering
    background: np.ndarray | None = None    # unresolved background on the render grid
    bead_halo: tuple | None = None          # (photo-electrons (n,), halo sigma um (n,))
    notes: dict = field(default_factory=dict)

    def volumes(self):
        """(name, array) of the volume components, modified in place by effects."""
        out = []
        if self.volume is not None:
            out.append(("objects", self.volume))
        if self.background is not None:
            out.append(("background", self.background))
        return out

    def total_emission(self) -> float:
        if self.volume is not None:
            return float(self.volume.sum(dtype=np.float64))
        return float(self.beads.brightness.sum()) if self.beads is not None else 0.0

    def add_background(self, dens):
        self.background = dens if self.background is None else self.background + dens

    def set_bead_halo(self, brightness, sigma_um):
        self.bead_halo = (np.asarray(brightness, float), np.asarray(sigma_um, float))

    def total_volume(self):
        if self.background is None:
            return self.volume
        return self.volume + self.background


def rasterise(grid: RenderGrid, objects, dtype=np.float32):
    """Ground-truth emission on the render grid from generated objects (Beads filled as spheres
    sampled finer than the grid, point clouds as they are). Returns (volume, dropped points)."""
    vol = np.zeros(grid.shape, dtype)
    dropped = 0
    spacing = 0.5 * min(float(grid.optics.object_pixel_um(0.0)), grid.dz_um)
    for obj in objects:
        if isinstance(obj, Beads):
            for d in np.unique(obj.diameter_um):
                sel = obj.diameter_um == d
                sub = bead_subpoints(float(d), spacing)
                pts = (obj.xyz_um[sel][:, None, :] + sub[None, :, :]).reshape(-1, 3)
                w = np.repeat(obj.brightness[sel] / len(sub), len(sub))
                # count a bead as dropped only once
                before = grid.splat(vol, pts, w)
                dropped += int(round(before / len(sub)))
        elif isinstance(obj, PointCloud):
            dropped += grid.splat(vol, obj.xyz_um, obj.weight)
    return vol, dropped


# --------------------------------------------------------------------------------------------
# sizes, memory, backends
# --------------------------------------------------------------------------------------------

def padded_shape_for(sensor_shape, backend: str) -> tuple:
    """The object grid: >= 2M - 1 (no wrap-around into the sensor window), on a size the renderer's
    FFT is fast on (the device FFT backend's, or scipy's for the numpy path)."""
    need = tuple(2 * int(m) - 1 for m in sensor_shape)
    if backend == "opencl":
        from ..device import fft
        b = fft.resolve_backend("auto")
        return tuple(fft.good_size(n, b) for n in need)
    from scipy import fft as sfft
    return tuple(sfft.next_fast_len(n, real=True) for n in need)


def estimate_bytes(n_planes: int, padded_shape, sensor_shape) -> int:
    """Host + device memory of a simulation: ~6 float32 volumes on the padded grid (render volume,
    background, ground truth, device copy, PSF spectra, FFT scratch)."""
    return int(6 * 4 * n_planes * padded_shape[0] * padded_shape[1] + 8 * 4 * sensor_shape[0] * sensor_shape[1])


def render_backend(backend: str, device=None) -> str:
    """The renderer: 'opencl', 'numpy', or 'auto' = opencl when any OpenCL device exists, else numpy
    (the record says which). A requested device (argument or CM2CL_DEVICE) that cannot be had is an
    error, not a fallback."""
    if backend in ("opencl", "numpy"):
        return backend
    if backend != "auto":
        raise InputError(f"render.backend: unknown backend {backend!r} (known: auto, opencl, numpy)")
    from ..device import get_runtime, list_devices
    from ..errors import DeviceError
    try:
        present = bool(list_devices())
    except DeviceError:            # pyopencl missing
        present = False
    if not present and device is None:
        return "numpy"
    get_runtime(device)
    return "opencl"


def convolve_numpy(psf, x, padded_shape) -> np.ndarray:
    """The simulator's own float64 image formation: C sum_i h_i (*) x_i by real FFTs on the padded
    grid. The PSF's axis pixel (My//2, Mx//2) maps an object voxel onto the same sensor-window pixel;
    the sensor window is centred on the padded grid."""
    from scipy import fft as sfft
    psf = np.asarray(psf, np.float64)
    nz, my, mx = psf.shape
    py, px = padded_shape
    # kernel with its axis tap at index (0, 0): place, then rotate by the axis position
    k = np.zeros((nz, py, px))
    k[:, :my, :mx] = psf
    k = np.roll(k, (-(my // 2), -(mx // 2)), axis=(1, 2))
    spec = sfft.rfft2(k, workers=-1) * sfft.rfft2(np.asarray(x, np.float64), s=(py, px), workers=-1)
    image = sfft.irfft2(spec.sum(axis=0), s=(py, px), workers=-1)
    oy, ox = (py - my) // 2, (px - mx) // 2
    return image[oy:oy + my, ox:ox + mx]


def forward(psf, x, padded_shape, backend: str, device=None) -> np.ndarray:
    """y = C sum_i h_i (*) x_i on the OpenCL device (float32) or in numpy (float64)."""
    if backend == "opencl":
        from ..solver.forward import ForwardModel
        model = ForwardModel(np.ascontiguousarray(psf, np.float32), padded_shape=padded_shape, device=device)
        return np.asarray(model.forward(np.ascontiguousarray(x, np.float32)), np.float64)
    return convolve_numpy(psf, x, padded_shape)


# --------------------------------------------------------------------------------------------
# the three paths
# --------------------------------------------------------------------------------------------

def render_shift_invariant(volume, psf, padded_shape, backend: str = "opencl", device=None) -> np.ndarray:
    """Expected sensor image of a render-grid volume with the on-axis PSF stack (nz, My, Mx):
    exactly ``forward(psf, volume)``. Empty planes are skipped (they contribute nothing)."""
    used = np.flatnonzero(np.asarray(volume).reshape(volume.shape[0], -1).any(axis=1))
    if used.size == 0:
        return np.zeros(psf.shape[1:])
    return forward(psf[used], volume[used], padded_shape, backend, device)


def _hat_nodes(n, axis, spacing):
    """Node positions covering 0..n-1 every ``spacing`` px through ``axis`` and their hat weights."""
    k0 = math.floor((0 - axis) / spacing)
    k1 = math.ceil((n - 1 - axis) / spacing)
    nodes = axis + spacing * np.arange(k0, k1 + 1)
    idx = np.arange(n)
    w = np.clip(1.0 - np.abs(idx[None, :] - nodes[:, None]) / spacing, 0.0, None)
    return nodes, w


def render_grid(volume, grid: RenderGrid, psf_kw: dict, node_spacing_mm: float,
                backend: str = "opencl", chunk: int = 16, device=None) -> tuple:
    """Shift-variant image by the local-convolution model on a lateral grid of field points every
    ``node_spacing_mm`` (object space at the nominal distance). Returns (image, info)."""
    opt = grid.optics
    spacing = node_spacing_mm * 1000.0 * float(opt.magnification(0.0)) / opt.pixel_size_um
    if spacing < 2:
        raise InputError(f"render.grid_mm: {node_spacing_mm} mm is under 2 pixels on this sensor")
    ar, ac = grid.axis_px
    nodes_r, wr = _hat_nodes(grid.padded_shape[0], ar, spacing)
    nodes_c, wc = _hat_nodes(grid.padded_shape[1], ac, spacing)
    oy, ox = grid.offsets
    image = np.zeros(opt.shape)
    kernels, planes = [], []
    n_kernels = 0

    def flush():
        nonlocal image
        if kernels:
            image += forward(np.stack(kernels), np.stack(planes), grid.padded_shape, backend, device)
            kernels.clear()
            planes.clear()

    for j, z in enumerate(grid.depths_um):
        xj = volume[j]
        rows_on = xj.any(axis=1)
        cols_on = xj.any(axis=0)
        if not rows_on.any():
            continue
        for a in range(len(nodes_r)):
            if not (rows_on & (wr[a] > 0)).any():
                continue
            for b in range(len(nodes_c)):
                if not (cols_on & (wc[b] > 0)).any():
                    continue
                part = xj * (wr[a][:, None] * wc[b][None, :]).astype(xj.dtype)
                if not part.any():
                    continue
                x_mm, y_mm = opt.sensor_to_object_mm(nodes_r[a] - oy, nodes_c[b] - ox, z)
                k = array_psf(opt, float(z), float(x_mm), float(y_mm), recenter=True, **psf_kw)
                if not k.any():
                    continue                   # every view of this field point is lost
                kernels.append(k)
                planes.append(part)
                n_kernels += 1
                if len(kernels) >= chunk:
                    flush()
    flush()
    return image, {"node_spacing_px": spacing, "nodes": [len(nodes_r), len(nodes_c)],
                   "kernels_used": n_kernels}


def render_emitters(beads: Beads, optics: CM2Optics, psf_kw: dict, halo=None) -> np.ndarray:
    """Shift-variant image of beads, each with its own array PSF at its exact position (and its
    scattering halo, if any)."""
    image = np.zeros(optics.shape)
    for i in range(len(beads)):
        x, y, z = beads.xyz_um[i]
        b = float(beads.brightness[i])
        if b > 0:
            array_psf(optics, float(z), x / 1000.0, y / 1000.0, bead_diameter_um=float(beads.diameter_um[i]),
                      scale=b, out=image, **psf_kw)
        if halo is not None and halo[0][i] > 0:
            array_psf(optics, float(z), x / 1000.0, y / 1000.0, bead_diameter_um=float(beads.diameter_um[i]),
                      blur_sigma_um=float(halo[1][i]), scale=float(halo[0][i]), out=image, **psf_kw)
    return image


def render_psf_stack(optics: CM2Optics, depths_um, psf_kw: dict) -> np.ndarray:
    """On-axis PSF stack at ``depths_um`` with the optics-stage effects (what a calibration measures)."""
    return axial_psf_stack(optics, depths_um, **psf_kw)

"""CM2 optics: the prototype's geometry and its closed forms (the PSF model is in :mod:`.psf`).

Geometry (paper, Results "Principle of the CM2" and Methods "The CM2 prototype"): a 3 x 3 microlens
array (MLA) of pitch D = 1 mm with square, 100 %-fill apertures sits l0 = 5 mm in front of the sensor
(Aptina MT9P031, 1944 x 2592 pixels of 2.2 um); the nominal working distance is l = 12 mm, where the
lenslets (NA = D / 2l ~ 0.042) focus a point onto the sensor. Each lenslet k (centre c_k) images a point
at object position p (mm, lateral, from the optical axis) and distance l onto

    s_k = c_k (1 + l0/l) - p l0/l                                   (chief ray through c_k)

so the foci separation is d = (l0/l + 1) D (Eq. 1) and the magnification l0/l (inverted image).

Conventions used everywhere in cm2cl:

* depth ``z_um`` is measured from the nominal working distance, away from the MLA: l = l_nom + z.
* lateral object positions ``x_mm, y_mm`` are from the optical axis; x runs along sensor columns,
  y along sensor rows.
* a sensor image has shape (rows, cols) = ``optics.shape``; its pixel (My//2, Mx//2) is the optical axis.
* PSFs are normalised so that the full, untruncated array of an on-axis point sums to 1 (each of the
  n lenslets carries 1/n); object intensities are therefore "photo-electrons collected by all views".

The PSF of a lenslet is scalar Fraunhofer diffraction of its square pupil with the defocus phase
pi/lambda (1/l - 1/l_nom) rho^2 (thin lens focused at l_nom), the lenslet's spherical aberration
(``spherical_waves``) and optionally Seidel field aberrations,
computed once per lenslet by FFT on a small supersampled patch, integrated over pixels exactly (pixel
transfer function in Fourier space) and placed on the sensor at the geometric focus with its sub-pixel
offset applied as a pupil phase ramp. Without any aberration (``spherical_waves=0``) the pupil is
separable and the spot is the outer product of two 1D transforms.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..validate import Checker

__all__ = [
    "CM2Optics", "Aberration", "foci_separation_mm", "axial_resolution_um", "sbp_3d",
    "depth_planes", "chief_ray_angles_deg", "angular_response", "lenslet_weights", "view_count", "view_crop",
]


# --------------------------------------------------------------------------------------------
# closed forms
# --------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=64)
def balancing_defocus_waves(w040: float, samples: int = 256) -> float:
    """The defocus W020 (waves, W = W020 rho^2 + W040 rho^4 over the square pupil |rx|, |ry| <= 1, rho^2 =
    rx^2 + ry^2) that maximises the Strehl ratio |<exp(2 pi i W)>|^2, the peak of the spot: the focus
    of best intensity. The phase is symmetric, so the peak lies on the chief ray and the on-axis value is
    the peak. Searched over [-3 W040, 3 W040] (the least-squares balance of a circular pupil is -W040, a
    square's corners push it further); 0 for W040 = 0."""
    if w040 == 0:
        return 0.0
    from scipy.optimize import minimize_scalar

    t = (np.arange(samples) + 0.5) / samples * 2.0 - 1.0      # midpoints over [-1, 1]
    r2 = (t[:, None] ** 2 + t[None, :] ** 2).ravel()
    r4 = r2 * r2

    def neg_strehl(w020):
        return -abs(np.mean(np.exp(2j * np.pi * (w020 * r2 + w040 * r4)))) ** 2

    # the Strehl ratio of a large aberration has side maxima: a coarse scan brackets the global one
    grid = np.linspace(-3.0 * abs(w040), 3.0 * abs(w040), 241)
    best = grid[int(np.argmin([neg_strehl(g) for g in grid]))]
    step = grid[1] - grid[0]
    res = minimize_scalar(neg_strehl, bounds=(best - step, best + step), method="bounded",
                          options={"xatol": 1e-6 * max(abs(w040), 1e-12)})
    return float(res.x)

def foci_separation_mm(l_mm, l0_mm: float = 5.0, pitch_mm: float = 1.0):
    """Eq. 1: separation d (mm, on the sensor) of neighbouring foci for an object at distance l (mm)."""
    return (l0_mm / np.asarray(l_mm, dtype=float) + 1.0) * pitch_mm


def axial_resolution_um(dd_um: float = 5.0, l_mm: float = 12.0, l0_mm: float = 5.0,
                        pitch_mm: float = 1.0) -> float:
    """Eq. 2: geometric axial resolution dl = dd l^2 / (D l0) (um) for a smallest distinguishable
    foci shift dd (um). The paper sets dd = 5 um (the object-space pixel) and gets ~144 um."""
    return float(dd_um * l_mm ** 2 / (pitch_mm * l0_mm))


def sbp_3d(fov_mm=(8.1, 7.3), dof_mm: float = 2.5, lateral_bandwidth_per_um: float = 0.143,
           axial_bandwidth_per_um: float = 0.0143) -> float:
    """3D space-bandwidth product (Methods): V * B with V = FOV x DOF and B = B_z B_x^2 / 2 (the
    lateral support is the autocorrelation of a square, area B_x^2 / 2). Paper values give ~21.6e6."""
    volume_um3 = float(fov_mm[0]) * float(fov_mm[1]) * float(dof_mm) * 1e9
    bandwidth = axial_bandwidth_per_um * lateral_bandwidth_per_um ** 2 / 2.0
    return volume_um3 * bandwidth


def depth_planes(start_um: float, stop_um: float, step_um: float) -> np.ndarray:
    """Depths start, start+step, ..., stop (inclusive when stop lies on the grid), in um."""
    if not step_um > 0:
        raise InputError(f"step_um: must be > 0, got {step_um!r}")
    if stop_um < start_um:
        raise InputError(f"depth range: stop {stop_um} um is below start {start_um} um")
    n = int(math.floor((stop_um - start_um) / step_um + 1e-9)) + 1
    return start_um + step_um * np.arange(n, dtype=float)


# --------------------------------------------------------------------------------------------
# the optics description
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Aberration:
    """Seidel field aberrations of each lenslet, in waves at the pupil edge (half-side a/2) for a
    chief-ray field angle of ``ref_angle_deg``; they grow with the lenslet's own field angle H:
    field curvature W020 H^2 rho^2, astigmatism W222 (H.rho)^2, coma W131 (H.rho) rho^2."""
    w020: float = 1.0
    w222: float = 1.0
    w131: float = 0.5
    ref_angle_deg: float = 20.0

    def __post_init__(self):
        Checker(None, "aberration").fields(self, {
            "w020": {"type": "float"}, "w222": {"type": "float"}, "w131": {"type": "float"},
            "ref_angle_deg": {"type": "float", "min": 0, "exclusive": True, "max": 89}})

    @property
    def total_waves(self) -> float:
        return abs(self.w020) + abs(self.w222) + abs(self.w131)


@dataclass(frozen=True)
class CM2Optics:
    """The CM2 prototype (defaults from the paper) on a possibly binned and cropped sensor.

    Parameters
    ----------
    lenses : (rows, cols) of the microlens array.
    pitch_mm : MLA pitch D.
    aperture_mm : side of each lenslet's square clear aperture (100 % fill factor: = pitch).
    l0_mm : MLA (2nd principal plane) to sensor distance.
    l_mm : nominal working distance (object to 1st principal plane), where z = 0.
    wavelength_um : emission wavelength.
    pixel_um : native sensor pixel pitch.
    sensor_px : native sensor size (rows, cols).
    binning : sensor pixel binning (int >= 1); the simulated pixel is ``binning * pixel_um``.
    sensor_shape : optional (rows, cols) of the simulated grid in binned pixels, centred on the
        optical axis; default ``sensor_px // binning``. Use it to simulate a cropped sensor.
    supersample : fine samples per (binned) pixel for the diffraction patch; default: just enough
        for the intensity band limit 2a / (lambda l0).
    spherical_waves : primary spherical aberration W040 of every lenslet, in waves at the middle of
        the aperture's side (rho = 1; the corners see 4x); 0 = diffraction limited. Each lenslet also
        carries the defocus that puts its best focus at z = 0 (:attr:`focus_waves`). The paper gives no
        value; the default 0.61 is fitted to its lateral resolution (~7 um against the 6.4 um
        diffraction limit: the model's spot FWHM 7 / 6.4 times its diffraction-limited one;
        ``tools/fit_optics.py``, docs/optics_fit.md, which also shows that the measured axial PCC widths
        are beyond this parameter's reach).
    """
    lenses: tuple = (3, 3)
    pitch_mm: float = 1.0
    aperture_mm: float = 1.0
    l0_mm: float = 5.0
    l_mm: float = 12.0
    wavelength_um: float = 0.530
    pixel_um: float = 2.2
    sensor_px: tuple = (1944, 2592)
    binning: int = 1
    sensor_shape: tuple | None = None
    supersample: int | None = None
    spherical_waves: float = 0.61

    def __post_init__(self):
        pos = {"type": "float", "min": 0, "exclusive": True}
        ck = Checker(None, "optics")
        ck.fields(self, {"pitch_mm": pos, "aperture_mm": pos, "l0_mm": pos, "l_mm": pos, "wavelength_um": pos,
                         "pixel_um": pos, "binning": {"type": "int", "min": 1},
                         "supersample": {"type": "int", "min": 1}, "spherical_waves": {"type": "float"}})
        for name in ("lenses", "sensor_px", "sensor_shape"):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, tuple(ck.value(name, list(v) if isinstance(v, (tuple, list)) else v,
                                                              {"type": "intpair2", "min": 1})))
        if self.shape[0] < 1 or self.shape[1] < 1:
            raise InputError(f"optics.binning: {self.binning} leaves no pixel of the {self.sensor_px} sensor")

    # ---- derived quantities ------------------------------------------------------------------
    def replace(self, **changes) -> "CM2Optics":
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict:
        return {f.name: (list(v) if isinstance(v := getattr(self, f.name), tuple) else v)
                for f in dataclasses.fields(self)}

    @property
    def shape(self) -> tuple:
        """Simulated sensor grid (rows, cols) in binned pixels."""
        if self.sensor_shape is not None:
            return tuple(self.sensor_shape)
        return (self.sensor_px[0] // self.binning, self.sensor_px[1] // self.binning)

    @property
    def pixel_size_um(self) -> float:
        """Pitch of the simulated (binned) pixel on the sensor."""
        return self.pixel_um * self.binning

    @property
    def na(self) -> float:
        """Lenslet numerical aperture at the working distance, (a/2) / l (~0.042)."""
        return self.aperture_mm / 2.0 / self.l_mm

    @property
    def n_lenses(self) -> int:
        return self.lenses[0] * self.lenses[1]

    @property
    def oversampling(self) -> int:
        """Fine samples per simulated pixel used for the diffraction patch."""
        if self.supersample is not None:
            return int(self.supersample)
        nyquist_um = self.wavelength_um * self.l0_mm / (2.0 * self.aperture_mm)  # intensity band limit
        return max(1, int(math.floor(self.pixel_size_um / nyquist_um)) + 1)

    def distance_mm(self, z_um):
        """Object-MLA distance l = l_nom + z (mm)."""
        return self.l_mm + np.asarray(z_um, dtype=float) / 1000.0

    @property
    def focus_waves(self) -> float:
        """The defocus W020 (waves at rho = 1, the aperture's half side) that every lenslet's pupil carries
        so that, with its spherical aberration, the sharpest spot is at z = 0 (the prototype is assembled
        with the best focus at the nominal working distance: the paper's PSF scan has z = 0, l = 12 mm, in
        focus). 0 without spherical aberration."""
        return balancing_defocus_waves(self.spherical_waves)

    def magnification(self, z_um=0.0):
        """Lateral magnification l0 / l (the image is inverted)."""
        return self.l0_mm / self.distance_mm(z_um)

    def object_pixel_um(self, z_um=0.0):
        """Size of one simulated pixel back-projected to the object at depth z (~5.3 um unbinned)."""
        return self.pixel_size_um / self.magnification(z_um)

    def foci_separation_px(self, z_um=0.0):
        """Eq. 1 on the sensor, in simulated pixels."""
        return foci_separation_mm(self.distance_mm(z_um), self.l0_mm, self.pitch_mm) * 1000.0 / self.pixel_size_um

    @property
    def lens_centers_mm(self) -> np.ndarray:
        """(n, 2) lenslet centres (y, x) in mm, row-major over the array, centred on the axis."""
        ny, nx = self.lenses
        cy = (np.arange(ny) - (ny - 1) / 2.0) * self.pitch_mm
        cx = (np.arange(nx) - (nx - 1) / 2.0) * self.pitch_mm
        yy, xx = np.meshgrid(cy, cx, indexing="ij")
        return np.stack([yy.ravel(), xx.ravel()], axis=1)

    @property
    def center_px(self) -> tuple:
        """Pixel of the optical axis (My//2, Mx//2)."""
        return (self.shape[0] // 2, self.shape[1] // 2)

    def foci_mm(self, z_um=0.0, x_mm=0.0, y_mm=0.0) -> np.ndarray:
        """(n, 2) geometric foci (y, x) on the sensor in mm from the axis: c (1 + m) - p m."""
        m = float(self.magnification(z_um))
        c = self.lens_centers_mm
        p = np.array([y_mm, x_mm], dtype=float)
        return c * (1.0 + m) - p[None, :] * m

    def foci_px(self, z_um=0.0, x_mm=0.0, y_mm=0.0) -> np.ndarray:
        """(n, 2) geometric foci as fractional (row, col) sensor pixel coordinates."""
        return self.foci_mm(z_um, x_mm, y_mm) * 1000.0 / self.pixel_size_um + np.array(self.center_px, float)

    def object_to_sensor_px(self, x_mm, y_mm, z_um=0.0):
        """Sensor pixel (row, col) on which the central lens images the object position (x_mm, y_mm) at depth
        z: the forward model's voxel for it (the inverse of :meth:`sensor_to_object_mm`)."""
        m = self.magnification(z_um)
        p = self.pixel_size_um / 1000.0
        return (self.center_px[0] - np.asarray(y_mm, float) * m / p,
                self.center_px[1] - np.asarray(x_mm, float) * m / p)

    def sensor_to_object_mm(self, row, col, z_um=0.0):
        """Object position (x_mm, y_mm) whose central-lens image falls on sensor pixel (row, col)
        (the position an object voxel of the forward model's grid stands for)."""
        m = self.magnification(z_um)
        p = self.pixel_size_um / 1000.0
        y = -(np.asarray(row, float) - self.center_px[0]) * p / m
        x = -(np.asarray(col, float) - self.center_px[1]) * p / m
        return x, y


# --------------------------------------------------------------------------------------------
# field-dependent lenslet weights: angular pixel response (truncation)
# --------------------------------------------------------------------------------------------

def chief_ray_angles_deg(optics: CM2Optics, z_um=0.0, x_mm=0.0, y_mm=0.0) -> np.ndarray:
    """(n, 2) chief-ray incidence angles (y, x components, degrees) of each lenslet's focus on the
    sensor: tan(theta) = (c_k - p) / l (same in object and image space for a thin lens)."""
    l = float(optics.distance_mm(z_um))
    p = np.array([y_mm, x_mm], dtype=float)
    return np.degrees(np.arctan((optics.lens_centers_mm - p[None, :]) / l))


def angular_response(theta_deg, cutoff_deg: float = 21.0, edge_deg: float = 1.0):
    """Pixel angular response: 1 below the cutoff, 0 above, with a raised-cosine edge of full width
    ``edge_deg`` centred on the cutoff (paper: ~21 deg for the MT9P031)."""
    t = np.abs(np.asarray(theta_deg, dtype=float))
    if edge_deg <= 0:
        return (t <= cutoff_deg).astype(float)
    u = np.clip((t - (cutoff_deg - edge_deg / 2.0)) / edge_deg, 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * u))


def lenslet_weights(optics: CM2Optics, z_um=0.0, x_mm=0.0, y_mm=0.0, cutoff_deg=None,
                    edge_deg: float = 1.0) -> np.ndarray:
    """(n,) relative power of each lenslet's focus: 1/n each, times the pixel angular response
    (separable in the x and y incidence angles) when ``cutoff_deg`` is given."""
    w = np.full(optics.n_lenses, 1.0 / optics.n_lenses)
    if cutoff_deg is not None:
        ang = chief_ray_angles_deg(optics, z_um, x_mm, y_mm)
        w = w * angular_response(ang[:, 0], cutoff_deg, edge_deg) * angular_response(ang[:, 1], cutoff_deg, edge_deg)
    return w


def view_count(optics: CM2Optics, z_um=0.0, x_mm=0.0, y_mm=0.0, cutoff_deg=21.0) -> int:
    """Number of foci of a point at (x, y, z) that land on the sensor and pass the angular cutoff
    (the "views" of paper Fig. 2C)."""
    r, c = optics.foci_px(z_um, x_mm, y_mm).T
    my, mx = optics.shape
    on = (r >= -0.5) & (r < my - 0.5) & (c >= -0.5) & (c < mx - 0.5)
    if cutoff_deg is not None:
        on &= lenslet_weights(optics, z_um, x_mm, y_mm, cutoff_deg, edge_deg=0.0) > 0
    return int(on.sum())



def view_crop(optics: CM2Optics, rows, cols, z_um: float = 0.0) -> tuple:
    """Sensor window (row slice, col slice) holding only the foci of lenslet ``rows`` x ``cols``
    (indices into the array, e.g. rows=(0, 1), cols=(0, 1) for a 2 x 2 sub-array) of an on-axis
    point: bounded half a foci separation beyond the chosen foci. Used to emulate 2x3 / 2x2 / 1x1
    arrays from a 3x3 PSF as in the paper's Methods (same NA per lenslet)."""
    d = float(optics.foci_separation_px(z_um))
    pos = optics.foci_px(z_um).reshape(optics.lenses + (2,))
    r = pos[list(rows), 0, 0]
    c = pos[0, list(cols), 1]
    my, mx = optics.shape
    r0, r1 = int(max(0, math.floor(r.min() - d / 2))), int(min(my, math.ceil(r.max() + d / 2)))
    c0, c1 = int(max(0, math.floor(c.min() - d / 2))), int(min(mx, math.ceil(c.max() + d / 2)))
    return slice(r0, r1), slice(c0, c1)

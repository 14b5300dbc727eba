"""CM2 optics: the prototype's geometry, its closed forms, and simulated array PSFs.

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
import math
from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

from .errors import InputError

__all__ = [
    "CM2Optics", "Aberration", "foci_separation_mm", "axial_resolution_um", "sbp_3d",
    "depth_planes", "chief_ray_angles_deg", "angular_response", "lenslet_weights", "view_count",
    "lenslet_spot", "array_psf", "axial_psf_stack", "lateral_psf_grid", "view_crop",
]


# --------------------------------------------------------------------------------------------
# closed forms
# --------------------------------------------------------------------------------------------

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
        for name in ("w020", "w222", "w131"):
            v = getattr(self, name)
            if not np.isfinite(v):
                raise InputError(f"aberration.{name}: must be finite, got {v!r}")
        if not (0 < self.ref_angle_deg < 89):
            raise InputError(f"aberration.ref_angle_deg: must be in (0, 89), got {self.ref_angle_deg!r}")

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
        the aperture's side (rho = 1; the corners see 4x); 0 = diffraction limited. The paper gives
        no value; the default 1 wave is an order-of-magnitude estimate for a plano-convex acrylic
        lenslet of f ~ 3.3 mm at this aperture, with which the simulated axial PCC widths come
        close to the measured ones (tests/test_optics.py reports them).
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
    spherical_waves: float = 1.0

    def __post_init__(self):
        def pos(name):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0:
                raise InputError(f"optics.{name}: must be a positive number, got {v!r}")
        for name in ("pitch_mm", "aperture_mm", "l0_mm", "l_mm", "wavelength_um", "pixel_um"):
            pos(name)

        def int_pair(name, v):
            try:
                pair = tuple(int(t) for t in v)
            except (TypeError, ValueError):
                raise InputError(f"optics.{name}: expected (rows, cols) integers, got {v!r}") from None
            if len(pair) != 2 or any(t < 1 for t in pair) or any(float(t) != float(s) for t, s in zip(pair, v)):
                raise InputError(f"optics.{name}: expected two positive integers (rows, cols), got {v!r}")
            object.__setattr__(self, name, pair)
        int_pair("lenses", self.lenses)
        int_pair("sensor_px", self.sensor_px)
        if self.sensor_shape is not None:
            int_pair("sensor_shape", self.sensor_shape)
        if isinstance(self.binning, bool) or not isinstance(self.binning, (int, np.integer)) or self.binning < 1:
            raise InputError(f"optics.binning: must be an integer >= 1, got {self.binning!r}")
        if self.supersample is not None and (isinstance(self.supersample, bool) or
                                             not isinstance(self.supersample, (int, np.integer))
                                             or self.supersample < 1):
            raise InputError(f"optics.supersample: must be an integer >= 1 or None, got {self.supersample!r}")
        if isinstance(self.spherical_waves, bool) or not isinstance(self.spherical_waves, (int, float)) \
                or not np.isfinite(self.spherical_waves):
            raise InputError(f"optics.spherical_waves: must be a finite number, got {self.spherical_waves!r}")
        if self.aperture_mm > self.pitch_mm * (1 + 1e-9):
            raise InputError(f"optics.aperture_mm: {self.aperture_mm} exceeds the pitch {self.pitch_mm}")
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


# --------------------------------------------------------------------------------------------
# the diffraction spot of one lenslet
# --------------------------------------------------------------------------------------------

def _fast_patch(n_pix: int, ss: int) -> int:
    """Smallest n >= n_pix (odd-free not required) with n * ss a fast FFT length."""
    n = max(int(n_pix), 3)
    while sfft.next_fast_len(n * ss) != n * ss:
        n += 1
    return n


def _patch_pixels(optics: CM2Optics, z_um: float, aberration: Aberration | None, extra_um: float,
                  h_max: float = 0.0) -> int:
    """Patch side (simulated pixels) that holds the defocused spot plus its diffraction tails."""
    a = optics.aperture_mm
    l = float(optics.distance_mm(z_um))
    blur_um = a * optics.l0_mm * abs(1.0 / l - 1.0 / optics.l_mm) * 1000.0
    if aberration is not None and h_max > 0:
        # largest wavefront slope (waves per unit normalised pupil radius, rho <= sqrt 2 in the
        # square's corners) -> transverse ray error l0 lambda slope / (a/2) on the sensor
        slope = (2.9 * (abs(aberration.w020) + abs(aberration.w222)) * h_max ** 2
                 + 6.0 * abs(aberration.w131) * h_max)
        blur_um += 2.0 * optics.l0_mm * optics.wavelength_um * slope / (a / 2.0)
    if optics.spherical_waves:
        blur_um += 2.0 * optics.l0_mm * optics.wavelength_um * 11.4 * abs(optics.spherical_waves) / (a / 2.0)
    tails_um = 24.0 * optics.wavelength_um * optics.l0_mm / a
    n = int(math.ceil((blur_um + 2.0 * tails_um + 2.0 * extra_um) / optics.pixel_size_um)) + 3
    return _fast_patch(n, optics.oversampling)


def _pupil_axis(optics: CM2Optics, n_fine: int):
    """Pupil coordinates u (mm) of an n_fine-sample FFT whose image samples are pixel/ss apart,
    and the aperture transmission with exact (area-weighted) edges."""
    ds_mm = optics.pixel_size_um / optics.oversampling / 1000.0
    du = optics.wavelength_um * 1e-3 * optics.l0_mm / (n_fine * ds_mm)
    u = (np.arange(n_fine) - n_fine // 2) * du
    half = optics.aperture_mm / 2.0
    if half > u[-1]:
        raise InputError("optics: the diffraction patch is too coarse for the aperture "
                         "(raise optics.supersample)")
    t = np.clip((half - np.abs(u)) / du + 0.5, 0.0, 1.0)
    return u, t, ds_mm


def _pixel_sample(intensity_ft, freqs_y, freqs_x, n_pix, ss, pixel_mm, transfer=None):
    """Integrate fine-grid intensity (given by its FFT) over pixels and sample at pixel centres."""
    filt = np.sinc(freqs_y * pixel_mm)[:, None] * np.sinc(freqs_x * pixel_mm)[None, :]
    if transfer is not None:
        filt = filt * transfer
    img = sfft.ifft2(intensity_ft * filt, axes=(-2, -1)).real
    n_fine = n_pix * ss
    idx = n_fine // 2 + (np.arange(n_pix) - n_pix // 2) * ss
    # fine grid index j holds position (j - n_fine//2) ds, stored in ifftshifted order
    idx = (idx - n_fine // 2) % n_fine
    return img[..., idx[:, None], idx[None, :]]


def _spot_1d(optics: CM2Optics, z_um: float, fracs_px: np.ndarray, n_pix: int) -> np.ndarray:
    """Pixel-integrated 1D intensity profiles (len(fracs), n_pix) of the separable lenslet spot,
    centred at patch pixel n_pix//2 + frac. Each row sums to 1."""
    ss = optics.oversampling
    n_fine = n_pix * ss
    u, t, ds_mm = _pupil_axis(optics, n_fine)
    lam = optics.wavelength_um * 1e-3
    l = float(optics.distance_mm(z_um))
    phase = np.pi / lam * (1.0 / l - 1.0 / optics.l_mm) * u ** 2
    shift_mm = np.asarray(fracs_px, float)[:, None] * optics.pixel_size_um / 1000.0
    ramp = 2.0 * np.pi * u[None, :] * shift_mm / (lam * optics.l0_mm)
    pupil = t[None, :] * np.exp(1j * (phase[None, :] + ramp))
    field_ = sfft.fft(sfft.ifftshift(pupil, axes=-1), axis=-1)     # image samples, ifftshifted order
    inten = np.abs(field_) ** 2
    f = sfft.fftfreq(n_fine, d=ds_mm)
    prof = sfft.ifft(sfft.fft(inten, axis=-1) * np.sinc(f * optics.pixel_size_um / 1000.0), axis=-1).real
    idx = (np.arange(n_pix) - n_pix // 2) * ss % n_fine
    prof = np.clip(prof[:, idx], 0.0, None)
    return prof / prof.sum(axis=1, keepdims=True)


def lenslet_spot(optics: CM2Optics, z_um: float = 0.0, offsets_px=((0.0, 0.0),), *,
                 field_angles_deg=None, aberration: Aberration | None = None,
                 bead_diameter_um: float = 0.0, blur_sigma_um: float = 0.0,
                 n_pix: int | None = None) -> np.ndarray:
    """Pixel-integrated focal spots of lenslets, each on an (n_pix, n_pix) patch of simulated pixels.

    Parameters
    ----------
    z_um : object depth from the nominal working distance.
    offsets_px : (k, 2) sub-pixel offsets (row, col) of each spot centre from patch pixel
        (n_pix//2, n_pix//2); any real value smaller than a few pixels.
    field_angles_deg : (k, 2) chief-ray angles (y, x) of each lenslet (for ``aberration``).
    aberration : Seidel field aberrations (makes the spot non-separable).
    bead_diameter_um : diameter of a uniform fluorescent sphere in the object (0 = point).
    blur_sigma_um : extra Gaussian blur (object space, e.g. a scattering halo).
    n_pix : patch size; default large enough for the defocus blur and diffraction tails.

    Returns
    -------
    (k, n_pix, n_pix) float64 spots, each summing to 1.
    """
    offsets = np.atleast_2d(np.asarray(offsets_px, dtype=float))
    k = offsets.shape[0]
    m = float(optics.magnification(z_um))
    extra_um = 3.0 * (bead_diameter_um / 2.0 + 2.0 * blur_sigma_um) * m
    if aberration is not None:
        if field_angles_deg is None:
            raise InputError("lenslet_spot: aberration needs field_angles_deg")
        ang = np.atleast_2d(np.asarray(field_angles_deg, dtype=float))
        h = np.tan(np.radians(ang)) / math.tan(math.radians(aberration.ref_angle_deg))   # (k, 2) (y, x)
    if n_pix is None:
        h_max = float(np.hypot(h[:, 0], h[:, 1]).max()) if aberration is not None else 0.0
        n_pix = _patch_pixels(optics, z_um, aberration, extra_um, h_max)
    ss = optics.oversampling
    separable = (aberration is None and bead_diameter_um <= 0 and blur_sigma_um <= 0
                 and optics.spherical_waves == 0)
    if separable:
        py = _spot_1d(optics, z_um, offsets[:, 0], n_pix)
        px = _spot_1d(optics, z_um, offsets[:, 1], n_pix)
        return py[:, :, None] * px[:, None, :]

    n_fine = n_pix * ss
    u, t, ds_mm = _pupil_axis(optics, n_fine)
    lam = optics.wavelength_um * 1e-3
    l = float(optics.distance_mm(z_um))
    uu = u[None, :]
    vv = u[:, None]
    rho2_mm = uu ** 2 + vv ** 2
    base_phase = np.pi / lam * (1.0 / l - 1.0 / optics.l_mm) * rho2_mm
    aperture = t[:, None] * t[None, :]
    pix_mm = optics.pixel_size_um / 1000.0
    f = sfft.fftfreq(n_fine, d=ds_mm)
    transfer = None
    if bead_diameter_um > 0 or blur_sigma_um > 0:
        fr = np.hypot(f[:, None], f[None, :])     # cycles / mm on the sensor
        transfer = np.ones_like(fr)
        if bead_diameter_um > 0:
            r_mm = bead_diameter_um / 2000.0 * m
            x = 2.0 * np.pi * fr * r_mm
            with np.errstate(invalid="ignore", divide="ignore"):
                tb = 3.0 * (np.sin(x) - x * np.cos(x)) / x ** 3
            transfer *= np.where(x < 1e-4, 1.0, tb)
        if blur_sigma_um > 0:
            s_mm = blur_sigma_um / 1000.0 * m
            transfer *= np.exp(-2.0 * (np.pi * s_mm * fr) ** 2)
    out = np.empty((k, n_pix, n_pix))
    ry = vv / (optics.aperture_mm / 2.0)
    rx = uu / (optics.aperture_mm / 2.0)
    rho2 = rx ** 2 + ry ** 2
    for i in range(k):
        phase = base_phase + 2.0 * np.pi / (lam * optics.l0_mm) * (
            uu * offsets[i, 1] * pix_mm + vv * offsets[i, 0] * pix_mm)
        if optics.spherical_waves:
            phase = phase + 2.0 * np.pi * optics.spherical_waves * rho2 ** 2
        if aberration is not None:
            hy, hx = h[i]
            hr = hx * rx + hy * ry
            w = (aberration.w020 * (hx * hx + hy * hy) * rho2 + aberration.w222 * hr ** 2
                 + aberration.w131 * hr * rho2)
            phase = phase + 2.0 * np.pi * w
        pupil = aperture * np.exp(1j * phase)
        fld = sfft.fft2(sfft.ifftshift(pupil))
        inten_ft = sfft.fft2(np.abs(fld) ** 2)
        spot = np.clip(_pixel_sample(inten_ft, f, f, n_pix, ss, pix_mm, transfer), 0.0, None)
        out[i] = spot / spot.sum()
    return out


# --------------------------------------------------------------------------------------------
# array PSFs on the sensor
# --------------------------------------------------------------------------------------------

def _add_patch(out, patch, r0, c0):
    """out[r0:r0+n, c0:c0+n] += patch, clipped at the sensor edges."""
    n0, n1 = patch.shape
    my, mx = out.shape
    ra, rb = max(r0, 0), min(r0 + n0, my)
    ca, cb = max(c0, 0), min(c0 + n1, mx)
    if ra < rb and ca < cb:
        out[ra:rb, ca:cb] += patch[ra - r0:rb - r0, ca - c0:cb - c0]


def array_psf(optics: CM2Optics, z_um: float = 0.0, x_mm: float = 0.0, y_mm: float = 0.0, *,
              cutoff_deg: float | None = None, edge_deg: float = 1.0,
              aberration: Aberration | None = None, recenter: bool = False,
              bead_diameter_um: float = 0.0, blur_sigma_um: float = 0.0,
              scale: float = 1.0, out: np.ndarray | None = None, dtype=np.float32) -> np.ndarray:
    """The sensor image (optics.shape) of a point source at (x_mm, y_mm, z_um).

    Parameters
    ----------
    z_um : depth from the nominal working distance (positive = farther from the MLA).
    x_mm, y_mm : lateral object position from the optical axis.
    cutoff_deg, edge_deg : pixel angular cutoff (truncation of views); None = no angular limit.
    aberration : field-dependent lenslet aberrations (the ``aberration`` effect); None = none.
    recenter : place the foci as for an on-axis point (shift by +p l0/l), keeping the field-dependent
        weights and aberrations: the local shift-invariant kernel at that field point.
    bead_diameter_um, blur_sigma_um : see :func:`lenslet_spot`.
    scale : multiply the PSF (the emitter's brightness).
    out : add into this (My, Mx) array instead of allocating.

    Foci that fall off the sensor are cut (finite sensor). The untruncated on-axis array sums to
    ``scale``.
    """
    if out is None:
        out = np.zeros(optics.shape, dtype=dtype)
    weights = lenslet_weights(optics, z_um, x_mm, y_mm, cutoff_deg, edge_deg) * scale
    pos = optics.foci_px(z_um, 0.0, 0.0) if recenter else optics.foci_px(z_um, x_mm, y_mm)
    keep = weights > 0
    if not keep.any():
        return out
    base = np.floor(pos + 0.5)
    frac = pos - base
    angles = chief_ray_angles_deg(optics, z_um, x_mm, y_mm) if aberration is not None else None
    m = float(optics.magnification(z_um))
    h_max = 0.0
    if aberration is not None:
        h_max = float(np.hypot(*np.tan(np.radians(angles[keep])).T).max()
                      / math.tan(math.radians(aberration.ref_angle_deg)))
    n_pix = _patch_pixels(optics, z_um, aberration,
                          3.0 * (bead_diameter_um / 2.0 + 2.0 * blur_sigma_um) * m, h_max)
    # skip foci whose patch misses the sensor entirely
    half = n_pix // 2
    my, mx = optics.shape
    keep &= (base[:, 0] + n_pix - half > 0) & (base[:, 0] - half < my)
    keep &= (base[:, 1] + n_pix - half > 0) & (base[:, 1] - half < mx)
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return out
    spots = lenslet_spot(optics, z_um, frac[idx], field_angles_deg=None if angles is None else angles[idx],
                         aberration=aberration, bead_diameter_um=bead_diameter_um,
                         blur_sigma_um=blur_sigma_um, n_pix=n_pix)
    for j, i in enumerate(idx):
        _add_patch(out, (weights[i] * spots[j]).astype(out.dtype, copy=False),
                   int(base[i, 0]) - half, int(base[i, 1]) - half)
    return out


def axial_psf_stack(optics: CM2Optics, depths_um=None, *, z_range_um=None, step_um=None,
                    x_mm: float = 0.0, y_mm: float = 0.0, dtype=np.float32, **psf_kw) -> np.ndarray:
    """(nz, My, Mx) PSFs of a point at (x_mm, y_mm) for each depth in ``depths_um`` (um), or over
    ``z_range_um=(start, stop)`` every ``step_um`` (inclusive, see :func:`depth_planes`).
    Other keyword arguments go to :func:`array_psf`.
    """
    if (depths_um is None) == (z_range_um is None):
        raise InputError("axial_psf_stack: give depths_um or z_range_um (with step_um), not both")
    if z_range_um is not None:
        if step_um is None:
            raise InputError("axial_psf_stack: z_range_um needs step_um")
        depths_um = depth_planes(float(z_range_um[0]), float(z_range_um[1]), float(step_um))
    depths = np.atleast_1d(np.asarray(depths_um, dtype=float))
    out = np.zeros((depths.size,) + optics.shape, dtype=dtype)
    for i, z in enumerate(depths):
        array_psf(optics, float(z), x_mm, y_mm, out=out[i], **psf_kw)
    return out


def lateral_psf_grid(optics: CM2Optics, z_um: float, x_mm, y_mm, *, recenter: bool = False,
                     dtype=np.float32, **psf_kw) -> np.ndarray:
    """(ny, nx, My, Mx) PSFs of points on the lateral grid y_mm x x_mm (1D arrays, mm) at depth z.

    With ``recenter=True`` each PSF is shifted back to the on-axis foci positions (the local
    kernels of a shift-variant model; also what the paper registers before computing PCC maps).
    """
    xs = np.atleast_1d(np.asarray(x_mm, dtype=float))
    ys = np.atleast_1d(np.asarray(y_mm, dtype=float))
    out = np.zeros((ys.size, xs.size) + optics.shape, dtype=dtype)
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            array_psf(optics, z_um, x, y, recenter=recenter, out=out[i, j], **psf_kw)
    return out


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

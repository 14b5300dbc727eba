"""Simulated CM2 array PSFs: scalar Fraunhofer diffraction of each lenslet (see :mod:`cm2cl.optics.geometry` for the conventions)."""

from __future__ import annotations

import math

import numpy as np
from scipy import fft as sfft

from ..errors import InputError
from .geometry import Aberration, CM2Optics, chief_ray_angles_deg, depth_planes, lenslet_weights

__all__ = ["lenslet_spot", "array_psf", "axial_psf_stack", "lateral_psf_grid"]


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
        if optics.spherical_waves:   # with the defocus that puts its best focus at z = 0
            phase = phase + 2.0 * np.pi * (optics.spherical_waves * rho2 ** 2 + optics.focus_waves * rho2)
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

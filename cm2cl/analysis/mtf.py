"""The 3D MTF of an axial PSF stack and the bandwidths and space-bandwidth product read from it (paper
Fig. 2B and Methods, "3D MTF calculation" and "Calculation of the 3D SBP").

As the paper does, the system is taken as shift-invariant and the MTF is the modulus of the stack's 3D
Fourier transform, normalised to 1 at zero frequency. Its *support* is where it stays above a floor
(a fraction of the DC value, or the noise floor when that is higher: the median of the MTF over the
outermost tenth of the frequencies, where a band-limited stack has only noise and aliasing):

- the lateral cutoff f_c: the largest lateral frequency along f_x (f_y = 0) up to which the support holds
  some f_z at every f_x; the lateral bandwidth B_x = 2 f_c;
- the axial bandwidth at a lateral frequency f_x: the extent max f_z - min f_z of the support on the f_x-f_z
  section (f_y = 0) at that f_x, which for the CM2 spans the tilted bands of the side lenslets
  (f_z = +-tan(alpha_MLA) f_x) as well as the central bowtie; B_z is its value at f_c;
- the 3D SBP (Methods): V B with V = FOV x DOF and B = B_z B_x^2 / 2 (the lateral support of a square
  aperture, the autocorrelation of a square, has area B_x^2 / 2).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

__all__ = ["mtf_3d", "support_floor", "lateral_cutoff", "axial_extent", "mtf_analysis"]

#: default floor of the support, as a fraction of the MTF at zero frequency
DEFAULT_FLOOR = 0.01


def mtf_3d(psf, dz_um: float, dy_um: float, dx_um: float) -> dict:
    """|FFT_3D(psf)| / its DC value, shifted so that zero frequency is at the centre: ``mtf`` (nz, ny, nx) and
    the frequencies ``fz``, ``fy``, ``fx`` in cycles / um (ascending, 0 at index n // 2)."""
    h = np.asarray(psf, np.float64)
    if h.ndim != 3 or h.shape[0] < 3 or min(h.shape[1:]) < 3:
        raise InputError(f"psf: expected an axial stack (nz >= 3, ny, nx >= 3), got shape {h.shape}")
    for name, d in (("dz_um", dz_um), ("dy_um", dy_um), ("dx_um", dx_um)):
        if not (np.isfinite(d) and d > 0):
            raise InputError(f"{name}: must be a positive number of um, got {d!r}")
    dc = h.sum()
    if not dc > 0:
        raise InputError("psf: its sum is not positive; no MTF to normalise")
    m = np.abs(np.fft.fftshift(np.fft.fftn(h))) / dc
    f = [np.fft.fftshift(np.fft.fftfreq(n, d)) for n, d in zip(h.shape, (dz_um, dy_um, dx_um))]
    return {"mtf": m, "fz": f[0], "fy": f[1], "fx": f[2]}


def support_floor(m: dict, floor: float = DEFAULT_FLOOR) -> dict:
    """The support's floor: ``floor`` x DC or the noise floor (median of the MTF where the normalised radial
    frequency exceeds 0.9 of the Nyquist corner), whichever is higher; returns both and the one used."""
    mt = m["mtf"]
    r = np.sqrt(sum((np.abs(f) / np.abs(f).max())[tuple(slice(None) if i == k else None for i in range(3))] ** 2
                    for k, f in enumerate((m["fz"], m["fy"], m["fx"]))))
    outer = mt[r > 0.9 * r.max()]
    noise = float(np.median(outer)) if outer.size else 0.0
    return {"relative": float(floor), "noise": noise, "used": max(float(floor), 2.0 * noise)}


def lateral_cutoff(m: dict, level: float) -> float:
    """The largest f_x >= 0 (cycles / um) up to which the support on the f_x-f_z section (f_y = 0) holds
    some f_z at every f_x (its column maximum >= level), interpolated linearly between samples; the Nyquist
    frequency if it never falls below. The column maximum, not the f_z = 0 line: an array PSF's foci
    interfere there (the array factor's zeros), while their tilted bands carry the frequency at f_z != 0."""
    mt, fx = m["mtf"], m["fx"]
    cz, cy, cx = (n // 2 for n in mt.shape)
    line = mt[:, cy, cx:].max(axis=0)
    f = fx[cx:]
    below = np.flatnonzero(line < level)
    if below.size == 0:
        return float(f[-1])
    k = int(below[0])
    if k == 0:
        return 0.0
    v0, v1 = line[k - 1], line[k]
    return float(f[k - 1] + (f[k] - f[k - 1]) * (v0 - level) / (v0 - v1))


def section_xz(m: dict) -> np.ndarray:
    """The f_x-f_z section (f_y = 0) of the MTF, (nz, nx)."""
    return m["mtf"][:, m["mtf"].shape[1] // 2, :]


def axial_extent(m: dict, fx_um: float, level: float) -> float:
    """The extent max f_z - min f_z (cycles / um) of the support (MTF >= level) on the f_x-f_z section at the
    lateral frequency ``fx_um`` (the nearest sample at or below it); 0 where nothing there reaches level."""
    sec, fx, fz = section_xz(m), m["fx"], m["fz"]
    if not 0 <= fx_um <= fx.max():
        raise InputError(f"fx: {fx_um:g} / um is outside the stack's lateral frequencies 0..{fx.max():g} / um")
    k = int(np.flatnonzero(fx <= fx_um + 1e-12 * max(1.0, abs(fx_um)))[-1])
    col = sec[:, k]
    inside = np.flatnonzero(col >= level)
    if inside.size == 0:
        return 0.0
    return float(fz[inside[-1]] - fz[inside[0]])


def mtf_analysis(psf, dz_um: float, dy_um: float, dx_um: float, *, floor: float = DEFAULT_FLOOR,
                 lateral_cutoff_um: float | None = None, fov_mm=None, dof_mm: float | None = None) -> dict:
    """The MTF (:func:`mtf_3d`), its support floor, the lateral cutoff f_c (measured, or ``lateral_cutoff_um``
    in cycles / um, e.g. 1 / (2 x a measured lateral FWHM) as the paper takes it), B_x = 2 f_c, the axial
    bandwidth B_z at f_c, the axial extent along f_x (``profile``) and the 3D SBP = FOV x DOF x B_z B_x^2 / 2
    with ``fov_mm`` (rows, cols) and ``dof_mm`` (default: the stack's own field and depth range)."""
    if not (np.isfinite(floor) and 0 < floor < 1):
        raise InputError(f"floor: {floor!r} must be between 0 and 1 (a fraction of the MTF at zero frequency)")
    m = mtf_3d(psf, dz_um, dy_um, dx_um)
    fl = support_floor(m, floor)
    level = fl["used"]
    measured = lateral_cutoff(m, level)
    fc = measured if lateral_cutoff_um is None else float(lateral_cutoff_um)
    if not (np.isfinite(fc) and 0 < fc <= m["fx"].max()):
        raise InputError(f"lateral cutoff: {fc:g} / um must be above 0 and at most the Nyquist frequency "
                         f"{m['fx'].max():g} / um")
    bz = axial_extent(m, fc, level)
    nz, ny, nx = np.shape(psf)
    fov = (ny * dy_um / 1000.0, nx * dx_um / 1000.0) if fov_mm is None else tuple(float(v) for v in fov_mm)
    dof = (nz - 1) * dz_um / 1000.0 if dof_mm is None else float(dof_mm)
    if len(fov) != 2 or not all(np.isfinite(v) and v > 0 for v in fov + (dof,)):
        raise InputError(f"FOV {fov} mm and DOF {dof} mm must be positive numbers")
    bx = 2.0 * fc
    volume_um3 = fov[0] * fov[1] * dof * 1e9
    fxs = m["fx"][m["fx"] >= 0]
    profile = [(float(f), axial_extent(m, float(f), level)) for f in fxs]
    return {"mtf": m, "floor": fl, "lateral_cutoff_measured_per_um": measured, "lateral_cutoff_per_um": fc,
            "lateral_bandwidth_per_um": bx, "axial_bandwidth_per_um": bz, "fov_mm": list(fov), "dof_mm": dof,
            "fov_given": fov_mm is not None, "dof_given": dof_mm is not None,
            "bandwidth_per_um3": bz * bx ** 2 / 2.0, "sbp": volume_um3 * bz * bx ** 2 / 2.0, "profile": profile}

"""Effects: each a separate, optional stage, run only when a scene names it.

Stages, in the order the pipeline runs them (within a stage, in the scene's order):

* ``object`` stage: change what the sample emits before imaging -- :func:`background`,
  :func:`scattering`, :func:`vignetting`. They act on a :class:`~cm2cl.simulate.render.Sample`
  (a volume on the render grid, or a list of beads for per-emitter rendering).
* ``optics`` stage: change the PSF -- :func:`truncation`, :func:`aberration`. They return keyword
  arguments for :func:`cm2cl.optics.array_psf`; naming either makes the model shift-variant.
* ``sensor`` stage: :func:`noise` turns expected photo-electrons into what the camera records.

The pipeline looks each function up by name in this module at run time, so a stage that a scene
does not name is never called (tests monkeypatch these functions to prove it).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from ..optics import Aberration

__all__ = ["EFFECTS", "STAGES", "background", "scattering", "vignetting", "truncation",
           "aberration", "noise"]

STAGES = ("object", "optics", "sensor")


# --------------------------------------------------------------------------------------------
# object stage
# --------------------------------------------------------------------------------------------

def _box_mask_plane(grid, j, box):
    """Boolean (Py, Px) mask of render-grid pixels of plane j inside the box laterally."""
    x_mm, y_mm = grid.field_axes_mm(j)
    cx, cy = box.center_mm
    hx, hy = box.size_mm[0] / 2.0, box.size_mm[1] / 2.0
    return (np.abs(y_mm - cy) <= hy)[:, None] & (np.abs(x_mm - cx) <= hx)[None, :]


def background(sample, grid, rng, *, fraction: float, texture_cv: float) -> dict:
    """Unresolved fluorescent background (paper: 1.1-um beads, neuropil): a uniform emitting density
    filling the scene's sample box, whose total emission is ``fraction`` x the objects' emission,
    with voxel-to-voxel fluctuations of coefficient of variation ``texture_cv``. Imaged through the
    same PSFs, it lowers the SBR most where most views overlap (paper Fig. 5B)."""
    if sample.volume is None:
        raise RuntimeError("background needs a volume sample (the pipeline renders it on the grid)")
    box = sample.box
    total_signal = sample.total_emission()
    dens = np.zeros(sample.volume.shape, np.float32)
    for j, z in enumerate(grid.depths_um):
        if box.z_range_um[0] - 1e-6 <= z <= box.z_range_um[1] + 1e-6:
            # equal emission per unit physical volume: an object voxel holds (pixel / m)^2 dz
            dens[j][_box_mask_plane(grid, j, box)] = 1.0 / float(grid.optics.magnification(z)) ** 2
    if dens.sum() == 0:
        raise RuntimeError("background: the sample box covers no voxel of the render grid")
    if texture_cv > 0:
        k = 1.0 / texture_cv ** 2
        dens *= rng.gamma(k, 1.0 / k, dens.shape).astype(np.float32)
    dens *= np.float32(fraction * total_signal / dens.sum())
    sample.add_background(dens)
    return {"total_background_e": float(dens.sum()), "total_signal_e": float(total_signal)}


def scattering(sample, grid, rng, *, ls_um: float, surface_z_um, halo_fraction: float,
               halo_sigma_per_depth: float) -> dict:
    """Bulk scattering of mean free path ``ls_um`` below the surface at ``surface_z_um`` (default:
    top of the sample box). Light from depth d keeps a ballistic fraction exp(-d / l_s); of the
    rest, ``halo_fraction`` still reaches the sensor as a halo, a Gaussian of sigma
    ``halo_sigma_per_depth`` x d in the object."""
    top = sample.box.z_range_um[0] if surface_z_um is None else float(surface_z_um)
    info = {"surface_z_um": top, "ballistic_fraction": {}}
    if sample.volume is not None:
        p_um = grid.optics.pixel_size_um
        for name, vol in sample.volumes():
            for j, z in enumerate(grid.depths_um):
                d = max(0.0, float(z) - top)
                if d == 0 or not vol[j].any():
                    continue
                e = math.exp(-d / ls_um)
                plane = vol[j].astype(np.float64)
                out = e * plane
                s = halo_fraction * (1.0 - e)
                if s > 0:
                    sigma_px = halo_sigma_per_depth * d * float(grid.optics.magnification(z)) / p_um
                    out += s * ndimage.gaussian_filter(plane, sigma_px, mode="constant", truncate=3.0)
                vol[j] = out.astype(vol.dtype)
        for j, z in enumerate(grid.depths_um):
            info["ballistic_fraction"][f"{float(z):g}"] = math.exp(-max(0.0, float(z) - top) / ls_um)
    if sample.beads is not None:
        b = sample.beads
        d = np.clip(b.xyz_um[:, 2] - top, 0.0, None)
        e = np.exp(-d / ls_um)
        halo = halo_fraction * (1.0 - e) * b.brightness
        sample.set_bead_halo(halo, halo_sigma_per_depth * d)
        b.brightness = b.brightness * e
        info["mean_ballistic_fraction_beads"] = float(e.mean()) if e.size else None
    return info


def vignetting_factor(x_mm, y_mm, z_um, optics, power: float, illumination_sigma_mm):
    """cos^power of the field angle atan(r / l) times a Gaussian illumination fall-off."""
    r2 = np.asarray(x_mm, float) ** 2 + np.asarray(y_mm, float) ** 2
    l = optics.distance_mm(z_um)
    f = np.cos(np.arctan(np.sqrt(r2) / l)) ** power
    if illumination_sigma_mm is not None:
        f = f * np.exp(-r2 / (2.0 * float(illumination_sigma_mm) ** 2))
    return f


def vignetting(sample, grid, rng, *, power: float, illumination_sigma_mm) -> dict:
    """Illumination and collection fall-off across the field: emission scaled by cos^power of the
    field angle (power 4: the cos^4 law) and, optionally, a Gaussian LED illumination profile of
    ``illumination_sigma_mm``."""
    if sample.volume is not None:
        for name, vol in sample.volumes():
            for j, z in enumerate(grid.depths_um):
                x_mm, y_mm = grid.field_axes_mm(j)
                f = vignetting_factor(x_mm[None, :], y_mm[:, None], z, grid.optics, power, illumination_sigma_mm)
                vol[j] *= f.astype(vol.dtype)
    if sample.beads is not None:
        b = sample.beads
        f = vignetting_factor(b.xyz_um[:, 0] / 1000.0, b.xyz_um[:, 1] / 1000.0, b.xyz_um[:, 2],
                              grid.optics, power, illumination_sigma_mm)
        b.brightness = b.brightness * f
        if sample.bead_halo is not None:
            sample.bead_halo = (sample.bead_halo[0] * f, sample.bead_halo[1])
    edge = vignetting_factor(grid.optics.shape[1] * grid.optics.pixel_size_um / 2000.0 /
                             float(grid.optics.magnification(0.0)), 0.0, 0.0, grid.optics,
                             power, illumination_sigma_mm)
    return {"factor_at_sensor_edge_x": float(edge)}


# --------------------------------------------------------------------------------------------
# optics stage
# --------------------------------------------------------------------------------------------

def truncation(*, cutoff_deg: float, edge_deg: float) -> dict:
    """Finite sensor (always: foci off the sensor are lost) plus the CMOS pixels' angular response:
    a lenslet's focus fades out when its chief ray arrives steeper than ``cutoff_deg`` (paper:
    ~21 deg) in x or y, over ``edge_deg``. Off-axis points lose views (3x3 -> 2x3 -> 2x2)."""
    return {"cutoff_deg": float(cutoff_deg), "edge_deg": float(edge_deg)}


def aberration(*, w020: float, w222: float, w131: float, ref_angle_deg: float) -> dict:
    """Field-dependent lenslet aberrations (field curvature, astigmatism, coma; waves at the pupil
    edge at ``ref_angle_deg`` chief-ray angle), growing with each lenslet's own field angle."""
    return {"aberration": Aberration(w020=w020, w222=w222, w131=w131, ref_angle_deg=ref_angle_deg)}


# --------------------------------------------------------------------------------------------
# sensor stage
# --------------------------------------------------------------------------------------------

def noise(image, optics, rng, *, read_noise_e: float, full_well_e: float, bit_depth: int,
          gain_e_per_dn, offset_dn: float, exposure: float):
    """The MT9P031 as the paper describes it: Poisson shot noise on ``exposure`` x the expected
    photo-electrons, Gaussian read noise (6.62 e-), clipping at the full well (6620 e-: 60 dB
    dynamic range over the read noise) and ``bit_depth``-bit quantisation (8) with
    ``gain_e_per_dn`` (default full well / (2^bits - 1)) plus ``offset_dn``.

    A binned pixel is the sum of binning^2 native pixels: read-noise variance and full well scale
    by binning^2 and so does the DN range (a binned 8-bit image is stored as uint16). With
    ``bit_depth = 0`` the result is float32 electrons (no quantisation).

    Returns (image, info)."""
    nb = optics.binning ** 2
    mean_e = np.clip(np.asarray(image, np.float64) * exposure, 0.0, None)
    e = rng.poisson(mean_e).astype(np.float64)
    e += rng.normal(0.0, read_noise_e * math.sqrt(nb), e.shape)
    e = np.minimum(e, full_well_e * nb)
    info = {"read_noise_e_per_pixel": read_noise_e * math.sqrt(nb), "full_well_e_per_pixel": full_well_e * nb,
            "saturated_pixels": int((mean_e >= full_well_e * nb).sum())}
    if bit_depth == 0:
        info["units"] = "photo-electrons"
        return e.astype(np.float32), info
    levels = 2 ** int(bit_depth) - 1
    gain = float(gain_e_per_dn) if gain_e_per_dn is not None else full_well_e / levels
    top = levels * nb
    dn = np.clip(np.rint(e / gain + offset_dn), 0, top)
    dtype = np.uint8 if top <= 255 else (np.uint16 if top <= 65535 else np.uint32)
    info.update(units="DN", gain_e_per_dn=gain, offset_dn=offset_dn, max_dn=int(top),
                dtype=np.dtype(dtype).name)
    return dn.astype(dtype), info


# --------------------------------------------------------------------------------------------
# registry: stage and parameters (type, default, constraint) used by scene validation
# --------------------------------------------------------------------------------------------

EFFECTS = {
    "noise": {"stage": "sensor", "params": {
        "read_noise_e": {"type": "float", "default": 6.62, "min": 0},
        "full_well_e": {"type": "float", "default": 6620.0, "min": 0, "exclusive": True},
        "bit_depth": {"type": "int", "default": 8, "min": 0, "max": 16},
        "gain_e_per_dn": {"type": "float", "default": None, "min": 0, "exclusive": True},
        "offset_dn": {"type": "float", "default": 0.0, "min": 0},
        "exposure": {"type": "float", "default": 1.0, "min": 0},
    }},
    "background": {"stage": "object", "params": {
        "fraction": {"type": "float", "default": 1.0, "min": 0},
        "texture_cv": {"type": "float", "default": 0.0, "min": 0},
    }},
    "scattering": {"stage": "object", "params": {
        "ls_um": {"type": "float", "required": True, "min": 0, "exclusive": True},
        "surface_z_um": {"type": "float", "default": None},
        "halo_fraction": {"type": "float", "default": 1.0, "min": 0, "max": 1},
        "halo_sigma_per_depth": {"type": "float", "default": 0.3, "min": 0},
    }},
    "truncation": {"stage": "optics", "params": {
        "cutoff_deg": {"type": "float", "default": 21.0, "min": 0, "max": 90, "exclusive": True},
        "edge_deg": {"type": "float", "default": 1.0, "min": 0},
    }},
    "aberration": {"stage": "optics", "params": {
        "w020": {"type": "float", "default": 1.0},
        "w222": {"type": "float", "default": 1.0},
        "w131": {"type": "float", "default": 0.5},
        "ref_angle_deg": {"type": "float", "default": 20.0, "min": 0, "max": 89, "exclusive": True},
    }},
    "vignetting": {"stage": "object", "params": {
        "power": {"type": "float", "default": 4.0, "min": 0},
        "illumination_sigma_mm": {"type": "float", "default": None, "min": 0, "exclusive": True},
    }},
}

"""The paper's characterisation of the optics model (Fig. 2A and the lateral resolution), computed from the
simulated PSFs: axial PCC curves per view configuration and their widths at PCC = 0.8, the sharpest plane,
and the in-focus spot's FWHM in object space. ``tools/fit_optics.py`` fits the model's aberration with
them (docs/optics_fit.md)."""

from __future__ import annotations

import numpy as np

from ..analysis.metrics import fwhm, pcc, width_at_level
from .geometry import CM2Optics, view_crop
from .psf import array_psf, lenslet_spot

__all__ = ["VIEW_CONFIGS", "PAPER_PCC_WIDTHS_UM", "view_pcc_curves", "pcc_widths", "sharpest_z_um",
           "spot_fwhm_um"]

#: lenslet rows and columns of the 3 x 3 array that each configuration keeps (paper Methods: the 2 x 3 and
#: 2 x 2 arrays are emulated by cropping the 3 x 3 PSF)
VIEW_CONFIGS = {"3x3": ((0, 1, 2), (0, 1, 2)), "2x3": ((0, 1), (0, 1, 2)), "2x2": ((0, 1), (0, 1))}
#: the paper's full widths at PCC = 0.8 of its measured PSF stack (Fig. 2A), um
PAPER_PCC_WIDTHS_UM = {"3x3": 155.0, "2x3": 179.0, "2x2": 206.0}


def view_pcc_curves(optics: CM2Optics, zs_um, configs=VIEW_CONFIGS, ref_z_um: float = 0.0,
                    max_shift: int = 30) -> dict:
    """{configuration: PCC of each plane's array PSF with the one at ``ref_z_um``}, each on the sensor
    window of the configuration's foci (:func:`view_crop`), registered by the cross-correlation peak."""
    crops = {k: view_crop(optics, *v) for k, v in configs.items()}
    ref = array_psf(optics, float(ref_z_um))
    curves = {k: [] for k in configs}
    for z in zs_um:
        img = array_psf(optics, float(z))
        for k, (rs, cs) in crops.items():
            curves[k].append(pcc(ref[rs, cs], img[rs, cs], max_shift=max_shift))
    return {k: np.array(v) for k, v in curves.items()}


def pcc_widths(optics: CM2Optics, zs_um, level: float = 0.8, **kw) -> dict:
    """{configuration: full width (um) of its axial PCC curve at ``level``} (paper Fig. 2A)."""
    zs = np.asarray(zs_um, float)
    return {k: width_at_level(zs, v, level) for k, v in view_pcc_curves(optics, zs, **kw).items()}


def sharpest_z_um(optics: CM2Optics, zs_um) -> float:
    """The depth among ``zs_um`` at which the on-axis array PSF has its highest peak."""
    zs = np.asarray(zs_um, float)
    return float(zs[int(np.argmax([array_psf(optics, float(z)).max() for z in zs]))])


def spot_fwhm_um(optics: CM2Optics, pixel_um: float = 0.25) -> float:
    """FWHM of the in-focus (z = 0) on-axis lenslet spot along a row, back-projected to the object (um),
    sampled on pixels of ``pixel_um`` (fine enough that the pixel hardly widens it). Diffraction-limited
    (square aperture): 0.886 lambda l0 / a / magnification = 5.6 um for the prototype."""
    fine = optics.replace(pixel_um=pixel_um, binning=1, sensor_shape=None, supersample=None)
    s = lenslet_spot(fine, 0.0, [[0.0, 0.0]])[0]
    return fwhm(s[s.shape[0] // 2], spacing=pixel_um) / float(fine.magnification(0.0))

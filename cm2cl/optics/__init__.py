"""CM2 optics: the prototype's geometry and closed forms (Eq. 1, Eq. 2, 3D SBP, views and angular
cutoff) in :mod:`.geometry`, and the diffraction model of its array PSFs in :mod:`.psf`."""

from .geometry import (Aberration, CM2Optics, angular_response, axial_resolution_um,  # noqa: F401
                       chief_ray_angles_deg, depth_planes, foci_separation_mm, lenslet_weights, sbp_3d,
                       view_count, view_crop)
from .psf import array_psf, axial_psf_stack, lateral_psf_grid, lenslet_spot  # noqa: F401

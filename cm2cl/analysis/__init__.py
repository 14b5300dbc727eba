"""Figures of merit of the paper and of reconstructions: PCC (Eq. 5), widths, FWHM, local SBR
(:mod:`.metrics`); emitter detection and matching against ground truth (:mod:`.emitters`); MIP
figures (:mod:`.figures`)."""

from .emitters import find_emitters, match_emitters, score_beads  # noqa: F401
from .figures import content_region, mip_png, scale_bar_um  # noqa: F401
from .pixels import check_pixels, hot_pixels, mask_weights, saturated_pixels  # noqa: F401
from .metrics import (axial_pcc, fwhm, local_sbr, pcc, register_shift, signal_mask,  # noqa: F401
                      width_at_level)

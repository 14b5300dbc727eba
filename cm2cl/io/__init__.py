"""Files in and out: TIFF / OME-TIFF with physical voxel sizes and depths (:mod:`.tiff`), outputs
that appear only when complete (:mod:`.staging`: checks, locks, folders swapped in whole; :mod:`.publish`:
a file and its sidecars published as one unit), and measurement / PSF preparation (camera offset,
binning; :mod:`.prepare`)."""

from .prepare import bin_image, estimate_offset, prepare, subtract_offset  # noqa: F401
from .staging import StagedOutput, check_output_dir, jsonable  # noqa: F401
from .tiff import OBJECT_SPACE, peek_tiff, read_tiff, tiff_stem, write_tiff  # noqa: F401

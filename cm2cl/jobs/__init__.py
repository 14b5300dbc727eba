"""Jobs of many frames (issue 9, part): a time series read frame by frame from TIFF headers
(:mod:`.frames`), an OME-Zarr output whose frames count as done only when wholly written, refused when it
holds another job, and resumable (:mod:`.store`), and the executors that spread frames over the local
OpenCL devices or a Dask cluster, each device building its PSF spectra once (:mod:`.run`)."""

from .frames import FrameSeries
from .run import JobSummary, run_series
from .store import FrameStore

__all__ = ["FrameSeries", "FrameStore", "JobSummary", "run_series"]

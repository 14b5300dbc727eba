"""Jobs of many frames and of large frames: a time series read frame by frame from TIFF headers
(:mod:`.frames`), an OME-Zarr output whose frames count as done only when wholly written, refused when it
holds another job, and resumable (:mod:`.store`), the executors that run frames in order with a warm
start, over the local OpenCL devices or on a Dask cluster, each device building its PSF spectra once
(:mod:`.executors`, run by :mod:`.run`), the PSF refined on a series' first frame (:mod:`.refine`), and
lateral tiles of one frame (:mod:`.tiles`)."""

from .executors import DaskCluster, FrameJob, InOrder, LocalDevices, executor_for
from .frames import FrameSeries
from .run import JobSummary, run_series
from .store import FrameStore
from .series import reconstruct_series
from .tiles import plan_tiles, reconstruct_tiled

__all__ = ["FrameSeries", "FrameStore", "JobSummary", "run_series", "plan_tiles", "reconstruct_tiled", "FrameJob",
           "executor_for", "InOrder", "LocalDevices", "DaskCluster", "reconstruct_series"]

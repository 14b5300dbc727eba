"""cm2cl: Computational Miniature Mesoscope reconstruction on any OpenCL device.

Packages, in the order data flows: :mod:`.io` (files in, preparation) -> :mod:`.solver` (forward
model and ADMM, on :mod:`.device`) -> :mod:`.io` (files out) -> :mod:`.analysis`. Beside them:
:mod:`.optics` (geometry, PSF model), :mod:`.simulate` (scenes -> measurements), :mod:`.cli` (the
command), :mod:`.reference` (float64 twins for tests). Library code logs to the ``cm2cl`` logger
and prints nothing.
"""

import logging

__version__ = "0.1.0"

logging.getLogger("cm2cl").addHandler(logging.NullHandler())

from .errors import CM2Error, DeviceError, InputError, JobError, KernelBuildError  # noqa: E402,F401
from .solver import ForwardModel, Reconstruction, reconstruct  # noqa: E402,F401
from .jobs.series import reconstruct_series  # noqa: E402,F401

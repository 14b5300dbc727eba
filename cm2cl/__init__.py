"""cm2cl: Computational Miniature Mesoscope reconstruction on any OpenCL device."""

__version__ = "0.1.0"

from .admm import reconstruct  # noqa: E402,F401
from .errors import CM2Error, DeviceError, InputError, KernelBuildError  # noqa: F401
from .forward import ForwardModel  # noqa: E402,F401
from .result import Reconstruction  # noqa: E402,F401

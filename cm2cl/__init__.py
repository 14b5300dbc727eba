"""cm2cl: Computational Miniature Mesoscope reconstruction on any OpenCL device."""

__version__ = "0.1.0"

from .errors import CM2Error, DeviceError, InputError, KernelBuildError  # noqa: F401

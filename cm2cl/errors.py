"""Exception types: every user-facing error names the input and the problem."""


class CM2Error(Exception):
    """Base class of cm2cl errors."""


class InputError(CM2Error, ValueError):
    """Bad input: wrong shape, dtype, NaN/Inf, empty PSF plane, bad parameter."""


class DeviceError(CM2Error, RuntimeError):
    """No usable OpenCL device, a device that lacks a capability, or too little memory."""


class KernelBuildError(CM2Error, RuntimeError):
    """An OpenCL program failed to build; the message holds the file name and the build log, ``summary``
    one line (what failed where, and the log's first error) and ``log`` the whole build log."""

    def __init__(self, message: str, summary: str | None = None, log: str | None = None):
        super().__init__(message)
        self.summary = summary or (message.splitlines() or [""])[0]
        self.log = log


class JobError(CM2Error, RuntimeError):
    """A job of many frames stopped by something outside the inputs (a Dask cluster that lost its workers
    or its scheduler); the message says what, which frames are kept, and how to resume."""

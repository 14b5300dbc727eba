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

#: the API's names, imported on first use (PEP 562): ``import cm2cl`` stays light, so that the ``cm2cl``
#: command can take Ctrl-C from its first moment (the solver's imports take about half a second)
_LAZY = {"ForwardModel": ".solver", "Reconstruction": ".solver", "reconstruct": ".solver",
         "reconstruct_series": ".jobs.series"}


def __getattr__(name):
    import importlib

    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value
        return value
    try:
        return importlib.import_module(f".{name}", __name__)    # cm2cl.solver, cm2cl.io, ... on first use
    except ModuleNotFoundError as exc:
        if exc.name != f"{__name__}.{name}":
            raise
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None


def __dir__():
    return sorted(list(globals()) + list(_LAZY))

"""Memory model: bytes the solver allocates on a device for a problem, whether it fits, and the
memory the host has available (psutil: Linux, macOS and Windows alike)."""

from __future__ import annotations

import numpy as np

from ..device.fft import spectrum_shape
from ..errors import DeviceError

__all__ = ["memory_estimate", "check_fits", "host_available_bytes"]


def host_available_bytes() -> int:
    """Memory the host can give without swapping (psutil's ``available``)."""
    import psutil

    return int(psutil.virtual_memory().available)


#: real volumes on the padded grid the solver keeps (x, x_old/scratch, u, w, eta, rho, px, py, pz)
REAL_VOLUMES = 9


def memory_estimate(nz, padded_shape, dtype, backend) -> dict:
    """Bytes the solver allocates on the device (FFT libraries may add their own scratch)."""
    py, px = padded_shape
    item = np.dtype(dtype).itemsize
    spec_plane = int(np.prod(spectrum_shape((py, px), backend))) * 2 * item
    real_plane = py * px * item
    per_plane = REAL_VOLUMES * real_plane + 2 * spec_plane  # + x spectra + PSF spectra
    fixed = 7 * real_plane + 4 * spec_plane  # planes: v, xi, hx, cty, cw, r, psf tmp; R, S, comp, hn2
    return {"per_plane": per_plane, "fixed": fixed, "total": nz * per_plane + fixed,
            "real_volume": nz * real_plane, "psf_spectra": nz * spec_plane}


def check_fits(rt, nz, padded_shape, dtype, backend, budget_fraction=0.9):
    est = memory_estimate(nz, padded_shape, dtype, backend)
    budget = int(rt.caps.global_mem * budget_fraction)
    if est["total"] > budget:
        fit = max(0, (budget - est["fixed"]) // est["per_plane"])
        raise DeviceError(
            f"problem too large for device '{rt.caps.name}': {nz} planes on a "
            f"{padded_shape[0]} x {padded_shape[1]} padded grid need {est['total'] / 2**30:.2f} GiB, "
            f"the device offers {budget / 2**30:.2f} GiB; {fit} planes fit at this size "
            "(use fewer planes, bin the measurement, or depth slabs over devices)"
        )
    return est

"""Attenuation by a scattering sample in the forward model: each plane's PSF scaled by its ballistic fraction.

A calibration PSF is measured in a clear medium. In a scattering sample an emitter at depth d below the
surface reaches the sensor with only the fraction exp(-d / l_s) of its light as the sharp, ballistic image
(l_s the scattering mean free path); the rest is scattered into a halo the PSF does not have (the
background term takes its smooth part). The forward model of such a sample is therefore

    y = C sum_i a_i H_i x_i + b,      a_i = exp(-max(0, z_i - z_surface) / l_s)

and the volume x holds each emitter's brightness before the attenuation, so that a deep emitter reads as
bright as a shallow one of the same brightness; without it the deep planes are dimmed by a_i and fall
below any detection threshold relative to the volume's peak (docs/paper_scenes.md, fig5_scattering).
Depth increases with z (the planes' ``depths_um``), as in cm2cl's simulator (cm2cl.simulate.effects).

``scattering_length_um='auto'`` (:func:`solve_estimated`): the frame is solved with the clear-medium stack, l_s
estimated from how that answer's emitters' light falls with depth (:mod:`cm2cl.analysis.attenuation`), and the
frame solved again with that l_s: the answer a user who gives the estimate gets, at twice the time.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

__all__ = ["AUTO", "ballistic_fractions", "check", "attenuate", "unattenuate", "estimate_on", "solve_estimated"]

#: the word of ``scattering_length_um`` that estimates it from the solved volume
AUTO = "auto"


def ballistic_fractions(depths_um, scattering_length_um: float, surface_um: float | None = None) -> np.ndarray:
    """(nz,) a_i = exp(-max(0, z_i - surface) / l_s); ``surface_um`` None: the shallowest plane."""
    z = np.asarray(depths_um, np.float64).ravel()
    top = float(np.min(z)) if surface_um is None else float(surface_um)
    return np.exp(-np.clip(z - top, 0.0, None) / float(scattering_length_um))


def check(params, depths_um, nz: int) -> bool:
    """Whether ``params`` ask for attenuation, after checking that they can have it (one-line InputErrors:
    a surface without a scattering length, no depths, depths that do not match the planes)."""
    ls = getattr(params, "scattering_length_um", None)
    if ls is None:
        if getattr(params, "surface_um", None) is not None:
            raise InputError("surface_um: only with a scattering length (the surface is where the attenuation starts)")
        return False
    if depths_um is None:
        raise InputError("scattering_length_um: needs the planes' depths (depths_um, or a PSF file that records "
                         "them) to know each plane's depth below the surface")
    if np.asarray(depths_um).size != nz:
        raise InputError(f"scattering_length_um: {np.asarray(depths_um).size} depths for {nz} PSF planes")
    return True


def attenuate(psf, depths_um, params) -> tuple[np.ndarray, dict | None]:
    """(the PSF stack with each plane scaled by its ballistic fraction, the record) for ``params``
    (an ADMMParams: ``scattering_length_um``, ``surface_um``); the stack itself and None without a scattering
    length. The scaled stack is a copy in the stack's own float dtype (one more stack in host memory)."""
    if not check(params, depths_um, psf.shape[0]) or params.scattering_length_um == AUTO:
        return psf, None
    ls = params.scattering_length_um
    z = np.asarray(depths_um, np.float64).ravel()
    a = ballistic_fractions(z, ls, params.surface_um)
    dtype = psf.dtype if np.issubdtype(psf.dtype, np.floating) else np.float64
    out = np.asarray(psf, dtype) * a.astype(dtype)[:, None, None]
    record = {"scattering_length_um": float(ls), "surface_um": float(np.min(z) if params.surface_um is None
                                                                       else params.surface_um),
              "ballistic_fraction": [float(v) for v in a]}
    return out, record


def unattenuate(psf, record) -> np.ndarray:
    """An attenuated stack (e.g. the one a PSF refinement fitted) back in the clear medium's units."""
    if not record:
        return psf
    a = np.asarray(record["ballistic_fraction"], np.float64)
    return np.asarray(psf, np.float64) / a[:, None, None]



def estimate_on(solve, volume_of, depths_um, params, call: dict) -> tuple:
    """``solve(**call)`` with the clear-medium model (``call`` without its scattering length and surface) and
    l_s estimated from its volume (``volume_of(result)``; :mod:`cm2cl.analysis.attenuation`). Returns (that
    result, the record: ``attenuate``'s keys, the fractions all 1 where the estimate does not apply, and
    ``estimate``: the estimator's dict and the clear-medium solve's iterations)."""
    from ..analysis.attenuation import estimate_scattering_length

    z = np.asarray(depths_um, np.float64).ravel()
    first = solve(**_clear(call))
    est = estimate_scattering_length(volume_of(first), z, params.surface_um)
    est["first_solve_iterations"] = _iterations(first)
    ls = est["scattering_length_um"]
    a = ballistic_fractions(z, ls, est["surface_um"]) if ls is not None else np.ones(z.size)
    return first, {"scattering_length_um": ls, "surface_um": est["surface_um"],
                   "ballistic_fraction": [float(v) for v in a], "estimate": est}


def solve_estimated(solve, volume_of, depths_um, params, call: dict) -> tuple:
    """``scattering_length_um='auto'``: :func:`estimate_on`, then, where the estimate applies,
    ``solve(**call, scattering_length_um=estimate)``: the answer a user giving that number gets. Returns (the
    result, its ``attenuation`` record)."""
    first, record = estimate_on(solve, volume_of, depths_um, params, call)
    if record["scattering_length_um"] is None:
        return first, record
    return solve(**_clear(call), scattering_length_um=record["scattering_length_um"],
                 surface_um=record["surface_um"]), record


def _clear(call: dict) -> dict:
    """A call's keywords without its scattering length and surface: the clear-medium model's."""
    return {k: v for k, v in call.items() if k not in ("scattering_length_um", "surface_um")}


def _iterations(result):
    """The iterations a solve's result ran (a Reconstruction, or a tiled (volume, info) pair)."""
    if isinstance(result, tuple):
        return int(sum(result[1]["iterations"]))
    return int(result.info.get("psf_refine", {}).get("iterations_total") or result.iterations)

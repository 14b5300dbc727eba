"""Float64 numpy twins of every device computation, written independently from the paper's
equations: for tests and tools only (no production path calls them). They import nothing from the
device layer or the solver's operators; the ADMM twin shares only the iteration policy
(:mod:`cm2cl.solver.params`, :mod:`cm2cl.solver.control`) so that penalties can be compared."""

from .admm import admm, normalisation  # noqa: F401
from .forward import (adjoint, centered_psf, convolve, convolve_spatial, correlate_spatial,  # noqa: F401
                      crop, crop_offsets, embed, forward, psf_spectra)
from .tv import tv_div, tv_dual_step, tv_grad, tv_prox, tv_value  # noqa: F401

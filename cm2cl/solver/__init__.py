"""The reconstruction: the forward operator H and its adjoint (paper Eq. 3), the ADMM solver
(Eq. 4), its parameters and iteration control (penalties, stopping), the result, and the
device memory model."""

from .admm import ADMMSolver, reconstruct  # noqa: F401
from .forward import ForwardModel  # noqa: F401
from .params import ADMMParams  # noqa: F401
from .result import Reconstruction  # noqa: F401

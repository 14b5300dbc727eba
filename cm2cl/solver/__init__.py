"""The reconstruction: the forward operator H and its adjoint (paper Eq. 3), the ADMM solver
(Eq. 4), where its depth planes live (resident or streamed parts on one or more devices), its
parameters and iteration control (penalties, stopping), the result, and the memory model and planner."""

from .admm import ADMMSolver  # noqa: F401
from .api import reconstruct  # noqa: F401
from .forward import ForwardModel  # noqa: F401
from .params import ADMMParams  # noqa: F401
from .result import Reconstruction  # noqa: F401

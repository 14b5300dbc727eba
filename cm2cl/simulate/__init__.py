"""The CM2 simulator: scenes (TOML; :mod:`.scene`) of objects (:mod:`.objects`), optional effects
(:mod:`.effects`), image formation (:mod:`.render`), and the pipeline that runs only the stages a
scene names and writes the outputs (:mod:`.pipeline`)."""

from .pipeline import SimulationResult, simulate, simulate_scene, write_simulation  # noqa: F401
from .scene import Scene, builtin_scenes, load_scene, resolve_scene  # noqa: F401

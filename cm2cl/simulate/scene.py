"""Scene files (TOML): parsing and validation.

A scene names the optics (overrides of :class:`cm2cl.optics.CM2Optics`), the sample volume and its
depth planes, the objects, the rendering options and an ordered list of effects::

    name = "demo_beads"
    description = "a few beads"
    seed = 1                              # default seed (overridden by simulate(seed=...))

    [optics]                              # any CM2Optics field
    binning = 8

    [volume]
    size_mm = [3.0, 2.0, 1.0]             # x, y, z extent of the sample box
    center_mm = [0.0, 0.0, 0.0]           # z relative to the nominal working distance
    dz_um = 250.0                         # depth planes every dz over the z extent

    [render]                              # optional
    mode = "auto"                         # auto | shift_invariant | grid | emitters
    grid_mm = 1.0                         # field-point spacing of the grid path
    z_oversample = 1                      # render planes per ground-truth plane
    backend = "auto"                      # auto | opencl | numpy

    [output]                              # optional
    measurement_dtype = "sensor"          # sensor (uint8/uint16 from noise) | float32

    [[objects]]
    type = "beads"                        # beads | fibres | target | vessels
    diameter_um = 10.0
    count = 12

    [[effects]]
    name = "noise"                        # noise | background | scattering | truncation | aberration | vignetting

Every problem raises :class:`cm2cl.errors.InputError` with a one-line message naming the scene
file, the key and the problem.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import tomllib

import numpy as np

from ..errors import InputError
from ..optics import CM2Optics, depth_planes
from ..validate import Checker
from .effects import EFFECTS, STAGES
from .objects import OBJECTS, Box

__all__ = ["Scene", "load_scene", "builtin_scenes", "resolve_scene"]

TOP_KEYS = ("name", "description", "seed", "optics", "volume", "render", "output", "objects", "effects")
RENDER_MODES = ("auto", "shift_invariant", "grid", "emitters")
BACKENDS = ("auto", "opencl", "numpy")


@dataclass
class Scene:
    """A validated scene. ``objects`` and ``effects`` hold the parameter tables with defaults filled."""
    name: str
    source: str
    description: str
    seed: int | None
    optics: CM2Optics
    box: Box
    dz_um: float
    objects: list
    effects: list                 # [{"name":..., "params": {...}}] in the scene's order
    render: dict
    output: dict
    raw: dict = field(repr=False, default_factory=dict)

    @property
    def label(self) -> str:
        return Path(self.source).name if self.source and not self.source.startswith("<") else self.source

    @property
    def depths_um(self) -> np.ndarray:
        """Ground-truth depth planes (um from the nominal working distance)."""
        z0, z1 = self.box.z_range_um
        if z1 - z0 <= 0:
            return np.array([z0])
        planes = depth_planes(z0, z1, self.dz_um)
        return planes

    @property
    def effect_names(self) -> list:
        return [e["name"] for e in self.effects]

    def error(self, key: str, problem: str) -> InputError:
        return InputError(f"scene '{self.label}': {key}: {problem}")

    def as_dict(self) -> dict:
        """The scene as a JSON-able dict (defaults filled)."""
        return {"name": self.name, "source": self.source, "description": self.description,
                "seed": self.seed, "optics": self.optics.as_dict(),
                "volume": {"size_mm": [*self.box.size_mm, (self.box.z_range_um[1] - self.box.z_range_um[0]) / 1000.0],
                           "center_mm": [*self.box.center_mm, (self.box.z_range_um[0] + self.box.z_range_um[1]) / 2000.0],
                           "dz_um": self.dz_um},
                "render": dict(self.render), "output": dict(self.output),
                "objects": [dict(o) for o in self.objects],
                "effects": [{"name": e["name"], **e["params"]} for e in self.effects]}


# --------------------------------------------------------------------------------------------
# built-in scenes
# --------------------------------------------------------------------------------------------


#: resource bounds a scene is checked against before anything is generated (the renderer's memory is
#: estimated separately from the planes and the grid, against the host's available memory)
MAX_PLANES = 100_000
MAX_OBJECTS = 2_000_000


def _check_object_size(ck, key, params, box) -> None:
    """Refuse object counts and sizes that cannot be generated on this machine, before generating."""
    vol_mm3 = box.size_mm[0] * box.size_mm[1] * max(box.z_range_um[1] - box.z_range_um[0], 1.0) / 1000.0
    n = params.get("count")
    if n is None and params.get("density_per_mm3") is not None:
        n = params["density_per_mm3"] * vol_mm3
    if n is not None and n > MAX_OBJECTS:
        ck.fail(key, f"{n:.3g} objects; at most {MAX_OBJECTS:g} can be generated (lower count or density_per_mm3)")
    d = params.get("diameter_um")
    extent_um = 1000.0 * max(box.size_mm[0], box.size_mm[1]) + (box.z_range_um[1] - box.z_range_um[0])
    if d is not None and d > extent_um:
        ck.fail(f"{key}.diameter_um", f"{d:g} um is larger than the volume ({extent_um:g} um)")
    if n is not None and d is not None and n * (d / 1000.0) ** 3 > 1e3 * vol_mm3:
        ck.fail(key, f"{n:.3g} objects of {d:g} um fill the volume many times over")

def builtin_scenes() -> dict:
    """{name: path} of the scenes shipped in cm2cl/simulate/scenes/."""
    root = resources.files("cm2cl.simulate.scenes")
    return {Path(p.name).stem: Path(str(p)) for p in sorted(root.iterdir(), key=lambda p: p.name)
            if p.name.endswith(".toml")}


def resolve_scene(name_or_path) -> Path:
    """A scene file from a path or the name of a built-in scene."""
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists() or len(p.parts) > 1:
        if not p.exists():
            raise InputError(f"scene '{p}': no such file")
        if p.is_dir():
            raise InputError(f"scene '{p}': is a directory, expected a .toml file")
        return p
    known = builtin_scenes()
    if str(name_or_path) in known:
        return known[str(name_or_path)]
    raise InputError(f"scene '{name_or_path}': no such file and no built-in scene of that name "
                     f"(built-in: {', '.join(known) or 'none'})")


# --------------------------------------------------------------------------------------------
# loading
# --------------------------------------------------------------------------------------------

_VOLUME = {
    "size_mm": {"type": "vec3", "required": True, "min": 0},
    "center_mm": {"type": "vec3", "default": [0.0, 0.0, 0.0]},
    "dz_um": {"type": "float", "default": None, "min": 0, "exclusive": True},
}
_RENDER = {
    "mode": {"type": "str", "default": "auto", "choices": RENDER_MODES},
    "grid_mm": {"type": "float", "default": 1.0, "min": 0, "exclusive": True},
    "z_oversample": {"type": "int", "default": 1, "min": 1},
    "backend": {"type": "str", "default": "auto", "choices": BACKENDS},
}
_OUTPUT = {
    "measurement_dtype": {"type": "str", "default": "sensor", "choices": ("sensor", "float32")},
}


def load_scene(source) -> Scene:
    """A :class:`Scene` from a built-in name, a .toml path, a dict (already parsed TOML) or a Scene."""
    if isinstance(source, Scene):
        return source
    if isinstance(source, dict):
        return _build(dict(source), "<dict>")
    path = resolve_scene(source)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"scene '{path.name}': cannot read ({exc})") from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"scene '{path.name}': not valid TOML ({exc})") from exc
    except RecursionError as exc:
        raise InputError(f"scene '{path.name}': nested too deeply to read") from exc
    return _build(data, str(path))


def _build(data: dict, source: str) -> Scene:
    label = Path(source).name if not source.startswith("<") else source
    ck = Checker(f"scene '{label}'")
    unknown = [k for k in data if k not in TOP_KEYS]
    if unknown:
        ck.fail(unknown[0], f"unknown key (known: {', '.join(TOP_KEYS)})")
    name = data.get("name", Path(source).stem if not source.startswith("<") else "scene")
    if not isinstance(name, str):
        ck.fail("name", f"expected a string, got {name!r}")
    description = data.get("description", "")
    if not isinstance(description, str):
        ck.fail("description", f"expected a string, got {description!r}")
    seed = data.get("seed")
    if seed is not None:
        seed = ck.number("seed", seed, {"min": 0}, integer=True)

    # optics
    ov = data.get("optics", {})
    if not isinstance(ov, dict):
        ck.fail("optics", f"expected a table, got {ov!r}")
    fields = {f.name for f in dataclasses.fields(CM2Optics)}
    for k in ov:
        if k not in fields:
            ck.fail(f"optics.{k}", f"unknown optics field (known: {', '.join(sorted(fields))})")
    kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in ov.items()}
    try:
        optics = CM2Optics(**kw)
    except InputError as exc:
        raise InputError(f"scene '{label}': {exc}") from None
    except TypeError as exc:
        ck.fail("optics", str(exc))

    # volume
    if "volume" not in data:
        ck.fail("volume", "missing (required): a table with size_mm = [x, y, z] and dz_um")
    vol = ck.table("volume", data["volume"], _VOLUME)
    sx, sy, sz = vol["size_mm"]
    cx, cy, cz = vol["center_mm"]
    if sx <= 0 or sy <= 0:
        ck.fail("volume.size_mm", f"the lateral extent must be > 0, got {vol['size_mm']!r}")
    if sz > 0 and vol["dz_um"] is None:
        ck.fail("volume.dz_um", "missing (required when the volume has a depth extent)")
    dz = vol["dz_um"] if vol["dz_um"] is not None else 1.0
    if sz > 0 and dz > 1000.0 * sz:
        ck.fail("volume.dz_um", f"{dz} um exceeds the depth extent {1000.0 * sz:g} um")
    if sz > 0 and 1000.0 * sz / dz > MAX_PLANES:
        ck.fail("volume.dz_um", f"{dz:g} um over a {1000.0 * sz:g} um depth makes {1000.0 * sz / dz:.3g} planes; "
                                f"at most {MAX_PLANES} (raise dz_um)")
    box = Box((cx, cy), (sx, sy), (1000.0 * (cz - sz / 2.0), 1000.0 * (cz + sz / 2.0)))
    if -box.z_range_um[0] >= 1000.0 * optics.l_mm:
        ck.fail("volume.center_mm", "the volume reaches the microlens array (z <= -l)")

    render = ck.table("render", data.get("render", {}), _RENDER)
    output = ck.table("output", data.get("output", {}), _OUTPUT)

    # objects
    objects = []
    for i, key, o, kind in ck.named_tables(data, "objects", "type", OBJECTS, "object"):
        spec = OBJECTS[kind]
        params = ck.table(key, o, spec["params"], skip=("type",))
        group = spec.get("one_of")
        if group:
            given = [g for g in group if params.get(g) is not None]
            if len(given) != 1:
                ck.fail(key, f"give exactly one of {', '.join(group)} (got {', '.join(given) or 'none'})")
        _check_object_size(ck, key, params, box)
        objects.append({"type": kind, **params})
    if not objects:
        ck.fail("objects", "the scene has no objects")

    # effects
    effects = []
    seen = {}
    last_stage = 0
    for i, key, e, n in ck.named_tables(data, "effects", "name", EFFECTS, "effect"):
        if n in seen:
            ck.fail(f"{key}.name", f"effect {n!r} named twice (also effects[{seen[n]}])")
        seen[n] = i
        stage = STAGES.index(EFFECTS[n]["stage"])
        if last_stage == STAGES.index("sensor") and stage < last_stage:
            ck.fail(f"{key}.name", f"{n!r} acts on the sample/optics and must come before the "
                                   "sensor-stage effect 'noise'")
        last_stage = max(last_stage, stage)
        params = ck.table(key, e, EFFECTS[n]["params"], skip=("name",))
        effects.append({"name": n, "params": params})

    names = [e["name"] for e in effects]
    sv = "truncation" in names or "aberration" in names
    if render["mode"] == "shift_invariant" and sv:
        ck.fail("render.mode", "'shift_invariant' cannot model the named effects "
                               f"{', '.join(n for n in names if n in ('truncation', 'aberration'))}; use auto, grid or emitters")
    if render["mode"] == "emitters":
        if any(o["type"] != "beads" for o in objects):
            ck.fail("render.mode", "'emitters' renders beads only; this scene has other objects")
        if "background" in names:
            ck.fail("render.mode", "'emitters' cannot render the volumetric 'background' effect; use grid")
    return Scene(name=name, source=source, description=description, seed=seed, optics=optics,
                 box=box, dz_um=float(dz), objects=objects, effects=effects, render=render,
                 output=output, raw=data)

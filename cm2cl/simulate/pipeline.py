"""CM2 simulator: scenes (TOML) -> measurement, PSF stack and ground truth.

    from cm2cl.simulate import simulate, simulate_scene
    record = simulate("demo_beads", "out/", seed=1)       # files + JSON record
    result = simulate_scene("demo_beads", seed=1)         # the same, in memory

Pipeline (only the stages a scene names run; see :mod:`cm2cl.simulate.effects`):

1. objects -> emitters in object space (:mod:`.objects`), rasterised onto the sensor-referred
   render grid (the forward model's padded object grid) -> ground truth;
2. object-stage effects in the scene's order (background, scattering, vignetting);
3. optics-stage effects (truncation, aberration) -> PSF options; the on-axis PSF stack is computed
   (that is also the PSF a calibration would measure, and it is saved);
4. image formation (:mod:`.render`): the shift-invariant forward operator, or -- only when
   truncation / aberration are named -- a shift-variant path (per-emitter for bead scenes, else a
   lateral grid of local PSFs);
5. sensor-stage effects (noise), then outputs.

Every random draw comes from a generator seeded by (seed, stage, index), so the same seed gives the
same result, and adding an effect does not move the objects.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.staging import StagedOutput, jsonable
from ..io.tiff import OBJECT_SPACE
from . import effects as _effects
from .objects import Beads, generate
from ..solver.memory import host_available_bytes
from .render import (RenderGrid, Sample, estimate_bytes, padded_shape_for, rasterise, render_backend,
                     render_emitters, render_grid, render_psf_stack, render_shift_invariant)
from .scene import Scene, load_scene

__all__ = ["simulate", "simulate_scene", "write_simulation", "SimulationResult", "EMITTER_COLUMNS"]

_STAGE_KEYS = {"objects": 1, "object": 2, "optics": 3, "sensor": 4, "random_seed": 5}

#: emitters.csv columns: napari's CSV points reader takes the ``axis-*`` columns as point coordinates
#: (data/voxel units of ground_truth.ome.tif: plane, row, column) and the others as point properties. The
#: ``z_um, y_um, x_um`` are the same points in the frame of the volumes and MIPs: napari's world coordinates
#: of ground_truth.ome.tif (index x voxel size, z from its first plane's depth, y and x from its first
#: voxel); simulation.json's ``emitters_frame`` says how they map to the object's position.
EMITTER_COLUMNS = ("index", "axis-0", "axis-1", "axis-2", "z_um", "y_um", "x_um", "brightness", "diameter_um")


def emitters_frame(optics: CM2Optics, depths, voxel) -> dict:
    """How emitters.csv's z_um, y_um, x_um (the volume's frame) map to the object's position (x, y from the
    optical axis, mirrored by the lens; the lateral scale of a plane at depth z is the nominal one times
    m(0) / m(z) = (l + z) / l)."""
    cy, cx = optics.center_px
    return {"frame": "napari world coordinates of ground_truth.ome.tif, um: z = the plane's depth, y = row x "
                     "dy, x = column x dx from the first voxel (as the MIPs and the volumes' axes)",
            "origin_um": [float(depths[0]), 0.0, 0.0], "voxel_size_um": list(voxel),
            "object_position": "x_obj = (x0_um - x_um) (l_um + z_um) / l_um, y_obj = (y0_um - y_um) (l_um + z_um) / "
                               "l_um, z_obj = z_um",
            "x0_um": cx * voxel[2], "y0_um": cy * voxel[1], "l_um": 1000.0 * optics.l_mm}


@dataclass
class SimulationResult:
    """In-memory outputs of :func:`simulate_scene`."""
    measurement: np.ndarray          # (My, Mx) as the sensor gives it (or float32)
    expected: np.ndarray             # (My, Mx) float64 noise-free expected photo-electrons
    psf: np.ndarray                  # (nz, My, Mx) float32 on-axis PSF at the ground-truth depths
    ground_truth: np.ndarray         # (nz, My, Mx) float32 emission per voxel (sensor window)
    depths_um: np.ndarray            # (nz,)
    voxel_size_um: tuple             # (dz, dy, dx) of the ground truth (object space, nominal)
    emitters: dict | None            # bead truth table (None without beads)
    record: dict = field(default_factory=dict)
    scene: Scene | None = None


def _rng(seed, stage, index=0):
    return np.random.default_rng([int(seed), _STAGE_KEYS[stage], int(index)])


def _effect(name):
    """The stage function, looked up at call time (never touched for unnamed effects)."""
    return getattr(_effects, name)


def _choose_path(scene: Scene, objects) -> str:
    names = scene.effect_names
    mode = scene.render["mode"]
    if mode != "auto":
        return mode
    if "truncation" not in names and "aberration" not in names:
        return "shift_invariant"
    if all(isinstance(o, Beads) for o in objects) and "background" not in names:
        if sum(len(o) for o in objects) <= 20000:
            return "emitters"
    return "grid"


def simulate_scene(scene, seed: int | None = None, device=None) -> SimulationResult:
    """Simulate a scene (name, path, dict or :class:`Scene`) in memory.

    ``seed`` overrides the scene's seed; ``device`` (index, name fragment, ...) picks the OpenCL
    device of the forward model (default: see :mod:`cm2cl.device`)."""
    t_start = time.perf_counter()
    timings = {}
    scene = load_scene(scene)
    if seed is not None:
        seed_source = "argument"
    elif scene.seed is not None:
        seed, seed_source = scene.seed, "scene"
    else:
        seed, seed_source = int(np.random.SeedSequence().entropy % (2 ** 63)), "random"
    seed = int(seed)
    if seed < 0:
        raise InputError(f"seed: must be >= 0, got {seed}")
    optics = scene.optics
    k = int(scene.render["z_oversample"])
    depths = scene.depths_um
    dz = scene.dz_um
    if k > 1:
        sub = (np.arange(k) - (k - 1) / 2.0) * dz / k
        render_depths = (depths[:, None] + sub[None, :]).ravel()
    else:
        render_depths = depths.copy()
    backend = render_backend(scene.render["backend"], device)
    padded = padded_shape_for(optics.shape, backend)
    need = estimate_bytes(len(render_depths), padded, optics.shape)
    have = host_available_bytes()
    if need > 0.8 * have:
        raise scene.error("volume", f"needs ~{need / 2**30:.1f} GiB for {len(render_depths)} planes on a "
                                    f"{padded[0]} x {padded[1]} grid, but only {have / 2**30:.1f} GiB is "
                                    "available; raise optics.binning or volume.dz_um, or crop optics.sensor_shape")
    # a single-plane scene collapses everything onto its plane
    grid = RenderGrid(optics, render_depths, dz / k if len(render_depths) > 1 else np.inf, padded)

    # 1. objects and ground truth
    t = time.perf_counter()
    spacing = 0.5 * float(optics.object_pixel_um(0.0))
    objects = [generate(spec, scene.box, _rng(seed, "objects", i), spacing) for i, spec in enumerate(scene.objects)]
    volume, dropped = rasterise(grid, objects)
    gt = volume[:, grid.crop[0], grid.crop[1]]
    gt = gt.reshape(len(depths), k, *optics.shape).sum(axis=1) if k > 1 else gt.copy()
    beads = [o for o in objects if isinstance(o, Beads)]
    timings["objects_s"] = time.perf_counter() - t
    path = _choose_path(scene, objects)

    # 2. object-stage effects
    applied = []
    if path == "emitters":
        allb = Beads(np.vstack([b.xyz_um for b in beads]) if beads else np.zeros((0, 3)),
                     np.concatenate([b.brightness for b in beads]) if beads else np.zeros(0),
                     np.concatenate([b.diameter_um for b in beads]) if beads else np.zeros(0))
        sample = Sample(scene.box, volume=None, beads=allb)
    else:
        sample = Sample(scene.box, volume=volume)
    psf_kw = {}
    for i, e in enumerate(scene.effects):
        stage = _effects.EFFECTS[e["name"]]["stage"]
        if stage != "object":
            continue
        t = time.perf_counter()
        info = _effect(e["name"])(sample, grid, _rng(seed, "object", i), **e["params"])
        applied.append({"name": e["name"], "stage": stage, "params": e["params"], "info": info,
                        "seconds": time.perf_counter() - t})
    # 3. optics-stage effects -> PSF options
    for e in scene.effects:
        stage = _effects.EFFECTS[e["name"]]["stage"]
        if stage == "optics":
            psf_kw.update(_effect(e["name"])(**e["params"]))
            applied.append({"name": e["name"], "stage": stage, "params": e["params"], "info": {}, "seconds": 0.0})
    t = time.perf_counter()
    psf = render_psf_stack(optics, depths, psf_kw)
    psf_render = psf if k == 1 else render_psf_stack(optics, render_depths, psf_kw)
    timings["psf_s"] = time.perf_counter() - t

    # 4. image formation
    t = time.perf_counter()
    render_info = {"path": path, "backend": backend if path != "emitters" else "numpy",
                   "padded_shape": list(padded), "render_planes": len(render_depths), "z_oversample": k}
    if path == "shift_invariant":
        expected = render_shift_invariant(sample.total_volume(), psf_render, padded, backend, device)
    elif path == "grid":
        expected, info = render_grid(sample.total_volume(), grid, psf_kw, scene.render["grid_mm"], backend,
                                     device=device)
        render_info.update(info)
    else:
        expected = render_emitters(sample.beads, optics, psf_kw, sample.bead_halo)
        render_info["emitters"] = len(sample.beads)
    expected = np.clip(np.asarray(expected, np.float64), 0.0, None)   # FFT round-off below zero
    timings["render_s"] = time.perf_counter() - t

    # 5. sensor-stage effects
    measurement = expected.astype(np.float32)
    units = "photo-electrons (expected, noise-free)"
    for i, e in enumerate(scene.effects):
        stage = _effects.EFFECTS[e["name"]]["stage"]
        if stage != "sensor":
            continue
        t = time.perf_counter()
        measurement, info = _effect(e["name"])(expected, optics, _rng(seed, "sensor", i), **e["params"])
        units = info.get("units", units)
        applied.append({"name": e["name"], "stage": stage, "params": e["params"], "info": info,
                        "seconds": time.perf_counter() - t})
    if scene.output["measurement_dtype"] == "float32":
        measurement = measurement.astype(np.float32)

    obj_px = float(optics.object_pixel_um(0.0))
    voxel = (float(dz), obj_px, obj_px)
    emitters = _truth_table(beads, grid, depths, dz) if beads else None
    record = {
        "scene": scene.as_dict(),
        "seed": seed, "seed_source": seed_source,
        "optics": {**optics.as_dict(), "shape": list(optics.shape), "pixel_size_um": optics.pixel_size_um,
                   "object_pixel_um": obj_px, "na": optics.na, "oversampling": optics.oversampling},
        "volume": {"depths_um": depths.tolist(), "voxel_size_um": list(voxel),
                   "frame": "sensor-referred: voxel (z, r, c) images onto sensor pixel (r, c) through the "
                            "central lens; object +x -> decreasing column, +y -> decreasing row",
                   "units": "photo-electrons per voxel (all views, on axis)",
                   "points_outside_render_grid": int(dropped)},
        "emitters_frame": emitters_frame(optics, depths, voxel),
        "render": render_info,
        "effects_applied": applied,
        "effects_not_named": [n for n in _effects.EFFECTS if n not in scene.effect_names],
        "objects": [{"type": s["type"], "count": len(o), "kind": o.kind} for s, o in zip(scene.objects, objects)],
        "measurement": {"units": units, "dtype": str(measurement.dtype), "shape": list(measurement.shape),
                        "pixel_size_um": optics.pixel_size_um},
        "psf": {"depths_um": depths.tolist(), "voxel_size_um": list(voxel), "voxel_space": OBJECT_SPACE,
                "sensor_pixel_um": optics.pixel_size_um,
                "note": "PSF images lie on the sensor grid; their voxel size is that of the object-space "
                        "reconstruction grid, which cm2cl reconstruct gives the volume"},
        "timings_s": {**timings, "total_s": time.perf_counter() - t_start},
    }
    return SimulationResult(measurement, expected, psf.astype(np.float32), gt.astype(np.float32), depths,
                            voxel, emitters, record, scene)


def _truth_table(beads, grid: RenderGrid, depths, dz) -> dict:
    """Bead centres: object (x, y, z) um, brightness, diameter, and their fractional position
    (plane, row, col) on the ground-truth grid (sensor window)."""
    xyz = np.vstack([b.xyz_um for b in beads])
    t, r, c = grid.to_grid(xyz)
    oy, ox = grid.offsets
    plane = (xyz[:, 2] - depths[0]) / dz if len(depths) > 1 else np.zeros(len(xyz))
    return {"x_um": xyz[:, 0], "y_um": xyz[:, 1], "z_um": xyz[:, 2],
            "brightness": np.concatenate([b.brightness for b in beads]),
            "diameter_um": np.concatenate([b.diameter_um for b in beads]),
            "plane": plane, "row": r - oy, "col": c - ox}


def _write_outputs(result: SimulationResult, scene: Scene, tmp: Path) -> dict:
    """measurement, PSF and ground truth as OME-TIFF; the bead table as CSV. The PSF stack carries
    the object-space voxel size of the reconstruction grid (what a volume reconstructed with it
    measures) and the depths; the measurement carries the sensor pixel it was recorded with."""
    from ..io.tiff import write_tiff

    opt = scene.optics
    p = opt.pixel_size_um
    files = {}
    channel = {"channel": "fluorescence", "emission_nm": opt.wavelength_um * 1e3}
    write_tiff(tmp / "measurement.ome.tif", result.measurement, voxel_size_um=(p, p),
               extra={"kind": "measurement", "units": result.record["measurement"]["units"],
                      "voxel_space": "sensor", "object_pixel_um": result.voxel_size_um[1], "scene": scene.name},
               name=f"{scene.name}: measurement", **channel)
    files["measurement"] = "measurement.ome.tif"
    write_tiff(tmp / "psf.ome.tif", result.psf, voxel_size_um=result.voxel_size_um, depths_um=result.depths_um,
               extra={"kind": "psf", "normalisation": "each plane: the untruncated on-axis array sums to 1",
                      "voxel_space": OBJECT_SPACE, "sensor_pixel_um": p,
                      "axis_pixel": list(opt.center_px), "scene": scene.name},
               name=f"{scene.name}: PSF stack", **channel)
    files["psf"] = "psf.ome.tif"
    write_tiff(tmp / "ground_truth.ome.tif", result.ground_truth, voxel_size_um=result.voxel_size_um,
               depths_um=result.depths_um,
               extra={"kind": "ground_truth", "units": "photo-electrons per voxel", "voxel_space": OBJECT_SPACE,
                      "frame": result.record["volume"]["frame"], "scene": scene.name},
               name=f"{scene.name}: ground truth", **channel)
    files["ground_truth"] = "ground_truth.ome.tif"
    if result.emitters is not None:
        e = result.emitters
        dz, dy, dx = result.voxel_size_um
        z0, n = float(result.depths_um[0]), len(e["plane"])
        z = z0 + e["plane"] * dz if len(result.depths_um) > 1 else np.full(n, z0)
        table = np.column_stack([np.arange(n), e["plane"], e["row"], e["col"], z, e["row"] * dy, e["col"] * dx,
                                 e["brightness"],
                                 e["diameter_um"]])
        np.savetxt(tmp / "emitters.csv", table, delimiter=",", header=",".join(EMITTER_COLUMNS), comments="",
                   fmt=["%d"] + ["%.9g"] * 6 + ["%.6g"] * (len(EMITTER_COLUMNS) - 7))
        files["emitters"] = "emitters.csv"
    return files


def simulate(scene, outdir, seed: int | None = None, device=None) -> dict:
    """Simulate a scene and write ``measurement.ome.tif``, ``psf.ome.tif``, ``ground_truth.ome.tif``
    (OME-TIFF with voxel sizes and depths), ``emitters.csv`` (bead scenes: voxel position as napari's
    ``axis-0..2`` columns, object position in um) and ``simulation.json`` (the record: scene with
    defaults, seed, effects applied, render path, timings) into ``outdir``.

    The output folder is checked and locked before the (long) run, the files are written into a staging
    folder beside ``outdir``, the JSON record last, and the folder is swapped in whole
    (:class:`cm2cl.io.staging.StagedOutput`): an interrupted run never leaves output that looks complete,
    nor new files beside a previous result. Returns the record (as written to simulation.json)."""
    scene = load_scene(scene)
    planes, (my, mx) = len(scene.depths_um), scene.optics.shape
    out_bytes = 4 * my * mx * (2 * planes + 1)       # measurement, PSF stack and ground truth (float32)
    with StagedOutput(outdir, "simulation.json", expected_bytes=out_bytes) as stage:
        return publish_simulation(simulate_scene(scene, seed, device), stage)


def write_simulation(result: SimulationResult, outdir) -> dict:
    """Write a :class:`SimulationResult` into ``outdir`` as :func:`simulate` does; returns the record."""
    with StagedOutput(outdir, "simulation.json") as stage:
        return publish_simulation(result, stage)


def publish_simulation(result: SimulationResult, stage: StagedOutput) -> dict:
    """Write the outputs into ``stage.dir`` and publish them with the record last; returns the record."""
    files = _write_outputs(result, result.scene, stage.dir)
    record = dict(result.record)
    record["files"] = files
    record["cm2cl_version"] = __import__("cm2cl").__version__
    text = json.dumps(jsonable(record), indent=2)
    stage.publish("simulation.json", text)
    return json.loads(text)

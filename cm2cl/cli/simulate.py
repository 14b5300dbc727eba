"""``cm2cl simulate SCENE -o OUTDIR [--seed N] [--list]``.

The main ``cm2cl`` command calls :func:`register`; errors are raised as InputError and turned into
a one-line message and exit code 2 there.
"""

from __future__ import annotations

import argparse

from ..errors import InputError

__all__ = ["register", "command"]


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``simulate`` sub-command to an argparse sub-parsers object."""
    p = subparsers.add_parser(
        "simulate", help="simulate a CM2 measurement, PSF stack and ground truth from a scene",
        description="Simulate a CM2 measurement from a scene file (TOML) or a built-in scene name. "
                    "Writes measurement.ome.tif (sensor pixel), psf.ome.tif and ground_truth.ome.tif (OME-TIFF "
                    "with the object-space voxel size and depths), emitters.csv for bead scenes (napari points: "
                    "axis-0..2 = plane, row, column; z_um, y_um, x_um in the volume's frame, from its first "
                    "voxel), and simulation.json (scene, seed, effects applied, the emitters' frame) last.")
    p.add_argument("scene", nargs="?", help="built-in scene name (see --list) or path to a .toml file")
    p.add_argument("-o", "--output", dest="outdir", metavar="OUTDIR", help="output directory")
    p.add_argument("--seed", type=int, default=None,
                   help="random seed (default: the scene's 'seed', else a fresh one, recorded in the JSON)")
    p.add_argument("--list", action="store_true", help="list the built-in scenes and exit")
    p.set_defaults(func=command)
    return p


def command(args) -> int:
    from ..simulate import builtin_scenes, load_scene, simulate

    if args.list:
        for name, path in builtin_scenes().items():
            try:
                desc = load_scene(path).description
            except InputError as exc:          # a broken built-in is a bug; show it, don't hide it
                desc = f"(invalid: {exc})"
            print(f"{name:18s} {desc}")
        return 0
    if not args.scene:
        raise InputError("simulate: give a SCENE (built-in name or .toml file), or --list to see the built-ins")
    if not args.outdir:
        raise InputError("simulate: -o OUTDIR is required")
    if args.seed is not None and args.seed < 0:
        raise InputError(f"--seed: must be >= 0, got {args.seed}")
    rec = simulate(args.scene, args.outdir, seed=args.seed)
    r = rec["render"]
    effects = ", ".join(e["name"] for e in rec["effects_applied"]) or "none"
    print(f"scene {rec['scene']['name']} (seed {rec['seed']}): {r['path'].replace('_', '-')} model, "
          f"{len(rec['volume']['depths_um'])} planes, effects: {effects}; "
          f"{rec['timings_s']['total_s']:.1f} s")
    print(f"wrote {args.outdir}: " + ", ".join(rec["files"].values()) + ", simulation.json")
    return 0

"""A napari screenshot of a reconstruction with its simulation's emitters (issue 26): runs ``cm2cl demo`` into a
temporary folder (or takes ``--demo DIR`` of an earlier run), opens ``reconstruction.ome.tif`` and
``simulation/emitters.csv`` with cm2cl's napari reader, shows them in 3D (maximum-intensity projection,
orthographic, looking along z) and saves the canvas.

    xvfb-run -a python tools/napari_screenshot.py [--demo DIR] [--out docs/img/napari_demo.png]

Needs ``pip install ".[napari]"`` and a display (Xvfb on a headless machine).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--demo", type=Path, default=None, help="a cm2cl demo output folder (default: run the demo)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img" / "napari_demo.png")
    args = ap.parse_args(argv)
    import napari

    from cm2cl.io.napari_reader import get_reader

    with tempfile.TemporaryDirectory() as tmp:
        demo = args.demo
        if demo is None:
            demo = Path(tmp) / "demo"
            subprocess.run([sys.executable, "-m", "cm2cl", "demo", "-o", str(demo)], check=True)
        viewer = napari.Viewer(show=True)
        for path in (demo / "reconstruction.ome.tif", demo / "simulation" / "emitters.csv"):
            for data, kw, kind in get_reader(str(path))(str(path)):
                getattr(viewer, f"add_{kind}")(data, **kw)
        img, pts = viewer.layers[0], viewer.layers[1]
        img.rendering, img.colormap = "mip", "magma"
        img.contrast_limits = (0.0, float(np.asarray(img.data).max()) * 0.5)
        pts.face_color, pts.border_color, pts.border_width, pts.size, pts.opacity = "transparent", "cyan", 0.15, 3.0, 0.9
        viewer.dims.ndisplay = 3
        camera = getattr(viewer, "scene", viewer).camera
        camera.perspective, camera.angles = 0.0, (0.0, 0.0, 90.0)
        viewer.reset_view()
        camera.zoom *= 2.5
        args.out.parent.mkdir(parents=True, exist_ok=True)
        viewer.screenshot(str(args.out), canvas_only=True, flash=False)
        viewer.close()
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The napari plugin headless (issue 26): the reconstruct widget runs a solve on the open layers in a worker
thread with progress and cancel and returns the volume at the PSF layer's physical scale; a screenshot
shows a simulation's emitters (cm2cl's reader) on its beads. Under Xvfb (pytest-xvfb starts it) with Mesa's
software OpenGL; skipped where napari or a display server is missing (the napari extra installs both)."""

import os

import numpy as np
import pytest

napari = pytest.importorskip("napari")
pytest.importorskip("pytestqt")
if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    # no display server (pytest-xvfb starts Xvfb where it is installed): Qt would abort the whole run
    pytest.skip("no display: install xvfb (apt-get install xvfb) and pytest-xvfb", allow_module_level=True)

from cm2cl.analysis import quality as Q  # noqa: E402
from cm2cl.io.napari_widget import ReconstructWidget, layer_geometry  # noqa: E402

SCALE, Z0 = (50.0, 5.0, 5.0), -150.0


def _problem(seed=2, nz=6, shape=(64, 64), n=6):
    psf = Q.array_psf(nz, shape)
    beads = Q.place_beads(n, nz, shape, seed)
    truth = Q.bead_volume(beads, np.ones(n), nz, shape)
    y = Q.object_image(psf, truth)
    return psf.astype(np.float32), y.astype(np.float32), beads


def _widget(viewer, psf, y, max_iter):
    viewer.add_image(psf, name="psf", scale=SCALE, translate=(Z0, 0.0, 0.0), metadata={"unit": "um"})
    viewer.add_image(y, name="frame")
    w = ReconstructWidget(viewer)
    w.measurement.value = viewer.layers["frame"]
    w.psf.value = viewer.layers["psf"]
    w.max_iter.value = max_iter
    return w


def test_widget_reconstructs_the_open_layers_at_their_scale(make_napari_viewer, qtbot):
    viewer = make_napari_viewer()
    psf, y, beads = _problem()
    w = _widget(viewer, psf, y, 300)
    assert [c for c in w.psf.choices] == [viewer.layers["psf"]]          # only 3D layers offered as the PSF
    w.run_button.clicked()
    assert not w.run_button.enabled and w.cancel_button.enabled
    qtbot.waitUntil(lambda: w.result_layer is not None, timeout=180_000)
    layer = w.result_layer
    assert layer.name == "frame: reconstruction" and layer.data.shape == psf.shape
    assert tuple(layer.scale) == SCALE and tuple(layer.translate) == (Z0, 0.0, 0.0)
    assert w.progress.value > 0 and w.status.value.startswith("done") and w.run_button.enabled
    score = Q.score_beads(np.asarray(layer.data), beads)
    assert score["recall"] >= 0.8, score
    geo = layer_geometry(viewer.layers["psf"])
    assert geo["depths_um"] == [Z0 + 50.0 * k for k in range(psf.shape[0])]


def test_widget_cancel_stops_the_solve_and_adds_nothing(make_napari_viewer, qtbot):
    viewer = make_napari_viewer()
    psf, y, _ = _problem()
    w = _widget(viewer, psf, y, 100000)
    w.preset.value = "best"          # runs far past any test's patience unless cancelled
    w.run_button.clicked()
    qtbot.waitUntil(lambda: w.progress.value >= 5, timeout=60_000)
    w.cancel_button.clicked()
    qtbot.waitUntil(lambda: w.status.value == "cancelled", timeout=60_000)
    assert w.result_layer is None and [lay.name for lay in viewer.layers] == ["psf", "frame"]
    assert w.run_button.enabled and not w.cancel_button.enabled and w.progress.value < 100000


def _blobs(mask):
    from scipy import ndimage

    lab, n = ndimage.label(mask)
    return lab, np.array(ndimage.center_of_mass(mask, lab, range(1, n + 1))).reshape(-1, 2)


def test_screenshot_shows_the_emitters_on_the_beads(make_napari_viewer, tmp_path):
    """A simulation opened with cm2cl's reader: its ground truth (MIP, 3D, orthographic, looking along z) and its
    emitters. Every emitter's marker sits on a bright bead of the image, and the same markers shifted by 200 um
    (5 voxels) do not (the check can fail)."""
    from cm2cl.io.napari_reader import get_reader
    from cm2cl.simulate import simulate_scene, write_simulation

    d = tmp_path / "sim"
    write_simulation(simulate_scene("demo_beads", seed=1), d)
    viewer = make_napari_viewer(show=True)      # a hidden window's canvas renders nothing
    for name in ("ground_truth.ome.tif", "emitters.csv"):
        for data, kw, kind in get_reader(str(d / name))(str(d / name)):
            getattr(viewer, f"add_{kind}")(data, **kw)
    img, pts = viewer.layers[0], viewer.layers[1]
    img.rendering, img.contrast_limits = "mip", (0.0, float(np.asarray(img.data).max()) * 0.3)
    pts.face_color, pts.border_width, pts.size = "red", 0.0, 1.5     # size in voxels
    viewer.dims.ndisplay = 3
    camera = getattr(viewer, "scene", viewer).camera      # napari 0.9 moved it under viewer.scene
    camera.perspective = 0.0
    camera.angles = (0.0, 0.0, 90.0)
    viewer.reset_view()
    camera.zoom *= 3

    def shot(image, points):
        img.visible, pts.visible = image, points
        return np.asarray(viewer.screenshot(canvas_only=True, flash=False))

    bright = shot(True, False)[..., :3].max(axis=-1) > 60
    red = shot(False, True)
    markers = (red[..., 0] > 150) & (red[..., 1] < 80)
    beads, _ = _blobs(bright)
    _, centres = _blobs(markers)
    assert len(centres) >= 8, len(centres)

    def on_beads(c):
        ij = np.clip(np.round(c).astype(int), 0, np.array(bright.shape) - 1)
        return np.mean(beads[ij[:, 0], ij[:, 1]] > 0)

    assert on_beads(centres) >= 0.9
    pts.translate = tuple(np.asarray(pts.translate) + np.array([0.0, 200.0, 200.0]))
    _, moved = _blobs((lambda r: (r[..., 0] > 150) & (r[..., 1] < 80))(shot(False, True)))
    assert on_beads(moved) < 0.5


def test_widget_docks_from_the_plugin_menu(make_napari_viewer):
    """napari finds the widget through cm2cl's manifest (Plugins > Reconstruct (cm2cl)) and hands it the viewer;
    its layer choices follow the viewer's layers."""
    viewer = make_napari_viewer()
    _, w = viewer.window.add_plugin_dock_widget("cm2cl", "Reconstruct (cm2cl)")
    assert w.viewer is not None and list(w.psf.choices) == []
    psf, y, _ = _problem()
    viewer.add_image(psf, name="psf")
    viewer.add_image(y, name="frame")
    assert [c.name for c in w.psf.choices] == ["psf"] and [c.name for c in w.measurement.choices] == ["frame"]

"""napari widget (the manifest's ``cm2cl.reconstruct_widget``): reconstruct the open measurement layer with
the open PSF-stack layer, in a worker thread, with a progress bar and a cancel button; the volume comes back
as a layer at the PSF layer's physical scale and depth offset (what :mod:`.napari_reader` gave it), so that
it overlays the ground truth and the emitters of a simulation.

The solve is :func:`cm2cl.reconstruct` with the widget's prior, preset and iteration cap; its callback
reports every few iterations to the GUI thread (a Qt signal) and raises :class:`Cancelled` once cancel is
pressed, which stops the solve at its next iteration. napari and Qt are imported only when the widget is
made."""

from __future__ import annotations

import threading

import numpy as np

__all__ = ["ReconstructWidget", "Cancelled", "layer_geometry", "solve_layers"]

#: iterations between two progress reports
REPORT_EVERY = 5


class Cancelled(Exception):
    """The user pressed cancel: the solve stops at its next iteration."""


def layer_geometry(layer) -> dict:
    """The PSF layer's voxel size and depths (um) for the reconstruction: its scale and its translate along z
    (a stack opened by cm2cl's reader carries both), or None where it has only pixels (scale 1, no offset)."""
    scale = tuple(float(s) for s in layer.scale)
    translate = tuple(float(t) for t in layer.translate)
    unit = (getattr(layer, "metadata", None) or {}).get("unit")
    physical = unit == "um" or any(s != 1.0 for s in scale) or translate[0] != 0.0
    if not physical:
        return {"voxel_size_um": None, "depths_um": None, "scale": scale, "translate": translate}
    nz = layer.data.shape[0]
    return {"voxel_size_um": scale, "depths_um": [translate[0] + k * scale[0] for k in range(nz)],
            "scale": scale, "translate": translate}


def solve_layers(y, psf, *, prior="default", preset="balanced", max_iter=None, progress=None, cancel=None, **kw):
    """:func:`cm2cl.reconstruct` of arrays ``y`` (2D) and ``psf`` (3D) for the widget: ``progress(row)`` every
    REPORT_EVERY iterations, and a stop (:class:`Cancelled`) at the next iteration once ``cancel`` (a
    threading.Event) is set. The arrays are checked by the solver (one-line errors)."""
    import cm2cl

    def callback(row):
        if cancel is not None and cancel.is_set():
            raise Cancelled("cancelled")
        if progress is not None:
            progress(row)

    from ..solver.params import layered

    extra = {} if max_iter is None else {"max_iter": int(max_iter)}
    params = layered(prior, preset, **extra).as_dict()
    return cm2cl.reconstruct(np.asarray(y), np.asarray(psf), callback=callback, callback_every=REPORT_EVERY,
                             **params, **kw)


def _make_widget_class():
    from magicgui.widgets import ComboBox, Container, Label, ProgressBar, PushButton, SpinBox
    from napari.layers import Image
    from napari.qt.threading import create_worker
    from qtpy.QtCore import QObject, Signal

    from ..solver.params import PRESETS, PRIORS

    class _Bridge(QObject):
        row = Signal(object)

    class ReconstructWidget(Container):
        """Measurement and PSF layers, prior, preset, iteration cap; Reconstruct / Cancel; progress."""

        def __init__(self, viewer):
            super().__init__()
            self.viewer = viewer
            self.measurement = ComboBox(label="measurement (2D)", choices=self._layers(2))
            self.psf = ComboBox(label="PSF stack (3D)", choices=self._layers(3))
            self.prior = ComboBox(label="prior", choices=list(PRIORS), value="default")
            self.preset = ComboBox(label="preset", choices=list(PRESETS), value="balanced")
            self.max_iter = SpinBox(label="max iterations", value=1000, min=1, max=100000)
            self.run_button = PushButton(text="Reconstruct")
            self.cancel_button = PushButton(text="Cancel", enabled=False)
            self.progress = ProgressBar(label="iterations", min=0, max=1000, value=0)
            self.status = Label(value="")
            self.extend([self.measurement, self.psf, self.prior, self.preset, self.max_iter, self.run_button,
                         self.cancel_button, self.progress, self.status])
            self.run_button.changed.connect(self.start)
            self.cancel_button.changed.connect(self.cancel)
            for ev in (viewer.layers.events.inserted, viewer.layers.events.removed):
                ev.connect(self._refresh)
            self._bridge = _Bridge()
            self._bridge.row.connect(self._on_row)
            self._cancel = threading.Event()
            self.worker = None
            self.result_layer = None

        def _layers(self, ndim):
            def choices(_widget=None):
                return [(lay.name, lay) for lay in self.viewer.layers if isinstance(lay, Image) and lay.data.ndim == ndim]
            return choices

        def _refresh(self, _event=None):
            self.measurement.reset_choices()
            self.psf.reset_choices()

        def start(self, _value=None):
            """Start the solve in a worker thread (the buttons and status follow it)."""
            meas, psf = self.measurement.value, self.psf.value
            if meas is None or psf is None:
                self.status.value = "open a 2D measurement and a 3D PSF stack first"
                return
            geo = layer_geometry(psf)
            self._cancel.clear()
            self.progress.max, self.progress.value = int(self.max_iter.value), 0
            self.status.value = f"reconstructing {meas.name} with {psf.name}"
            self.run_button.enabled, self.cancel_button.enabled = False, True
            kw = {"voxel_size_um": geo["voxel_size_um"], "depths_um": geo["depths_um"]} if geo["voxel_size_um"] else {}
            self.worker = create_worker(solve_layers, np.asarray(meas.data), np.asarray(psf.data),
                                        prior=self.prior.value, preset=self.preset.value,
                                        max_iter=int(self.max_iter.value), progress=self._bridge.row.emit,
                                        cancel=self._cancel, _ignore_errors=True, **kw)   # errors: _failed
            name = f"{meas.name}: reconstruction"
            self.worker.returned.connect(lambda rec: self._done(rec, name, geo))
            self.worker.errored.connect(self._failed)
            self.worker.start()

        def cancel(self, _value=None):
            self._cancel.set()
            self.status.value = "cancelling at the next iteration"

        def _on_row(self, row):
            self.progress.value = min(int(row["iter"]), self.progress.max)
            self.status.value = f"iteration {int(row['iter'])}, objective {row['objective']:.4g}"

        def _done(self, rec, name, geo):
            self.run_button.enabled, self.cancel_button.enabled = True, False
            it = len(rec.log)
            self.progress.value = min(it, self.progress.max)
            self.status.value = f"done: {it} iterations, {'converged' if rec.info.get('converged') else 'stopped at the cap'}"
            self.result_layer = self.viewer.add_image(rec.volume, name=name, scale=geo["scale"],
                                                      translate=geo["translate"], colormap="magma",
                                                      metadata={"cm2cl": {"iterations": it, "stop": rec.info.get("stop")}})

        def _failed(self, exc):
            self.run_button.enabled, self.cancel_button.enabled = True, False
            self.status.value = "cancelled" if isinstance(exc, Cancelled) else f"failed: {exc}"

    return ReconstructWidget


_CLASS = None


class ReconstructWidget:
    """The widget for ``napari_viewer`` (the manifest's widget; napari passes the viewer by this name, read
    from ``__init__``'s signature). The Qt class is built on first use, so that importing this module needs
    neither napari nor Qt; ``ReconstructWidget(viewer)`` returns an instance of it."""

    def __new__(cls, napari_viewer):
        global _CLASS
        if _CLASS is None:
            _CLASS = _make_widget_class()
        return _CLASS(napari_viewer)

    def __init__(self, napari_viewer):   # pragma: no cover - never runs: __new__ returns the Qt class's instance
        raise AssertionError("unreachable")

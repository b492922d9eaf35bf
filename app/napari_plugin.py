"""The napari plugin (``isolume[napari]``, manifest ``napari.yaml``): a dock widget that
shows the isosurface of a 3-D Image layer lit with global illumination.

Its isovalue slider adds, then updates, a Surface layer (named after the Image, "…
isosurface") placed with the Image layer's own scale, translate, rotate, shear and affine
(`app.napari_layers`). Its vertex colours carry the light ``isolume export`` writes at
``render``'s exposure and tone curve, and the layer's own shading is off: napari does
not light it again. The light is traced in a background process for the shown isovalue
only, in passes of 4, 16, then the requested paths per texel (`app.napari_worker`); each
pass replaces the colours, and a new isovalue or light cuts the passes short. The
light's direction (the sky's sun) and the environment are controls, so are the exposure,
the paths per texel and the seed; "save view…" writes a state file that ``isolume render
--state FILE`` draws (`app.state`), with the volume beside it as a ``.npz``.

Layout: the controls are built by `_Controls`; `IsolumeWidget` holds the link to the
lighting process and the Surface layer, and polls the process from a Qt timer, so
napari's UI thread never waits on the light.
"""

from __future__ import annotations

import argparse
import itertools
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from qtpy.QtCore import Qt, QTimer
from qtpy.QtWidgets import (
    QComboBox,
    QDoubleSpinBox,
    QFileDialog,
    QFormLayout,
    QLabel,
    QLineEdit,
    QOpenGLWidget,
    QPushButton,
    QSlider,
    QSpinBox,
    QWidget,
)

from isolume import volumes
from isolume.app.napari_layers import (
    NapariLayerError,
    angles_of,
    data_vertices,
    direction_from_angles,
    display_colours,
    layer_transform,
    layer_volume,
    saved_camera,
    write_volume,
)
from isolume.volumes.errors import IsolumeError

if TYPE_CHECKING:
    import napari

    from isolume.app.napari_worker import LightingLink
    from isolume.baking.config import BakeConfig

ISO_STEPS = 10000
"""Positions of the isovalue slider across the data range."""
DEBOUNCE_MS = 150
"""A control change waits this long for the next before the light is asked for."""
POLL_MS = 30
"""Milliseconds between looks at the lighting process's results."""
DEFAULT_SAMPLES = 64
"""Paths per texel of the last pass (``isolume export``'s default)."""


class _Controls:
    """The widget's controls in a form layout on `parent` (no behaviour of their own)."""

    layer: QComboBox
    iso: QSlider
    iso_value: QLabel
    azimuth: QSlider
    elevation: QSlider
    env: QLineEdit
    exposure: QDoubleSpinBox
    samples: QSpinBox
    seed: QSpinBox
    save: QPushButton
    status: QLabel

    def __init__(self, parent: QWidget) -> None:
        from isolume.baking.config import DEFAULT_ENV

        form = QFormLayout(parent)
        self.layer = QComboBox()
        self.iso = _slider(0, ISO_STEPS)
        self.iso_value = QLabel("")
        self.azimuth = _slider(-180, 180)
        self.elevation = _slider(-90, 90)
        self.env = QLineEdit(DEFAULT_ENV)
        self.exposure = QDoubleSpinBox()
        self.exposure.setDecimals(3)
        self.exposure.setRange(0.001, 1000.0)
        self.exposure.setSingleStep(0.1)
        self.exposure.setValue(1.0)
        self.samples, self.seed = QSpinBox(), QSpinBox()
        self.samples.setRange(1, 4096)
        self.samples.setValue(DEFAULT_SAMPLES)
        self.seed.setRange(0, 2**31 - 1)
        self.save = QPushButton("save view…")
        self.status = QLabel("")
        self.status.setWordWrap(True)
        rows = [("image", self.layer), ("isovalue", self.iso), ("", self.iso_value),
                ("light azimuth°", self.azimuth), ("light elevation°", self.elevation),
                ("environment", self.env), ("exposure ×", self.exposure),
                ("paths per texel", self.samples), ("seed", self.seed), ("", self.save),
                ("", self.status)]
        for label, widget in rows:
            form.addRow(label, widget)


def _slider(lo: int, hi: int) -> QSlider:
    slider = QSlider(Qt.Horizontal)
    slider.setRange(lo, hi)
    return slider


class IsolumeWidget(QWidget):
    """The dock widget: one Image layer's isosurface, lit in the background.

    Attributes:
        viewer: the napari viewer.
        layer, volume: the Image layer lit and its `volumes.Volume` (None: none yet).
        surface: the Surface layer it adds (None before a layer is lit).
        iso: the isovalue (field units); env: the environment spec as typed;
        sun: (azimuth, elevation) degrees of the sun turned with the controls, or None
            (as the environment says).
        shown_paths: paths per texel of the light on screen (0: none yet).
        exposure_used: the linear exposure of the colours on screen (the multiplier
            times the automatic exposure).
    """

    viewer: napari.viewer.Viewer
    workers: int | None
    controls: _Controls
    layer: napari.layers.Image | None
    volume: volumes.Volume | None
    surface: napari.layers.Surface | None
    link: LightingLink | None
    iso: float
    sun: tuple[float, float] | None
    env: str
    shown_paths: int
    exposure_used: float

    def __init__(self, napari_viewer: napari.viewer.Viewer, workers: int | None = None
                 ) -> None:
        super().__init__()
        self.viewer, self.workers = napari_viewer, workers
        self.controls = _Controls(self)
        self.layer = self.volume = self.surface = self.link = None
        self.iso, self.sun, self.env = 0.0, None, self.controls.env.text()
        self.request: dict[str, Any] | None = None
        self._ids = itertools.count(1)
        self._surface: tuple | None = None  # the last surface sent: (key, vertices, …)
        self._mesh: tuple | None = None  # (request id, surface key, (V, 3) indices, faces,
        # areas): the surface of the request on screen
        self._surface_mesh = None  # the key of the surface the Surface layer shows
        self.radiance: np.ndarray | None = None
        self.shown_paths, self.exposure_used = 0, 1.0
        self._debounce = QTimer(self)
        self._debounce.setSingleShot(True)
        self._debounce.setInterval(DEBOUNCE_MS)
        self._debounce.timeout.connect(self.relight)
        self._poller = QTimer(self)
        self._poller.setInterval(POLL_MS)
        self._poller.timeout.connect(self._poll)
        self._connect()
        self._show_light_angles()
        self._refresh_layers()

    # -- wiring -----------------------------------------------------------------------
    def _connect(self) -> None:
        c = self.controls
        c.layer.activated.connect(self._layer_chosen)
        c.iso.valueChanged.connect(self._iso_moved)
        c.azimuth.valueChanged.connect(self._light_moved)
        c.elevation.valueChanged.connect(self._light_moved)
        c.env.editingFinished.connect(lambda: self.set_environment(c.env.text()))
        c.exposure.valueChanged.connect(lambda _: self._recolour())
        c.samples.valueChanged.connect(lambda _: self._debounce.start())
        c.seed.valueChanged.connect(lambda _: self._debounce.start())
        c.save.clicked.connect(self._save_clicked)
        self.viewer.layers.events.inserted.connect(self._refresh_layers)
        self.viewer.layers.events.removed.connect(self._layer_removed)

    def _images(self) -> list:
        from napari.layers import Image

        return [layer for layer in self.viewer.layers if isinstance(layer, Image)]

    def _refresh_layers(self, event=None) -> None:
        """List the Image layers; light the active one (else the first) if none is lit."""
        combo = self.controls.layer
        combo.clear()
        combo.addItems([layer.name for layer in self._images()])
        if self.layer is not None:
            combo.setCurrentText(self.layer.name)
            return
        images, active = self._images(), self.viewer.layers.selection.active
        if not images:
            self._say("add a 3-D Image layer to light its isosurface")
            return
        self._try(self.set_layer, active if active in images else images[0])

    def _layer_chosen(self, index: int) -> None:
        images = self._images()
        if 0 <= index < len(images) and images[index] is not self.layer:
            self._try(self.set_layer, images[index])

    def _layer_removed(self, event) -> None:
        if event.value is self.layer:
            self.stop()
            self.layer = self.volume = None
            self._refresh_layers()
        elif event.value is self.surface:
            self.surface = None
        else:
            self._refresh_layers()

    def _iso_moved(self, position: int) -> None:
        lo, hi = self.volume.value_range
        self.iso = lo + (hi - lo) * position / ISO_STEPS
        self._show_iso()
        self._debounce.start()

    def _light_moved(self, _) -> None:
        self.sun = (float(self.controls.azimuth.value()),
                    float(self.controls.elevation.value()))
        self._debounce.start()

    def _save_clicked(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Save the view", "isolume.view.json",
                                              "isolume views (*.view.json)")
        if path:
            self._try(self.save_view, path)

    def _try(self, action, *args) -> None:
        """Run `action`; an isolume error goes to the status line instead."""
        try:
            action(*args)
        except IsolumeError as exc:
            self._say(str(exc))

    def _say(self, text: str) -> None:
        self.controls.status.setText(text)

    # -- what the controls set -------------------------------------------------------------
    def set_layer(self, layer: napari.layers.Image) -> None:
        """Light the Image `layer` (a new lighting process for its volume) at its first
        suggested isovalue, in a Surface layer of its own (the one of the layer lit
        before is removed: it would no longer follow the controls).

        Raises:
            NapariLayerError: a layer the plugin cannot light (`layer_volume`).
        """
        volume = layer_volume(layer)
        self.stop()
        if self.surface is not None and self.surface in self.viewer.layers:
            self.viewer.layers.remove(self.surface)  # the last layer's light: it stops here
        self.layer, self.volume, self.surface = layer, volume, None
        self._surface = self._mesh = None  # the new process sends its surfaces anew
        self.controls.layer.setCurrentText(layer.name)
        from isolume.app.napari_worker import LightingLink

        self.link = LightingLink(volume, self.workers)
        self._poller.start()
        self._add_surface()
        suggested = volumes.suggest_isovalues(volume)
        lo, hi = volume.value_range
        self.set_isovalue(suggested[0] if suggested else (lo + hi) / 2)

    def set_isovalue(self, iso: float) -> None:
        """Show the isosurface at `iso` (field units, exactly) and light it."""
        self.iso = volumes.check_isovalue(self.volume, iso)
        lo, hi = self.volume.value_range
        self.controls.iso.blockSignals(True)
        self.controls.iso.setValue(round((self.iso - lo) / (hi - lo or 1.0) * ISO_STEPS))
        self.controls.iso.blockSignals(False)
        self._show_iso()
        self.relight()

    def set_light(self, azimuth: float, elevation: float) -> None:
        """Turn the sun (or the first directional light) to `azimuth`, `elevation`
        degrees (the volume's world: azimuth from +x towards +y) and light again."""
        self.sun = (float(azimuth), float(elevation))
        self._show_light_angles()
        self.relight()

    def set_environment(self, spec: str) -> None:
        """Light with the environment `spec` (``--env``'s: ``sky:...``, ``constant:...``,
        an HDR file, ``none``), its own sun direction; a bad spec goes to the status."""
        self.env, self.sun = spec, None
        self.controls.env.setText(spec)
        self._show_light_angles()
        if self.volume is not None:
            self._try(self.relight)

    def set_exposure(self, multiplier: float) -> None:
        """Multiply the automatic exposure by `multiplier` (colours only: no new light)."""
        self.controls.exposure.setValue(multiplier)

    def set_sampling(self, samples: int, seed: int) -> None:
        """Paths per texel of the last pass, and the random seed; lights again."""
        for box, value in ((self.controls.samples, samples), (self.controls.seed, seed)):
            box.blockSignals(True)
            box.setValue(value)
            box.blockSignals(False)
        self.relight()

    # -- the light ------------------------------------------------------------------------
    def lighting_spec(self) -> str:
        """The environment spec lit now: as typed, its sun turned to `sun` if set.

        Raises:
            IsolumeError: a bad spec (one line), or a turn with no sun to turn.
        """
        from isolume.app.options import parse_lighting

        lighting = parse_lighting(self.env, None)
        if self.sun is not None:
            if lighting.turnable() is None:
                raise NapariLayerError(f"environment {self.env!r} has no sun to turn")
            lighting = lighting.turned(direction_from_angles(*self.sun))
        return lighting.to_spec()[0]

    def config(self) -> BakeConfig:
        """The `BakeConfig` of the light to trace (``isolume export``'s, through
        `app.options.view_light`, for the controls' environment, paths and seed)."""
        from isolume.app.options import view_light
        from isolume.baking.config import DEFAULT_BOUNCES

        options = argparse.Namespace(
            env=self.lighting_spec(), light=None, samples=self.controls.samples.value(),
            bounces=DEFAULT_BOUNCES, albedo=None, seed=self.controls.seed.value(),
            normals="smooth", flip_normals=False)
        return view_light(options, self.volume)

    def relight(self) -> None:
        """Ask the lighting process for the light of the controls' settings now."""
        if self.link is None:
            return
        self._debounce.stop()
        self.request = {"id": next(self._ids), "iso": self.iso,
                        "config": self.config().to_dict()}
        self.link.send(self.request)
        self._say(f"iso {self.iso:.4g}: lighting…")

    @property
    def refined(self) -> bool:
        """Whether the light on screen is the last request's, fully refined."""
        return (self.request is not None and self._mesh is not None
                and self._mesh[0] == self.request["id"]
                and self.shown_paths == self.request["config"]["samples"])

    def _poll(self) -> None:
        """Show what the lighting process sent since the last look."""
        for kind, rid, *rest in self.link.poll() if self.link is not None else ():
            if kind == "mesh" and len(rest) > 1:  # a new surface: kept whoever asked
                key, vertices, faces, areas = rest
                self._surface = (key, data_vertices(self.volume, vertices), faces, areas)
            if rid is not None and (self.request is None or rid != self.request["id"]):
                continue  # an older request's
            if kind == "mesh":  # the surface sent last (its key: the worker's check)
                if self._surface is None or self._surface[0] != rest[0]:
                    self._say(f"iso {self.iso:.4g}: the lighting process's surface was lost")
                    continue
                self._mesh = (rid, *self._surface)
                self.shown_paths, self.radiance = 0, None
            elif kind == "light":
                self.shown_paths, self.radiance = rest
                self._recolour()
            else:  # "empty", "error"
                self._say(f"iso {self.iso:.4g}: {rest[0]}")
                if rid is None:
                    self.stop()

    def _recolour(self) -> None:
        """Colour the Surface layer from the light on screen at the exposure set."""
        if self.radiance is None or self._mesh is None:
            return
        _, _, vertices, faces, areas = self._mesh
        colours, self.exposure_used = display_colours(self.radiance, areas,
                                                      self.controls.exposure.value())
        self._update_surface(vertices, faces, colours)
        samples = self.request["config"]["samples"]
        self._say(f"iso {self.iso:.4g}: {len(vertices):,} vertices, {self.shown_paths} of "
                  f"{samples} paths per texel{' (refined)' if self.refined else ''}, "
                  f"exposure {self.exposure_used:.3g}")

    def _add_surface(self) -> None:
        """Add the Surface layer, placed as the Image layer, shading off, holding one
        degenerate triangle until the first light arrives: adding a layer costs napari's
        UI thread a few hundred milliseconds once (its controls, pandas' import), which
        thus falls on the choice of the layer rather than on the refinement."""
        placeholder = (np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.int32))
        self._surface_mesh = None
        self.surface = self.viewer.add_surface(
            placeholder, vertex_colors=np.zeros((3, 3), np.float32), shading="none",
            name=f"{self.layer.name} isosurface", **layer_transform(self.layer))

    def _update_surface(self, vertices: np.ndarray, faces: np.ndarray,
                        colours: np.ndarray) -> None:
        """Give the Surface layer (added again if it was deleted) the new mesh and
        colours."""
        if self.surface is None:
            self._add_surface()
        if self._surface_mesh != self._mesh[1]:  # a new surface, not a new light
            with self.surface.events.data.blocker():  # one redraw, with the colours
                self.surface.vertex_colors = None  # the old ones do not fit the new mesh
                self.surface.data = (vertices, faces)
        self.surface.vertex_colors = colours
        self._surface_mesh = self._mesh[1]

    def _show_iso(self) -> None:
        self.controls.iso_value.setText(f"{self.iso:.6g}")

    def _show_light_angles(self) -> None:
        """Set the light sliders to the sun lit now (disabled where there is none)."""
        from isolume.app.options import parse_lighting

        try:
            light = parse_lighting(self.env, None).turnable()
        except (IsolumeError, ValueError):
            light = None
        angles = self.sun or (angles_of(light.direction) if light is not None else None)
        for slider, value in zip((self.controls.azimuth, self.controls.elevation),
                                 angles or (0, 0), strict=True):
            slider.blockSignals(True)
            slider.setValue(round(value))
            slider.setEnabled(light is not None)
            slider.blockSignals(False)

    # -- saving and stopping --------------------------------------------------------------------
    def save_view(self, path: str | os.PathLike[str]) -> Path:
        """Write the view as a state file at `path` for ``isolume render --state`` (and
        ``view``, ``movie``): napari's camera, the isovalue, the lighting and the exposure
        on screen; the volume goes beside it as ``NAME.npz``. Returns the path.

        Raises:
            IsolumeError: no layer lit yet.
        """
        from isolume.app.state import SUFFIX, SavedView
        from isolume.baking.config import DEFAULT_ALBEDO

        if self.volume is None:
            raise NapariLayerError("no Image layer is lit yet; nothing to save")
        path = Path(path)
        stem = path.name[:-len(SUFFIX)] if path.name.endswith(SUFFIX) else path.stem
        volume_file = path.with_name(f"{stem}.npz").resolve()
        write_volume(self.volume, volume_file)
        height, width = self.canvas_size()
        scene = getattr(self.viewer, "scene", None)  # napari ≥ 0.9; before: viewer.camera
        camera = scene.camera if scene is not None else self.viewer.camera
        camera = saved_camera(self.layer, self.volume, camera, (height, width),
                              volumes.level_points(self.volume, self.iso))
        SavedView(volume=str(volume_file), iso=self.iso, camera=camera,
                  size=f"{width}x{height}", shading="irradiance",
                  exposure=self.controls.exposure.value(), auto_exposure=True,
                  shown_exposure=self.exposure_used, tonemap="aces",
                  albedo=str(DEFAULT_ALBEDO),
                  env=self.lighting_spec(), normals="smooth", flip_normals=False).save(path)
        self._say(f"saved the view in {path}")
        return path

    def canvas_size(self) -> tuple[int, int]:
        """(height, width) pixels of napari's canvas (the largest GL widget of the window
        the dock widget sits in).

        Raises:
            IsolumeError: the widget is not docked in a napari window.
        """
        canvases = self.window().findChildren(QOpenGLWidget)
        if not canvases:
            raise NapariLayerError("the widget is not docked in a napari window")
        canvas = max(canvases, key=lambda c: c.width() * c.height())
        return canvas.height(), canvas.width()

    def stop(self) -> None:
        """End the lighting process (the Surface layer stays)."""
        self._poller.stop()
        self._debounce.stop()
        if self.link is not None:
            self.link.close()
            self.link = None

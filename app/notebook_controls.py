"""The ipywidgets beside `isolume.show`'s picture: the isovalue, the light's azimuth and
elevation, the shading mode, and a status text (the surface, the lazy bake's progress, the
last message).

`Controls` sends what the user sets to its `app.notebook_view.NotebookView` (``set_iso``,
``set_light``, ``set_shading``) and shows what the view holds (`Controls.show_state`)
without sending it back.
"""

from __future__ import annotations

import html
from contextlib import contextmanager
from typing import TYPE_CHECKING, Protocol

from isolume.app.viewer.actions import ISO_STEPS

if TYPE_CHECKING:
    import ipywidgets

    from isolume.app.notebook_scene import NotebookScene

WIDTH = "330px"
"""Width of the controls' column (CSS)."""


class ControlledView(Protocol):
    """What `Controls` drive and show: an `app.notebook_view.NotebookView` (named here
    without importing it, which imports this module)."""

    @property
    def scene(self) -> NotebookScene | None: ...
    def set_iso(self, iso: float) -> None: ...
    def set_light(self, azimuth: float | None, elevation: float = 0.0) -> None: ...
    def set_shading(self, mode: str) -> None: ...


class Controls:
    """The controls of one view.

    Attributes:
        iso: isovalue slider over the volume's value range (field units).
        azimuth, elevation: the light's direction (degrees; moving either fixes the light
            to the world, as a ctrl-drag does).
        shading: the shading modes usable now.
        status: the status text (HTML).
        box: all of them, one above the other (an ``ipywidgets.VBox``).
    """

    view: ControlledView
    iso: ipywidgets.FloatSlider
    azimuth: ipywidgets.FloatSlider
    elevation: ipywidgets.FloatSlider
    shading: ipywidgets.Dropdown
    status: ipywidgets.HTML
    box: ipywidgets.VBox

    def __init__(self, view: ControlledView) -> None:
        """Controls showing and driving `view` (an `app.notebook_view.NotebookView`)."""
        import ipywidgets as widgets

        self.view = view
        scene = view.scene
        lo, hi = scene.volume.value_range
        style = {"description_width": "90px"}
        layout = widgets.Layout(width=WIDTH)
        self.iso = widgets.FloatSlider(
            value=scene.state.view.iso, min=lo, max=hi, step=(hi - lo) / ISO_STEPS,
            description="isovalue", readout_format=".4g", style=style, layout=layout)
        self.azimuth = widgets.FloatSlider(value=0.0, min=0.0, max=360.0, step=1.0,
                                           description="light azimuth", style=style,
                                           layout=layout)
        self.elevation = widgets.FloatSlider(value=0.0, min=-90.0, max=90.0, step=1.0,
                                             description="light elevation", style=style,
                                             layout=layout)
        self.shading = widgets.Dropdown(description="shading", style=style, layout=layout)
        self.status = widgets.HTML(layout=widgets.Layout(width=WIDTH))
        self.box = widgets.VBox([self.iso, self.azimuth, self.elevation, self.shading,
                                 self.status])
        self._showing = False
        self.show_state()
        self.iso.observe(self._on_iso, names="value")
        self.azimuth.observe(self._on_light, names="value")
        self.elevation.observe(self._on_light, names="value")
        self.shading.observe(self._on_shading, names="value")

    @contextmanager
    def _quiet(self):
        """Set the widgets without their observers driving the view."""
        self._showing = True
        try:
            yield
        finally:
            self._showing = False

    def show_state(self) -> None:
        """Show the view's isovalue, light, shading mode and status."""
        scene = self.view.scene
        view = scene.state.view
        azimuth, elevation = scene.actions.light_angles()
        with self._quiet():
            self.iso.value = view.iso
            self.azimuth.value = azimuth % 360.0
            self.elevation.value = elevation
            self.shading.options = scene.drawing.usable_modes()
            self.shading.value = view.shading
            self.status.value = status_html(scene)

    def _on_iso(self, change) -> None:
        if not self._showing:
            self.view.set_iso(change["new"])

    def _on_light(self, _change) -> None:
        if not self._showing:
            self.view.set_light(self.azimuth.value, self.elevation.value)

    def _on_shading(self, change) -> None:
        if not self._showing and change["new"] is not None:
            self.view.set_shading(change["new"])


def status_html(scene: NotebookScene) -> str:
    """The status text of `scene` (an `app.notebook_scene.NotebookScene`): the surface's
    line, the lazy bake's lines and the last message, escaped, one per line."""
    fractions, lines = scene.illumination.status()
    if fractions is not None:
        lines = (*lines, f"visible texels {100 * fractions[0]:.0f} %, surface "
                 f"{100 * fractions[1]:.0f} %")
    shown = [scene.surfaces.info, *lines, scene.state.message]
    text = "<br>".join(html.escape(line) for line in shown if line)
    return f"<small>{text}</small>"

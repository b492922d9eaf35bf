"""`NotebookView`: the widget `isolume.show` returns, a ``jupyter_rfb.RemoteFrameBuffer``.

Its frames come from an `app.notebook_scene.NotebookScene` (the desktop viewer's drawing,
surfaces and lazy bake on a headless GL context, in the kernel); jupyter_rfb sends them to
the browser and its events back. While the kernel's event loop runs, a timer
(`TICK_S`) takes what the surface worker and the bake process delivered and asks for a
frame when the picture changed, so the global illumination refines on screen as in the
desktop viewer.

Events (jupyter_rfb's format; buttons 1 left, 2 right, 3 middle): a left drag orbits,
shift- or middle-drag pans, ctrl- or right-drag turns the light, the wheel zooms, a resize
redraws at the new size.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from jupyter_rfb import RemoteFrameBuffer

from isolume import volumes
from isolume.app.notebook_scene import NotebookScene
from isolume.app.viewer.command import Options
from isolume.app.viewer.panel import (
    ZOOM_PER_WHEEL,
    Drag,
    drag_target,
)

if TYPE_CHECKING:
    from ipywidgets import HBox

    from isolume.app.notebook_controls import Controls
    from isolume.baking.view_texels import LatticeOnFile

TICK_S = 0.05
"""Seconds between two looks at the workers while the kernel's event loop runs."""
STATUS_S = 0.5
"""Seconds between two refreshes of the status text."""
WHEEL_PX_PER_NOTCH = 100.0
"""Browser wheel pixels (``dy``) per notch of a mouse wheel (one `ZOOM_PER_WHEEL` step)."""


class NotebookView(RemoteFrameBuffer):
    """An interactive view of a volume's isosurface in a notebook (see the module
    docstring); make it with `isolume.show` (`app.notebook.show`).

    Displaying it shows `panel`: the picture with `controls` beside it.

    Attributes:
        scene: the picture's parts (`app.notebook_scene.NotebookScene`).
        size: (W, H) pixels of the frames (the browser's size of the picture, after a
            resize).
        controls: the `app.notebook_controls.Controls` (``controls.box``, a VBox).
        panel: the picture and the controls side by side (an ``ipywidgets.HBox``).
    """

    controls: Controls | None
    panel: HBox | None

    def __init__(self, volume: volumes.Volume, iso: float, lattice: LatticeOnFile | None,
                 options: Options, gl: str = "auto", temporary: Path | None = None) -> None:
        """The view of `volume` at `iso` with the ``isolume view`` `options`; `lattice`, `gl`
        and `temporary` as `NotebookScene` takes them."""
        from ipywidgets import HBox

        from isolume.app.notebook_controls import Controls

        w, h = options.size
        with _outside_a_kernel_quiet():  # jupyter_rfb displays an output widget: a script
            super().__init__(css_width=f"{w}px", css_height=f"{h}px", resizable=True)
        self.size: tuple[int, int] = (w, h)
        self.scene: NotebookScene | None = None
        self.controls = self.panel = None
        self._drag: Drag | None = None
        self._status_at = 0.0
        self._timer = None
        self._home = home_loop()
        try:
            self.scene = NotebookScene(volume, iso, lattice, options, gl=gl,
                                       temporary=temporary)
            self.controls = Controls(self)
            self.panel = HBox([self, self.controls.box])
        except BaseException:
            self.close()
            raise
        self._schedule()

    # -- the kernel's thread -----------------------------------------------------------------
    def _elsewhere(self, call, *args) -> bool:
        """Whether this runs off the thread of the event loop the view was made on (where
        its GL context is current): then `call(*args)` is sent there and True returned.
        A kernel may deliver widget messages on another thread (ipykernel's subshells,
        which JupyterLab asks for by default)."""
        home = self._home
        if home is None or threading.get_ident() == home[1]:
            return False
        home[0].call_soon_threadsafe(call, *args)
        return True

    def _rfb_handle_msg(self, widget, content, buffers) -> None:
        """jupyter_rfb's message handler, on the view's own thread."""
        if not self._elsewhere(super()._rfb_handle_msg, widget, content, buffers):
            super()._rfb_handle_msg(widget, content, buffers)

    def _rfb_schedule_maybe_draw(self, *args) -> None:
        """jupyter_rfb's frame scheduling, on the view's own thread (its frame feedback
        arrives with the kernel's messages)."""
        if not self._elsewhere(self._rfb_maybe_draw):
            super()._rfb_schedule_maybe_draw(*args)

    # -- display -------------------------------------------------------------------------
    def _repr_mimebundle_(self, **kwargs):
        """Show `panel` (the picture and its controls) where the view is displayed."""
        return self.panel._repr_mimebundle_(**kwargs)

    def display(self) -> None:
        """Display `panel` (the picture and its controls)."""
        from IPython.display import display

        display(self.panel)

    # -- frames --------------------------------------------------------------------------
    def get_frame(self) -> np.ndarray | None:
        """The next frame for jupyter_rfb: (h, w, 3) uint8 sRGB, at most `size`, smaller
        while the view moves (the browser scales it); None once closed."""
        if self.closed:
            return None
        scene = self.scene
        scene.step(self.size)
        return scene.render(self.size, interacting=scene.state.interacting(time.perf_counter()))

    def snapshot(self) -> np.ndarray:
        """Draw a frame now and return it: (H, W, 3) uint8 sRGB of `size`, at full detail,
        once the full-resolution surface of the isovalue set has arrived. (jupyter_rfb's
        ``snapshot``, an IPython image of the last frame sent, is not offered.)

        Raises:
            IsolumeError: the view is closed, or the surface did not come
                (`NotebookScene.wait_surface`).
        """
        self._check_open()
        self.scene.wait_surface(self.size)
        return self.scene.render(self.size)

    def update(self) -> None:
        """Take what the surface worker and the lazy bake delivered, refresh the status
        text (at most every `STATUS_S`), and ask jupyter_rfb for a frame when one is due
        (`NotebookScene.frame_due`). The kernel's event loop calls it every `TICK_S`."""
        if self.closed:
            return
        scene = self.scene
        scene.step(self.size)
        now = time.perf_counter()
        if now - self._status_at > STATUS_S:
            self._status_at = now
            self.controls.show_state()
        if scene.frame_due(now):
            self.request_draw()

    def _schedule(self) -> None:
        """Call `_tick` in `TICK_S` on the running event loop (none: nothing happens by
        itself, `snapshot` and `update` do it)."""
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return
        self._timer = loop.call_later(TICK_S, self._tick)

    def _tick(self) -> None:
        """The timer's call: `update`, then the next call."""
        self._timer = None
        if not self.closed:
            self.update()
            self._schedule()

    # -- the programmatic API ------------------------------------------------------------
    def orbit(self, d_azimuth: float, d_elevation: float = 0.0) -> None:
        """Turn the camera by degrees of azimuth and elevation (as a drag does)."""
        self._act(self.scene.actions.move_camera, "orbit", d_azimuth, d_elevation)

    def zoom(self, factor: float) -> None:
        """Move the camera `factor` times closer (< 1: away)."""
        self._act(self.scene.actions.move_camera, "zoom", factor)

    def pan(self, dx: float, dy: float) -> None:
        """Move the orbit centre right and up by volume diagonals."""
        self._act(self.scene.actions.move_camera, "pan", dx, dy)

    def set_iso(self, iso: float) -> None:
        """Show the isosurface at `iso` (field units; clamped into the data range): it is
        extracted in the background, coarse first."""
        self._act(self.scene.actions.request_iso, iso)

    def set_light(self, azimuth: float | None, elevation: float = 0.0) -> None:
        """Fix the light (the environment in sh mode) to the world at (azimuth,
        elevation) degrees; `azimuth` None: back to the light that follows the camera."""
        angles = None if azimuth is None else (azimuth, elevation)
        self._act(self.scene.actions.set_light, angles)

    def set_shading(self, mode: str) -> None:
        """Shade with `mode` (`app.render.settings.SHADING_MODES`).

        Raises:
            ViewerError: the mode cannot be drawn now (a lattice mode without a lattice).
        """
        self._act(self.scene.actions.set_mode, mode)

    def set_exposure(self, exposure: float) -> None:
        """Linear exposure multiplier (on the automatic exposure, when it is on)."""
        self._act(self.scene.actions.set_exposure, exposure)

    def _act(self, action, *args) -> None:
        """Apply `action(*args)` on the scene, show it in the controls, ask for a frame (on
        the view's own thread: `_elsewhere`)."""
        if self._elsewhere(self._act, action, *args):
            return
        self._check_open()
        action(*args)
        self.controls.show_state()
        self.request_draw()

    def _check_open(self) -> None:
        """Raise `IsolumeError` once the view is closed."""
        from isolume.volumes.errors import IsolumeError

        if self.closed:
            raise IsolumeError("this isolume view is closed")

    # -- events --------------------------------------------------------------------------
    def handle_event(self, event: dict[str, Any]) -> None:
        """Handle a jupyter_rfb event: ``pointer_down``, ``pointer_move`` and
        ``pointer_up`` (x, y in CSS pixels, ``button``, ``modifiers``) drag, ``wheel``
        (``dy`` in pixels, negative up) zooms, ``resize`` (``width``, ``height``) sets
        `size`, ``close`` releases everything (`close`)."""
        kind = event.get("type", event.get("event_type"))
        if kind == "close":
            self._release()
            return
        handlers = {"pointer_down": self._press, "pointer_move": self._move,
                    "pointer_up": self._release_button, "wheel": self._wheel,
                    "resize": self._resize}
        if self.closed or kind not in handlers:
            return
        handlers[kind](event)
        if self.scene.state.dirty:  # not for a mere hover
            self.request_draw()

    def _press(self, event: dict) -> None:
        """Start the drag the button and modifiers ask for (`app.viewer.panel.drag_target`;
        jupyter_rfb numbers the buttons from 1, glfw from 0)."""
        modifiers = event.get("modifiers", ())
        target = drag_target(int(event.get("button", 0)) - 1, "Shift" in modifiers,
                             "Control" in modifiers)
        if target is not None:
            self._drag = Drag(target, float(event["x"]), float(event["y"]))
            self.scene.state.drag = self._drag

    def _move(self, event: dict) -> None:
        """Move what the drag moves by the pointer's motion since the last event."""
        drag = self._drag
        if drag is None:
            return
        x, y = float(event["x"]), float(event["y"])
        dx, dy = x - drag.x, y - drag.y
        drag.x, drag.y = x, y
        self.scene.actions.drag(drag.target, dx, dy, self.size[1])

    def _release_button(self, _event: dict) -> None:
        """End the drag; the light's sliders show where it went."""
        if self._drag is not None and self._drag.target == "light":
            self.controls.show_state()
        self._drag = self.scene.state.drag = None

    def _wheel(self, event: dict) -> None:
        """Zoom by `ZOOM_PER_WHEEL` per notch (`WHEEL_PX_PER_NOTCH`), closer upwards."""
        self.scene.actions.move_camera(
            "zoom", ZOOM_PER_WHEEL ** (float(event.get("dy", 0.0)) / WHEEL_PX_PER_NOTCH))

    def _resize(self, event: dict) -> None:
        """Frames of the picture's new size in CSS pixels (on a HiDPI screen the browser
        scales them up: twice as many pixels would halve the frame rate)."""
        self.size = (max(1, round(event["width"])), max(1, round(event["height"])))
        self.scene.state.redraw()

    # -- the end -------------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        """The view was closed (or never opened): its scene is freed."""
        return self.scene is None or self.scene.gl is None

    def close(self) -> None:
        """Close the widget's views and free the scene: the bake process, the extraction
        thread, the GL context (`NotebookScene.close`, which saves a lattice file named in
        `isolume.show`)."""
        super().close()  # emits the "close" event: `_release`
        self._release()

    def _release(self) -> None:
        """Stop the timer, free the scene, close the controls' widgets."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self.scene is not None:
            self.scene.close()
        if self.panel is not None:
            for widget in (*self.controls.box.children, self.controls.box, self.panel):
                widget.close()


def home_loop() -> tuple[asyncio.AbstractEventLoop, int] | None:
    """(the running event loop, its thread's id), or None when no loop runs (a script)."""
    try:
        return asyncio.get_running_loop(), threading.get_ident()
    except RuntimeError:
        return None


def _outside_a_kernel_quiet() -> contextlib.AbstractContextManager:
    """Standard output held back outside an IPython kernel (a script, a test), where the
    output widget jupyter_rfb displays would print as its repr; as it is in a kernel."""
    try:
        from IPython import get_ipython
    except ImportError:
        return contextlib.redirect_stdout(io.StringIO())
    shell = get_ipython()
    if shell is not None and getattr(shell, "kernel", None) is not None:
        return contextlib.nullcontext()
    return contextlib.redirect_stdout(io.StringIO())


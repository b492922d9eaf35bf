"""The viewer's state: what the user controls and what asks for the next frame.

Data flows one way: input (`app.viewer.input`) → actions (`app.viewer.actions`) →
`ViewerState` → drawing (`app.viewer.draw`) and the loop (`app.viewer.window`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

from isolume.app.render.camera import Camera
from isolume.app.viewer.draw import ViewState
from isolume.app.viewer.panel import Drag
from isolume.volumes.errors import IsolumeError

MOTION_S = 0.3
"""The camera or light counts as moving this long after it last moved (seconds)."""


class ViewerError(IsolumeError):
    """A request the viewer cannot honour (bad script step, missing lattice); one line."""


@dataclass
class ViewerState:
    """What the viewer shows and what makes it draw; times are seconds of
    `time.perf_counter`.

    Attributes:
        view: isovalue, shading mode, exposure, light and panel visibility.
        camera: the camera now; home: where ``R`` (reset) returns to.
        framed: the first surface has been framed (`home` aims at it).
        panel_shift: (pan per unit of distance, distance ratio) between a camera framed in
            the part of the window the panel leaves free and the same view framed in the
            whole window (`whole_window`); (0, 1) without a panel.
        panel_rect: (x, y, width, height) of the panel in window units (None: not drawn
            yet); panel_frames: frames the panel has been drawn (its size settles in two).
        message: the status line (the last note or error).
        quit: the loop ends.
        dirty: something on screen changed: draw a frame.
        lattice_changed: lazily baked texels were uploaded since the last frame.
        last_input: time of the last input event; last_motion: of the last camera or
            light movement.
        drag: the mouse drag in progress (None: none).
    """

    view: ViewState
    camera: Camera
    home: Camera
    framed: bool = False
    panel_shift: tuple[float, float] = (0.0, 1.0)
    panel_rect: tuple[float, float, float, float] | None = None
    panel_frames: int = 0
    message: str = ""
    quit: bool = False
    dirty: bool = True
    lattice_changed: bool = False
    last_input: float = 0.0
    last_motion: float = 0.0
    drag: Drag | None = None

    def whole_window(self) -> Camera:
        """The camera now, framed in the whole window rather than beside the panel: what
        screenshots and saved views show."""
        per_distance, ratio = self.panel_shift
        camera = self.camera
        own = camera.pan[0] - per_distance * camera.distance  # the user's own pan
        return replace(camera, distance=camera.distance * ratio, pan=(own, camera.pan[1]))

    def beside_panel(self, camera: Camera) -> Camera:
        """`camera` framed in the whole window (a saved view's) moved to the part the panel
        leaves free; `whole_window` undoes it."""
        per_distance, ratio = self.panel_shift
        distance = camera.distance / ratio
        return replace(camera, distance=distance,
                       pan=(camera.pan[0] + per_distance * distance, camera.pan[1]))

    def redraw(self) -> None:
        """Something on screen changed: draw again."""
        self.dirty = True

    def touched(self) -> None:
        """An input event arrived (frames follow for a while)."""
        self.last_input = time.perf_counter()
        self.dirty = True

    def moved(self) -> None:
        """The user moves the camera or light (interactive quality applies)."""
        self.last_motion = time.perf_counter()
        self.redraw()

    def interacting(self, now: float) -> bool:
        """A drag is in progress, or the camera or light moved less than `MOTION_S` ago."""
        return self.drag is not None or now - self.last_motion < MOTION_S

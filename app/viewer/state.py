"""The viewer's state: what the user controls and what asks for the next frame.

Data flows one way: input (`app.viewer.input`) → actions (`app.viewer.actions`) →
`ViewerState` → drawing (`app.viewer.draw`) and the loop (`app.viewer.window`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

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
    panel_rect: tuple[float, float, float, float] | None = None
    panel_frames: int = 0
    message: str = ""
    quit: bool = False
    dirty: bool = True
    lattice_changed: bool = False
    last_input: float = 0.0
    last_motion: float = 0.0
    drag: Drag | None = None

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

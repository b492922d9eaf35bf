"""What the user can do in the viewer: change the isovalue, shading mode, exposure, light
and camera, take screenshots, save the view and the lattice, hold the lazy bake.

Keys and drags (`app.viewer.input`), the panel's `app.viewer.panel.Action`s (`Actions.apply`)
and scripts (`Actions` is the `app.viewer.script.ScriptTarget`) all end here; the methods
change the `app.viewer.state.ViewerState` and ask the collaborators that own the rest: the
surface feed (`app.viewer.surfaces.SurfaceFeed`), the lattice and its lazy bake
(`app.viewer.illumination.Illumination`) and the files (`app.viewer.saving.Saver`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from isolume import volumes
from isolume.app.viewer.draw import Drawing
from isolume.app.viewer.illumination import Illumination
from isolume.app.viewer.panel import (
    ROTATE_DEG_PER_PX,
    Action,
    orbit,
    pan,
    pan_per_pixel,
    zoom,
)
from isolume.app.viewer.saving import Saver
from isolume.app.viewer.state import ViewerError, ViewerState
from isolume.app.viewer.surfaces import SurfaceFeed
from isolume.volumes.errors import WriteError

ISO_STEPS = 1000
"""A fine isovalue step is 1/ISO_STEPS of the data range (shift: ×10)."""
EXPOSURE_RANGE = (1e-3, 1e3)
"""Allowed linear exposure multipliers."""


def check_mode(drawing: Drawing, mode: str) -> None:
    """Raise `ViewerError` (one line, saying what is missing) unless `drawing` can draw
    the shading `mode` now: the reason is the renderer's (`SurfaceRenderer.check_mode`:
    the lattice's kind, the sky and bounces an occlusion lattice is baked with, ...)."""
    modes = drawing.modes
    if mode not in modes:
        raise ViewerError(f"unknown shading mode {mode!r}; expected one of "
                          f"{', '.join(modes)}")
    if mode in drawing.usable_modes():
        return
    lattice = drawing.renderer.lattice
    if lattice is None:
        raise ViewerError(f"shading {mode!r} needs a lattice: pass --lattice FILE, or "
                          "leave out --no-bake to bake one lazily")
    try:
        drawing.renderer.check_mode(mode)
    except ValueError as exc:
        raise ViewerError(f"shading {mode!r} cannot be drawn from the {lattice.kind} "
                          f"lattice shown: {exc}{_kind_hint(mode, lattice.kind)}") from None


def _kind_hint(mode: str, kind: str) -> str:
    """How the lazy bake makes the kind of lattice `mode` reads when the one shown is of
    another `kind` ("" when it is of that kind: its bake settings are what differ)."""
    from isolume.app.render.settings import LATTICE_MODES

    want = LATTICE_MODES[mode].lattice_kind
    return "" if want == kind else f" (a lazy bake makes one with --bake-mode {want})"


class Actions:
    """The viewer's public interface (`app.viewer.script.ScriptTarget`): requests change
    the state; problems raise `ViewerError` (a `ValueError`)."""

    volume: volumes.Volume
    state: ViewerState
    drawing: Drawing
    surfaces: SurfaceFeed
    illumination: Illumination
    saver: Saver

    def __init__(self, volume: volumes.Volume, state: ViewerState, drawing: Drawing,
                 surfaces: SurfaceFeed, illumination: Illumination, saver: Saver) -> None:
        self.volume, self.state, self.drawing = volume, state, drawing
        self.surfaces, self.illumination, self.saver = surfaces, illumination, saver

    # -- the surface and its shading -----------------------------------------------------
    def redraw(self) -> None:
        """Something on screen changed: draw again."""
        self.state.redraw()

    def request_iso(self, iso: float) -> None:
        """Show the isosurface at `iso` (clamped inside the data range)."""
        lo, hi = self.volume.value_range
        eps = 1e-6 * (hi - lo)
        iso = float(np.clip(iso, lo + eps, hi - eps))
        self.state.view.iso = iso
        self.surfaces.request(iso)
        self.redraw()

    def step_iso(self, steps: int) -> None:
        """Move the isovalue by `steps` fine steps (`ISO_STEPS`)."""
        lo, hi = self.volume.value_range
        self.request_iso(self.state.view.iso + steps * (hi - lo) / ISO_STEPS)

    def set_mode(self, mode: str) -> None:
        """Shade with `mode` (`check_mode`)."""
        check_mode(self.drawing, mode)
        self.drawing.ensure_texel_isovalues(mode)
        self.state.view.shading = mode
        self.redraw()

    def set_exposure(self, exposure: float) -> None:
        """Linear exposure multiplier, clamped to `EXPOSURE_RANGE`."""
        self.state.view.exposure = float(np.clip(exposure, *EXPOSURE_RANGE))
        self.redraw()

    # -- light and camera ----------------------------------------------------------------
    def set_light(self, angles: tuple[float, float] | None, moving: bool = False) -> None:
        """World-fixed light at (azimuth, elevation) degrees, or None: fixed to the camera;
        `moving`: as a drag does (interactive quality applies)."""
        self.state.view.light = None if angles is None else (float(angles[0]) % 360.0,
                                                             float(angles[1]))
        if moving:
            self.state.moved()
        self.redraw()

    def light_angles(self) -> tuple[float, float]:
        """(azimuth, elevation) degrees of the light as drawn now (also when it follows
        the camera)."""
        return self.drawing.light_angles(self.state.view, self.state.camera)

    def move_camera(self, how: str, a: float, b: float = 0.0) -> None:
        """Move the camera as a drag would: "orbit" by (a, b) degrees of azimuth and
        elevation, "zoom" closer by the factor a, "pan" by (a, b) diagonals."""
        moves = {"orbit": lambda c: orbit(c, a, b), "zoom": lambda c: zoom(c, a),
                 "pan": lambda c: pan(c, a, b)}
        self.state.camera = moves[how](self.state.camera)
        self.state.moved()

    def drag(self, target: str, dx: float, dy: float, height_px: float) -> None:
        """Move what a drag of the pointer by (dx, dy) pixels moves (`target`, from
        `app.viewer.panel.drag_target`): "rotate" orbits the camera, "pan" pans it (a
        picture `height_px` pixels high), "light" turns the light, its elevation kept
        within ±90°."""
        if target == "rotate":
            self.move_camera("orbit", -dx * ROTATE_DEG_PER_PX, dy * ROTATE_DEG_PER_PX)
        elif target == "pan":
            k = pan_per_pixel(self.state.camera, height_px)
            self.move_camera("pan", -dx * k, dy * k)
        elif target == "light":
            az, el = self.light_angles()
            self.set_light((az + dx * ROTATE_DEG_PER_PX,
                            float(np.clip(el - dy * ROTATE_DEG_PER_PX, -90, 90))), moving=True)

    def reset_camera(self) -> None:
        """Back to the home camera (the first surface framed)."""
        self.state.camera = self.state.home
        self.redraw()

    def request_quit(self) -> None:
        self.state.quit = True

    # -- panel and keys ------------------------------------------------------------------
    def apply(self, action: Action) -> None:
        """Apply an `app.viewer.panel.Action` (from the panel or a key); problems become
        the status message."""
        name, value = action.name, action.value
        if name == "panel_rect":  # where the panel is (window units), for framing
            self.state.panel_rect = value
            self.state.panel_frames += 1
            return
        view = self.state.view
        simple = {
            "iso": lambda: self.request_iso(value),
            "iso_step": lambda: self.step_iso(value),
            "mode": lambda: self.set_mode(value),
            "exposure": lambda: self.set_exposure(value),
            "exposure_by": lambda: self.set_exposure(view.exposure * value),
            "light": lambda: self.set_light(value),
            "light_camera": lambda: self.set_light(None if value else self.light_angles()),
            "toggle_light": lambda: self.set_light(
                None if view.light is not None else self.light_angles()),
            "reset_camera": self.reset_camera,
            "screenshot": self.screenshot,
            "save_view": self.save_view,
            "save_lattice": self.save_lattice,
            "pause_bake": lambda: self.illumination.pause(value),
            "toggle_bake": lambda: self.illumination.toggle_pause(),
            "toggle_ui": lambda: setattr(view, "show_ui", not view.show_ui),
            "quit": self.request_quit,
        }
        try:
            simple[name]()
        except (ViewerError, WriteError, OSError) as exc:  # said in the window
            self.state.message = str(exc)
        self.redraw()

    # -- files ---------------------------------------------------------------------------
    def screenshot(self, path: str | os.PathLike[str] | None = None) -> tuple[Path, Path]:
        """Write the view as PNG and EXR (`app.viewer.saving.Saver.screenshot`)."""
        return self.saver.screenshot(path)

    def window_pixels(self) -> np.ndarray:
        """(H, W, 3) uint8 of the window's back buffer, top row first (UI included)."""
        return self.saver.window_pixels()

    def save_view(self, path: str | os.PathLike[str] | None = None) -> Path:
        """Write what is on screen as a state file (`app.viewer.saving.Saver.save_view`)."""
        return self.saver.save_view(path)

    def save_lattice(self, path: str | os.PathLike[str] | None = None) -> Path | None:
        """Write the lattice (`app.viewer.saving.Saver.save_lattice`)."""
        return self.saver.save_lattice(path)

    # -- what scripts wait for -----------------------------------------------------------
    def surface_ready(self) -> bool:
        """The full-resolution surface of the requested isovalue is on screen, the camera
        framing the first surface (`Viewer._frame_first_surface`) where there is one."""
        shown = any(not m.empty for m in self.drawing.meshes.values())
        return self.surfaces.ready(self.state.view.iso) and (self.state.framed or not shown)

    def gi_shown(self) -> bool:
        """Global illumination of the displayed isovalue is on screen
        (`app.viewer.illumination.Illumination.gi_shown`)."""
        return self.illumination.gi_shown()

    def bake_progress(self) -> tuple[float | None, str | None]:
        """The lazy bake's progress near the surface
        (`app.viewer.illumination.Illumination.bake_progress`)."""
        return self.illumination.bake_progress()

    def relit_progress(self) -> tuple[float | None, str | None]:
        """The lazy bake's progress on the turned light
        (`app.viewer.illumination.Illumination.relit_progress`)."""
        return self.illumination.relit_progress()

    def hold_bake(self, held: bool) -> None:
        """Pause (True) or resume the lazy bake, if one runs; `bake_held` says when the
        process has stopped writing."""
        self.illumination.hold(held)

    def bake_held(self) -> bool:
        """No lazy bake writes texels now (none runs, or it acknowledged a pause)."""
        return self.illumination.held()

    def check_lattice(self) -> dict[str, Any]:
        """Compare the GL textures with the lattice
        (`app.viewer.illumination.Illumination.check`)."""
        return self.illumination.check()

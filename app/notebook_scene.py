"""The picture behind `isolume.show`'s notebook widget, without the widget: frames drawn
off-screen into arrays.

`NotebookScene` holds a headless OpenGL context (`open_context`: EGL, else OSMesa) and the
desktop viewer's parts below its window: the drawing (`app.viewer.draw.Drawing`), the
isosurfaces extracted off the kernel's thread (`app.viewer.surfaces.SurfaceFeed`), the
lattice and its lazy bake in a separate process (`app.viewer.illumination.Illumination`)
and what the user can do (`app.viewer.actions.Actions`). `step` takes what the workers
delivered, `render` draws a frame and reads it back; `app.notebook_view.NotebookView`
streams those frames to the browser.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.app.render.glcontext import GLUnavailable, HeadlessContext
from isolume.app.viewer.command import Options

if TYPE_CHECKING:
    import moderngl

    from isolume.app.viewer.actions import Actions
    from isolume.app.viewer.draw import Drawing
    from isolume.app.viewer.illumination import Illumination
    from isolume.app.viewer.state import ViewerState
    from isolume.app.viewer.surfaces import SurfaceFeed
    from isolume.baking.view_texels import LatticeOnFile

SURFACE_TIMEOUT_S = 60.0
"""The longest `NotebookScene.wait_surface` waits for a surface (seconds)."""


def open_context(backend: str = "auto") -> HeadlessContext:
    """A headless OpenGL 3.3 context for the notebook (`create_headless`: "auto" tries
    EGL, then OSMesa; "egl" or "osmesa" only that one).

    Raises:
        GLUnavailable: neither works (macOS has neither: Apple ships no EGL, and Mesa's
            OSMesa is not installed there); one line naming the desktop viewer instead.
    """
    from isolume.app.render.glcontext import create_headless

    try:
        return create_headless(backend)
    except GLUnavailable as exc:
        raise GLUnavailable(
            f"isolume.show draws off-screen with EGL or OSMesa (Mesa's headless OpenGL, on "
            f"Linux), which is unavailable here ({' '.join(str(exc).split())}); on macOS "
            "or Windows use the desktop viewer, isolume view") from None


class NotebookScene:
    """The viewer's parts on an off-screen context (see the module docstring).

    Attributes:
        gl: the headless context (None once closed).
        volume, options: what is shown, and the `isolume view` options it is shown with.
        state: what the user controls (`app.viewer.state.ViewerState`).
        drawing, surfaces, illumination, actions: the viewer's parts.
        reduced: the last frame had less detail than there is (one more frame is due once
            the motion stops).
        last_end, last_frame_s: `time.perf_counter` at the end of the last frame, and its
            duration in seconds (None before the first).
    """

    volume: volumes.Volume
    options: Options
    temporary: Path | None
    drawing: Drawing | None
    surfaces: SurfaceFeed | None
    illumination: Illumination | None
    state: ViewerState
    actions: Actions

    def __init__(self, volume: volumes.Volume, iso: float, lattice: LatticeOnFile | None,
                 options: Options, gl: str = "auto", temporary: Path | None = None) -> None:
        """`lattice`: a lattice file opened (`baking.view_texels.LatticeOnFile`) or None;
        `gl`: the context's backend (`open_context`); `temporary`: a file `close`
        deletes (`lattice`'s, written for the view)."""
        self.gl: HeadlessContext | None = open_context(gl)
        self.volume, self.options, self.temporary = volume, options, temporary
        self.reduced: bool = False
        self.last_end: float | None = None
        self.last_frame_s: float | None = None
        self._target = None  # the picture's framebuffer (`picture_target`), of its size
        self.drawing = self.surfaces = self.illumination = None
        try:
            self._build(iso, lattice)
        except BaseException:
            self._free(stop=True)
            raise

    def _build(self, iso: float, lattice: LatticeOnFile | None) -> None:
        """Make the parts, as `app.viewer.window.Viewer` does, without a window."""
        from isolume.app.render.renderer import default_camera
        from isolume.app.viewer.actions import Actions, check_mode
        from isolume.app.viewer.draw import Drawing, ViewState
        from isolume.app.viewer.illumination import Illumination
        from isolume.app.viewer.saving import Saver
        from isolume.app.viewer.state import ViewerState
        from isolume.app.viewer.surfaces import SurfaceFeed

        volume, options = self.volume, self.options
        self.drawing = Drawing(self.gl.ctx, volume, options.auto_exposure)
        home = default_camera(volume)
        self.state = ViewerState(ViewState(iso, "phong_hemi", options.exposure, options.light),
                                 home, home)
        self.illumination = Illumination(volume, self.drawing, self.state, options)
        self.surfaces = SurfaceFeed(volume, normals=options.normals, flip=options.flip_normals)
        saver = Saver(volume, None, self.drawing, self.state, self.illumination, options)
        self.actions = Actions(volume, self.state, self.drawing, self.surfaces,
                               self.illumination, saver)
        self.illumination.start(lattice, iso)
        shown = self.drawing.renderer.lattice  # the default shading follows the lattice
        shading = options.shading or (shown.kind if shown else "phong_hemi")
        check_mode(self.drawing, shading)
        self.drawing.ensure_texel_isovalues(shading)
        self.state.view.shading = shading
        self.actions.request_iso(iso)

    # -- what arrived --------------------------------------------------------------------
    def step(self, size: tuple[int, int]) -> None:
        """Take the surfaces and lazily baked texels that arrived (the first surface framed
        in a picture of `size` (W, H) pixels), and tell the bake what a frame of `size`
        shows once the view has settled."""
        self.gl.make_current()
        self._receive_surfaces()
        self._frame_first_surface(size)
        self.illumination.receive()
        self.illumination.update_view(self.surfaces.stage_at(self.state.view.iso), size)

    def _receive_surfaces(self) -> None:
        """Hand the surfaces the worker made to the drawing and the GPU
        (`app.viewer.surfaces.hand_over`, as the viewer's loop does: the bake's view of
        the visible texels is read from the surface there, also while no frame is
        drawn)."""
        from isolume.app.viewer.surfaces import hand_over

        hand_over(self.surfaces, self.drawing, self.state)

    def frame_due(self, now: float) -> bool:
        """Whether a frame should be drawn at `now` (`time.perf_counter`): something
        changed, the exposure is still adapting, full detail is owed after a motion, or
        baked texels arrived and the viewer's pacing lets them show
        (`app.viewer.window.bake_frame_due`)."""
        from isolume.app.viewer.window import bake_frame_due

        state = self.state
        settle = self.reduced and not state.interacting(now)
        baked = state.lattice_changed and bake_frame_due(now, self.last_end, self.last_frame_s)
        return state.dirty or settle or self.drawing.adapting or baked

    def wait_surface(self, size: tuple[int, int], timeout: float = SURFACE_TIMEOUT_S) -> None:
        """Wait until the full-resolution surface of the requested isovalue has arrived.

        Raises:
            IsolumeError: it did not within `timeout` seconds.
        """
        from isolume.volumes.errors import IsolumeError

        deadline = time.perf_counter() + timeout
        while True:
            self.step(size)
            if self.surfaces.ready(self.state.view.iso):
                return
            if time.perf_counter() > deadline:
                raise IsolumeError(f"no surface at isovalue {self.state.view.iso:g} after "
                                   f"{timeout:g} s")
            time.sleep(0.01)

    # -- frames --------------------------------------------------------------------------
    def render(self, size: tuple[int, int], interacting: bool = False) -> np.ndarray:
        """Draw a frame of `size` (W, H) pixels and read it back: (H, W, 3) uint8 sRGB,
        top row first. While `interacting`, with the viewer's reduced detail (the preview
        surface, then fewer pixels: the array is then smaller than `size`, and the
        browser scales it up)."""
        start = time.perf_counter()
        self.gl.make_current()
        drawing = self.drawing
        drawing.sync_mesh(preview=(interacting and drawing.quality.coarse) or self._heavy_wait())
        scale = drawing.quality.scale if interacting else 1.0
        small = (max(1, round(size[0] * scale)), max(1, round(size[1] * scale)))
        if self._target is None or self._target.size != small:
            self._target = picture_target(self.gl.ctx, small, self._target)
        pixels = self._draw_or_fall_back(small)
        end = time.perf_counter()
        if interacting:
            full = drawing.meshes.get("full")
            drawing.quality.adapt(1000 * (end - start), len(full.faces) if full else 0)
        self.reduced = (interacting and scale < 1) or (drawing.on_gpu == "coarse"
                                                       and "full" in drawing.meshes)
        self.last_end, self.last_frame_s = end, end - start
        self.state.dirty = self.state.lattice_changed = False
        return pixels

    def _heavy_wait(self) -> bool:
        """A new surface is being extracted and the full one shown is big: draw the
        preview meanwhile (`app.viewer.window.Viewer._heavy_wait`)."""
        from isolume.app.viewer.draw import PREVIEW_TRIANGLES

        full = self.drawing.meshes.get("full")
        return self.surfaces.pending and full is not None and len(full.faces) > PREVIEW_TRIANGLES

    def _draw_or_fall_back(self, size: tuple[int, int]) -> np.ndarray:
        """Draw a frame of `size` (W, H) into the picture's framebuffer as the viewer draws
        its window (`Drawing.draw`, the smoothly adapting automatic exposure included) and
        read it back: (H, W, 3) uint8 sRGB, top row first. A shading mode that lacks what
        it needs falls back to phong_hemi, with a message (as in the viewer)."""
        state = self.state
        try:
            self._draw(size)
        except ValueError as exc:  # app.render.settings.RenderError
            state.message = f"shading {state.view.shading!r}: {exc}; back to phong_hemi"
            state.view.shading = "phong_hemi"
            self._draw(size)
        w, h = size
        data = np.frombuffer(self._target.read(components=3), np.uint8).reshape(h, w, 3)
        return np.ascontiguousarray(data[::-1])

    def _draw(self, size: tuple[int, int]) -> None:
        """`Drawing.draw` at `size` (W, H) into the picture's framebuffer."""
        state = self.state
        self.drawing.draw(state.camera, state.view, size, 1.0, target=self._target)

    def _frame_first_surface(self, size: tuple[int, int]) -> None:
        """Aim the camera at the first surface that arrives (its vertices, framed in a
        picture of `size`), unless it was moved already; that view becomes the home."""
        from isolume.app.render.camera import frame_points
        from isolume.volumes.mesh import LEVEL_POINTS

        state = self.state
        meshes = [m for m in self.drawing.meshes.values() if not m.empty]
        if state.framed or not meshes:
            return
        vertices = meshes[0].vertices
        points = vertices[::-(-len(vertices) // LEVEL_POINTS)]
        home = frame_points(state.home, points, size[0] / max(size[1], 1))
        if state.camera == state.home:
            state.camera = home
        state.home, state.framed = home, True

    # -- the end -------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the extraction thread and the bake process, save the lattice to its file
        when one was named and baked into, free the shared lattice and the GL context,
        delete the temporary lattice file. Idempotent."""
        if self.gl is None:
            return
        self.surfaces.close()
        self.illumination.stop()
        try:
            path = self.options.lattice_path
            if path is not None and self.illumination.shared is not None \
                    and not self.illumination.relit_file:
                self.actions.save_lattice(path)
        finally:
            self._free(stop=False)

    def _free(self, stop: bool) -> None:
        """Free every part made so far (with `stop`, first stop the extraction thread and
        the bake process: after a failed start), then the GL context; delete the
        temporary lattice file."""
        if stop and self.surfaces is not None:
            self.surfaces.close()
        if stop and self.illumination is not None:
            self.illumination.stop()
        if self.illumination is not None:
            self.illumination.close()
        self.gl.make_current()
        if self.drawing is not None:
            self.drawing.release()
        if self._target is not None:
            release_target(self._target)
        self.gl.release()
        self.gl = None
        if self.temporary is not None:
            self.temporary.unlink(missing_ok=True)


def picture_target(ctx: moderngl.Context, size: tuple[int, int],
                   old: moderngl.Framebuffer | None = None) -> moderngl.Framebuffer:
    """An off-screen RGBA8 framebuffer of `size` (W, H) in the context `ctx`, which the
    viewer's `app.viewer.draw.Drawing` draws the picture into (a window's would be its
    default framebuffer); `old`, the previous one, is released (`release_target`)."""
    target = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, 4)])
    if old is not None:
        release_target(old)
    return target


def release_target(target: moderngl.Framebuffer) -> None:
    """Free a `picture_target` framebuffer and its colour buffer."""
    for attachment in target.color_attachments:
        attachment.release()
    target.release()

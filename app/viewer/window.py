"""``isolume view``: the command's entry point (`run`), the window and the main loop.

One render thread owns the window, the GL context and the UI; the slow work happens
elsewhere so that the window never freezes. `Viewer` builds the parts and runs the loop
that ties them together (events, surfaces, bake, script, frames, paced); each part has one
job:

* `app.viewer.command`: the command line (``HELP``, `add_arguments`, `Options`);
* `app.viewer.input`: mouse and keyboard, the UI first (Dear ImGui via `app.viewer.panel`),
  then the camera, light and keys;
* `app.viewer.actions`: what the user can do; keys, panel and scripts all end there;
* `app.viewer.state`: what the user controls and what asks for a frame;
* `app.viewer.surfaces`: isosurfaces off the render thread (`MeshWorker`: a coarse surface
  first, then the full one, in slabs that a newer request cancels; `SurfaceFeed`);
* `app.viewer.illumination`: the lattice shown and its lazy bake (`app.viewer.bake_client`:
  `BakeLink` to a separate process that bakes the texels around the displayed surface,
  into a `SharedLattice`);
* `app.viewer.draw`: the drawing and the lighting (`Drawing`: the surface and lattice on
  the GPU, re-uploads of baked texels, the light, the detail while moving). Texels not
  computed yet fall back to local shading (tinted);
* `app.viewer.saving`: screenshots, saved views (`app.state`), the lattice and ``--stats``
  on disk;
* `app.viewer.script`: ``--script`` drives the viewer without a person, through
  `app.viewer.actions.Actions` (the `app.viewer.script.ScriptTarget` protocol).

`app.cli` takes the command from this module (``HELP`` and `add_arguments`, re-exported
from `app.viewer.command`, and `run`).
"""

from __future__ import annotations

import sys
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume import volumes
from isolume.app.viewer.actions import Actions, check_mode
from isolume.app.viewer.command import HELP as HELP
from isolume.app.viewer.command import Options, read_options, script_commands
from isolume.app.viewer.command import add_arguments as add_arguments
from isolume.app.viewer.draw import PREVIEW_TRIANGLES, Drawing, ViewState, frame_size
from isolume.app.viewer.illumination import Illumination
from isolume.app.viewer.input import Input
from isolume.app.viewer.saving import Saver, write_json
from isolume.app.viewer.state import ViewerError, ViewerState
from isolume.app.viewer.surfaces import SurfaceFeed, hand_over
from isolume.volumes import cores

if TYPE_CHECKING:
    import argparse

    from isolume.app.render.glcontext import Window
    from isolume.app.viewer.panel import ImGuiLayer
    from isolume.app.viewer.script import ScriptRunner
    from isolume.baking.view_texels import LatticeOnFile

BAKE_REFRESH_S = 0.5
BAKE_FRAME_SPACING = 4.0
"""New texels alone bring a frame at most every `BAKE_REFRESH_S` seconds and no sooner than
`BAKE_FRAME_SPACING` frame times after the last one (`bake_frame_due`)."""


# -- the command --------------------------------------------------------------------------
def run(args: argparse.Namespace) -> int:
    """Entry point of ``isolume view``: bad input ends in one line on stderr, status 2.

    (The errors are reported here rather than by `app.cli.main`: under ``python -m isolume.app.cli``
    that module runs as ``__main__`` and its `CLIError` is not the one this module sees.)
    """
    from isolume.app.options import EXIT_USER_ERROR, CLIError
    from isolume.app.viewer.script import ScriptError

    try:
        return _run(args)
    except (CLIError, ScriptError, ViewerError) as exc:
        print(f"isolume: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return EXIT_USER_ERROR


def _run(args: argparse.Namespace) -> int:
    from isolume.app.options import EXIT_INTERRUPTED, isovalue, load_volume

    options = read_options(args)
    volume = load_volume(args)
    cores.stage("surface")  # --timeline: until the first surface is drawn
    iso = isovalue(volume, args.iso)
    lattice = None
    if options.lattice_path is not None and options.lattice_path.exists():
        from isolume.baking.view_texels import LatticeOnFile

        lattice = LatticeOnFile.open(options.lattice_path, volume)
    from isolume.app.render.settings import LATTICE_MODES

    if options.shading in LATTICE_MODES and lattice is None and not options.bake:
        raise ViewerError(f"--shading {options.shading} needs a lattice: pass --lattice FILE, or "
                          "leave out --no-bake to bake one lazily")

    viewer = Viewer(volume, iso, lattice, options)
    try:
        return viewer.run()
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    finally:
        viewer.close()


# -- frame pacing -------------------------------------------------------------------------
@dataclass
class FrameClock:
    """Frame times of the render thread."""

    times: deque[float] = field(default_factory=lambda: deque(maxlen=120))
    all_ms: list[float] = field(default_factory=list)
    interactive_ms: list[float] = field(default_factory=list)
    last_end: float | None = None
    count: int = 0

    def add(self, start: float, end: float) -> None:
        self.times.append(end - start)
        self.all_ms.append(1000 * (end - start))
        self.last_end = end
        self.count += 1

    @property
    def mean_ms(self) -> float:
        return 1000 * float(np.mean(self.times)) if self.times else 0.0


def bake_frame_due(now: float, last_end: float | None, last_frame_s: float | None) -> bool:
    """Whether texels that arrived from the lazy bake may be shown now (seconds of
    `time.perf_counter`): at least `BAKE_REFRESH_S` after the last frame ended, and no
    sooner than `BAKE_FRAME_SPACING` times its duration, so that drawing takes at most a
    1 / (1 + spacing) share of the time (software GL at 1024×700 with the sun's soft
    shadows takes 0.4–1 s a frame; redrawn for every upload, the bake process — at idle
    priority — got a tenth of a core and planned CThead in 14 s, not 1.4)."""
    if last_end is None or last_frame_s is None:
        return True
    return now - last_end >= max(BAKE_REFRESH_S, BAKE_FRAME_SPACING * last_frame_s)


# -- the viewer ---------------------------------------------------------------------------
class Viewer:
    """The interactive viewer: it builds the window and the parts (see the module
    docstring) and runs the loop.

    Attributes:
        state: what the user controls (`app.viewer.state.ViewerState`).
        actions: what the user can do; the target of scripts.
        drawing, surfaces, illumination, saver, input: the parts.
        ui: the control panel (None: ``--no-ui``, or imgui-bundle missing).
        clock: frame times; reduced: the last frame had less detail than there is.
    """

    volume: volumes.Volume
    options: Options
    window: Window
    drawing: Drawing
    ui: ImGuiLayer | None
    state: ViewerState
    illumination: Illumination
    surfaces: SurfaceFeed
    saver: Saver
    actions: Actions
    reduced: bool
    clock: FrameClock
    surface_shown: bool
    script: ScriptRunner
    input: Input

    def __init__(self, volume: volumes.Volume, iso: float, lattice: LatticeOnFile | None,
                 options: Options) -> None:
        from isolume.app.render.glcontext import create_window
        from isolume.app.render.renderer import default_camera
        from isolume.app.viewer.script import ScriptRunner

        self.volume, self.options = volume, options
        self.window = create_window(options.size, f"isolume — {volume.name}")
        self.drawing = Drawing(self.window.ctx, volume, options.auto_exposure)
        home = options.camera or default_camera(volume)
        self.ui = self._make_ui() if options.ui else None
        self.state = ViewerState(ViewState(iso, "phong_hemi", options.exposure, options.light),
                                 home, home)
        self.illumination = Illumination(volume, self.drawing, self.state, options)
        self.illumination.start(lattice, iso)
        shown = self.drawing.renderer.lattice  # the default shading follows the lattice
        shading = options.shading or (shown.kind if shown else "phong_hemi")
        self.state.view.shading = shading
        check_mode(self.drawing, shading)
        self.drawing.ensure_texel_isovalues(shading)
        self.surfaces = SurfaceFeed(volume, normals=options.normals, flip=options.flip_normals)
        self.saver = Saver(volume, self.window, self.drawing, self.state, self.illumination,
                           options)
        self.actions = Actions(volume, self.state, self.drawing, self.surfaces,
                               self.illumination, self.saver)
        self.reduced = False
        self.clock = FrameClock()
        self.surface_shown = False  # --timeline: "draw" begins with the first surface
        self.script = ScriptRunner(script_commands(options))
        self.input = Input(self.window, self.ui, self.state, self.actions, self.drawing.modes)
        self.actions.request_iso(iso)

    def _make_ui(self) -> ImGuiLayer | None:
        from isolume.app.viewer.panel import ImGuiLayer

        try:
            return ImGuiLayer(self.window.glfw, self.window.ui_scale)
        except ImportError:
            print("isolume: note: imgui-bundle is not installed; no control panel "
                  "(pip install imgui-bundle)", file=sys.stderr)
        except RuntimeError as exc:
            print(f"isolume: note: {exc}; no control panel", file=sys.stderr)
        return None

    # -- the loop ------------------------------------------------------------------------
    def run(self) -> int:
        """Run until the window closes, `quit`, or the script/--frames ends it."""
        glfw, state = self.window.glfw, self.state
        while not (state.quit or self.window.should_close()):
            if self._wants_frame():
                glfw.poll_events()
            else:
                glfw.wait_events_timeout(0.03)
            self._receive_surfaces()
            self.illumination.receive()
            self.script.step(self.actions)
            self.illumination.update_view(self.surfaces.stage_at(state.view.iso),
                                          frame_size(self.window))
            if self._wants_frame():
                self.draw_frame()
                self._pace()
        return 0

    def _pace(self) -> None:
        """While a surface is extracted, leave the worker at least a third of the time
        (drawing holds the GIL; waiting for events does not)."""
        if self.surfaces.pending and self.clock.times:
            self.window.glfw.wait_events_timeout(min(0.5 * self.clock.times[-1], 0.05))

    def _wants_frame(self) -> bool:
        now, state = time.perf_counter(), self.state
        recent_input = now - state.last_input < 0.25
        settle = self.reduced and not state.interacting(now)  # one full-detail frame
        return (state.dirty or recent_input or settle or self.script.forces_frames
                or self.drawing.adapting or (state.lattice_changed and self._bake_frame_due(now)))

    def _bake_frame_due(self, now: float) -> bool:
        last = self.clock.times[-1] if self.clock.times else None
        return bake_frame_due(now, self.clock.last_end, last)

    def draw_frame(self) -> None:
        """Draw the scene and the panel, swap, and account the frame."""
        start = time.perf_counter()
        state = self.state
        w, h = self.window.framebuffer_size
        if w == 0 or h == 0:  # minimised
            state.dirty = False
            return
        if self.input.ui_shown:
            self._run_panel((w, h), start)
        self._frame_first_surface()
        interacting = state.interacting(start)
        drawing = self.drawing
        drawing.sync_mesh(preview=(interacting and drawing.quality.coarse)
                          or self._heavy_wait())
        scale = drawing.quality.scale if interacting else 1.0
        try:
            drawing.draw(state.camera, state.view, (w, h), scale)
        except ValueError as exc:  # app.render.settings.RenderError: a mode without what it needs
            state.message = f"shading {state.view.shading!r}: {exc}; back to phong_hemi"
            state.view.shading = "phong_hemi"
            drawing.draw(state.camera, state.view, (w, h), scale)
        if self.input.ui_shown:
            self.ui.render()
        self.script.before_swap(self.actions)
        self.window.swap()
        end = time.perf_counter()
        self._account_frame(start, end)
        if interacting:
            full = drawing.meshes.get("full")
            drawing.quality.adapt(1000 * (end - start), len(full.faces) if full else 0)
            self.clock.interactive_ms.append(1000 * (end - start))
        # drawn with less detail than there is: one more frame once the motion stops
        self.reduced = (interacting and scale < 1) or (drawing.on_gpu == "coarse"
                                                       and "full" in drawing.meshes)
        state.dirty = state.lattice_changed = False

    def _run_panel(self, size: tuple[int, int], now: float) -> None:
        """Start the UI's frame, then lay out the panel and apply what the user did in it."""
        from isolume.app.viewer.panel import draw_panel

        self.ui.new_frame(self.window.window_size, size, now)
        self.input.confirm_press()
        for action in draw_panel(self.ui.imgui, self._panel_model()):
            self.actions.apply(action)

    def _heavy_wait(self) -> bool:
        """A new surface is being extracted and the full one on screen is big: show the
        preview meanwhile (software GL holds the GIL while it draws, which would starve
        the extraction)."""
        full = self.drawing.meshes.get("full")
        return self.surfaces.pending and full is not None and len(full.faces) > PREVIEW_TRIANGLES

    def _account_frame(self, start: float, end: float) -> None:
        previous = self.clock.last_end
        self.clock.add(start, end)
        extractions = self.surfaces.extractions
        pending = extractions[-1] if extractions else None
        if pending is not None and pending.full_s is None:
            pending.frames += 1
            if previous is not None and previous >= pending.requested:
                pending.max_gap_ms = max(pending.max_gap_ms, 1000 * (end - previous))
        self.script.frame_done()

    def _receive_surfaces(self) -> None:
        """Hand the surfaces that arrived to the drawing (`surfaces.hand_over`); the
        timeline's "draw" begins with the first one."""
        if hand_over(self.surfaces, self.drawing, self.state) and not self.surface_shown:
            self.surface_shown = True
            cores.stage("draw")

    def _frame_first_surface(self) -> None:
        """Aim the camera at the first surface (its vertices), in the part of the window
        the panel leaves free (once the panel has its size; the whole window while it is
        folded to its title bar), or move a saved view's camera (framed in the whole
        window) there; that view becomes the one `R` returns to. A camera the user (or a
        script) has moved already stays where it is."""
        from isolume.app.render.camera import frame_points
        from isolume.app.viewer.panel import MAX_PANEL_WIDTH, room_beside
        from isolume.volumes.mesh import LEVEL_POINTS

        state, shown = self.state, self.input.ui_shown
        meshes = [m for m in self.drawing.meshes.values() if not m.empty]
        if state.framed or not meshes or (shown and state.panel_frames < 2):
            return
        mesh = meshes[0]
        w, h = self.window.window_size
        left = 0.0
        if shown and state.panel_rect is not None and not self.ui.panel_folded:
            x, _, width, _ = state.panel_rect
            left = min(max(room_beside(x + width, w), 0.0), MAX_PANEL_WIDTH)
        points = mesh.vertices[::-(-len(mesh.vertices) // LEVEL_POINTS)]
        beside = frame_points(state.home, points, w / max(h, 1), (left, 1.0))
        whole = frame_points(state.home, points, w / max(h, 1))
        state.panel_shift = (beside.pan[0] / beside.distance, whole.distance / beside.distance)
        home = beside if self.options.camera is None else state.beside_panel(state.home)
        if state.camera == state.home:
            state.camera = home
        state.home, state.framed = home, True

    # -- panel ---------------------------------------------------------------------------
    def _panel_model(self):
        from isolume.app.viewer.panel import PanelModel

        z, y, x = self.volume.data.shape
        view, illumination = self.state.view, self.illumination
        fractions, lines = illumination.status()
        return PanelModel(
            title=f"{self.volume.name}  {x}x{y}x{z}", iso=view.iso,
            iso_range=self.volume.value_range, mesh_status=self.surfaces.info,
            modes=self.drawing.modes, enabled=self.drawing.usable_modes(),
            mode=view.shading, exposure=view.exposure,
            light=view.light, light_note=illumination.light_note(), bake_lines=lines,
            auto_exposure=self.drawing.auto if self.drawing.auto_exposure else None,
            bake_fractions=fractions, bake_paused=illumination.paused,
            can_bake=illumination.bake is not None, can_save=illumination.shared is not None,
            frame_ms=self.clock.mean_ms, size=frame_size(self.window),
            message=self.state.message,
        )

    # -- figures and shutdown ------------------------------------------------------------
    def figures(self) -> dict[str, Any]:
        """What `--stats` writes."""
        times = np.array(self.clock.all_ms) if self.clock.all_ms else np.zeros(1)
        cam = self.state.camera
        state = asdict(self.state.view) | {"camera": {
            "azimuth": cam.azimuth, "elevation": cam.elevation, "distance": cam.distance,
            "pan": list(cam.pan)}}
        extractions = [{k: v for k, v in asdict(e).items() if k != "requested"}
                       for e in self.surfaces.extractions]
        moving = self.clock.interactive_ms
        return {"frames": self.clock.count, "frame_ms_mean": float(times.mean()),
                "frame_ms_p95": float(np.percentile(times, 95)), "state": state,
                "interactive_frames": len(moving),
                "interactive_ms_median": float(np.median(moving)) if moving else None,
                "interactive_ms_last10": [float(v) for v in moving[-10:]],
                "quality": asdict(self.drawing.quality),
                "extractions": extractions,
                "bake": self.illumination.figures(), "checks": self.illumination.checks,
                "size": list(frame_size(self.window)), "ui": self.ui is not None}

    def close(self) -> None:
        """Stop the workers, save what should be saved, and free the window."""
        self.surfaces.close()
        self.illumination.stop()
        options = self.options
        try:
            if options.screenshot is not None and self.surfaces.stage is not None:
                self.saver.screenshot(options.screenshot)
            if (options.lattice_path is not None and self.illumination.shared is not None
                    and not self.illumination.relit_file):
                self.saver.save_lattice(options.lattice_path, on_exit=True)
            if options.stats is not None:
                write_json(options.stats, self.figures())
        finally:
            self.drawing.release()
            if self.ui is not None:
                self.ui.close()
            self.window.close()
            self.illumination.close()

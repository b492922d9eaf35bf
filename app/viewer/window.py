"""``isolume view``: the interactive viewer — its window, input and main loop.

One render thread owns the window, the GL context and the UI; the slow work happens
elsewhere so that the window never freezes. The parts, one job each:

* this module: options, the window and its input (the UI first, Dear ImGui via `app.viewer.panel`,
  then the camera when the UI does not want it), the actions that keys, panel and script
  end in, and the loop that ties the parts together;
* `app.viewer.surfaces`: isosurfaces off the render thread (`MeshWorker`: a coarse surface
  first, then the full one, in slabs that a newer request cancels);
* `app.viewer.bake_client`: the lazy-bake client (`BakeLink` to a separate process that bakes
  the texels around the displayed surface, into a `SharedLattice`);
* `app.viewer.draw`: the drawing and the lighting (`Drawing`: the surface and lattice on
  the GPU, re-uploads of baked texels, the light, the detail while moving). Texels not
  computed yet fall back to local shading (tinted);
* `app.viewer.script`: ``--script`` drives the viewer without a person, through the
  public methods of `Viewer` that the `app.viewer.script.ScriptTarget` protocol lists.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from isolume import volumes
from isolume.app.viewer.bake_client import BakeLink, SharedLattice, lattice_meta, range_warning
from isolume.app.viewer.draw import PREVIEW_TRIANGLES, Drawing, ViewState
from isolume.app.viewer.surfaces import MeshWorker
from isolume.volumes.errors import IsolumeError

HELP = "open the interactive viewer (live isovalue, light, lazy global illumination)"

SETTLE_S = 0.2
"""The view must be still this long before the visible texels are measured again."""
ISO_STEPS = 1000
"""A fine isovalue step is 1/ISO_STEPS of the data range (shift: ×10)."""
DEFAULT_BAKE_SAMPLES = 256
"""Paths per texel a new lazy lattice is refined up to (rounds of 4, 16, 64, 256)."""
BAKE_REFRESH_S = 0.5
BAKE_FRAME_SPACING = 4.0
"""New texels alone bring a frame at most every `BAKE_REFRESH_S` seconds and no sooner than
`BAKE_FRAME_SPACING` frame times after the last one (`Viewer._bake_frame_due`)."""


# -- command line -------------------------------------------------------------------------
def add_arguments(parser) -> None:
    """Options of ``isolume view``."""
    from isolume.app.options import add_volume_options
    from isolume.baking.config import DEFAULT_ENV

    add_volume_options(parser, optional=True)
    parser.add_argument("--iso", type=float, help="isovalue (default: first suggested)")
    parser.add_argument("--lattice", metavar="FILE",
                        help="illumination lattice: shown and, if incomplete, baked further "
                        "lazily; a new file is created; saved on exit and with S")
    parser.add_argument("--shading", default=None,
                        help="initial shading mode (default: irradiance when a lattice is "
                        "shown or baked, else phong_hemi)")
    parser.add_argument("--size", default="1024x768", help="window size WxH (screen units)")
    parser.add_argument("--exposure", type=float, default=1.0,
                        help="linear exposure multiplier on the automatic exposure (which "
                        "brings the log-average of the surface's luminance to middle grey "
                        "and adapts smoothly)")
    parser.add_argument("--no-auto-exposure", action="store_true",
                        help="no automatic exposure: --exposure is the whole linear scale")
    parser.add_argument("--frames", type=int, metavar="N",
                        help="render N frames once the surface is ready (after --script), "
                        "then exit")
    parser.add_argument("--screenshot", metavar="FILE",
                        help="on exit write FILE.png (sRGB) and FILE.exr (linear radiance)")
    parser.add_argument("--script", metavar="FILE",
                        help="commands, one per line: iso V | orbit DAZ DEL | zoom F | "
                        "pan DX DY | reset | mode NAME | light AZ EL | light camera | "
                        "exposure X | wait-mesh [T] | wait-bake FRACTION [T] | "
                        "wait-light FRACTION [T] | frames N | sleep S | screenshot FILE | "
                        "window-shot FILE | save-lattice [FILE] | check-lattice | quit")
    parser.add_argument("--stats", metavar="FILE.json",
                        help="write frame times, extraction and bake figures on exit")
    parser.add_argument("--no-bake", action="store_true",
                        help="no lazy global illumination (local shading, or --lattice as is)")
    parser.add_argument("--bake-mode", default="irradiance", choices=["irradiance", "sh"],
                        help="what a new lazy lattice holds: irradiance (fixed light) or SH "
                        "transfer (the environment rotates with the light controls)")
    parser.add_argument("--bake-env", default=DEFAULT_ENV,
                        help="environment of a new lazy lattice: constant:R,G,B | sky[:...] | "
                        f"FILE.exr/.hdr (as isolume bake --env; default {DEFAULT_ENV})")
    parser.add_argument("--bake-samples", type=int, default=DEFAULT_BAKE_SAMPLES,
                        help="paths per texel the lazy bake refines up to (new lattices)")
    parser.add_argument("--bake-workers", type=int, default=None,
                        help="tracing threads of the lazy bake (default: all cores)")
    parser.add_argument("--bake-max-levels", type=int, default=64, metavar="K",
                        help="isovalue levels of a new lazy lattice (fewer: the first sweep "
                        "builds fewer scenes and converges sooner, texels move farther "
                        "onto their levels and a few come out wrong; default 64)")
    parser.add_argument("--no-ui", action="store_true", help="no control panel")
    parser.add_argument("--normals", default="smooth", choices=["smooth", "gradient"])
    parser.add_argument("--flip-normals", action="store_true",
                        help="material less dense than air")


@dataclass(frozen=True)
class Options:
    """Validated viewer options (everything checked before a window opens)."""

    size: tuple[int, int]
    shading: str | None
    exposure: float
    auto_exposure: bool
    frames: int | None
    screenshot: Path | None
    script: tuple
    stats: Path | None
    bake: bool
    bake_mode: str
    bake_env: str
    bake_samples: int
    bake_workers: int | None
    bake_max_levels: int
    ui: bool
    normals: str
    flip_normals: bool
    lattice_path: Path | None


def _options(args) -> Options:
    """Check the command line; raise `app.cli.CLIError` with one-line messages."""
    from isolume.app.options import CLIError, parse_size
    from isolume.app.render.images import check_output_path
    from isolume.app.render.renderer import SHADING_MODES
    from isolume.app.viewer.script import load_script

    if args.shading is not None and args.shading not in SHADING_MODES:
        raise CLIError(f"--shading {args.shading!r}: expected one of {', '.join(SHADING_MODES)}")
    if not args.exposure > 0:
        raise CLIError(f"--exposure {args.exposure:g}: must be positive")
    if args.frames is not None and args.frames < 1:
        raise CLIError(f"--frames {args.frames}: expected at least 1")
    if args.bake_samples < 1:
        raise CLIError(f"--bake-samples {args.bake_samples}: expected at least 1")
    if args.bake_workers is not None and args.bake_workers < 1:
        raise CLIError(f"--bake-workers {args.bake_workers}: expected at least 1")
    if not 2 <= args.bake_max_levels <= 1024:
        raise CLIError(f"--bake-max-levels {args.bake_max_levels}: expected 2 to 1024")
    if not args.no_bake:
        from isolume.baking.environment import parse_env

        parse_env(args.bake_env)  # EnvSpecError (a one-line user error) before any window
    screenshot = check_output_path(args.screenshot) if args.screenshot else None
    stats = check_output_path(args.stats, (".json",)) if args.stats else None
    lattice = check_output_path(args.lattice, (".npz",)) if args.lattice else None
    script = tuple(load_script(args.script, SHADING_MODES)) if args.script else ()
    return Options(
        size=parse_size(args.size), shading=args.shading, exposure=args.exposure,
        auto_exposure=not args.no_auto_exposure,
        frames=args.frames, screenshot=screenshot, script=script, stats=stats,
        bake=not args.no_bake, bake_mode=args.bake_mode, bake_env=args.bake_env,
        bake_samples=args.bake_samples, bake_workers=args.bake_workers,
        bake_max_levels=args.bake_max_levels, ui=not args.no_ui, normals=args.normals,
        flip_normals=args.flip_normals, lattice_path=lattice,
    )


def run(args) -> int:
    """Entry point of ``isolume view``: bad input ends in one line on stderr, status 2.

    (The errors are reported here rather than by `app.cli.main`: under ``python -m app.cli``
    that module runs as ``__main__`` and its `CLIError` is not the one this module sees.)
    """
    from isolume.app.options import EXIT_USER_ERROR, CLIError
    from isolume.app.viewer.script import ScriptError

    try:
        return _run(args)
    except (CLIError, ScriptError, ViewerError) as exc:
        print(f"isolume: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return EXIT_USER_ERROR


def _run(args) -> int:
    from isolume.app.options import isovalue, load_volume

    options = _options(args)
    volume = load_volume(args)
    iso = isovalue(volume, args.iso)
    lattice = None
    if options.lattice_path is not None and options.lattice_path.exists():
        from isolume.baking.lattice import Lattice

        lattice = Lattice.load(options.lattice_path, volume)
    from isolume.app.render.renderer import LATTICE_MODES

    if options.shading in LATTICE_MODES and lattice is None and not options.bake:
        raise ViewerError(f"--shading {options.shading} needs a lattice: pass --lattice FILE, or "
                       "leave out --no-bake to bake one lazily")

    viewer = Viewer(volume, iso, lattice, options)
    try:
        return viewer.run()
    except KeyboardInterrupt:
        return 130
    finally:
        viewer.close()


# -- the viewer ---------------------------------------------------------------------------
@dataclass
class Extraction:
    """Figures of one isovalue change: seconds to the coarse and full surface, frames drawn
    meanwhile and the longest gap between frames."""

    iso: float
    requested: float
    coarse_s: float | None = None
    full_s: float | None = None
    frames: int = 0
    max_gap_ms: float = 0.0
    triangles: int = 0


@dataclass
class FrameClock:
    """Frame times of the render thread."""

    times: deque = field(default_factory=lambda: deque(maxlen=120))
    all_ms: list = field(default_factory=list)
    interactive_ms: list = field(default_factory=list)
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


class ViewerError(IsolumeError):
    """A request the viewer cannot honour (bad script step, missing lattice); one line."""


class Viewer:
    """The interactive viewer: window, input and loop; it holds the drawing
    (`app.viewer.draw.Drawing`), the surface worker, the lazy-bake link and the script.

    Its public methods below "actions" are what keys, the panel and scripts use
    (`app.viewer.script.ScriptTarget`)."""

    def __init__(self, volume: volumes.Volume, iso: float, lattice, options: Options) -> None:
        from isolume.app.render.glcontext import create_window
        from isolume.app.render.renderer import default_camera
        from isolume.app.viewer.script import ScriptRunner

        self.volume, self.options = volume, options
        self.window = create_window(options.size, f"isolume — {volume.name}")
        self.drawing = Drawing(self.window.ctx, volume, options.auto_exposure)
        self.home = default_camera(volume)
        self.camera = self.home
        self.framed = False  # the first surface has been framed
        self.panel_rect: tuple[float, float, float, float] | None = None
        self.panel_frames = 0  # frames the panel has been drawn (its size settles in two)
        self.ui = self._make_ui() if options.ui else None
        self.message = ""
        self.shared: SharedLattice | None = None
        self.bake: BakeLink | None = None
        self.static_lattice = lattice
        self.relit_file = False  # a complete file's lattice re-baked for a turned light
        self._setup_lattice(lattice, iso)
        shading = options.shading or (self.drawing.renderer.lattice.kind
                                      if self.drawing.renderer.lattice else "phong_hemi")
        self.state = ViewState(iso, shading, options.exposure)
        self._check_mode(shading)
        self.drawing.ensure_texel_isovalues(shading)
        self.mesh_worker = MeshWorker(volume, normals=options.normals,
                                      flip=options.flip_normals)
        self.mesh_stage: str | None = None
        self.mesh_iso: float | None = None
        self.last_motion = 0.0
        self.reduced = False
        self.mesh_info = "extracting..."
        self.extractions: list[Extraction] = []
        self.clock = FrameClock()
        self.dirty = True
        self.lattice_changed = False  # texels uploaded since the last frame
        self.last_input = 0.0
        self.view_sent: tuple | None = None
        self.view_seen: tuple | None = None
        self.view_since = 0.0
        self.drag = None
        self.pending_press: str | None = None
        self.quit = False
        self.checks: list[dict] = []
        self.script = ScriptRunner(self._script_commands(options))
        self._install_callbacks()
        self.request_iso(iso)

    # -- setup ---------------------------------------------------------------------------
    def _make_ui(self):
        from isolume.app.viewer.panel import ImGuiLayer

        try:
            return ImGuiLayer(self.window.glfw, self.window.ui_scale)
        except ImportError:
            print("isolume: note: imgui-bundle is not installed; no control panel "
                  "(pip install imgui-bundle)", file=sys.stderr)
        except RuntimeError as exc:
            print(f"isolume: note: {exc}; no control panel", file=sys.stderr)
        return None

    def _setup_lattice(self, lattice, iso: float) -> None:
        """Show `lattice` (if any) and start the lazy bake when it is missing or incomplete."""
        from isolume.baking.config import BakeConfig

        config = None
        if lattice is not None:
            config = BakeConfig.from_dict(lattice.meta["config"])
            self.drawing.albedo = tuple(config.albedo)
            done = lattice.samples[lattice.active] >= config.samples
            if done.all() or not self.options.bake:
                self._show_lattice(lattice)
                return
        if not self.options.bake:
            return
        if config is None:
            config = BakeConfig(mode=self.options.bake_mode, env=self.options.bake_env,
                                samples=self.options.bake_samples,
                                max_levels=self.options.bake_max_levels)
        self._start_bake(lattice, config, iso)

    def _start_bake(self, lattice, config, iso: float) -> None:
        """Show `lattice` (None: a new one for `config`) from shared memory and start its
        lazy bake with `config`."""
        from isolume.baking.lattice import LatticeGeometry

        geometry = LatticeGeometry.for_volume(self.volume, config.scale)
        meta = lattice.meta if lattice is not None else lattice_meta(self.volume, config)
        self.shared = SharedLattice.create(geometry, meta["channels"], meta, lattice)
        self.static_lattice = None
        if self._show_lattice(self.shared.lattice):
            self.drawing.track_uploads()
        self.bake = BakeLink(self.volume, config, self.shared, self.options.bake_workers, iso,
                             follow_iso=lattice is None)

    def _show_lattice(self, lattice) -> bool:
        problem = self.drawing.show_lattice(lattice)
        if problem is not None:
            self.message = problem
        return problem is None

    def _script_commands(self, options: Options) -> list:
        from isolume.app.viewer.script import Command

        commands = list(options.script)
        if options.frames is not None:
            if not commands:
                commands.append(Command("wait-mesh", (), 0))
            commands += [Command("frames", (options.frames,), 0), Command("quit", (), 0)]
        return commands

    def _install_callbacks(self) -> None:
        glfw, handle = self.window.glfw, self.window.handle
        glfw.set_cursor_pos_callback(handle, self._on_cursor)
        glfw.set_mouse_button_callback(handle, self._on_mouse_button)
        glfw.set_scroll_callback(handle, self._on_scroll)
        glfw.set_key_callback(handle, self._on_key)
        glfw.set_char_callback(handle, self._on_char)
        glfw.set_window_focus_callback(handle, self._on_focus)
        glfw.set_framebuffer_size_callback(handle, lambda *_: self.redraw())
        glfw.set_window_refresh_callback(handle, lambda *_: self.redraw())

    def _moved(self) -> None:
        """The user moves the camera or light (interactive quality applies)."""
        self.last_motion = time.perf_counter()
        self.redraw()

    @property
    def _ui_shown(self) -> bool:
        return self.ui is not None and self.state.show_ui

    def _interacting(self, now: float) -> bool:
        return self.drag is not None or now - self.last_motion < 0.3

    # -- input: UI first, then the camera ------------------------------------------------
    def _input(self) -> None:
        self.last_input = time.perf_counter()
        self.dirty = True

    def _on_cursor(self, _handle, x: float, y: float) -> None:
        self._input()
        if self.ui is not None:
            self.ui.mouse_pos(x, y)
        if self.drag is None:
            return
        dx, dy = x - self.drag.x, y - self.drag.y
        self.drag.x, self.drag.y = x, y
        self._drag_by(self.drag.target, dx, dy)

    def _drag_by(self, target: str, dx: float, dy: float) -> None:
        from isolume.app.viewer.panel import ROTATE_DEG_PER_PX, orbit, pan, pan_per_pixel

        if target == "rotate":
            self.camera = orbit(self.camera, -dx * ROTATE_DEG_PER_PX, dy * ROTATE_DEG_PER_PX)
        elif target == "pan":
            k = pan_per_pixel(self.camera, self.window.window_size[1])
            self.camera = pan(self.camera, -dx * k, dy * k)
        elif target == "light":
            az, el = self._light_angles()
            self.set_light((az + dx * ROTATE_DEG_PER_PX,
                            float(np.clip(el - dy * ROTATE_DEG_PER_PX, -90, 90))))
        self._moved()

    def _on_mouse_button(self, _handle, button: int, action: int, mods: int) -> None:
        from isolume.app.viewer.panel import drag_target

        glfw = self.window.glfw
        self._input()
        if self.ui is not None:
            self.ui.mouse_button(button, action == glfw.PRESS)
        if action == glfw.RELEASE:
            self.drag = self.pending_press = None
            return
        target = drag_target(button, bool(mods & glfw.MOD_SHIFT), bool(mods & glfw.MOD_CONTROL))
        if target is None:
            return
        if self._ui_shown:
            # ImGui decides at its next frame whether the press is its own (it only then
            # knows what lies under the pointer); `_confirm_press` starts the drag if not
            self.pending_press = target
        else:
            self._start_drag(target)

    def _start_drag(self, target: str) -> None:
        from isolume.app.viewer.panel import Drag

        x, y = self.window.glfw.get_cursor_pos(self.window.handle)
        self.drag = Drag(target, x, y)

    def _confirm_press(self) -> None:
        """After the UI's new frame: a pending press drags the camera unless ImGui took it."""
        if self.pending_press is not None and not self.ui.wants_mouse:
            self._start_drag(self.pending_press)
        self.pending_press = None

    def _on_scroll(self, _handle, dx: float, dy: float) -> None:
        from isolume.app.viewer.panel import ZOOM_PER_WHEEL, zoom

        self._input()
        if self.ui is not None:
            self.ui.scroll(dx, dy)
            if self._ui_shown and self.ui.wants_mouse:
                return
        self.camera = zoom(self.camera, ZOOM_PER_WHEEL ** -dy)
        self._moved()

    def _on_char(self, _handle, codepoint: int) -> None:
        self._input()
        if self.ui is not None:
            self.ui.char(codepoint)

    def _on_focus(self, _handle, focused: int) -> None:
        self._input()
        if self.ui is not None:
            self.ui.focus(bool(focused))

    def _on_key(self, _handle, key: int, _scancode: int, action: int, mods: int) -> None:
        glfw = self.window.glfw
        self._input()
        if self.ui is not None:
            self.ui.key(key, action != glfw.RELEASE, mods)
            if self._ui_shown and self.ui.wants_keyboard:
                return
        if action == glfw.RELEASE:
            return
        from isolume.app.viewer.panel import key_action

        requested = key_action(glfw, key, mods, self.drawing.modes)
        if requested is not None:
            self.apply(requested)

    # -- actions (keys, panel and script all end here) -----------------------------------
    def redraw(self) -> None:
        """Something on screen changed: draw again."""
        self.dirty = True

    def request_iso(self, iso: float) -> None:
        """Show the isosurface at `iso` (clamped inside the data range)."""
        lo, hi = self.volume.value_range
        eps = 1e-6 * (hi - lo)
        iso = float(np.clip(iso, lo + eps, hi - eps))
        self.state.iso = iso
        self.mesh_worker.request(iso)
        self.extractions.append(Extraction(iso, time.perf_counter()))
        self.redraw()

    def step_iso(self, steps: int) -> None:
        lo, hi = self.volume.value_range
        self.request_iso(self.state.iso + steps * (hi - lo) / ISO_STEPS)

    def _check_mode(self, mode: str) -> None:
        modes = self.drawing.modes
        if mode not in modes:
            raise ViewerError(f"unknown shading mode {mode!r}; expected one of "
                              f"{', '.join(modes)}")
        if mode in self.drawing.usable_modes():
            return
        lattice = self.drawing.renderer.lattice
        if lattice is None:
            raise ViewerError(f"shading {mode!r} needs a lattice: pass --lattice FILE, or "
                              "leave out --no-bake to bake one lazily")
        raise ViewerError(f"shading {mode!r} cannot be drawn from the {lattice.kind}"
                          " lattice shown (irradiance modes need an irradiance lattice, sh an "
                          "SH one: --bake-mode)")

    def set_mode(self, mode: str) -> None:
        self._check_mode(mode)
        self.drawing.ensure_texel_isovalues(mode)
        self.state.shading = mode
        self.redraw()

    def set_exposure(self, exposure: float) -> None:
        self.state.exposure = float(np.clip(exposure, 1e-3, 1e3))
        self.redraw()

    def set_light(self, angles: tuple[float, float] | None, moving: bool = False) -> None:
        """World-fixed light at (azimuth, elevation) degrees, or None: fixed to the camera;
        `moving`: as a drag does (interactive quality applies)."""
        self.state.light = None if angles is None else (float(angles[0]) % 360.0,
                                                        float(angles[1]))
        if moving:
            self._moved()
        self.redraw()

    def _light_angles(self) -> tuple[float, float]:
        return self.drawing.light_angles(self.state, self.camera)

    def move_camera(self, how: str, a: float, b: float = 0.0) -> None:
        """Move the camera as a drag would: "orbit" by (a, b) degrees of azimuth and
        elevation, "zoom" closer by the factor a, "pan" by (a, b) diagonals."""
        from isolume.app.viewer.panel import orbit, pan, zoom

        moves = {"orbit": lambda c: orbit(c, a, b), "zoom": lambda c: zoom(c, a),
                 "pan": lambda c: pan(c, a, b)}
        self.camera = moves[how](self.camera)
        self._moved()

    def _frame_first_surface(self) -> None:
        """Aim the camera at the first surface's bounding box, in the part of the window
        the panel leaves free (once the panel has its size); that view becomes the one `R`
        returns to. A camera the user (or a script) has moved already stays where it is."""
        from isolume.app.render.camera import frame_box

        meshes = [m for m in self.drawing.meshes.values() if not m.empty]
        if self.framed or not meshes or (self._ui_shown and self.panel_frames < 2):
            return
        mesh = meshes[0]
        w, h = self.window.window_size
        left = 0.0
        if self._ui_shown and self.panel_rect is not None:
            x, _, width, _ = self.panel_rect
            left = min(max((x + width + 10) / max(w, 1), 0.0), 0.5)  # at most half
        home = frame_box(self.home, mesh.vertices.min(axis=0), mesh.vertices.max(axis=0),
                         w / max(h, 1), (left, 1.0))
        if self.camera == self.home:
            self.camera = home
        self.home, self.framed = home, True

    def reset_camera(self) -> None:
        self.camera = self.home
        self.redraw()

    def request_quit(self) -> None:
        self.quit = True

    def apply(self, action) -> None:
        """Apply an `app.viewer.panel.Action` (from the panel or a key); problems become the status
        message."""
        name, value = action.name, action.value
        if name == "panel_rect":  # where the panel is (window units), for framing
            self.panel_rect = value
            self.panel_frames += 1
            return
        simple = {
            "iso": lambda: self.request_iso(value),
            "iso_step": lambda: self.step_iso(value),
            "mode": lambda: self.set_mode(value),
            "exposure": lambda: self.set_exposure(value),
            "exposure_by": lambda: self.set_exposure(self.state.exposure * value),
            "light": lambda: self.set_light(value),
            "light_camera": lambda: self.set_light(None if value else self._light_angles()),
            "toggle_light": lambda: self.set_light(
                None if self.state.light is not None else self._light_angles()),
            "reset_camera": self.reset_camera,
            "screenshot": self.screenshot,
            "save_lattice": self.save_lattice,
            "pause_bake": lambda: self.bake and self.bake.pause(value),
            "toggle_bake": lambda: self.bake and self.bake.pause(not self.bake.paused),
            "toggle_ui": lambda: setattr(self.state, "show_ui", not self.state.show_ui),
            "quit": self.request_quit,
        }
        try:
            simple[name]()
        except (ViewerError, OSError) as exc:
            self.message = str(exc)
        self.redraw()

    def screenshot(self, path: str | os.PathLike | None = None) -> tuple[Path, Path]:
        """Write the current view (without the panel) as PNG (sRGB) and EXR (linear
        radiance, before exposure) next to each other; returns both paths."""
        from isolume.app.render.images import write_exr, write_png
        from isolume.app.viewer.script import screenshot_paths

        if path is None:
            stamp = time.strftime("%Y%m%d-%H%M%S")
            path = Path(f"isolume-{self.volume.name}-{stamp}.png")
        png, exr = screenshot_paths(path)
        if not png.parent.is_dir():
            raise ViewerError(f"screenshot {png}: directory {png.parent} does not exist")
        frame = self.drawing.frame(self.camera, self.state, self._frame_size())
        write_png(png, frame.srgb)
        write_exr(exr, frame.linear)
        self.message = f"wrote {png} and {exr}"
        print(f"isolume: {self.message}")
        return png, exr

    def window_pixels(self) -> np.ndarray:
        """(H, W, 3) uint8 of the window's back buffer, top row first (UI included)."""
        w, h = self.window.framebuffer_size
        return np.frombuffer(self.window.read_back(), np.uint8).reshape(h, w, 3)[::-1]

    def save_lattice(self, path: str | os.PathLike | None = None) -> Path | None:
        """Write the lattice being shown/baked to `path` (default: --lattice, else
        isolume-NAME.npz)."""
        if self.shared is None:
            self.message = "no lazily baked lattice to save"
            return None
        lattice = (self.bake.snapshot(self.shared) if self.bake is not None
                   else self.shared.snapshot())
        default = self.options.lattice_path or Path(f"isolume-{self.volume.name}.npz")
        if self.relit_file:  # not over the file's whole bake
            default = default.with_name(f"{default.stem}-relit.npz")
        path = Path(path or default)
        lattice.save(path)
        done = int((lattice.samples > 0).sum())
        self.message = f"saved {path} ({done:,} texels computed)"
        print(f"isolume: {self.message}")
        return path

    def surface_ready(self) -> bool:
        """The full-resolution surface of the requested isovalue is on screen."""
        return self.mesh_stage == "full" and self.mesh_iso == self.state.iso

    def bake_progress(self) -> tuple[float | None, str | None]:
        """(fraction of the texels near the displayed surface with an estimate, None
        before the bake reports on this isovalue; the bake's error or None).

        Raises:
            ViewerError: no lazy bake runs.
        """
        if self.bake is None:
            raise ViewerError("no lazy bake is running (--no-bake, or the lattice is "
                              "complete)")
        return self.bake.near_fraction(self.state.iso), self.bake.error

    def relit_progress(self) -> tuple[float | None, str | None]:
        """(share of the visible texels showing the bounced light of the light as turned
        now, None before the bake reports on it; the bake's error or None).

        Raises:
            ViewerError: no lazy bake runs, or no light is shaded per pixel.
        """
        from isolume.baking.config import BakeConfig
        from isolume.baking.lazy import same_direction, turned_light

        turned = self.drawing.turned_light(self.state)
        file = self.static_lattice is not None and self.options.bake
        if turned is None or (self.bake is None and not file):
            raise ViewerError("no lazy bake of a per-pixel sun or light to wait for "
                              "(mode irradiance with a lattice that --no-bake leaves as is)")
        if self.bake is None:  # a complete file: its bake starts once the light rests turned
            baked = turned_light(BakeConfig.from_dict(self.static_lattice.meta["config"]))
            return (1.0 if same_direction(turned[1], baked) else None), None
        return self.bake.relit_fraction(turned[1]), self.bake.error

    def hold_bake(self, held: bool) -> None:
        """Pause (True) or resume the lazy bake, if one runs; `bake_held` says when the
        process has stopped writing."""
        if self.bake is not None:
            if held:
                self.bake.paused_ack = False
            self.bake.pause(held)

    def bake_held(self) -> bool:
        """No lazy bake writes texels now (none runs, or it acknowledged a pause)."""
        return self.bake is None or self.bake.paused_ack

    def check_lattice(self) -> dict:
        """Upload what is pending, compare the GL textures with the lattice
        (`app.viewer.draw.check_textures`), note and print the result.

        Raises:
            ViewerError: no lattice is shown.
        """
        if self.drawing.renderer.lattice is None:
            raise ViewerError("no lattice is shown")
        self._receive_bake()  # texels committed before a pause took effect
        result = self.drawing.check_lattice()
        self.checks.append(result)
        print(f"isolume: check-lattice: {json.dumps(result)}")
        return result

    # -- the loop ------------------------------------------------------------------------
    def run(self) -> int:
        """Run until the window closes, `quit`, or the script/--frames ends it."""
        glfw = self.window.glfw
        while not (self.quit or self.window.should_close()):
            if self._wants_frame():
                glfw.poll_events()
            else:
                glfw.wait_events_timeout(0.03)
            self._receive_mesh()
            self._receive_bake()
            self.script.step(self)
            self._update_view()
            if self._wants_frame():
                self.draw_frame()
                self._pace()
        return 0

    def _pace(self) -> None:
        """While a surface is extracted, leave the worker at least a third of the time
        (drawing holds the GIL; waiting for events does not)."""
        if self._extraction_pending() and self.clock.times:
            self.window.glfw.wait_events_timeout(min(0.5 * self.clock.times[-1], 0.05))

    def _wants_frame(self) -> bool:
        now = time.perf_counter()
        recent_input = now - self.last_input < 0.25
        settle = self.reduced and not self._interacting(now)  # one full-detail frame
        return (self.dirty or recent_input or settle or self.script.forces_frames
                or self.drawing.adapting or (self.lattice_changed and self._bake_frame_due(now)))

    def _bake_frame_due(self, now: float) -> bool:
        last = self.clock.times[-1] if self.clock.times else None
        return bake_frame_due(now, self.clock.last_end, last)

    def _frame_size(self) -> tuple[int, int]:
        w, h = self.window.framebuffer_size
        return max(w, 1), max(h, 1)

    def draw_frame(self) -> None:
        """Draw the scene and the panel, swap, and account the frame."""
        start = time.perf_counter()
        w, h = self.window.framebuffer_size
        if w == 0 or h == 0:  # minimised
            self.dirty = False
            return
        if self._ui_shown:
            self.ui.new_frame(self.window.window_size, (w, h), start)
            self._confirm_press()
            from isolume.app.viewer.panel import draw_panel

            for action in draw_panel(self.ui.imgui, self._panel_model()):
                self.apply(action)
        self._frame_first_surface()
        interacting = self._interacting(start)
        drawing = self.drawing
        drawing.sync_mesh(preview=(interacting and drawing.quality.coarse)
                          or self._heavy_wait())
        scale = drawing.quality.scale if interacting else 1.0
        try:
            drawing.draw(self.camera, self.state, (w, h), scale)
        except ValueError as exc:  # app.render.renderer.RenderError: a mode without what it needs
            self.message = f"shading {self.state.shading!r}: {exc}; back to phong_hemi"
            self.state.shading = "phong_hemi"
            drawing.draw(self.camera, self.state, (w, h), scale)
        if self._ui_shown:
            self.ui.render()
        self.script.before_swap(self)
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
        self.dirty = self.lattice_changed = False

    def _extraction_pending(self) -> bool:
        return bool(self.extractions) and self.extractions[-1].full_s is None

    def _heavy_wait(self) -> bool:
        """A new surface is being extracted and the full one on screen is big: show the
        preview meanwhile (software GL holds the GIL while it draws, which would starve
        the extraction)."""
        full = self.drawing.meshes.get("full")
        return (self._extraction_pending() and full is not None
                and len(full.faces) > PREVIEW_TRIANGLES)

    def _account_frame(self, start: float, end: float) -> None:
        previous = self.clock.last_end
        self.clock.add(start, end)
        pending = self.extractions[-1] if self.extractions else None
        if pending is not None and pending.full_s is None:
            pending.frames += 1
            if previous is not None and previous >= pending.requested:
                pending.max_gap_ms = max(pending.max_gap_ms, 1000 * (end - previous))
        self.script.frame_done()

    def _receive_mesh(self) -> None:
        if self.mesh_worker.error:
            self.message, self.mesh_worker.error = self.mesh_worker.error, None
        for result in self.mesh_worker.poll():
            mesh = result.mesh
            if result.stage == "lod":  # a lighter preview for moving the camera
                if result.iso == self.mesh_iso:
                    self.drawing.meshes["coarse"] = mesh
                continue
            self.drawing.set_surface(result.stage, mesh, new_iso=result.iso != self.mesh_iso)
            self.drawing.sync_mesh(preview=self.drawing.quality.coarse
                                   and self._interacting(time.perf_counter()))
            self.mesh_stage, self.mesh_iso = result.stage, result.iso
            stage = "full resolution" if result.stage == "full" else "preview"
            self.mesh_info = (mesh.message if mesh.empty else
                              f"{stage}: {len(mesh.faces):,} triangles, "
                              f"{len(mesh.vertices):,} vertices")
            record = self.extractions[-1]
            if result.stage == "coarse":
                record.coarse_s = result.seconds
            else:
                record.full_s, record.triangles = result.seconds, len(mesh.faces)
            self.redraw()

    def _receive_bake(self) -> None:
        if self.bake is None:
            return
        for ids in self.bake.poll():
            self.drawing.mark_texels(ids)
        if self.bake.error:
            self.message = f"lazy bake stopped: {self.bake.error}"
        if self.drawing.upload_texels() and self.state.shading in self._lattice_modes():
            self.lattice_changed = True  # shown by `_wants_frame`, at a pace

    def _lattice_modes(self) -> tuple[str, ...]:
        from isolume.app.render.renderer import LATTICE_MODES

        return tuple(LATTICE_MODES)

    def _update_view(self) -> None:
        """Tell the bake process what is on screen once the view has settled."""
        if self.bake is None and self.static_lattice is not None:
            self._bake_turned_file()
        if self.bake is None or self.mesh_iso != self.state.iso or self.mesh_stage is None:
            return
        turned = self.drawing.turned_light(self.state)  # its bounced light follows it
        key = (self.state.iso, self.camera, self.mesh_stage == "full",
               None if turned is None else turned[1])
        now = time.perf_counter()
        if key != self.view_seen:  # the view changed: wait until it holds still
            self.view_seen, self.view_since = key, now
            return
        if key == self.view_sent or now - self.view_since < SETTLE_S or self.drag is not None:
            return
        from isolume.baking.lazy import View, visible_cells

        points = self.drawing.visible_points(self.camera, self.state, self._frame_size())
        cells = visible_cells(self.shared.lattice.geometry, points)
        self.bake.send_view(View(self.state.iso, tuple(float(v) for v in self.camera.eye),
                                 cells, key[3]))
        self.view_sent = key

    def _bake_turned_file(self) -> None:
        """A complete lattice from a file whose sun (or light) the user turned: start a
        lazy bake with the file's config, which re-bakes the bounced light for the turned
        light around the view. Its result is saved only on request, beside the file
        (`save_lattice`): the file keeps its whole bake."""
        from isolume.baking.config import BakeConfig
        from isolume.baking.lazy import same_direction, turned_light

        turned = self.drawing.turned_light(self.state)
        if not self.options.bake or self.drag is not None or turned is None:
            return
        config = BakeConfig.from_dict(self.static_lattice.meta["config"])
        if same_direction(turned[1], turned_light(config)):
            return
        self.relit_file = True
        self._start_bake(self.static_lattice, config, self.state.iso)

    # -- panel ---------------------------------------------------------------------------
    def _panel_model(self):
        from isolume.app.viewer.panel import PanelModel

        z, y, x = self.volume.data.shape
        light_note = ""
        if self.state.shading == "sh":
            light_note = "The light controls rotate the environment (SH transfer)."
        elif self.drawing.light_note(self.state) is not None:  # sun/lights per pixel
            light_note = self._relit_line() or self.drawing.light_note(
                self.state, rebakes=self.bake is not None)
        elif self.state.shading in self._lattice_modes():
            light_note = ("The light is baked into the lattice (fixed); rotating it moves "
                          "only the fallback light of texels not computed yet.")
        fractions, lines = self._bake_status()
        return PanelModel(
            title=f"{self.volume.name}  {x}x{y}x{z}", iso=self.state.iso,
            iso_range=self.volume.value_range, mesh_status=self.mesh_info,
            modes=self.drawing.modes, enabled=self.drawing.usable_modes(),
            mode=self.state.shading, exposure=self.state.exposure,
            light=self.state.light, light_note=light_note, bake_lines=lines,
            auto_exposure=self.drawing.auto if self.drawing.auto_exposure else None,
            bake_fractions=fractions, bake_paused=bool(self.bake and self.bake.paused),
            can_bake=self.bake is not None, can_save=self.shared is not None,
            frame_ms=self.clock.mean_ms, size=self._frame_size(), message=self.message,
        )

    def _relit_line(self) -> str | None:
        """The lazy bake's progress on the bounced light of the light as turned (None
        before it starts on it)."""
        turned = self.drawing.turned_light(self.state)
        if self.bake is None or turned is None:
            return None
        return self.bake.relit_line(turned[1], turned[0])

    def _bake_status(self) -> tuple[tuple[float, float] | None, tuple[str, ...]]:
        if self.bake is None:
            if self.static_lattice is not None:
                return None, (*range_warning(self.static_lattice.meta, self.state.iso),
                              "lattice loaded (complete)")
            return None, ()
        return self.bake.status(self.state.iso)

    # -- figures and shutdown ------------------------------------------------------------
    def figures(self) -> dict:
        """What `--stats` writes."""
        times = np.array(self.clock.all_ms) if self.clock.all_ms else np.zeros(1)
        bake = None
        uploader = self.drawing.uploader
        if self.bake is not None:
            p = self.bake.progress
            bake = {"ready": {k: v for k, v in (self.bake.ready or {}).items() if k != "meta"},
                    "progress": asdict(p) if p is not None else None,
                    "previews": [{"at_s": at, **f} for at, f in self.bake.previews],
                    "stats": self.bake.stats, "error": self.bake.error,
                    "turns": [{k: v for k, v in t.items() if k != "sent"}
                              for t in self.bake.turns],
                    "blocks_uploaded": uploader.uploaded if uploader else 0}
        cam = self.camera
        state = asdict(self.state) | {"camera": {
            "azimuth": cam.azimuth, "elevation": cam.elevation, "distance": cam.distance,
            "pan": list(cam.pan)}}
        extractions = [{k: v for k, v in asdict(e).items() if k != "requested"}
                       for e in self.extractions]
        moving = self.clock.interactive_ms
        return {"frames": self.clock.count, "frame_ms_mean": float(times.mean()),
                "frame_ms_p95": float(np.percentile(times, 95)), "state": state,
                "interactive_frames": len(moving),
                "interactive_ms_median": float(np.median(moving)) if moving else None,
                "interactive_ms_last10": [float(v) for v in moving[-10:]],
                "quality": asdict(self.drawing.quality),
                "extractions": extractions,
                "bake": bake, "checks": self.checks, "size": list(self._frame_size()),
                "ui": self.ui is not None}

    def close(self) -> None:
        """Stop the workers, save what should be saved, and free the window."""
        self.mesh_worker.close()
        if self.bake is not None:
            self.bake.stop()
        try:
            if self.options.screenshot is not None and self.mesh_stage is not None:
                self.screenshot(self.options.screenshot)
            if (self.options.lattice_path is not None and self.shared is not None
                    and not self.relit_file):
                self.save_lattice(self.options.lattice_path)
            if self.options.stats is not None:
                self.options.stats.write_text(json.dumps(self.figures(), indent=1,
                                                         default=_json_default))
        finally:
            self.drawing.release()
            if self.ui is not None:
                self.ui.close()
            self.window.close()
            if self.shared is not None:
                self.shared.close()


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")

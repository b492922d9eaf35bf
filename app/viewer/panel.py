"""The viewer's in-window UI (Dear ImGui via imgui-bundle) and its mouse/keyboard controls.

Why this integration. imgui-bundle's pure-Python backends (``imgui_bundle.python_backends``)
draw through PyOpenGL, which is not a dependency here (and a second GL binding next to
moderngl would issue GL calls behind moderngl's back). imgui-bundle also exposes Dear
ImGui's own C++ backends; the OpenGL 3 *renderer* (``imgui.backends.opengl3_*``) loads its
GL functions from whatever context is current, so it draws into the moderngl-managed glfw
context as is, saving and restoring the GL state it touches. Its glfw *platform* backend,
on the other hand, needs the window to come from the very libglfw that imgui-bundle links,
so instead the viewer's own glfw callbacks feed ImGui (`ImGuiLayer.mouse_*`, `key`, ...)
and then pass the event on to the camera only when ImGui does not want it.

Nothing here draws the scene; `draw_panel` turns a `PanelModel` snapshot into `Action`s
the viewer applies, the same way it applies keys and script commands.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from isolume.app.render.camera import Camera

if TYPE_CHECKING:
    from imgui_bundle import imgui as _imgui

ROTATE_DEG_PER_PX = 0.4
"""Camera and light rotation per mouse movement (screen coordinates)."""
ZOOM_PER_WHEEL = 0.88
"""Distance factor per wheel notch (wheel up moves closer)."""
DISTANCE_RANGE = (0.15, 20.0)
"""Allowed eye distance, in volume diagonals."""


# -- camera and light controls (no GL) ---------------------------------------------------
def direction_from_angles(azimuth: float, elevation: float) -> np.ndarray:
    """(3,) unit vector pointing from the scene towards azimuth/elevation (degrees), the
    same convention as the camera's eye: azimuth 0 is −y, elevation 90 is +z."""
    az, el = math.radians(azimuth), math.radians(elevation)
    return np.array([math.cos(el) * math.sin(az), -math.cos(el) * math.cos(az), math.sin(el)])


def angles_from_direction(d: np.ndarray) -> tuple[float, float]:
    """Inverse of `direction_from_angles`: (azimuth, elevation) degrees of a vector."""
    d = np.asarray(d, np.float64) / np.linalg.norm(d)
    return (math.degrees(math.atan2(d[0], -d[1])),
            math.degrees(math.asin(float(np.clip(d[2], -1.0, 1.0)))))


def orbit(camera: Camera, d_azimuth: float, d_elevation: float) -> Camera:
    """Camera turned by the given degrees (elevation kept within ±89.5°)."""
    el = float(np.clip(camera.elevation + d_elevation, -89.5, 89.5))
    return replace(camera, azimuth=(camera.azimuth + d_azimuth) % 360.0, elevation=el)


def zoom(camera: Camera, factor: float) -> Camera:
    """Camera moved `factor` times closer (factor < 1 moves away), within DISTANCE_RANGE."""
    d = float(np.clip(camera.distance / factor, *DISTANCE_RANGE))
    return replace(camera, distance=d)


def pan(camera: Camera, dx: float, dy: float) -> Camera:
    """Orbit centre moved right/up by (dx, dy) volume diagonals."""
    return replace(camera, pan=(camera.pan[0] + dx, camera.pan[1] + dy))


def pan_per_pixel(camera: Camera, window_height: float) -> float:
    """Diagonals per screen-coordinate pixel at the orbit centre (so the surface under the
    cursor follows it)."""
    return 2 * camera.distance * math.tan(math.radians(camera.fov_y) / 2) / max(window_height, 1)


@dataclass
class Drag:
    """A mouse drag in progress: what it moves and where the cursor was."""

    target: str  # "rotate" | "pan" | "light"
    x: float
    y: float


DRAG_BUTTONS = {0: "rotate", 1: "light", 2: "pan"}
"""glfw mouse button → what a plain drag with it moves (left, right, middle)."""


def drag_target(button: int, shift: bool, ctrl: bool) -> str | None:
    """What a drag with `button` and modifiers moves: shift → pan, ctrl → light."""
    if button not in DRAG_BUTTONS:
        return None
    if button == 0 and shift:
        return "pan"
    if button == 0 and ctrl:
        return "light"
    return DRAG_BUTTONS[button]


# -- the panel ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Action:
    """Something the user asked for through the panel or a key: name and value (applied by
    `app.viewer.actions.Actions.apply`)."""

    name: str
    value: object = None


@dataclass(frozen=True)
class PanelModel:
    """What the panel shows (a snapshot taken by the viewer every frame).

    Attributes:
        title: volume name and dimensions.
        iso, iso_range: isovalue and the data range (field units).
        mesh_status: e.g. "full resolution, 594,782 triangles".
        modes: every shading mode; enabled: those usable now (lattice modes need one),
            the ones the mode selector offers.
        mode, exposure: current shading mode and exposure (a multiplier on the automatic
            one, `auto_exposure`, when that is on; else None).
        light: (azimuth, elevation) degrees, or None for the camera-fixed light.
        light_note: shown under the light controls (e.g. the lattice's light is fixed).
        bake_lines: status lines of the lazy bake ("" entries are skipped).
        bake_fractions: (visible, surface) shares with samples of their own, or None.
        bake_paused: whether the lazy bake is on hold; can_bake: a lazy bake exists.
        can_save: a lattice can be saved; frame_ms: mean frame time; size: framebuffer.
        message: last status or error message.
        keys_help: lines of the key reference (default `KEYS_HELP`).
    """

    title: str
    iso: float
    iso_range: tuple[float, float]
    mesh_status: str
    modes: tuple[str, ...]
    enabled: tuple[str, ...]
    mode: str
    exposure: float
    light: tuple[float, float] | None
    light_note: str = ""
    auto_exposure: float | None = None
    bake_lines: tuple[str, ...] = ()
    bake_fractions: tuple[float, float] | None = None
    bake_paused: bool = False
    can_bake: bool = False
    can_save: bool = False
    frame_ms: float = 0.0
    size: tuple[int, int] = (0, 0)
    message: str = ""
    keys_help: tuple[str, ...] = field(default_factory=tuple)


def key_action(glfw: ModuleType, key: int, mods: int,
               modes: tuple[str, ...]) -> Action | None:
    """What a key press asks for (see KEYS_HELP), as an `Action`; None for other keys.

    Args:
        glfw: the glfw module (key and modifier codes).
        modes: shading modes in the order of the number keys.
    """
    steps = {glfw.KEY_LEFT: -1, glfw.KEY_RIGHT: 1, glfw.KEY_LEFT_BRACKET: -1,
             glfw.KEY_RIGHT_BRACKET: 1}
    if key in steps:
        return Action("iso_step", steps[key] * (10 if mods & glfw.MOD_SHIFT else 1))
    if glfw.KEY_1 <= key <= glfw.KEY_9:
        index = key - glfw.KEY_1
        return Action("mode", modes[index]) if index < len(modes) else None
    named = {
        glfw.KEY_EQUAL: ("exposure_by", 1.25), glfw.KEY_KP_ADD: ("exposure_by", 1.25),
        glfw.KEY_MINUS: ("exposure_by", 0.8), glfw.KEY_KP_SUBTRACT: ("exposure_by", 0.8),
        glfw.KEY_R: ("reset_camera", None), glfw.KEY_L: ("toggle_light", None),
        glfw.KEY_F12: ("screenshot", None), glfw.KEY_P: ("screenshot", None),
        glfw.KEY_V: ("save_view", None), glfw.KEY_S: ("save_lattice", None),
        glfw.KEY_B: ("toggle_bake", None),
        glfw.KEY_H: ("toggle_ui", None), glfw.KEY_F1: ("toggle_ui", None),
        glfw.KEY_ESCAPE: ("quit", None), glfw.KEY_Q: ("quit", None),
    }
    return Action(*named[key]) if key in named else None


KEYS_HELP = (
    "drag: rotate   shift/middle-drag: pan   wheel: zoom   R: reset",
    "ctrl/right-drag: light   L: light on camera",
    "left/right or [ ]: isovalue (shift: x10)   1-9: mode",
    "+/-: exposure   F12/P: screenshot   V: save view   S: save lattice",
    "B: pause bake   C: fold panel   H: hide panel   Esc/Q: quit",
)

PANEL_ID = "###isolume"
"""Dear ImGui's name for the panel window: its title changes (`_title`), its identity not."""
PANEL_GAP = 10.0
"""Window units between the panel and the window's top-left corner, and between the panel
and the part of the window the surface is framed in beside it (`room_beside`)."""
MAX_PANEL_WIDTH = 0.5
"""Fraction of the window's width the open panel (and `PANEL_GAP`) may take at the start;
a wider one starts folded to its title bar (`_fold`), the surface framed in the whole
window."""
FOLD_HINT = "C: show the controls"
"""What the folded panel's title bar says after the name."""


def room_beside(right: float, window_width: float) -> float:
    """Left edge of the part of the window beside a panel whose right edge is at `right`
    (window units), as a fraction of `window_width` (window units): (right + gap) / width."""
    return (right + PANEL_GAP) / max(window_width, 1.0)


def draw_panel(imgui: ModuleType, model: PanelModel) -> list[Action]:
    """Draw the control panel for `model` (folded to its title bar where the window is too
    narrow for it, `_fold`); return what the user changed this frame, and where the panel
    is (its "panel_rect", window units)."""
    actions: list[Action] = []
    imgui.set_next_window_pos(imgui.ImVec2(PANEL_GAP, PANEL_GAP), imgui.Cond_.once)
    imgui.set_next_window_bg_alpha(0.85)
    flags = imgui.WindowFlags_.always_auto_resize | imgui.WindowFlags_.no_saved_settings
    folded = _fold(imgui)
    if folded:  # the title bar only as wide as its hint
        imgui.set_next_window_size(imgui.ImVec2(_folded_width(imgui), 0))
    visible, _ = imgui.begin(_title(folded), None, flags)
    pos, size = imgui.get_window_pos(), imgui.get_window_size()
    actions.append(Action("panel_rect", (pos.x, pos.y, size.x, size.y)))
    if visible:
        _surface_section(imgui, model, actions)
        _shading_section(imgui, model, actions)
        _bake_section(imgui, model, actions)
        _status_section(imgui, model, actions)
    imgui.end()
    return actions


def _fold(imgui) -> bool:
    """Fold or open the panel (called before its `begin`); return whether it is folded
    this frame.

    Dear ImGui lays a new panel out hidden in its first frame; before the next, where it
    first shows, it is folded if open it would take more than `MAX_PANEL_WIDTH` of the
    window's width (a small window: the surface stays in sight, the title bar names the
    key that opens it). Later the C key folds or opens it, as the arrow on its title bar
    does (the panel's own key: Tab is Dear ImGui's, to step through its fields).
    """
    panel = imgui.internal.find_window_by_name(PANEL_ID)
    if panel is None:  # not laid out yet
        return False
    if panel.hidden:
        width = imgui.get_io().display_size.x
        folded = room_beside(_open_right_edge(panel), width) > MAX_PANEL_WIDTH
    elif imgui.is_key_pressed(imgui.Key.c, False) and not imgui.get_io().want_text_input:
        folded = not panel.collapsed
    else:  # as it is, or as the arrow clicked in the last frame leaves it
        return panel.collapsed != panel.want_collapse_toggle
    imgui.set_next_window_collapsed(folded, imgui.Cond_.always)
    return folded


def _open_right_edge(panel) -> float:
    """Right edge (window units) of the open `panel` (a Dear ImGui window) as the content it
    laid out last asks: what its automatic size will be."""
    return panel.dc.cursor_max_pos.x + panel.window_padding.x


def _title(folded: bool) -> str:
    """The panel's title: its name, and `FOLD_HINT` while it is folded."""
    return f"isolume   {FOLD_HINT}{PANEL_ID}" if folded else f"isolume{PANEL_ID}"


def _folded_width(imgui) -> float:
    """Width (window units) of the folded panel's title bar: its arrow, title and padding."""
    style = imgui.get_style()
    text = imgui.calc_text_size(_title(True), hide_text_after_double_hash=True).x
    return text + imgui.get_font_size() + 2 * (style.item_inner_spacing.x + style.frame_padding.x)


def _width(imgui) -> float:
    """Widget width: 20 em, so it follows the font scale on HiDPI displays."""
    return 20 * imgui.get_font_size()


def _surface_section(imgui, model: PanelModel, actions: list[Action]) -> None:
    imgui.text(model.title)
    lo, hi = model.iso_range
    imgui.push_item_width(_width(imgui))
    changed, iso = imgui.slider_float("isovalue", model.iso, lo, hi, "%.5g")
    imgui.pop_item_width()
    if changed:
        actions.append(Action("iso", float(iso)))
    if imgui.button("<"):
        actions.append(Action("iso_step", -1))
    imgui.same_line()
    if imgui.button(">"):
        actions.append(Action("iso_step", 1))
    imgui.same_line()
    imgui.text_disabled(model.mesh_status)


def _shading_section(imgui, model: PanelModel, actions: list[Action]) -> None:
    imgui.separator_text("shading")
    usable = list(model.enabled)  # lattice modes appear once a lattice is shown or baked
    index = usable.index(model.mode) if model.mode in usable else 0
    imgui.push_item_width(_width(imgui))
    changed, index = imgui.combo("mode", index, usable)
    if changed:
        actions.append(Action("mode", usable[index]))
    changed, exposure = imgui.slider_float("exposure", model.exposure, 0.05, 20.0, "%.3g",
                                           imgui.SliderFlags_.logarithmic)
    if changed:
        actions.append(Action("exposure", float(exposure)))
    if model.auto_exposure is not None:
        imgui.text_disabled(f"x automatic exposure {model.auto_exposure:.3g}")
    camera_light = model.light is None
    changed, camera_light = imgui.checkbox("light follows the camera", camera_light)
    if changed:
        actions.append(Action("light_camera", camera_light))
    if model.light is not None:
        changed, angles = imgui.drag_float2("light az/el", list(model.light), 0.5, -360, 360,
                                            "%.1f")
        if changed:
            actions.append(Action("light", (float(angles[0]),
                                            float(np.clip(angles[1], -90, 90)))))
    imgui.pop_item_width()
    if model.light_note:
        imgui.text_wrapped(model.light_note)


def _bake_section(imgui, model: PanelModel, actions: list[Action]) -> None:
    if not (model.can_bake or model.bake_lines or model.can_save):
        return
    imgui.separator_text("global illumination")
    if model.bake_fractions is not None:
        visible, surface = model.bake_fractions
        size = imgui.ImVec2(_width(imgui), 0)
        imgui.progress_bar(visible, size, f"visible {visible:.0%}")
        imgui.progress_bar(surface, size, f"surface {surface:.0%}")
    for line in model.bake_lines:
        if line:  # wrapped to the panel's width: a long warning stays inside the window
            imgui.text_wrapped(line)
    if model.can_bake:
        changed, paused = imgui.checkbox("pause baking", model.bake_paused)
        if changed:
            actions.append(Action("pause_bake", paused))
        imgui.same_line()
    if model.can_save and imgui.button("save lattice"):
        actions.append(Action("save_lattice"))


def _status_section(imgui, model: PanelModel, actions: list[Action]) -> None:
    imgui.separator()
    fps = 1000.0 / model.frame_ms if model.frame_ms > 0 else 0.0
    imgui.text(f"{model.frame_ms:.1f} ms/frame ({fps:.0f} fps), {model.size[0]}x{model.size[1]}")
    if imgui.button("reset camera"):
        actions.append(Action("reset_camera"))
    imgui.same_line()
    if imgui.button("screenshot"):
        actions.append(Action("screenshot"))
    imgui.same_line()
    if imgui.button("save view"):
        actions.append(Action("save_view"))
    if model.message:
        imgui.text_wrapped(model.message)
    if imgui.collapsing_header("keys"):
        for line in model.keys_help or KEYS_HELP:
            imgui.text_disabled(line)


# -- Dear ImGui on the window -------------------------------------------------------------
class ImGuiLayer:
    """Dear ImGui drawing into the window's GL context; input fed from glfw callbacks.

    Raises ImportError when imgui-bundle is not installed (the viewer then runs without
    a panel).
    """

    imgui: ModuleType
    glfw: ModuleType

    def __init__(self, glfw: ModuleType, ui_scale: float = 1.0) -> None:
        """`ui_scale`: factor for widget and font sizes in window coordinates
        (`app.render.glcontext.Window.ui_scale`); ImGui itself renders fonts at the framebuffer's
        density."""
        from imgui_bundle import imgui

        self.imgui, self.glfw = imgui, glfw
        self.context: _imgui.internal.Context = imgui.create_context()
        io = imgui.get_io()
        io.set_ini_filename(None)  # no imgui.ini next to the user's files
        style = imgui.get_style()
        if ui_scale > 1.01:
            style.scale_all_sizes(ui_scale)
            style.font_scale_dpi = ui_scale
        if not imgui.backends.opengl3_init("#version 330"):
            imgui.destroy_context(self.context)
            raise RuntimeError("Dear ImGui's OpenGL 3 renderer failed to start")
        self._keys = _key_map(glfw, imgui)
        self._last_time: float | None = None

    # input, in window (screen) coordinates
    def mouse_pos(self, x: float, y: float) -> None:
        self.imgui.get_io().add_mouse_pos_event(x, y)

    def mouse_button(self, button: int, down: bool) -> None:
        if 0 <= button < 5:
            self.imgui.get_io().add_mouse_button_event(button, down)

    def scroll(self, dx: float, dy: float) -> None:
        self.imgui.get_io().add_mouse_wheel_event(dx, dy)

    def char(self, codepoint: int) -> None:
        if 0 < codepoint < 0x10000:
            self.imgui.get_io().add_input_character(codepoint)

    def key(self, glfw_key: int, down: bool, mods: int) -> None:
        io, imgui, glfw = self.imgui.get_io(), self.imgui, self.glfw
        io.add_key_event(imgui.Key.mod_ctrl, bool(mods & glfw.MOD_CONTROL))
        io.add_key_event(imgui.Key.mod_shift, bool(mods & glfw.MOD_SHIFT))
        io.add_key_event(imgui.Key.mod_alt, bool(mods & glfw.MOD_ALT))
        io.add_key_event(imgui.Key.mod_super, bool(mods & glfw.MOD_SUPER))
        key = self._keys.get(glfw_key)
        if key is not None:
            io.add_key_event(key, down)

    def focus(self, focused: bool) -> None:
        self.imgui.get_io().add_focus_event(bool(focused))

    @property
    def wants_mouse(self) -> bool:
        """True while the pointer is over the panel or a widget is being dragged."""
        return bool(self.imgui.get_io().want_capture_mouse)

    @property
    def wants_keyboard(self) -> bool:
        """True while a text field has the focus."""
        return bool(self.imgui.get_io().want_capture_keyboard)

    @property
    def panel_folded(self) -> bool:
        """True while the panel is folded to its title bar (`draw_panel`)."""
        panel = self.imgui.internal.find_window_by_name(PANEL_ID)
        return panel is not None and bool(panel.collapsed)

    # frames
    def new_frame(self, window_size: tuple[int, int], framebuffer_size: tuple[int, int],
                  now: float) -> None:
        """Start a UI frame: display size in screen coordinates, pixel ratio, time step."""
        imgui = self.imgui
        io = imgui.get_io()
        w, h = max(window_size[0], 1), max(window_size[1], 1)
        io.display_size = imgui.ImVec2(w, h)
        io.display_framebuffer_scale = imgui.ImVec2(framebuffer_size[0] / w,
                                                    framebuffer_size[1] / h)
        dt = now - self._last_time if self._last_time is not None else 1 / 60
        io.delta_time = max(dt, 1e-4)
        self._last_time = now
        imgui.backends.opengl3_new_frame()
        imgui.new_frame()

    def render(self) -> None:
        """Finish the UI frame and draw it over whatever the framebuffer holds."""
        self.imgui.render()
        self.imgui.backends.opengl3_render_draw_data(self.imgui.get_draw_data())

    def close(self) -> None:
        self.imgui.backends.opengl3_shutdown()
        self.imgui.destroy_context(self.context)


def _key_map(glfw, imgui) -> dict[int, object]:
    """glfw key codes → ImGui keys for the keys widgets use (navigation, editing, text
    shortcuts, digits and letters)."""
    named = {
        "TAB": "tab", "LEFT": "left_arrow", "RIGHT": "right_arrow", "UP": "up_arrow",
        "DOWN": "down_arrow", "PAGE_UP": "page_up", "PAGE_DOWN": "page_down", "HOME": "home",
        "END": "end", "INSERT": "insert", "DELETE": "delete", "BACKSPACE": "backspace",
        "SPACE": "space", "ENTER": "enter", "ESCAPE": "escape", "KP_ENTER": "keypad_enter",
        "LEFT_CONTROL": "left_ctrl", "RIGHT_CONTROL": "right_ctrl",
        "LEFT_SHIFT": "left_shift", "RIGHT_SHIFT": "right_shift",
        "LEFT_ALT": "left_alt", "RIGHT_ALT": "right_alt",
        "LEFT_SUPER": "left_super", "RIGHT_SUPER": "right_super",
        "MINUS": "minus", "PERIOD": "period", "COMMA": "comma",
    }
    keys = {getattr(glfw, f"KEY_{g}"): getattr(imgui.Key, i) for g, i in named.items()}
    for c in "ABCDEFGHIJKLMNOPQRSTUVWXYZ":
        keys[getattr(glfw, f"KEY_{c}")] = getattr(imgui.Key, c.lower())
    for d in "0123456789":
        keys[getattr(glfw, f"KEY_{d}")] = getattr(imgui.Key, f"_{d}")
    return keys

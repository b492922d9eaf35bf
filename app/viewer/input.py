"""The viewer's mouse and keyboard: glfw callbacks → the UI first, then actions.

Every event goes to the control panel (Dear ImGui, `app.viewer.panel.ImGuiLayer`) first;
what the panel does not want moves the camera or the light (drags and the wheel) or
becomes an `app.viewer.panel.Action` (keys, `app.viewer.panel.key_action`), applied by
`app.viewer.actions.Actions`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from isolume.app.viewer.actions import Actions
from isolume.app.viewer.panel import (
    ZOOM_PER_WHEEL,
    Drag,
    ImGuiLayer,
    drag_target,
    key_action,
)
from isolume.app.viewer.state import ViewerState

if TYPE_CHECKING:
    from isolume.app.render.glcontext import Window


class Input:
    """The window's input callbacks (installed by the constructor).

    Attributes:
        pending_press: what a mouse press will drag once the panel has said it does not
            take it (None: no press waits).
    """

    window: Window
    ui: ImGuiLayer | None
    state: ViewerState
    actions: Actions
    modes: tuple[str, ...]

    def __init__(self, window: Window, ui: ImGuiLayer | None, state: ViewerState,
                 actions: Actions, modes: tuple[str, ...]) -> None:
        """`window`: the `app.render.glcontext.Window`; `ui`: its `ImGuiLayer` (None: no
        panel); `modes`: shading modes in the order of the number keys."""
        self.window, self.ui, self.state, self.actions, self.modes = (
            window, ui, state, actions, modes)
        self.pending_press: str | None = None
        self._install()

    def _install(self) -> None:
        glfw, handle, state = self.window.glfw, self.window.handle, self.state
        glfw.set_cursor_pos_callback(handle, self._on_cursor)
        glfw.set_mouse_button_callback(handle, self._on_mouse_button)
        glfw.set_scroll_callback(handle, self._on_scroll)
        glfw.set_key_callback(handle, self._on_key)
        glfw.set_char_callback(handle, self._on_char)
        glfw.set_window_focus_callback(handle, self._on_focus)
        glfw.set_framebuffer_size_callback(handle, lambda *_: state.redraw())
        glfw.set_window_refresh_callback(handle, lambda *_: state.redraw())

    @property
    def ui_shown(self) -> bool:
        """The panel exists and is not hidden (``H``)."""
        return self.ui is not None and self.state.view.show_ui

    def confirm_press(self) -> None:
        """After the UI's new frame: a pending press drags the camera unless ImGui took it."""
        if self.pending_press is not None and not self.ui.wants_mouse:
            self._start_drag(self.pending_press)
        self.pending_press = None

    # -- the mouse -----------------------------------------------------------------------
    def _on_cursor(self, _handle, x: float, y: float) -> None:
        self.state.touched()
        if self.ui is not None:
            self.ui.mouse_pos(x, y)
        drag = self.state.drag
        if drag is None:
            return
        dx, dy = x - drag.x, y - drag.y
        drag.x, drag.y = x, y
        self._drag_by(drag.target, dx, dy)

    def _drag_by(self, target: str, dx: float, dy: float) -> None:
        """Move what a drag by (dx, dy) screen units moves."""
        self.actions.drag(target, dx, dy, self.window.window_size[1])

    def _on_mouse_button(self, _handle, button: int, action: int, mods: int) -> None:
        glfw = self.window.glfw
        self.state.touched()
        if self.ui is not None:
            self.ui.mouse_button(button, action == glfw.PRESS)
        if action == glfw.RELEASE:
            self.state.drag = self.pending_press = None
            return
        target = drag_target(button, bool(mods & glfw.MOD_SHIFT), bool(mods & glfw.MOD_CONTROL))
        if target is None:
            return
        if self.ui_shown:
            # ImGui decides at its next frame whether the press is its own (it only then
            # knows what lies under the pointer); `confirm_press` starts the drag if not
            self.pending_press = target
        else:
            self._start_drag(target)

    def _start_drag(self, target: str) -> None:
        x, y = self.window.glfw.get_cursor_pos(self.window.handle)
        self.state.drag = Drag(target, x, y)

    def _on_scroll(self, _handle, dx: float, dy: float) -> None:
        self.state.touched()
        if self.ui is not None:
            self.ui.scroll(dx, dy)
            if self.ui_shown and self.ui.wants_mouse:
                return
        self.actions.move_camera("zoom", ZOOM_PER_WHEEL ** -dy)

    # -- the keyboard and focus ----------------------------------------------------------
    def _on_char(self, _handle, codepoint: int) -> None:
        self.state.touched()
        if self.ui is not None:
            self.ui.char(codepoint)

    def _on_focus(self, _handle, focused: int) -> None:
        self.state.touched()
        if self.ui is not None:
            self.ui.focus(bool(focused))

    def _on_key(self, _handle, key: int, _scancode: int, action: int, mods: int) -> None:
        glfw = self.window.glfw
        self.state.touched()
        if self.ui is not None:
            self.ui.key(key, action != glfw.RELEASE, mods)
            if self.ui_shown and self.ui.wants_keyboard:
                return
        if action == glfw.RELEASE:
            return
        requested = key_action(glfw, key, mods, self.modes)
        if requested is not None:
            self.actions.apply(requested)

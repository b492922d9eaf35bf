"""Scripted input for the viewer (``isolume view --script FILE``), parsed without GL.

One command per line; ``#`` starts a comment; blank lines are ignored. Angles are degrees,
distances are in units of the volume's diagonal, times are seconds::

    iso 0.42                 # set the isovalue (extraction runs in the background)
    orbit 30 10              # add to the camera azimuth and elevation
    zoom 1.2                 # move closer by this factor (0.5 moves away)
    pan 0.1 0                # shift the view centre right/up
    reset                    # the initial camera
    mode irradiance          # shading mode
    light 45 30              # light/environment azimuth and elevation (world fixed)
    light camera             # light fixed to the camera again
    exposure 0.8             # linear exposure multiplier
    wait-mesh [TIMEOUT]      # until the full-resolution surface is on screen
    wait-gi [TIMEOUT]        # until global illumination of the isovalue is on screen (the
                             # lazy bake's first preview pass, or a lattice's texels)
    wait-bake 0.5 [TIMEOUT]  # until 50 % of the texels near the surface have samples of
                             # their own (after a turn: under the turned light): what
                             # save-lattice writes
    wait-light 1 [TIMEOUT]   # until 100 % of the visible texels show the bounced light
                             # of the sun (or light) as turned (a lazy bake re-bakes it;
                             # its previews count, and are not saved: see wait-bake)
    frames 5                 # render 5 frames
    sleep 0.5                # keep rendering for 0.5 s
    screenshot out.png       # out.png (sRGB) and out.exr (linear radiance)
    window-shot ui.png       # the whole window, UI included (PNG)
    save-view [FILE]         # what is on screen as a state file (isolume render --state)
    save-lattice [FILE]      # write the lattice being baked (default: --lattice FILE; a
                             # file shown as it is: a copy to FILE)
    check-lattice            # compare the GL textures with the lattice (tests)
    quit

Every line is checked before the window opens; errors name the line.
"""

from __future__ import annotations

import math
import os
import shlex
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from isolume.app import STARTED
from isolume.volumes.errors import IsolumeError

DEFAULT_TIMEOUT = 120.0
"""Seconds a ``wait-*`` command waits before the script fails."""


class ScriptError(IsolumeError):
    """A script line that cannot be run; the message names the file and line."""


@dataclass(frozen=True)
class Command:
    """One parsed script line.

    Attributes:
        name: the command word, e.g. "iso".
        args: converted arguments (floats, ints or strings).
        line: 1-based line number in the script.
    """

    name: str
    args: tuple[Any, ...]
    line: int


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{text!r} is not a number")
    return value


def _positive(text: str) -> float:
    value = _number(text)
    if value <= 0:
        raise ValueError(f"{text} is not positive")
    return value


def _fraction(text: str) -> float:
    value = _number(text)
    if not 0 <= value <= 1:
        raise ValueError(f"{text} is not within [0, 1]")
    return value


def _count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise ValueError(f"{text} is not a positive whole number")
    return value


def _elevation(text: str) -> float:
    value = _number(text)
    if abs(value) > 90:
        raise ValueError(f"elevation {text} is outside [-90, 90]")
    return value


def _text(text: str) -> str:
    return text


@dataclass(frozen=True)
class _Spec:
    required: tuple[Callable[[str], object], ...]
    optional: tuple[Callable[[str], object], ...]
    usage: str


_SPECS: dict[str, _Spec] = {
    "iso": _Spec((_number,), (), "iso VALUE"),
    "orbit": _Spec((_number, _number), (), "orbit D_AZIMUTH D_ELEVATION"),
    "zoom": _Spec((_positive,), (), "zoom FACTOR"),
    "pan": _Spec((_number, _number), (), "pan DX DY"),
    "reset": _Spec((), (), "reset"),
    "mode": _Spec((_text,), (), "mode NAME"),
    "light": _Spec((_text,), (_elevation,), "light AZIMUTH ELEVATION | light camera"),
    "exposure": _Spec((_positive,), (), "exposure VALUE"),
    "wait-mesh": _Spec((), (_positive,), "wait-mesh [TIMEOUT]"),
    "wait-gi": _Spec((), (_positive,), "wait-gi [TIMEOUT]"),
    "wait-bake": _Spec((_fraction,), (_positive,), "wait-bake FRACTION [TIMEOUT]"),
    "wait-light": _Spec((_fraction,), (_positive,), "wait-light FRACTION [TIMEOUT]"),
    "frames": _Spec((_count,), (), "frames N"),
    "sleep": _Spec((_positive,), (), "sleep SECONDS"),
    "screenshot": _Spec((_text,), (), "screenshot FILE.png|FILE.exr"),
    "window-shot": _Spec((_text,), (), "window-shot FILE.png"),
    "save-view": _Spec((), (_text,), "save-view [FILE]"),
    "save-lattice": _Spec((), (_text,), "save-lattice [FILE.npz]"),
    "check-lattice": _Spec((), (), "check-lattice"),
    "quit": _Spec((), (), "quit"),
}
COMMANDS: tuple[str, ...] = tuple(_SPECS)
"""Every command word, in the order of the module docstring."""


def _light_args(args: tuple, where: str) -> tuple:
    """``light camera`` or ``light AZ EL`` (two numbers)."""
    if args == ("camera",):
        return args
    if len(args) != 2:
        raise ScriptError(f"{where}: expected `light AZIMUTH ELEVATION` or `light camera`")
    try:
        return (_number(args[0]), args[1])
    except ValueError as exc:
        raise ScriptError(f"{where}: light azimuth: {exc}") from None


def parse_line(text: str, line: int, source: str = "script",
               modes: Iterable[str] | None = None) -> Command | None:
    """Parse one line (None for blank lines and comments).

    Args:
        modes: accepted shading-mode names for ``mode`` (None: any word).

    Raises:
        ScriptError: "SOURCE:LINE: what is wrong; usage".
    """
    where = f"{source}:{line}"
    try:
        words = shlex.split(text, comments=True)
    except ValueError as exc:
        raise ScriptError(f"{where}: {exc}") from None
    if not words:
        return None
    name, raw = words[0].lower(), words[1:]
    spec = _SPECS.get(name)
    if spec is None:
        raise ScriptError(f"{where}: unknown command {words[0]!r}; expected one of "
                          f"{', '.join(COMMANDS)}")
    lo, hi = len(spec.required), len(spec.required) + len(spec.optional)
    if not lo <= len(raw) <= hi:
        want = f"{lo}" if lo == hi else f"{lo} to {hi}"
        raise ScriptError(f"{where}: {name} takes {want} argument(s), got {len(raw)}; "
                          f"usage: {spec.usage}")
    args = []
    for convert, value in zip((*spec.required, *spec.optional), raw, strict=False):
        try:
            args.append(convert(value))
        except ValueError as exc:
            raise ScriptError(f"{where}: {name}: {exc}; usage: {spec.usage}") from None
    args = tuple(args)
    if name == "light":
        args = _light_args(args, where)
    if name == "mode" and modes is not None:
        modes = tuple(modes)
        if args[0] not in modes:
            raise ScriptError(f"{where}: unknown shading mode {args[0]!r}; expected one of "
                              f"{', '.join(modes)}")
    if name == "screenshot" and Path(args[0]).suffix.lower() not in (".png", ".exr"):
        raise ScriptError(f"{where}: screenshot {args[0]!r} must end in .png or .exr")
    if name == "window-shot" and Path(args[0]).suffix.lower() != ".png":
        raise ScriptError(f"{where}: window-shot {args[0]!r} must end in .png")
    return Command(name, args, line)


def parse_script(text: str, source: str = "script",
                 modes: Iterable[str] | None = None) -> list[Command]:
    """Parse a whole script; the first bad line raises `ScriptError`."""
    modes = None if modes is None else tuple(modes)
    commands = []
    for number, line in enumerate(text.splitlines(), start=1):
        command = parse_line(line, number, source, modes)
        if command is not None:
            commands.append(command)
    return commands


def load_script(path: str | os.PathLike[str], modes: Iterable[str] | None = None) -> list[Command]:
    """Read and parse a script file.

    Raises:
        ScriptError: unreadable file or a bad line.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ScriptError(f"--script {path}: cannot read it ({exc.__class__.__name__}: "
                          f"{exc})") from None
    return parse_script(text, str(path), modes)


def screenshot_paths(path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """The PNG and EXR written for a screenshot named `path` (either suffix, or none)."""
    path = Path(path)
    stem = path.with_suffix("") if path.suffix.lower() in (".png", ".exr") else path
    return stem.with_suffix(".png"), stem.with_suffix(".exr")


# -- running a script in the viewer -------------------------------------------------------
class ScriptTarget(Protocol):
    """What a script drives: the viewer's public interface, `app.viewer.actions.Actions`.

    Errors that the script should report raise `ValueError` (the viewer's `ViewerError`)."""

    def redraw(self) -> None: ...
    def request_iso(self, iso: float) -> None: ...
    def set_mode(self, mode: str) -> None: ...
    def set_exposure(self, exposure: float) -> None: ...
    def set_light(self, angles: tuple[float, float] | None, moving: bool = False) -> None: ...
    def move_camera(self, how: str, a: float, b: float = 0.0) -> None: ...
    def reset_camera(self) -> None: ...
    def request_quit(self) -> None: ...
    def screenshot(self, path: str | os.PathLike[str] | None = None) -> tuple[Path, Path]: ...
    def window_pixels(self) -> np.ndarray: ...
    def save_view(self, path: str | os.PathLike[str] | None = None) -> Path: ...
    def save_lattice(self, path: str | os.PathLike[str] | None = None) -> Path | None: ...
    def surface_ready(self) -> bool: ...
    def gi_shown(self) -> bool: ...
    def bake_progress(self) -> tuple[float | None, str | None]: ...
    def relit_progress(self) -> tuple[float | None, str | None]: ...
    def hold_bake(self, held: bool) -> None: ...
    def bake_held(self) -> bool: ...
    def check_lattice(self) -> dict[str, Any]: ...


class ScriptRunner:
    """Runs script commands between frames of a `ScriptTarget` (the viewer); waiting
    commands (frames, sleep, wait-*) keep frames coming. Errors raise `ScriptError` naming
    the line."""

    def __init__(self, commands: list[Command]) -> None:
        self.commands: deque[Command] = deque(commands)
        self.current: Command | None = None
        self.frames_left: int = 0
        self.deadline: float = 0.0
        self.started: float = 0.0
        self.pending_window_shot: Path | None = None

    @property
    def forces_frames(self) -> bool:
        """Frames, sleep and wait-mesh render continuously (frames are what they count or
        measure); wait-bake does not, so that the bake gets the processor."""
        if self.current is None:
            return bool(self.commands)
        return self.current.name in ("frames", "sleep", "wait-mesh", "window-shot")

    def step(self, viewer: ScriptTarget) -> None:
        """Run commands until one has to wait; a finished ``wait-*`` says on stderr when
        it ended, in seconds since the program started (`isolume.app.STARTED`)."""
        while True:
            if self.current is not None and not self._finished(viewer):
                return
            if self.current is not None and self.current.name.startswith("wait-"):
                print(f"script line {self.current.line}: {self.current.name} done "
                      f"{time.perf_counter() - STARTED:.1f} s after the start",
                      file=sys.stderr, flush=True)
            self.current = None
            if not self.commands:
                return
            command = self.commands.popleft()
            try:
                self._start(command, viewer)
            except ValueError as exc:
                raise ScriptError(f"script line {command.line}: {exc}") from None

    def frame_done(self) -> None:
        if self.current is not None and self.current.name == "frames":
            self.frames_left -= 1

    def before_swap(self, viewer: ScriptTarget) -> None:
        """Read the back buffer for a pending ``window-shot``."""
        if self.pending_window_shot is None:
            return
        from isolume.app.render.png import write_png

        write_png(self.pending_window_shot, viewer.window_pixels())
        self.pending_window_shot = None

    def _start(self, command: Command, viewer: ScriptTarget) -> None:
        name, args = command.name, command.args
        now = time.perf_counter()
        simple = {
            "iso": lambda: viewer.request_iso(args[0]),
            "mode": lambda: viewer.set_mode(args[0]),
            "exposure": lambda: viewer.set_exposure(args[0]),
            "reset": viewer.reset_camera,
            "quit": viewer.request_quit,
            "save-view": lambda: viewer.save_view(args[0] if args else None),
            "save-lattice": lambda: viewer.save_lattice(args[0] if args else None),
            "screenshot": lambda: viewer.screenshot(args[0]),
            "orbit": lambda: viewer.move_camera("orbit", args[0], args[1]),
            "zoom": lambda: viewer.move_camera("zoom", args[0]),
            "pan": lambda: viewer.move_camera("pan", args[0], args[1]),
            "light": lambda: viewer.set_light(None if args == ("camera",) else
                                              (args[0], args[1]), moving=True),
        }
        if name in simple:
            simple[name]()
        else:
            self._start_wait(command, viewer, now)
        viewer.redraw()

    def _start_wait(self, command: Command, viewer: ScriptTarget, now: float) -> None:
        name, args = command.name, command.args
        self.current, self.started = command, now
        if name == "frames":
            self.frames_left = args[0]
        elif name == "sleep":
            self.deadline = now + args[0]
        elif name == "window-shot":
            self.pending_window_shot = Path(args[0])
            self.frames_left = 1
        elif name in ("wait-mesh", "wait-gi"):
            self.deadline = now + (args[0] if args else DEFAULT_TIMEOUT)
        elif name == "check-lattice":
            self.deadline = now + DEFAULT_TIMEOUT
            viewer.hold_bake(True)  # the lattice stands still while it is compared
        elif name in ("wait-bake", "wait-light"):
            try:
                (viewer.bake_progress if name == "wait-bake" else viewer.relit_progress)()
            except ValueError as exc:
                raise ScriptError(f"{name}: {exc}") from None
            self.deadline = now + (args[1] if len(args) > 1 else DEFAULT_TIMEOUT)

    def _finished(self, viewer: ScriptTarget) -> bool:
        name, args = self.current.name, self.current.args
        now = time.perf_counter()
        if name == "frames":
            return self.frames_left <= 0
        if name == "window-shot":
            return self.pending_window_shot is None
        if name == "sleep":
            return now >= self.deadline
        if name == "check-lattice":
            if not viewer.bake_held():
                return self._timeout(now, "the bake to pause")
            self._check_lattice(viewer)
            return True
        if name == "wait-mesh":
            return viewer.surface_ready() or self._timeout(now, "the full-resolution surface")
        if name == "wait-gi":
            return viewer.gi_shown() or self._timeout(now, "global illumination on screen")
        if name in ("wait-bake", "wait-light"):
            progress = viewer.bake_progress if name == "wait-bake" else viewer.relit_progress
            fraction, error = progress()
            if error:
                raise ScriptError(f"script line {self.current.line}: {name}: {error}")
            done = fraction is not None and fraction >= args[0]
            what = (f"{args[0]:.0%} of the texels near the surface" if name == "wait-bake"
                    else f"{args[0]:.0%} of the visible texels under the turned light")
            if fraction is not None:
                what += f" (at {fraction:.0%})"
            return done or self._timeout(now, what)
        return True

    def _timeout(self, now: float, what: str) -> bool:
        if now < self.deadline:
            return False
        raise ScriptError(f"script line {self.current.line}: {self.current.name} waited "
                          f"{now - self.started:.0f} s for {what}")

    def _check_lattice(self, viewer: ScriptTarget) -> None:
        """Compare the textures with the lattice, then resume the bake."""
        try:
            viewer.check_lattice()
        except ValueError as exc:
            raise ScriptError(f"script line {self.current.line}: check-lattice: {exc}") from None
        finally:
            viewer.hold_bake(False)

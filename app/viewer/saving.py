"""What the viewer writes to files: screenshots (PNG and EXR), the window's pixels, the
lazily baked lattice, saved views (`app.state`) and the ``--stats`` figures (JSON)."""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume import volumes
from isolume.app.state import SUFFIX, SavedView
from isolume.app.viewer.command import Options
from isolume.app.viewer.draw import Drawing, frame_size
from isolume.app.viewer.illumination import Illumination
from isolume.app.viewer.state import ViewerError, ViewerState
from isolume.volumes.writing import atomic_write

if TYPE_CHECKING:
    from isolume.app.render.glcontext import Window


class Saver:
    """Writes the view, the window, the lattice and saved views; every file written, and
    every lattice save that writes nothing (why), is announced on stdout and in the status
    message.

    Attributes:
        options: the viewer's options (the volume as named, for saved views).
        lattice_path: ``--lattice`` (None: none), the default file of `save_lattice`.
    """

    volume: volumes.Volume
    window: Window | None
    drawing: Drawing
    state: ViewerState
    illumination: Illumination
    options: Options

    def __init__(self, volume: volumes.Volume, window: Window | None, drawing: Drawing,
                 state: ViewerState, illumination: Illumination, options: Options) -> None:
        """`window`: the `app.render.glcontext.Window` drawn into."""
        self.volume, self.window, self.drawing = volume, window, drawing
        self.state, self.illumination, self.options = state, illumination, options
        self.lattice_path: Path | None = options.lattice_path

    def _stamped(self, suffix: str) -> Path:
        """isolume-NAME-DATE-TIME + `suffix` in the working folder: the file a screenshot
        or a saved view goes to when no name is given."""
        return Path(f"isolume-{self.volume.name}-{time.strftime('%Y%m%d-%H%M%S')}{suffix}")

    def screenshot(self, path: str | os.PathLike[str] | None = None) -> tuple[Path, Path]:
        """Write the current view as PNG (sRGB) and EXR (linear radiance, before exposure)
        next to each other, framed in the whole window (`ViewerState.whole_window`: without
        the panel, nor the room left for it); returns both paths.

        Raises:
            ViewerError: the directory does not exist.
        """
        from isolume.app.render.images import write_image
        from isolume.app.viewer.script import screenshot_paths

        png, exr = screenshot_paths(self._stamped(".png") if path is None else path)
        if not png.parent.is_dir():
            raise ViewerError(f"screenshot {png}: directory {png.parent} does not exist")
        state = self.state
        frame = self.drawing.frame(state.whole_window(), state.view, frame_size(self.window))
        write_image(png, frame.linear, frame.srgb)  # each whole or not at all
        write_image(exr, frame.linear, frame.srgb)
        self._announce(f"wrote {png} and {exr}")
        return png, exr

    def window_pixels(self) -> np.ndarray:
        """(H, W, 3) uint8 of the window's back buffer, top row first (UI included)."""
        w, h = self.window.framebuffer_size
        return np.frombuffer(self.window.read_back(), np.uint8).reshape(h, w, 3)[::-1]

    def save_lattice(self, path: str | os.PathLike[str] | None = None,
                     on_exit: bool = False) -> Path | None:
        """Write the lattice being baked to `path` (default: --lattice, else
        isolume-NAME.npz; a file's lattice re-baked for a turned light: beside it, with
        ``-relit``): the texels with samples of their own, not the previews on screen.
        Unless `on_exit`, a warning follows while the bake has not given every texel near
        the surface samples (`_unfinished`). A lattice file shown as it is
        (`_save_file`): copied to another `path`, else nothing is written; nor while its
        bake for a turned light has not begun on it. Returns the file written, or None."""
        if self.illumination.relight_pending():
            self._announce("nothing saved yet: the bake for the turned light is starting "
                           "(in a script, wait-bake FRACTION waits for its texels)")
            return None
        lattice = self.illumination.snapshot()
        if lattice is None:
            return self._save_file(path)
        default = self.lattice_path or Path(f"isolume-{self.volume.name}.npz")
        relit = self.illumination.relit_file
        if relit:  # not over the file's whole bake
            default = default.with_name(f"{default.stem}-relit.npz")
        path = Path(path or default)
        lattice.save(path)
        done = int((lattice.samples > 0).sum())
        what = (f"the bounced light re-baked for the turned light, {done:,} texels computed; "
                f"{self.lattice_path} keeps its whole bake" if relit
                else f"{done:,} texels computed")
        self._announce(f"saved {path} ({what})")
        warning = None if on_exit else self._unfinished()
        if warning is not None:
            self._warn(warning)
        return path

    def _unfinished(self) -> str | None:
        """A warning while the lazy bake has not given every texel near the displayed
        surface samples of its own under the light as turned (the previews that put light
        on screen first are never saved), saying how a script waits for them; None once
        it has."""
        fraction, _ = self.illumination.bake_progress()
        if fraction is not None and fraction >= 1.0:
            return None
        share = "none" if not fraction else f"only {fraction:.0%}"
        return (f"{share} of the texels near the surface have samples of their own yet: "
                "the saved lattice holds those, not the previews on screen (in a script, "
                "wait-bake FRACTION waits for them before save-lattice)")

    def _save_file(self, path: str | os.PathLike[str] | None) -> Path | None:
        """`save_lattice` of a lattice file shown as it is (no lazy bake started): a copy
        of it at `path` when another file is named; else nothing is written, and the
        line on stdout says why. Returns the copy, or None."""
        source = self.lattice_path if self.illumination.static_lattice is not None else None
        if source is None:
            self._announce("nothing saved: no lattice is shown nor baked (--no-bake)")
            return None
        if path is None or Path(path).resolve() == source.resolve():
            self._announce(f"nothing saved: the lattice shown is {source} as it is on disk "
                           "(the viewer has baked nothing into it); save-lattice OTHER.npz "
                           "writes a copy")
            return None
        path = Path(path)
        atomic_write(path, lambda tmp: shutil.copyfile(source, tmp), "lattice")
        self._announce(f"saved {path} (a copy of {source}, shown as it is)")
        return path

    def save_view(self, path: str | os.PathLike[str] | None = None) -> Path:
        """Write what is on screen as a state file (`app.state.SavedView`) to `path`
        (default: beside the screenshots, isolume-NAME-DATE-TIME.view.json); returns it.

        Raises:
            ViewerError: the directory does not exist.
        """
        path = self._stamped(SUFFIX) if path is None else Path(path)
        if not path.parent.is_dir():
            raise ViewerError(f"save view {path}: directory {path.parent} does not exist")
        self.saved_view().save(path)
        self._announce(f"saved the view in {path} (isolume render --state {path})")
        return path

    def saved_view(self) -> SavedView:
        """The `app.state.SavedView` of what is on screen: the volume as named, the camera
        (framed in the whole window, as screenshots are), the isovalue, the shading, the
        exposure, the light and the lattice file shown."""
        state, view, options = self.state, self.state.view, self.options
        size = frame_size(self.window)
        lattice = self._lattice_file()
        env, lights = self._lighting(lattice)
        return SavedView(
            **asdict(options.source), iso=float(view.iso), camera=state.whole_window(),
            size=f"{size[0]}x{size[1]}", shading=view.shading, exposure=float(view.exposure),
            auto_exposure=options.auto_exposure,
            shown_exposure=float(self.drawing.metered(state.whole_window(), view, size).exposure),
            tonemap=self.drawing.settings(view, size).tonemap,
            albedo=",".join(repr(float(a)) for a in self.drawing.albedo), env=env,
            lights=lights, light_angles=view.light,
            lattice=None if lattice is None else str(lattice.absolute()),
            normals=options.normals, flip_normals=options.flip_normals)

    def _lattice_file(self) -> Path | None:
        """``--lattice`` when a lattice is shown (from it, or baked lazily into it and
        written there on exit), else None."""
        if self.drawing.renderer.lattice is None:
            return None
        return self.lattice_path

    def _lighting(self, lattice: Path | None) -> tuple[str | None, tuple[str, ...]]:
        """(``--env``, ``--light`` specs) of the light on screen: none for a lattice file
        (its own light); else the lazy bake's environment, its sun or directional light
        turned as the user turned it (`baking.lighting.Lighting.turned`)."""
        if lattice is not None:
            return None, ()
        env = self.options.bake_env
        turned = self.drawing.turned_light(self.state.view)
        if turned is None:
            return env, ()
        from isolume.baking.lighting import lighting_of

        return lighting_of(env).turned(turned[1]).to_spec()

    def _announce(self, message: str) -> None:
        self.state.message = message
        print(f"isolume: {message}")

    def _warn(self, message: str) -> None:
        """`message` as a warning on stdout, and under the status message."""
        self.state.message += f"\nwarning: {message}"
        print(f"isolume: warning: {message}")


def write_json(path: Path, figures: dict[str, Any]) -> None:
    """Write `figures` (NumPy scalars and arrays included) as indented JSON, whole or not
    at all (`volumes.writing.atomic_write`)."""
    text = json.dumps(figures, indent=1, default=_json_default)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text), "figures")


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")

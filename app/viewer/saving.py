"""What the viewer writes to files: screenshots (PNG and EXR), the window's pixels, the
lazily baked lattice and the ``--stats`` figures (JSON)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from isolume import volumes
from isolume.app.viewer.draw import Drawing, frame_size
from isolume.app.viewer.illumination import Illumination
from isolume.app.viewer.state import ViewerError, ViewerState


class Saver:
    """Writes the view, the window and the lattice; every file written is announced on
    stdout and in the status message.

    Attributes:
        lattice_path: ``--lattice`` (None: none), the default file of `save_lattice`.
    """

    def __init__(self, volume: volumes.Volume, window, drawing: Drawing, state: ViewerState,
                 illumination: Illumination, lattice_path: Path | None) -> None:
        """`window`: the `app.render.glcontext.Window` drawn into."""
        self.volume, self.window, self.drawing = volume, window, drawing
        self.state, self.illumination, self.lattice_path = state, illumination, lattice_path

    def screenshot(self, path: str | os.PathLike | None = None) -> tuple[Path, Path]:
        """Write the current view (without the panel) as PNG (sRGB) and EXR (linear
        radiance, before exposure) next to each other; returns both paths.

        Raises:
            ViewerError: the directory does not exist.
        """
        from isolume.app.render.images import write_exr, write_png
        from isolume.app.viewer.script import screenshot_paths

        if path is None:
            stamp = time.strftime("%Y%m%d-%H%M%S")
            path = Path(f"isolume-{self.volume.name}-{stamp}.png")
        png, exr = screenshot_paths(path)
        if not png.parent.is_dir():
            raise ViewerError(f"screenshot {png}: directory {png.parent} does not exist")
        state = self.state
        frame = self.drawing.frame(state.camera, state.view, frame_size(self.window))
        write_png(png, frame.srgb)
        write_exr(exr, frame.linear)
        self._announce(f"wrote {png} and {exr}")
        return png, exr

    def window_pixels(self) -> np.ndarray:
        """(H, W, 3) uint8 of the window's back buffer, top row first (UI included)."""
        w, h = self.window.framebuffer_size
        return np.frombuffer(self.window.read_back(), np.uint8).reshape(h, w, 3)[::-1]

    def save_lattice(self, path: str | os.PathLike | None = None) -> Path | None:
        """Write the lattice being shown/baked to `path` (default: --lattice, else
        isolume-NAME.npz; a file's lattice re-baked for a turned light: beside it, with
        ``-relit``); None when no lazy bake started."""
        lattice = self.illumination.snapshot()
        if lattice is None:
            self.state.message = "no lazily baked lattice to save"
            return None
        default = self.lattice_path or Path(f"isolume-{self.volume.name}.npz")
        if self.illumination.relit_file:  # not over the file's whole bake
            default = default.with_name(f"{default.stem}-relit.npz")
        path = Path(path or default)
        lattice.save(path)
        done = int((lattice.samples > 0).sum())
        self._announce(f"saved {path} ({done:,} texels computed)")
        return path

    def _announce(self, message: str) -> None:
        self.state.message = message
        print(f"isolume: {message}")


def write_json(path: Path, figures: dict) -> None:
    """Write `figures` (NumPy scalars and arrays included) as indented JSON."""
    path.write_text(json.dumps(figures, indent=1, default=_json_default))


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")

"""Where ``isolume movie`` writes its frames: an MP4 file (H.264 in yuv420p, through the
ffmpeg binary the ``imageio-ffmpeg`` wheel ships) or a folder of PNG frames, each frame's
shot and exposure in its text chunks."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from isolume.app.render.images import OutputError, check_output_path, unwritable
from isolume.volumes.writing import atomic_write

FRAME_PATTERN = re.compile(r"frame_\d+\.png")
"""Names of the PNG frames a movie writes (`PngFrames.name`)."""
MIN_DIGITS = 4
"""Digits of a PNG frame's number, at least (frame_0000.png)."""


def is_folder(text: str) -> bool:
    """Whether ``--out`` `text` names a folder of PNG frames: it ends in a separator or is
    an existing folder."""
    return text.endswith(("/", os.sep)) or Path(text).is_dir()


def check_movie_output(text: str, size: tuple[int, int]) -> Path:
    """The checked ``--out`` path for frames of `size` (width, height) pixels.

    Raises:
        OutputError: neither FILE.mp4 nor a folder; a missing or read-only parent folder;
            an odd width or height for MP4 (yuv420p stores colour for 2×2 pixel blocks).
    """
    path = Path(text)
    if is_folder(text):
        if path.exists() and not path.is_dir():
            raise OutputError(f"--out {text}: {path} is a file, not a folder for PNG frames")
        parent = path if path.is_dir() else path.parent
        if not parent.is_dir():
            raise OutputError(f"--out {text}: folder {parent} does not exist")
        why = unwritable(parent)
        if why is not None:
            raise OutputError(f"--out {text}: folder {parent} is not writable ({why})")
        return path
    if path.suffix.lower() != ".mp4":
        raise OutputError(f"--out {text}: expected FILE.mp4 or a folder for PNG frames "
                          "(a new folder's name ends in /)")
    check_output_path(path, (".mp4",))
    w, h = size
    if w % 2 or h % 2:
        raise OutputError(f"--size {w}x{h}: an MP4 (H.264, yuv420p) needs an even width and "
                          f"height, e.g. {w + w % 2}x{h + h % 2}; PNG frames take any size")
    return path


class PngFrames:
    """A folder of PNG frames ``frame_0000.png``, ``frame_0001.png``, ... (created if
    missing; frames of the same names are replaced).

    Args:
        folder: where the frames go.
        frames: how many the movie has (sets the digits of the names).
    """

    folder: Path
    frames: int
    digits: int

    def __init__(self, folder: Path, frames: int) -> None:
        self.folder, self.frames = Path(folder), frames
        self.digits = max(MIN_DIGITS, len(str(frames - 1)))
        self.folder.mkdir(exist_ok=True)

    def __enter__(self) -> PngFrames:
        return self

    def __exit__(self, *_exc: object) -> None:
        return None

    def name(self, index: int) -> str:
        """The file name of frame `index`."""
        return f"frame_{index:0{self.digits}d}.png"

    def write(self, index: int, srgb: np.ndarray, text: dict[str, str]) -> None:
        """Write frame `index`: (H, W, 3) uint8 sRGB, with `text` as PNG text chunks
        (deflated on every core: `app.render.png`)."""
        from isolume.app.render.png import write_png

        atomic_write(self.folder / self.name(index), lambda tmp: write_png(tmp, srgb, text),
                     "movie frame")

    def others(self) -> list[str]:
        """Names of the frame files in the folder that are not this movie's."""
        mine = {self.name(i) for i in range(self.frames)}
        return sorted(p.name for p in self.folder.iterdir()
                      if FRAME_PATTERN.fullmatch(p.name) and p.name not in mine)


class Mp4Frames:
    """An H.264 MP4 (yuv420p) written frame by frame through imageio-ffmpeg.

    Args:
        path: the FILE.mp4.
        size: (width, height) pixels, both even.
        fps: frames per second.
        crf: x264's constant rate factor, 0 (lossless) to 51.
        comment: the file's comment metadata.
    """

    def __init__(self, path: Path, size: tuple[int, int], fps: float, crf: int,
                 comment: str) -> None:
        try:
            import imageio_ffmpeg

            self._writer = imageio_ffmpeg.write_frames(
                str(path), size, fps=fps, codec="libx264", quality=None, macro_block_size=1,
                ffmpeg_log_level="error",
                output_params=["-crf", str(crf), "-preset", "medium", "-movflags",
                               "+faststart", "-metadata", f"comment={comment}"])
            self._writer.send(None)  # starts ffmpeg
        except (ImportError, OSError, RuntimeError) as exc:
            raise OutputError(f"--out {path}: cannot start ffmpeg (pip install "
                              f"imageio-ffmpeg): {exc}") from None
        self.path = path

    def __enter__(self) -> Mp4Frames:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def write(self, index: int, srgb: np.ndarray, text: dict[str, str]) -> None:
        """Append frame `index`: (H, W, 3) uint8 sRGB (`text` is not stored per frame)."""
        del index, text
        try:
            self._writer.send(np.ascontiguousarray(srgb, np.uint8).tobytes())
        except OSError as exc:
            raise OutputError(f"--out {self.path}: ffmpeg stopped: {exc}") from None

    def close(self) -> None:
        """Finish the file."""
        try:
            self._writer.close()
        except OSError as exc:
            raise OutputError(f"--out {self.path}: ffmpeg failed: {exc}") from None

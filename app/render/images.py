"""Writing pictures: sRGB PNG (display) and linear-radiance OpenEXR (analysis)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from isolume.app.render.png import write_png
from isolume.volumes.errors import IsolumeError
from isolume.volumes.writing import atomic_write


class OutputError(IsolumeError):
    """An output path that cannot be written."""


IMAGE_SUFFIXES = (".png", ".exr")


def check_output_path(path: str | os.PathLike[str],
                      suffixes: tuple[str, ...] = IMAGE_SUFFIXES) -> Path:
    """Validate an output path before any work is done.

    Raises:
        OutputError: wrong suffix, or a folder that cannot hold it (`check_output_folder`).
    """
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        expected = " or ".join(suffixes)
        raise OutputError(f"{path}: output must end in {expected}, got {path.suffix!r}")
    return check_output_folder(path)


def check_output_folder(path: str | os.PathLike[str]) -> Path:
    """`path`, whose folder exists, is a directory and is writable.

    Raises:
        OutputError: a missing folder, a file where a folder should be (the first path
            above `path` that exists is not a directory), or a folder that is not
            writable.
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        above = next((p for p in (parent, *parent.parents) if p.exists()), None)
        if above is not None and not above.is_dir():
            raise OutputError(f"{path}: {above} is not a directory")
        raise OutputError(f"{path}: directory {parent} does not exist")
    why = unwritable(parent)
    if why is not None:
        raise OutputError(f"{path}: directory {parent} is not writable ({why})")
    return path


def output_folder(path: str | os.PathLike[str], what: str = "--out") -> Path:
    """The folder `path`, made where missing (its parents too), that can take new files.

    Raises:
        OutputError: naming `what` (the option), the folder and the system's reason.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{what} {path}: exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{what} {path}: cannot make the folder "
                          f"({exc.strerror or exc})") from None
    why = unwritable(path)
    if why is not None:
        raise OutputError(f"{what} {path}: the folder is not writable ({why})")
    return path


def unwritable(folder: Path) -> str | None:
    """Why `folder` cannot take a new file (the system's reason), or None: a temporary
    file is made there and removed, which also finds read-only mounts and what a root
    user is refused, where permission bits alone do not."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            return None
    except OSError as exc:
        return exc.strerror or str(exc)


def write_exr(path: str | os.PathLike[str], linear: np.ndarray,
              extra: dict[str, np.ndarray] | None = None) -> None:
    """Write an (H, W, 3) float32 linear-radiance image as a ZIP-compressed float EXR.

    Args:
        extra: optional further channel groups, name -> (H, W) or (H, W, 3) float32
            (e.g. a per-pixel standard error).
    """
    import OpenEXR

    channels = {"RGB": np.ascontiguousarray(linear, np.float32)}
    for name, value in (extra or {}).items():
        channels[name] = np.ascontiguousarray(value, np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as exr:
        try:
            exr.write(str(path))
        except RuntimeError as exc:  # OpenEXR's failed write ('… to image file "…". Reason.')
            raise OSError(str(exc).rsplit('". ', 1)[-1].rstrip(".")) from exc


def read_exr(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read every channel group of an EXR: name -> array ("RGB" -> (H, W, 3))."""
    import OpenEXR

    with OpenEXR.File(str(path)) as exr:
        return {name: np.array(ch.pixels) for name, ch in exr.channels().items()}


def write_image(path: str | os.PathLike[str], linear: np.ndarray, srgb: np.ndarray) -> None:
    """Write `srgb` (PNG) or `linear` (EXR) according to the suffix of `path`, atomically
    (`volumes.writing.atomic_write`: a write that fails, a full disk, is one
    `WriteError` line and leaves no broken file)."""
    if Path(path).suffix.lower() == ".exr":
        atomic_write(path, lambda tmp: write_exr(tmp, linear), "picture")
    else:
        atomic_write(path, lambda tmp: write_png(tmp, srgb), "picture")

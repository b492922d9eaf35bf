"""Writing a file whole or not at all (`atomic_write`), with one-line errors: what every
layer uses for the files it writes (lattices, pictures, movie frames, meshes, views,
references, timelines)."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from isolume.volumes.errors import WriteError


def atomic_write(path: str | os.PathLike[str], write: Callable[[str], object],
                 what: str = "file", kept: str = "") -> None:
    """Call ``write(tmp)`` on a temporary file next to `path` (its name and suffix, then
    a random part), then rename it to `path`: an interrupted or failed write never leaves
    a broken file, and a file already at `path` stays until the new one replaces it.

    Raises:
        WriteError: the write failed with an `OSError` (a full disk, a quota): one line
            naming `path` as the `what`, the system's reason, and what `path` holds now
            (the file that was there, `kept` added, or nothing).
    """
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=path.suffix, dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise _unwritable(path, exc, what, kept) from exc
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise _unwritable(path, exc, what, kept) from exc
        raise


def _unwritable(path: Path, exc: OSError, what: str, kept: str) -> WriteError:
    """`atomic_write`'s one-line error."""
    left = (f"the file there is left as it was{kept}" if path.exists()
            else "nothing was written")
    return WriteError(f"{path}: cannot write the {what}: {exc.strerror or exc}; {left}",
                      subject=path)

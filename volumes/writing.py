"""Writing a file whole or not at all (`atomic_write`), with one-line errors: what every
layer uses for the files it writes (lattices, pictures and screenshots, movie frames,
meshes, saved views, HDR probes, references, timelines, the viewer's figures)."""

from __future__ import annotations

import errno
import os
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path

from isolume.volumes.errors import WriteError

_UMASK = os.umask(0o022)
os.umask(_UMASK)  # read once, as the module loads: setting it is not thread-safe
NEW_FILE_MODE = 0o666 & ~_UMASK
"""The permissions a new file gets (as `open` gives it: 0o666 less the umask)."""


def atomic_write(path: str | os.PathLike[str], write: Callable[[str], object],
                 what: str = "file", kept: str = "") -> None:
    """Call ``write(tmp)`` on a hidden temporary file beside `path` (a dot, its name, a
    random part, its suffix), then rename it to `path`: an interrupted or failed write
    never leaves a broken file, and a file already at `path` stays until the new one
    replaces it. The new file gets the old one's permissions, or a new file's
    (`NEW_FILE_MODE`); a symbolic link is written through (its target is replaced); a
    file that may not be written (read-only) is refused, as writing it in place would be.

    Raises:
        WriteError: the write failed with an `OSError` (a full disk, a quota, a read-only
            file): one line naming `path` as the `what`, the system's reason, and what
            `path` holds now (the file that was there, `kept` added, or nothing).
    """
    path = Path(path)
    target = Path(os.path.realpath(path))
    try:
        mode = stat.S_IMODE(os.stat(target).st_mode) if target.exists() else NEW_FILE_MODE
        if target.exists() and not os.access(target, os.W_OK):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES))
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=target.suffix,
                                   dir=target.parent)
        os.close(fd)
        os.chmod(tmp, mode)
    except OSError as exc:
        raise _unwritable(path, exc, what, kept) from exc
    try:
        write(tmp)
        os.replace(tmp, target)
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

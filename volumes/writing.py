"""Writing a file whole or not at all (`atomic_write`), with one-line errors: what every
layer uses for the files it writes (lattices, pictures and screenshots, movie frames,
meshes, saved views, HDR probes, references, timelines, the viewer's figures)."""

from __future__ import annotations

import errno
import os
import re
import socket
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path

from isolume.volumes.errors import WriteError

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None

_UMASK = os.umask(0o022)
os.umask(_UMASK)  # read once, as the module loads: setting it is not thread-safe
NEW_FILE_MODE = 0o666 & ~_UMASK
"""The permissions a new file gets (as `open` gives it: 0o666 less the umask)."""
HOST = re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:24]
"""This machine's name as a temporary file's name carries it (letters, digits and
hyphens, 24 at most): on a folder several machines share, a process id means something only on the
machine that wrote the file."""


def atomic_write(path: str | os.PathLike[str], write: Callable[[str], object],
                 what: str = "file", kept: str = "", durable: bool = False) -> None:
    """Call ``write(tmp)`` on a hidden temporary file beside `path` (a dot, its name, the
    writing machine's name (`HOST`) and process id, a random part, its suffix), then
    rename it to `path`: an interrupted or failed write never leaves a broken file, and a
    file already at `path` stays until the new one replaces it. The new file gets the old
    one's permissions, or a new file's (`NEW_FILE_MODE`); a symbolic link is written
    through (its target is replaced); a file that may not be written (read-only) is
    refused, as writing it in place would be. With `durable` (the lattice files a bake
    resumes from), the file's data and then the rename reach the disk before it returns
    (`_sync`), so that the file survives a power cut, not only a killed process; and the
    temporary files that earlier writes of `path` left in processes since gone (killed
    mid-write: a lattice's can take gigabytes) are removed first, where they can be
    (`_remove_orphans`).

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
        if durable:
            _remove_orphans(target)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.{HOST}-{os.getpid()}.",
                                   suffix=target.suffix, dir=target.parent)
        os.close(fd)
        os.chmod(tmp, mode)
    except OSError as exc:
        raise _unwritable(path, exc, what, kept) from exc
    try:
        write(tmp)
        if durable:
            _sync(tmp)
        os.replace(tmp, target)
        if durable:
            _sync_folder(target.parent)
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


def _sync(path: str | os.PathLike[str], flags: int = os.O_RDWR) -> None:
    """Flush the file `path`, opened with `flags` (Windows flushes only a file open for
    writing), to the disk: ``F_FULLFSYNC`` where the system has it (macOS, whose
    ``fsync`` leaves the data in the drive's cache), else ``fsync``. A file system that
    cannot (``EINVAL``: some network and virtual ones) is taken as it is."""
    try:
        fd = os.open(path, flags)
    except PermissionError:  # a file whose mode lets this user read it only
        fd = os.open(path, os.O_RDONLY)
    try:
        _flush(fd)
    except OSError as exc:
        if exc.errno != errno.EINVAL:
            raise
    finally:
        os.close(fd)


def _flush(fd: int) -> None:
    """``F_FULLFSYNC`` of `fd` where the system has it and the file system takes it, else
    ``fsync``."""
    full = getattr(fcntl, "F_FULLFSYNC", None) if fcntl is not None else None
    if full is not None:
        try:
            fcntl.fcntl(fd, full)
            return
        except OSError:
            pass
    os.fsync(fd)


def _sync_folder(folder: Path) -> None:
    """Flush the entries of `folder` (a rename in it) to the disk, where its file system
    lets a folder be opened and flushed (not on Windows): the file is in place either
    way."""
    try:
        _sync(folder, os.O_RDONLY)
    except OSError:
        pass


def _remove_orphans(target: Path) -> None:
    """Remove the hidden temporary files `atomic_write` left beside `target` in processes
    of this machine that are gone (a SIGKILL or a power cut mid-write): names of its
    pattern with this `HOST` whose process id names no running process. A file whose
    process lives (another write of `target` under way, or an unrelated process that took
    the id), or another machine's (its processes are not seen from here), is left alone;
    so is one this process may not remove or a folder it may not list (another user's
    file in a shared folder): the cleanup never stops the write."""
    pattern = re.compile(rf"\.{re.escape(target.name)}\.{re.escape(HOST)}-(\d+)\."
                         rf"[A-Za-z0-9_]{{8}}{re.escape(target.suffix)}")
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return
    for entry in entries:
        found = pattern.fullmatch(entry.name)
        try:
            if found is not None and entry.is_file(follow_symlinks=False) \
                    and not _running(int(found.group(1))):
                Path(entry.path).unlink(missing_ok=True)
        except OSError:
            continue


def _running(pid: int) -> bool:
    """Whether a process `pid` exists (one of another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except (OverflowError, OSError):  # not a process id
        return False
    return True

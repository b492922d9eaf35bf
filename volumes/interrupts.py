"""Ctrl-C where Python would lose it: `on_interrupt`, the SIGINT handler the command line
installs (`install`), raises KeyboardInterrupt as Python's own does, except inside a
callback that C code makes into Python (llvmlite's, as numba compiles a kernel on the main
thread), a finaliser or a weak reference's callback — where Python prints the
KeyboardInterrupt and goes on, so that the command ignores the Ctrl-C or fails later
(numba's "no compiled object yet") — it sends the signal again `RESEND_S` later, once the
callback has returned. A Ctrl-C at a random moment of twelve kernels compiled on the main
thread: with Python's handler 16 of 60 were ignored, with this one none of 60.

SIGTERM and SIGHUP stop a command as a Ctrl-C does (`on_terminate`): a batch system's
time limit (SLURM sends SIGTERM, then SIGKILL 30 s later by default), a `kill`, a closed
terminal — a bake keeps its finished texels, the viewer closes its bake process and its
shared memory."""

from __future__ import annotations

import os
import signal
import threading
from types import FrameType

RESEND_S = 0.05
"""Seconds after which a Ctrl-C that came inside a callback is sent again."""
CALLBACKS = {("executionengine.py", "_raw_object_cache_notify"),
             ("executionengine.py", "_raw_object_cache_getbuffer")}
"""(file, function) of the callbacks from C code that a Ctrl-C must not interrupt:
llvmlite's, with which numba takes a kernel's machine code as it compiles (the first run
on a machine); interrupted, the kernel has no code and numba fails with RuntimeError."""


TERMINATING = (signal.SIGTERM, signal.SIGHUP)
"""Signals that stop a command as a Ctrl-C does (`on_terminate`)."""

_TERMINALS: dict[int, int | None] = {}
"""{descriptor: device number} of standard output and error where they were a terminal
when `install` ran."""


def install() -> None:
    """On the main thread, make `on_interrupt` SIGINT's handler where Python's own is,
    and `on_terminate` the handler of each `TERMINATING` signal that has its default
    action (another handler, an application's, or a signal ignored, as SIGHUP under
    nohup, is left as it is). A process forked after this starts with their default
    actions."""
    if threading.current_thread() is not threading.main_thread():
        return
    _TERMINALS.update({fd: _device(fd) for fd in (1, 2) if os.isatty(fd)})
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, on_interrupt)
    for signum in TERMINATING:
        if signal.getsignal(signum) is signal.SIG_DFL:
            signal.signal(signum, on_terminate)
    os.register_at_fork(after_in_child=_default_termination)


def on_terminate(signum: int, frame: FrameType | None) -> None:
    """A `TERMINATING` signal's handler: what a Ctrl-C does now — SIGINT's current
    handler (`on_interrupt`; while a finished bake saves, the save's, which lets it end
    first), or `on_interrupt` where SIGINT is ignored (a shell's background job); after
    a hangup, with the terminal left first (`_leave_terminal`)."""
    if signum == signal.SIGHUP:
        _leave_terminal()
    handler = signal.getsignal(signal.SIGINT)
    (handler if callable(handler) else on_interrupt)(signal.SIGINT, frame)


def _leave_terminal() -> None:
    """Point standard output and error, where they were a terminal when the handlers were
    installed (`_TERMINALS`), at the null device: after a hangup the terminal refuses
    writes (EIO; and `os.isatty` says False), and a message or a progress bar would stop
    the save of a bake's finished texels with an OSError."""
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd, device in _TERMINALS.items():
            if _device(fd) == device:
                os.dup2(null, fd)
    finally:
        os.close(null)


def _device(fd: int) -> int | None:
    """The device number of what the descriptor `fd` refers to; None where it is closed."""
    try:
        return os.fstat(fd).st_rdev
    except OSError:
        return None


def _default_termination() -> None:
    """Give a forked child the default action of each `TERMINATING` signal the parent
    handles with `on_terminate` (the child's SIGINT may be ignored, and a pool's or the
    viewer's bake process must end on the SIGTERM that stops it)."""
    for signum in TERMINATING:
        if signal.getsignal(signum) is on_terminate:
            signal.signal(signum, signal.SIG_DFL)


def raises_keyboard_interrupt(handler: object) -> bool:
    """Whether a stop raises KeyboardInterrupt under the SIGINT `handler`: Python's own or
    `on_interrupt` (a Ctrl-C), or SIGINT ignored (a shell's background job) while SIGTERM
    is `on_terminate`'s, which then calls `on_interrupt`."""
    return handler is signal.default_int_handler or handler is on_interrupt or (
        handler is signal.SIG_IGN and signal.getsignal(signal.SIGTERM) is on_terminate)


def on_interrupt(signum: int, frame: FrameType | None) -> None:
    """SIGINT's handler: KeyboardInterrupt, or, inside a callback (`in_callback`), the
    signal sent again `RESEND_S` later."""
    if in_callback(frame):
        resend = threading.Timer(RESEND_S, os.kill, (os.getpid(), signum))
        resend.daemon = True
        resend.start()
        return
    raise KeyboardInterrupt


def in_callback(frame: FrameType | None) -> bool:
    """Whether `frame` or a caller of it runs a callback of `CALLBACKS`, a ``__del__`` or
    the code of the standard library's `weakref` (its callbacks, run as objects are
    collected)."""
    while frame is not None:
        code = frame.f_code
        file = os.path.basename(code.co_filename)
        if code.co_name == "__del__" or file == "weakref.py" or \
                (file, code.co_name) in CALLBACKS:
            return True
        frame = frame.f_back
    return False

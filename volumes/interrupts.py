"""Ctrl-C where Python would lose it: `on_interrupt`, the SIGINT handler the command line
installs (`install`), raises KeyboardInterrupt as Python's own does, except inside a
callback that C code makes into Python (llvmlite's, as numba compiles a kernel on the main
thread), a finaliser or a weak reference's callback — where Python prints the
KeyboardInterrupt and goes on, so that the command ignores the Ctrl-C or fails later
(numba's "no compiled object yet") — it sends the signal again `RESEND_S` later, once the
callback has returned. A Ctrl-C at a random moment of twelve kernels compiled on the main
thread: with Python's handler 16 of 60 were ignored, with this one none of 60."""

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


def install() -> None:
    """Make `on_interrupt` SIGINT's handler where Python's own is (on the main thread;
    another handler, an application's, is left as it is)."""
    if threading.current_thread() is threading.main_thread() \
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, on_interrupt)


def raises_keyboard_interrupt(handler: object) -> bool:
    """Whether the SIGINT `handler` is Python's own or `on_interrupt`: one that raises
    KeyboardInterrupt."""
    return handler is signal.default_int_handler or handler is on_interrupt


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

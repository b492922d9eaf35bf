"""`IsolumeError`: the base of every error isolume raises for bad input; `interrupted_by`:
whether an error is how a Ctrl-C came out of a library.

It lives on the ground floor (`isolume.volumes` imports nothing of isolume's) so that every
layer can raise it; each layer derives its own errors from it (`VolumeError`,
`baking.errors.BakeError`, `app.render.settings.RenderError`, …). The command line turns
any of them into one line on stderr and exit status 2; anything else is a bug and keeps
its traceback.
"""

from __future__ import annotations


class IsolumeError(ValueError):
    """Bad input: the message names the file or value and says what was expected.

    Attributes:
        subject: the file, option or value that was wrong (None when the message says it).
        expected: what was expected instead (None when the message says it).
    """

    def __init__(self, message: str, *, subject: object = None,
                 expected: str | None = None) -> None:
        super().__init__(message)
        self.subject = subject
        self.expected = expected


class WriteError(IsolumeError):
    """A file that could not be written (a full disk, a quota, a device gone): the message
    names it, the system's reason and what its path holds now."""


def interrupted_by(error: BaseException) -> bool:
    """Whether `error` is a Ctrl-C, or carries one in its chain of causes: a
    KeyboardInterrupt raised while numba loads a kernel from its cache comes out of the
    call as a ``SystemError`` whose context is the interrupt."""
    seen: BaseException | None = error
    met: set[int] = set()
    while seen is not None and id(seen) not in met:  # a re-raise can close the chain
        if isinstance(seen, KeyboardInterrupt):
            return True
        met.add(id(seen))
        seen = seen.__cause__ or seen.__context__
    return False

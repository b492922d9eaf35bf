"""`IsolumeError`: the base of every error isolume raises for bad input.

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

"""The error raised for bad bake input (configuration, lattice files, light specs), and the
interrupt of a bake that saved its finished texels."""


from isolume.volumes.errors import IsolumeError


class BakeError(IsolumeError):
    """Bad bake input; the one-line message names the file or value and what was expected."""


class BakeInterrupted(KeyboardInterrupt):
    """A Ctrl-C that stopped a bake after its `finished` texels (those with paths) were
    saved to its file (`baking.bake.bake`): a KeyboardInterrupt that knows the count, so
    that nobody reads the file again to tell it (2.7 s for the 512³ foot's)."""

    def __init__(self, finished: int) -> None:
        super().__init__(finished)
        self.finished = finished


class SaveAbandoned(KeyboardInterrupt):
    """A second Ctrl-C that stopped the save of a bake's `finished` texels (interrupted,
    or done: `baking.bake.bake`): the file keeps what it held before (its last save, or
    nothing), the texels traced since are given up."""

    def __init__(self, finished: int) -> None:
        super().__init__(finished)
        self.finished = finished

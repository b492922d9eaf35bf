"""The error raised for bad bake input (configuration, lattice files, light specs)."""


class BakeError(ValueError):
    """Bad bake input; the one-line message names the file or value and what was expected."""

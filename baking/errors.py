"""The error raised for bad bake input (configuration, lattice files, light specs)."""


from isolume.volumes.errors import IsolumeError


class BakeError(IsolumeError):
    """Bad bake input; the one-line message names the file or value and what was expected."""

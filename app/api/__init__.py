"""isolume from Python: load a volume, render its isosurface with global illumination,
bake illumination lattices, export lit meshes, make movies and reference images, all in
this process (one GL context kept across calls), and look at it in a notebook.

    import isolume
    volume = isolume.load("synthetic:engine:64")
    isolume.render(volume, size=(256, 256)).save("engine.png")
    lattice = isolume.bake(volume, samples=64, out="engine.npz")
    isolume.render(volume, lattice=lattice)            # a Picture; a notebook shows it

Every function's keyword arguments are the options of the command of the same name
(``isolume render --env-rotation 30,0`` is ``isolume.render(v, env_rotation=(30, 0))``),
with the same defaults; errors are `IsolumeError`s with the commands' one-line messages.
Names load when first used (PEP 562): ``import isolume`` loads neither OpenGL nor the
baker. The stability policy is in docs/python.md.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if __name__ != "isolume":  # app/api is the package `isolume`, never `isolume.app.api`
    raise ImportError(f"{__name__}: import isolume instead (one name for one module)")

if TYPE_CHECKING:
    from isolume._calls import bake as bake
    from isolume._calls import export as export
    from isolume._calls import info as info
    from isolume._calls import load as load
    from isolume._calls import movie as movie
    from isolume._calls import reference as reference
    from isolume._calls import render as render
    from isolume._calls import show as show
    from isolume._picture import Picture as Picture
    from isolume.app.notebook_view import NotebookView as NotebookView
    from isolume.app.state import SavedView as View
    from isolume.baking.lattice import Lattice as Lattice
    from isolume.volumes.core import Volume as Volume
    from isolume.volumes.errors import IsolumeError as IsolumeError
    from isolume.volumes.stats import VolumeInfo as VolumeInfo

__all__ = [
    "IsolumeError",
    "Lattice",
    "NotebookView",
    "Picture",
    "View",
    "Volume",
    "VolumeInfo",
    "__version__",
    "bake",
    "export",
    "info",
    "load",
    "movie",
    "reference",
    "render",
    "show",
]

_WHERE = {
    "load": ("isolume._calls", "load"),
    "render": ("isolume._calls", "render"),
    "bake": ("isolume._calls", "bake"),
    "export": ("isolume._calls", "export"),
    "info": ("isolume._calls", "info"),
    "movie": ("isolume._calls", "movie"),
    "reference": ("isolume._calls", "reference"),
    "show": ("isolume._calls", "show"),
    "Picture": ("isolume._picture", "Picture"),
    "View": ("isolume.app.state", "SavedView"),
    "Lattice": ("isolume.baking.lattice", "Lattice"),
    "Volume": ("isolume.volumes.core", "Volume"),
    "VolumeInfo": ("isolume.volumes.stats", "VolumeInfo"),
    "IsolumeError": ("isolume.volumes.errors", "IsolumeError"),
}
"""Public name → (module, attribute), imported on first use."""


def __getattr__(name: str) -> object:
    if name == "__version__":
        from importlib.metadata import version

        value: object = version("isolume")
    elif name == "NotebookView":  # the notebook extras may be missing: a one-line error
        from isolume.app.notebook import notebook_view_class

        value = notebook_view_class()
    elif name in _WHERE:
        module, attribute = _WHERE[name]
        value = getattr(importlib.import_module(module), attribute)
    else:
        raise AttributeError(f"module 'isolume' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))

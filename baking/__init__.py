"""Baking: illumination lattices computed by Monte Carlo path tracing with Embree.

Needs no display and no GL. The only module importing ``embreex`` is `baking.trace`,
and it is imported only when a bake actually runs. The names below load when first used
(PEP 562): ``import isolume.baking`` compiles no kernel.
"""

import sys
import types
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from isolume.baking.bake import bake
    from isolume.baking.config import BakeConfig
    from isolume.baking.errors import BakeError
    from isolume.baking.lattice import Lattice, LatticeGeometry

__all__ = ["BakeConfig", "BakeError", "Lattice", "LatticeGeometry", "bake"]

_WHERE = {"bake": "bake", "BakeConfig": "config", "BakeError": "errors",
          "Lattice": "lattice", "LatticeGeometry": "lattice"}
"""Public name → the module of `isolume.baking` that defines it."""


def __getattr__(name: str) -> object:
    if name not in _WHERE:
        raise AttributeError(f"module 'isolume.baking' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"isolume.baking.{_WHERE[name]}"), name)
    globals()[name] = value
    return value


class _Baking(types.ModuleType):
    """This package, whose ``bake`` stays the function when its module `baking.bake` is
    imported (the import system then sets the package's attribute of that name)."""

    def __setattr__(self, name: str, value: object) -> None:
        if name == "bake" and isinstance(value, types.ModuleType):
            value = value.bake
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Baking

"""Baking: illumination lattices computed by Monte Carlo path tracing with Embree.

Needs no display and no GL. The only module importing ``embreex`` is `baking.trace`,
and it is imported only when a bake actually runs.
"""

from .bake import bake
from .config import BakeConfig
from .errors import BakeError
from .lattice import Lattice, LatticeGeometry

__all__ = ["BakeConfig", "BakeError", "Lattice", "LatticeGeometry", "bake"]

"""Baking: illumination lattices computed by Monte Carlo path tracing with Embree.

Needs no display and no GL. The only module importing ``embreex`` is `baking.trace`,
and it is imported only when a bake actually runs.
"""

from isolume.baking.bake import bake
from isolume.baking.config import BakeConfig
from isolume.baking.errors import BakeError
from isolume.baking.lattice import Lattice, LatticeGeometry

__all__ = ["BakeConfig", "BakeError", "Lattice", "LatticeGeometry", "bake"]

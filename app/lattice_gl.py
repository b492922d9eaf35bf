"""Illumination lattices as 3-D textures.

Irradiance: one GL_RGB9_E5 texture (4 bytes per texel, shared exponent: relative error
≤ 2⁻⁹ of the brightest channel) holding E·valid, plus one R8 texture holding `valid`
(1 where the texel has samples). Both are filtered trilinearly by the hardware; the shader
divides the two, which interpolates over computed texels only, and falls back to local
shading where no neighbour is computed yet. Sub-regions can be re-uploaded while a lazy
bake fills the lattice.

numpy (z, y, x, c) arrays map to GL (width, height, depth) = (x, y, z): x varies fastest
in memory, as GL expects.
"""

from __future__ import annotations

import moderngl
import numpy as np

from baking.lattice import Lattice

from .glcontext import store_rgb9e5


class LatticeTextures:
    """GL textures of one lattice, with the uniforms that map world → texture space."""

    def __init__(self, ctx: moderngl.Context, lattice: Lattice) -> None:
        if lattice.kind != "irradiance":
            raise ValueError(f"lattice kind {lattice.kind!r}: only irradiance is drawn here")
        self.ctx = ctx
        self.lattice = lattice
        z, y, x = lattice.geometry.shape
        self.irradiance = ctx.texture3d((x, y, z), 3, dtype="f4")
        store_rgb9e5(ctx, self.irradiance, self._premultiplied(lattice.values, lattice.samples))
        self.valid = ctx.texture3d((x, y, z), 1, self._valid_bytes(lattice.samples), dtype="f1")
        for tex in (self.irradiance, self.valid):
            tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            tex.repeat_x = tex.repeat_y = tex.repeat_z = False  # clamp to edge
        lo, hi = np.array(lattice.geometry.lo), np.array(lattice.geometry.hi)
        self.box_lo, self.box_size = lo, hi - lo

    @staticmethod
    def _premultiplied(values: np.ndarray, samples: np.ndarray) -> np.ndarray:
        return np.where(samples[..., None] > 0, values[..., :3], 0).astype(np.float32)

    @staticmethod
    def _valid_bytes(samples: np.ndarray) -> bytes:
        return np.where(samples > 0, 255, 0).astype(np.uint8).tobytes()

    def update(self, z0: int, z1: int) -> None:
        """Re-upload slabs z0 ≤ z < z1 of the lattice (after a lazy bake filled them)."""
        lat = self.lattice
        _, y, x = lat.geometry.shape
        values = self._premultiplied(lat.values[z0:z1], lat.samples[z0:z1])
        viewport = (0, 0, z0, x, y, z1 - z0)
        self.irradiance.write(values.tobytes(), viewport=viewport)
        self.valid.write(self._valid_bytes(lat.samples[z0:z1]), viewport=viewport)

    def bind(self, program: moderngl.Program, first_unit: int = 1) -> None:
        """Bind the textures to units first_unit.. and set the mapping uniforms."""
        self.irradiance.use(location=first_unit)
        self.valid.use(location=first_unit + 1)
        values = {"u_irradiance": first_unit, "u_valid": first_unit + 1,
                  "u_box_lo": tuple(self.box_lo), "u_box_size": tuple(self.box_size)}
        for name, value in values.items():
            if name in program:
                program[name].value = value

    def release(self) -> None:
        self.irradiance.release()
        self.valid.release()

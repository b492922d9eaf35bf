"""Illumination lattices as 3-D textures.

SH transfer: ⌈n²/4⌉ RGBA16F textures holding τ·valid, four coefficients each (three such
groups for coloured transfer, one per channel), plus the same `valid` texture. The shader
forms E = Σ τ_i ℓ_i with the environment's coefficients ℓ (rotated on the CPU) as uniforms.
GL 3.3 guarantees 16 texture units in a fragment shader: gray transfer up to order 7,
coloured up to order 4.

Irradiance: one GL_RGB9_E5 texture (4 bytes per texel, shared exponent: relative error
≤ 2⁻⁹ of the brightest channel) holding E·valid, plus one R8 texture holding `valid`
(1 where the texel has samples). Both are filtered trilinearly by the hardware; the shader
divides the two, which interpolates over computed texels only, and falls back to local
shading where no neighbour is computed yet. Sub-regions can be re-uploaded while a lazy
bake fills the lattice. Optionally a third, R32F texture holds each texel's own isovalue
ρ(x_t), for the closest-isovalue lookup (paper Fig. 6a); it depends on the volume only,
so a bake never changes it.

Facing: an RG8 texture of each shown texel's facing (`baking.Lattice.displayed_facing`:
octahedral bytes, (0, 0) unknown), read with texelFetch by the side-aware lookup
(``lattice.glsl``, FACING 1: `facing_known`); 2 bytes per texel beside irradiance's 5.

numpy (z, y, x, c) arrays map to GL (width, height, depth) = (x, y, z): x varies fastest
in memory, as GL expects.
"""

from __future__ import annotations

import moderngl
import numpy as np

from isolume.app.render.glcontext import store_rgb9e5
from isolume.baking.lattice import FACING_POWER, SIDE_BLEND, Lattice
from isolume.baking.sh import transfer_blocks

MAX_TEXTURE_UNITS = 16  # guaranteed by GL 3.3 for fragment shaders
SH_FIRST_UNIT = 2  # units 0: HDR resolve input or shadow map, 1: valid mask


def sh_layout(order: int, rgb: bool, blocks: int = 1) -> tuple[int, int]:
    """(textures per colour group, groups) for SH transfer of `order` bands in `blocks`
    transfer blocks (2 for a split transfer: `baking.sh.transfer_blocks`).

    Raises:
        ValueError: when the textures would not fit the fragment shader's units.
    """
    per_group = -(-blocks * order * order // 4)
    groups = 3 if rgb else 1
    if SH_FIRST_UNIT + per_group * groups + 1 > MAX_TEXTURE_UNITS:  # + the facings
        limit = "7" if not rgb else "4"
        split = " split" if blocks > 1 else ""
        raise ValueError(f"SH order {order}{split} needs {per_group * groups} textures; the "
                         f"renderer draws {'coloured' if rgb else 'gray'} transfer up to "
                         f"order {limit} (split: fewer)")
    return per_group, groups


class LatticeTextures:
    """GL textures of one lattice, with the uniforms that map world → texture space.

    Attributes:
        kind: "irradiance" or "sh".
        sh_order, sh_groups, sh_textures: SH layout (order, 1 or 3 colour groups, textures
            per group); zeros for irradiance.
        sh_coefficients: transfer coefficients per colour: n², or 2n² for a split
            transfer (direct, then indirect; `u_light` then holds the sun-free sky's
            coefficients, then the whole sky's).
        texel_iso: R32F texture of the texel isovalues ρ(x_t), or None (not given, or an
            SH lattice: the lookup variants read irradiance lattices only).
        facing: RG8 texture of the texels' facings (`baking.Lattice.displayed_facing`).
        facing_known: whether any uploaded texel has a known facing (the FACING define:
            without one, the lookup is the plain trilinear one, exactly).
    """

    def __init__(self, ctx: moderngl.Context, lattice: Lattice,
                 texel_isovalues: np.ndarray | None = None) -> None:
        """Upload `lattice`; `texel_isovalues` is (Z, Y, X) ρ at the texel centres (value
        units, `baking.plan.texel_values`) for the closest-isovalue lookup."""
        if texel_isovalues is not None and np.shape(texel_isovalues) != lattice.geometry.shape:
            raise ValueError(f"texel isovalues of shape {np.shape(texel_isovalues)}, the "
                             f"lattice has {lattice.geometry.shape}")
        self.ctx = ctx
        self.lattice = lattice
        self.kind = lattice.kind
        z, y, x = lattice.geometry.shape
        shown = lattice.shown()
        self.valid = ctx.texture3d((x, y, z), 1, self._valid_bytes(shown), dtype="f1")
        self.sh_order = self.sh_groups = self.sh_textures = self.sh_coefficients = 0
        if self.kind == "irradiance":
            self.irradiance = ctx.texture3d((x, y, z), 3, dtype="f4")
            store_rgb9e5(ctx, self.irradiance, lattice.displayed()[..., :3])
            self.textures = [self.irradiance]
        elif self.kind == "sh":
            self.sh_order = int(lattice.meta["sh_order"])
            blocks = transfer_blocks(lattice)  # 2: direct, indirect transfer
            self.sh_coefficients = blocks * self.sh_order**2
            rgb = lattice.values.shape[-1] != self.sh_coefficients
            self.sh_textures, self.sh_groups = sh_layout(self.sh_order, rgb, blocks)
            self.textures = [ctx.texture3d((x, y, z), 4, dtype="f2")
                             for _ in range(self.sh_textures * self.sh_groups)]
            self._write_sh(0, z)
        else:
            raise ValueError(f"lattice kind {self.kind!r} is not drawable")
        for tex in (*self.textures, self.valid):
            tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            tex.repeat_x = tex.repeat_y = tex.repeat_z = False  # clamp to edge
        facing = lattice.displayed_facing()
        self.facing = ctx.texture3d((x, y, z), 2, np.ascontiguousarray(facing).tobytes(),
                                    dtype="f1", alignment=1)
        self.facing.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.facing_known = bool(facing.any())
        self.texel_iso = None
        if texel_isovalues is not None and self.kind == "irradiance":
            self.texel_iso = self._texel_iso_texture(texel_isovalues)
        lo, hi = np.array(lattice.geometry.lo), np.array(lattice.geometry.hi)
        self.box_lo, self.box_size = lo, hi - lo

    def _texel_iso_texture(self, rho: np.ndarray) -> moderngl.Texture3D:
        """R32F texture of (Z, Y, X) texel isovalues, read with texelFetch only."""
        z, y, x = self.lattice.geometry.shape
        data = np.ascontiguousarray(rho, np.float32).tobytes()
        tex = self.ctx.texture3d((x, y, z), 1, data, dtype="f4")
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        return tex

    def _sh_groups(self, z0: int, z1: int) -> list[np.ndarray]:
        """(z, y, x, 4) float16 arrays, one per texture: τ·valid, four coefficients each."""
        lat = self.lattice
        values = lat.displayed(np.s_[z0:z1])  # zero where nothing is shown
        n2 = self.sh_coefficients
        values = values.reshape(*values.shape[:3], n2, -1)  # (..., n², 1 or 3)
        padded = np.zeros((*values.shape[:3], self.sh_textures * 4, values.shape[-1]),
                          np.float16)
        padded[..., :n2, :] = values
        out = []
        for channel in range(self.sh_groups):
            for t in range(self.sh_textures):
                out.append(np.ascontiguousarray(padded[..., 4 * t:4 * t + 4, channel]))
        return out

    def _write_sh(self, z0: int, z1: int) -> None:
        _, y, x = self.lattice.geometry.shape
        for tex, data in zip(self.textures, self._sh_groups(z0, z1), strict=True):
            tex.write(data.tobytes(), viewport=(0, 0, z0, x, y, z1 - z0))

    @staticmethod
    def _valid_bytes(shown: np.ndarray) -> bytes:
        return np.where(shown, 255, 0).astype(np.uint8).tobytes()

    def update(self, z0: int, z1: int) -> None:
        """Re-upload slabs z0 ≤ z < z1 of the lattice (after a lazy bake filled them); the
        texel isovalues do not change with the bake and stay as uploaded."""
        lat = self.lattice
        _, y, x = lat.geometry.shape
        viewport = (0, 0, z0, x, y, z1 - z0)
        shown = lat.shown(np.s_[z0:z1])
        if self.kind == "irradiance":
            values = np.ascontiguousarray(lat.displayed(np.s_[z0:z1])[..., :3])
            self.irradiance.write(values.tobytes(), viewport=viewport)
        else:
            self._write_sh(z0, z1)
        self.valid.write(self._valid_bytes(shown), viewport=viewport)
        self._write_facing(np.s_[z0:z1], viewport)

    def write_box(self, lo: tuple[int, int, int], hi: tuple[int, int, int]) -> None:
        """Re-upload texels lo ≤ (z, y, x) < hi of an irradiance lattice (values, valid
        mask and facings; the viewer's block-wise uploads)."""
        lat = self.lattice
        (z0, y0, x0), (z1, y1, x1) = lo, hi
        region = np.s_[z0:z1, y0:y1, x0:x1]
        premultiplied = np.ascontiguousarray(lat.displayed(region)[..., :3])  # 0: not shown
        viewport = (x0, y0, z0, x1 - x0, y1 - y0, z1 - z0)
        self.irradiance.write(premultiplied.tobytes(), viewport=viewport, alignment=4)
        self.valid.write(self._valid_bytes(lat.shown(region)), viewport=viewport,
                         alignment=1)
        self._write_facing(region, viewport)

    def _write_facing(self, region: tuple, viewport: tuple) -> None:
        """Upload the facings of `region` (slices of (Z, Y, X)) into `viewport`."""
        facing = np.ascontiguousarray(self.lattice.displayed_facing(region))
        self.facing.write(facing.tobytes(), viewport=viewport, alignment=1)
        self.facing_known = self.facing_known or bool(facing.any())

    @property
    def units(self) -> int:
        """Texture units `bind` takes."""
        return 2 + len(self.textures) + (self.texel_iso is not None)  # + valid, facing

    def bind(self, program: moderngl.Program) -> None:
        """Bind the textures (valid on unit 1, the rest from unit 2, then the texel
        isovalues, the facings last) and set the uniforms that map world positions to
        texture coordinates."""
        self.valid.use(location=1)
        values = {"u_valid": 1, "u_box_lo": tuple(self.box_lo),
                  "u_box_size": tuple(self.box_size)}
        for i, tex in enumerate(self.textures):
            tex.use(location=SH_FIRST_UNIT + i)
            values["u_irradiance" if self.kind == "irradiance" else f"u_sh{i}"] = (
                SH_FIRST_UNIT + i)
        if self.texel_iso is not None:
            unit = SH_FIRST_UNIT + len(self.textures)
            self.texel_iso.use(location=unit)
            values["u_texel_iso"] = unit
        unit = SH_FIRST_UNIT + len(self.textures) + (self.texel_iso is not None)
        self.facing.use(location=unit)
        values["u_facing"] = unit
        for name, value in values.items():
            if name in program:
                program[name].value = value

    def facing_defines(self) -> tuple[tuple[str, object], ...]:
        """Shader defines of the side-aware lookup: FACING (1 once a texel's facing is
        known), its power and blend (`baking.lattice.FACING_POWER`, `SIDE_BLEND`)."""
        return (("FACING", int(self.facing_known)), ("FACING_POWER", FACING_POWER),
                ("FACING_BLEND", SIDE_BLEND))

    def sh_defines(self) -> tuple[tuple[str, object], ...]:
        """Shader defines that declare and sum the SH textures (GLSL 3.3 cannot index
        sampler arrays with loop variables, so the sum is unrolled here).

        ``SH_DECLARE`` declares ``u_sh0..``; ``SH_IRRADIANCE(tc)`` is the RGB sum
        Σ_j dot(texture(u_sh_j, tc), u_light[j]) per colour, with ``u_light`` holding the
        environment's coefficients packed four per vec4, red group first;
        ``SH_IRRADIANCE_AT(t)`` the same of the one texel t (texelFetch, the side-aware
        lookup).
        """
        n = self.sh_textures
        declare = " ".join(f"uniform sampler3D u_sh{i};" for i in range(n * self.sh_groups))
        def total(fetch: str) -> str:  # fetch: the read of texture {i}
            channels = []
            for c in range(3):
                group = c if self.sh_groups == 3 else 0
                terms = [f"dot({fetch.format(i=group * n + j)}, u_light[{c * n + j}])"
                         for j in range(n)]
                channels.append(" + ".join(terms))
            return f"vec3({', '.join(channels)})"

        return (("SH_TEXTURES", n), ("SH_DECLARE", declare),
                ("SH_IRRADIANCE(tc)", total("texture(u_sh{i}, tc)")),
                ("SH_IRRADIANCE_AT(t)", total("texelFetch(u_sh{i}, t, 0)")))

    def light_uniform(self, coeffs: np.ndarray) -> np.ndarray:
        """(3 * textures, 4) float32: (n², 3) environment coefficients packed for
        ``u_light`` (zero-padded to a multiple of four)."""
        n = self.sh_textures
        packed = np.zeros((3, n * 4), np.float32)
        packed[:, : coeffs.shape[0]] = np.asarray(coeffs, np.float32).T
        return packed.reshape(3 * n, 4)

    def release(self) -> None:
        for tex in (*self.textures, self.valid, self.facing):
            tex.release()
        if self.texel_iso is not None:
            self.texel_iso.release()

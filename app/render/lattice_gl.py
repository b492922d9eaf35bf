"""Illumination lattices as 3-D textures, stored sparsely in brick atlases.

Every texture holds the lattice's bricks that a lookup can read a shown texel from, in the
slots of an atlas, and one integer texture, the indirection, sends each brick of the
lattice to its slot (`app.render.bricks`: 8³ bricks stored with a one-texel apron, so
hardware trilinear filtering works inside a slot): texture memory follows the shown
texels, not the volume's box. The shader maps a lattice texel t of a cell whose lower
corner is in brick b to the atlas texel t + 9·slot(b) − 8·b (``lattice.glsl``).

SH transfer: ⌈n²/4⌉ RGBA16F atlases holding τ·valid, four coefficients each (three such
groups for coloured transfer, one per channel). The shader forms E = Σ τ_i ℓ_i with the
environment's coefficients ℓ (rotated on the CPU) as uniforms. GL 3.3 guarantees 16
texture units in a fragment shader: gray transfer up to order 7, coloured up to order 4.

Irradiance: one GL_RGB9_E5 atlas (4 bytes per texel, shared exponent: relative error
≤ 2⁻⁹ of the brightest channel) holding E·valid. Both kinds share an RGB8 atlas of each
texel's state: R its validity (1 where `baking.Lattice.shown`), GB its facing
(`baking.Lattice.displayed_facing`: octahedral bytes, (0, 0) unknown), read with
texelFetch by the side-aware lookup (``lattice.glsl``, FACING 1). Filtered trilinearly,
E·valid over valid interpolates over the shown texels only, and the shader falls back to
local shading where no neighbour is shown. Bricks can be re-uploaded while a lazy
bake fills the lattice (`LatticeTextures.write_bricks`). Optionally an R32F atlas holds
each texel's own isovalue ρ(x_t), for the closest-isovalue lookup (paper Fig. 6a); it
depends on the volume only.

numpy (z, y, x, c) arrays map to GL (width, height, depth) = (x, y, z): x varies fastest
in memory, as GL expects.
"""

from __future__ import annotations

import moderngl
import numpy as np

from isolume.app.render.bricks import (
    GROWTH,
    STORED,
    AtlasLayout,
    assemble_layer,
    block_region,
    brick_grid,
    cell_bricks,
    needed_bricks,
)
from isolume.app.render.glcontext import read_rgb9e5, rgb9e5_texture
from isolume.app.render.settings import RenderError
from isolume.baking import octahedral
from isolume.baking.lattice import Lattice
from isolume.baking.sh import transfer_blocks
from isolume.baking.sided import FACING_POWER, SIDE_BLEND
from isolume.volumes import cores

ATLAS_WAVE = 4
"""Atlas z-layers gathered at once, on as many of the pool's threads, when the atlases are
made: their copies in memory."""

MAX_TEXTURE_UNITS: int = 16  # guaranteed by GL 3.3 for fragment shaders
SH_FIRST_UNIT: int = 2  # units 0: HDR resolve input or shadow map, 1: the texels' state
_LOWER = np.array([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)])
"""(8, 3) z, y, x offsets to a brick's lower neighbours (itself first): their aprons
copy its first texels."""


def _facing_known(parts: list[np.ndarray]) -> bool:
    """Whether the `blocks` `parts` (the state first: RGB8, facing code in G and B) hold
    a known facing."""
    return bool(octahedral.known(parts[0][..., 1:]).any())


def _marked(bricks: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """(BZ, BY, BX) bool, True at (N, 3) `bricks`."""
    out = np.zeros(shape, bool)
    out[tuple(np.asarray(bricks).T)] = True
    return out


def sh_layout(order: int, rgb: bool, blocks: int = 1) -> tuple[int, int]:
    """(textures per colour group, groups) for SH transfer of `order` bands in `blocks`
    transfer blocks (2 for a split transfer: `baking.sh.transfer_blocks`).

    Raises:
        ValueError: when the textures would not fit the fragment shader's units.
    """
    per_group = -(-blocks * order * order // 4)
    groups = 3 if rgb else 1
    if SH_FIRST_UNIT + per_group * groups + 1 > MAX_TEXTURE_UNITS:  # + the indirection
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
        slot: (BZ, BY, BX) int32 each brick's atlas slot (0: none, the empty slot).
        layout: the atlas's `AtlasLayout`; ``used`` slots of it are taken (slot 0 too).
        state: RGB8 atlas of the texels' validity and facings.
        values: the atlases of the values (irradiance: one RGB9_E5; SH: RGBA16F each).
        texel_iso: R32F atlas of the texel isovalues ρ(x_t), or None (not given, or an
            SH lattice: the lookup variants read irradiance lattices only).
        facing_known: whether any uploaded texel has a known facing (the FACING define:
            without one, the lookup is the plain trilinear one, exactly).
    """

    shape: tuple[int, ...]
    sh_order: int
    sh_groups: int
    sh_textures: int
    sh_coefficients: int
    slot: np.ndarray
    facing_known: bool
    state: moderngl.Texture3D | None
    texel_iso: moderngl.Texture3D | None
    indirection: moderngl.Texture3D | None
    box_lo: np.ndarray
    box_size: np.ndarray
    used: int
    layout: AtlasLayout
    owner: np.ndarray

    def __init__(self, ctx: moderngl.Context, lattice: Lattice,
                 texel_isovalues: np.ndarray | None = None) -> None:
        """Upload `lattice`; `texel_isovalues` is (Z, Y, X) ρ at the texel centres (value
        units, `baking.plan.texel_values`) for the closest-isovalue lookup."""
        shape = lattice.geometry.shape
        if texel_isovalues is not None and np.shape(texel_isovalues) != shape:
            raise ValueError(f"texel isovalues of shape {np.shape(texel_isovalues)}, the "
                             f"lattice has {shape}")
        if lattice.kind not in ("irradiance", "sh"):
            raise ValueError(f"lattice kind {lattice.kind!r} is not drawable")
        self.ctx = ctx
        self.lattice = lattice
        self.kind = lattice.kind
        self.shape = tuple(int(n) for n in shape)
        self.sh_order = self.sh_groups = self.sh_textures = self.sh_coefficients = 0
        if self.kind == "sh":
            self.sh_order = int(lattice.meta["sh_order"])
            blocks = transfer_blocks(lattice)  # 2: direct, indirect transfer
            self.sh_coefficients = blocks * self.sh_order**2
            rgb = lattice.values.shape[-1] != self.sh_coefficients
            self.sh_textures, self.sh_groups = sh_layout(self.sh_order, rgb, blocks)
        self._rho = (None if texel_isovalues is None or self.kind != "irradiance"
                     else np.asarray(texel_isovalues, np.float32))
        self.slot = np.zeros(brick_grid(self.shape), np.int32)
        self.facing_known = False
        self.values: list[moderngl.Texture3D] = []
        self.state = self.texel_iso = self.indirection = None
        self._build(needed_bricks(lattice.shown, self.shape))
        lo, hi = np.array(lattice.geometry.lo), np.array(lattice.geometry.hi)
        self.box_lo, self.box_size = lo, hi - lo

    # -- the atlas ---------------------------------------------------------------------
    def _build(self, needed: np.ndarray, at_least: int = 0) -> None:
        """Give every `needed` (BZ, BY, BX) brick a slot in fresh atlases of at least
        `at_least` slots (and `GROWTH` × the slots taken) and upload them all."""
        bricks = np.argwhere(needed)
        self.used = len(bricks) + 1
        max_size = int(self.ctx.info["GL_MAX_3D_TEXTURE_SIZE"])
        room = max(int(np.ceil(self.used * GROWTH)), at_least)
        try:
            self.layout = AtlasLayout.with_room(self.used, room, max_size)
        except ValueError as exc:
            raise RenderError(f"lattice of {self.shape[::-1]} texels: {exc}") from None
        self.slot[...] = 0
        self.slot[tuple(bricks.T)] = np.arange(1, self.used, dtype=np.int32)
        self.owner = np.zeros((self.layout.capacity, 3), np.int64)  # slot -> brick
        self.owner[1:self.used] = bricks
        self._release_atlases()
        self._make_atlases()
        layers = [layer for layer in range(self.layout.dims[0])
                  if self.layout.layer_slots(layer).start < self.used]
        wave = min(cores.threads(), ATLAS_WAVE)
        for first in range(0, len(layers), wave):
            self._upload_layers(layers[first:first + wave])
        self._write_indirection()

    def _make_atlases(self) -> None:
        """Empty atlases of `layout`'s size and the indirection texture."""
        size = self.layout.texels_xyz
        ctx = self.ctx
        self.state = ctx.texture3d(size, 3, dtype="f1")
        if self.kind == "irradiance":
            self.values = [rgb9e5_texture(ctx, size)]
        else:
            self.values = [ctx.texture3d(size, 4, dtype="f2")
                           for _ in range(self.sh_textures * self.sh_groups)]
        for tex in (*self.values, self.state):
            tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            tex.repeat_x = tex.repeat_y = tex.repeat_z = False  # clamp to edge
        if self._rho is not None:
            self.texel_iso = ctx.texture3d(size, 1, dtype="f4")
            self.texel_iso.filter = (moderngl.NEAREST, moderngl.NEAREST)
        bz, by, bx = self.slot.shape
        self.indirection = ctx.texture3d((bx, by, bz), 3, dtype="u2")
        self.indirection.filter = (moderngl.NEAREST, moderngl.NEAREST)

    def _textures(self) -> list[moderngl.Texture3D]:
        """The atlases in upload order: the state, the values, the texel isovalues."""
        return [self.state, *self.values] + ([self.texel_iso] if self._rho is not None
                                              else [])

    def blocks(self, bricks: np.ndarray) -> list[np.ndarray]:
        """The `STORED`³ blocks of (M, 3) z, y, x `bricks`, one (M, 9, 9, 9, C) array per
        atlas (`_textures` order) as uploaded: state RGB8 (validity 255 or 0, facing
        code), values premultiplied by validity (0 where not shown), texel isovalues."""
        region = block_region(bricks, self.shape)
        shown, facing, values = self.lattice.display(region)  # values: 0 where not shown
        state = np.concatenate([np.where(shown, 255, 0).astype(np.uint8)[..., None], facing],
                               axis=-1)
        if self.kind == "irradiance":
            out = [state, np.ascontiguousarray(values[..., :3])]
        else:
            out = [state, *self._sh_groups(values)]
        if self._rho is not None:
            out.append(self._rho[region][..., None])
        return out

    def _sh_groups(self, values: np.ndarray) -> list[np.ndarray]:
        """(…, 4) float16 arrays, one per SH atlas, of (…, C) transfer values: four
        coefficients each."""
        n2 = self.sh_coefficients
        values = values.reshape(*values.shape[:-1], n2, -1)  # (..., n², 1 or 3)
        padded = np.zeros((*values.shape[:-2], self.sh_textures * 4, values.shape[-1]),
                          np.float16)
        padded[..., :n2, :] = values
        return [np.ascontiguousarray(padded[..., 4 * t:4 * t + 4, channel])
                for channel in range(self.sh_groups) for t in range(self.sh_textures)]

    def _uploaded(self, bricks: np.ndarray) -> list[np.ndarray]:
        """`blocks` of (M, 3) bricks about to be uploaded; notes a known facing."""
        parts = self.blocks(bricks)
        self.facing_known = self.facing_known or _facing_known(parts)
        return parts

    def _upload_layers(self, layers: list[int]) -> None:
        """Upload the atlas z-layers `layers` (their slots; those past `used` stay zero):
        their texels gathered and laid out on the pool's threads (at most `ATLAS_WAVE`
        layers at a time: their copies in memory), written to GL here, in order."""
        data: list[tuple[list[np.ndarray], bool]] = [([], False)] * len(layers)

        def gather(i: int) -> None:
            data[i] = self._layer_data(self.layout.layer_slots(layers[i]))

        cores.for_items(gather, len(layers), "atlas")
        width, height, _ = self.layout.texels_xyz
        for layer, (laid, known) in zip(layers, data, strict=True):
            self.facing_known = self.facing_known or known
            viewport = (0, 0, layer * STORED, width, height, STORED)
            for tex, texels in zip(self._textures(), laid, strict=True):
                tex.write(texels.tobytes(), viewport=viewport, alignment=1)

    def _layer_data(self, slots: range) -> tuple[list[np.ndarray], bool]:
        """The atlas z-layer of `slots` as laid out for each texture (`_textures` order),
        and whether its `blocks` hold a known facing."""
        taken = np.arange(slots.start, min(slots.stop, self.used))
        parts = self.blocks(self.owner[taken])
        known = _facing_known(parts)
        laid = []
        for part in parts:
            part[taken == 0] = 0  # slot 0 stays empty
            full = np.zeros((len(slots), *part.shape[1:]), part.dtype)
            full[:len(taken)] = part
            laid.append(np.ascontiguousarray(assemble_layer(full, self.layout)))
        return laid, known

    def _write_indirection(self) -> None:
        """Upload each brick's slot corner (x, y, z in slots) to the indirection."""
        corners = self.layout.corners(self.slot.reshape(-1)).astype(np.uint16)
        self.indirection.write(corners.tobytes(), alignment=1)

    def write_bricks(self, bricks: np.ndarray) -> np.ndarray:
        """Re-upload (N, 3) z, y, x bricks whose texels changed (a lazy bake), with the
        bricks whose aprons copy them; bricks that come to need a slot get one (all slots
        taken: the atlases are made again, larger, from the lattice as it is now).

        Returns:
            (M, 3) the bricks whose whole blocks in GL are now the lattice's (every brick
            with a slot when the atlases were made again).
        """
        if not len(bricks):
            return np.zeros((0, 3), np.int64)
        grid = np.array(cell_bricks(self.shape))
        near = (np.asarray(bricks, np.int64)[:, None, :] - _LOWER[None]).reshape(-1, 3)
        near = np.unique(near[(near >= 0).all(axis=1) & (near < grid).all(axis=1)], axis=0)
        parts = self._uploaded(near)
        shows = parts[0][..., 0].any(axis=(1, 2, 3))  # a shown texel in its block
        fresh = near[shows & (self.slot[tuple(near.T)] == 0)]
        if self.used + len(fresh) > self.layout.capacity:
            self._build((self.slot > 0) | _marked(fresh, self.slot.shape),
                        at_least=2 * self.layout.capacity)
            return np.argwhere(self.slot > 0)
        if len(fresh):
            self.slot[tuple(fresh.T)] = np.arange(self.used, self.used + len(fresh))
            self.owner[self.used:self.used + len(fresh)] = fresh
            self.used += len(fresh)
            self._write_indirection()
        slotted = self.slot[tuple(near.T)] > 0
        near = near[slotted]
        corners = self.layout.corners(self.slot[tuple(near.T)]) * STORED
        for tex, part in zip(self._textures(), parts, strict=True):
            for corner, block in zip(corners, part[slotted], strict=True):
                tex.write(np.ascontiguousarray(block).tobytes(),
                          viewport=(*(int(v) for v in corner), STORED, STORED, STORED),
                          alignment=1)
        return near

    def read_blocks(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """What the atlases hold: ((M, 3) z, y, x bricks with a slot, one (M, 9, 9, 9, C)
        array per atlas in `_textures` order; the irradiance as float32)."""
        taken = np.arange(1, self.used)
        corners = self.layout.corners(taken) * STORED
        out = []
        for tex in self._textures():
            atlas = self._read_atlas(tex)
            steps = np.arange(STORED)
            x, y, z = (corners[:, a, None] + steps for a in range(3))
            out.append(atlas[z[:, :, None, None], y[:, None, :, None], x[:, None, None, :]])
        return self.owner[taken], out

    def _read_atlas(self, tex: moderngl.Texture3D) -> np.ndarray:
        """(depth, height, width, C) contents of one atlas texture (the RGB9E5 irradiance
        as float32)."""
        if self.kind == "irradiance" and tex is self.values[0]:
            return read_rgb9e5(self.ctx, tex, self.layout.texels_xyz)
        width, height, depth = self.layout.texels_xyz
        dtype = {"f1": np.uint8, "f2": np.float16, "f4": np.float32}[tex.dtype]
        return np.frombuffer(tex.read(alignment=1), dtype).reshape(depth, height, width,
                                                                    tex.components)

    @property
    def units(self) -> int:
        """Texture units `bind` takes."""
        return 2 + len(self.values) + (self.texel_iso is not None)  # + state, indirection

    def bind(self, program: moderngl.Program) -> None:
        """Bind the atlases (the state on unit 1, the values from unit 2, then the texel
        isovalues, the indirection last) and set the uniforms that map world positions to
        atlas texels."""
        self.state.use(location=1)
        values = {"u_state": 1, "u_box_lo": tuple(self.box_lo),
                  "u_box_size": tuple(self.box_size),
                  "u_lattice_size": tuple(float(n) for n in self.shape[::-1]),
                  "u_atlas_size": tuple(float(n) for n in self.layout.texels_xyz)}
        for i, tex in enumerate(self.values):
            tex.use(location=SH_FIRST_UNIT + i)
            values["u_irradiance" if self.kind == "irradiance" else f"u_sh{i}"] = (
                SH_FIRST_UNIT + i)
        unit = SH_FIRST_UNIT + len(self.values)
        if self.texel_iso is not None:
            self.texel_iso.use(location=unit)
            values["u_texel_iso"] = unit
            unit += 1
        self.indirection.use(location=unit)
        values["u_bricks"] = unit
        for name, value in values.items():
            if name in program:
                program[name].value = value

    def facing_defines(self) -> tuple[tuple[str, object], ...]:
        """Shader defines of the side-aware lookup: FACING (1 once a texel's facing is
        known), its power and blend (`baking.sided.FACING_POWER`, `SIDE_BLEND`)."""
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

    def _release_atlases(self) -> None:
        for tex in (*self.values, self.state, self.texel_iso, self.indirection):
            if tex is not None:
                tex.release()
        self.values, self.state, self.texel_iso, self.indirection = [], None, None, None

    def release(self) -> None:
        self._release_atlases()

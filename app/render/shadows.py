"""Shadow maps: the key light's (shadow modes) and the per-pixel lights' atlas of tiles
(``direct.glsl``), their light-space transforms, GL textures and shader uniforms.

The key light's map is one orthographic depth view fitted to the scene's bounding sphere.
The per-pixel lights share one linear-depth atlas: a tile per distant light or sun (an
orthographic view like the key light's), six per point light (a cube of 90° views); the
sun's penumbra comes from its angular radius, read against the atlas's raw depths.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import moderngl
import numpy as np

from isolume.app.render.lights import is_point
from isolume.app.render.settings import MAX_DIRECT_LIGHTS, MAX_DIRECT_TILES, direct_tiles

if TYPE_CHECKING:
    from isolume.app.render.settings import DirectLight

SHADOW_BIAS_TEXELS = (0.5, 2.5)
"""Shadow-map depth bias, in shadow texels of world depth: constant + slope × tan θ (θ the
angle between facet and key light). The PCF footprint reaches 1 + √2 ≈ 2.41 texels from
the looked-up point (a diagonal tap plus its bilinear neighbours), across which a surface
of slope tan θ changes depth by 2.41 tan θ texels; the constant covers depth rounding and
curvature. Less slope bias shows as acne (tests/test_render_modes.py fails at 2.3)."""
SHADOW_MARGIN = 1.01
"""The light's view spans this many scene-sphere radii (surfaces on the sphere stay in)."""
DIRECT_BIAS_TEXELS = (0.5, 1.5)
"""Depth bias of the per-pixel lights' shadows, in tile texels: constant + slope × tan θ.
Each filter tap is compared against the receiver's own plane at that tap, so only the
hardware's bilinear 2×2 comparison (≤ 1.5 texels from the tap across a plane of slope
tan θ) and depth rounding need a bias (tests/test_direct_light.py: no acne on lit slopes,
shadows that meet their casters)."""
DIRECT_UNITS = (14, 15)
"""Texture units of the direct lights' shadow atlas: compared, raw (lattices use 1–13)."""


def light_view_proj(direction: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """(4, 4) world → clip transform of an orthographic view along −`direction` (unit,
    towards the light) that encloses the sphere (`centre` (3,), `radius` world units).

    Clip x, y span the sphere's silhouette; clip z runs from −1 at the sphere's point
    nearest the light to +1 at the farthest, so depth is linear in world distance.
    """
    back = np.asarray(direction, np.float64)
    helper = np.array([0.0, 0.0, 1.0]) if abs(back[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right = np.cross(helper, back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, up, back
    view[:3, 3] = -view[:3, :3] @ np.asarray(centre, np.float64)
    ortho = np.diag([1.0 / radius, 1.0 / radius, -1.0 / radius, 1.0])
    return ortho @ view


_CUBE_FACES = (((1, 0, 0), (0, -1, 0)), ((-1, 0, 0), (0, -1, 0)), ((0, 1, 0), (0, 0, 1)),
               ((0, -1, 0), (0, 0, -1)), ((0, 0, 1), (0, -1, 0)), ((0, 0, -1), (0, -1, 0)))
"""(axis, up) of a point light's six 90° shadow faces, in the order +x −x +y −y +z −z."""


def point_face_view_proj(position: np.ndarray, face: int, near: float, far: float
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(4, 4) world → clip transform of face `face` (`_CUBE_FACES`) of a point light at
    `position`, and its linear depth plane (4,): depth = (axis·(p − position)) / far."""
    axis, up = (np.asarray(v, np.float64) for v in _CUBE_FACES[face])
    right = np.cross(axis, up)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, up, -axis
    view[:3, 3] = -view[:3, :3] @ position
    proj = np.zeros((4, 4))  # 90° field of view both ways
    proj[0, 0] = proj[1, 1] = 1.0
    proj[2, 2] = -(far + near) / (far - near)
    proj[2, 3] = -2.0 * far * near / (far - near)
    proj[3, 2] = -1.0
    plane = np.concatenate([axis / far, [-(axis @ position) / far]])
    return proj @ view, plane


def light_tiles(light: DirectLight, centre: np.ndarray, radius: float
                ) -> Iterator[tuple[np.ndarray, np.ndarray, float]]:
    """(view_proj (4, 4), linear depth plane (4,), world units per unit of depth) of each
    shadow tile of `light` for a scene within the sphere (`centre`, `radius`)."""
    if is_point(light):
        position = np.asarray(light.position, np.float64)
        reach = float(np.linalg.norm(position - centre)) + radius
        near = max(1e-4 * reach, reach - 2 * radius)
        for face in range(6):
            view_proj, plane = point_face_view_proj(position, face, near, reach)
            yield view_proj, plane, reach
        return
    direction = np.asarray(light.direction, np.float64)
    view_proj = light_view_proj(direction, centre, radius)
    yield view_proj, 0.5 * view_proj[2] + 0.5 * np.eye(4)[3], 2.0 * radius


def direct_uniforms(lights: Sequence[DirectLight], matrices: Sequence[np.ndarray],
                    planes: Sequence[np.ndarray],
                    rects: Sequence[tuple[float, float, float, float]],
                    ranges: Sequence[float], tile_texels: Sequence[int]) -> dict[str, bytes]:
    """The ``direct.glsl`` uniform arrays (padded to their declared sizes); `tile_texels`:
    each tile's side in texels (no tiles: the lights' arrays alone, for traced light)."""
    from isolume.baking.lights import SunLight

    def padded(rows, width, count, dtype="f4"):
        out = np.zeros((count, width), dtype)
        if len(rows):
            out[:len(rows)] = rows
        return out.tobytes()

    where = [(*light.position, 1.0) if is_point(light) else (*light.direction, 0.0)
             for light in lights]
    rgb = [light.intensity if is_point(light) else light.irradiance for light in lights]
    tan_r = [[math.tan(math.radians(light.radius))] if isinstance(light, SunLight) else [0.0]
             for light in lights]
    axes = [m[:2, :3] / np.linalg.norm(m[:2, :3], axis=1, keepdims=True) for m in matrices]
    n, t = MAX_DIRECT_LIGHTS, MAX_DIRECT_TILES
    return {
        "u_direct_where": padded(where, 4, n), "u_direct_rgb": padded(rgb, 3, n),
        "u_direct_tan_radius": padded(tan_r, 1, n),
        "u_tile_view_proj": b"".join(m.T.astype("f4").tobytes() for m in matrices)
        + bytes(64 * (t - len(matrices))),
        "u_tile_depth": padded(planes, 4, t), "u_tile_rect": padded(rects, 4, t),
        "u_tile_range": padded([[r] for r in ranges], 1, t),
        "u_tile_right": padded([a[0] for a in axes], 3, t),
        "u_tile_up": padded([a[1] for a in axes], 3, t),
        "u_tile_texel": padded([[1.0 / texels] for texels in tile_texels], 1, t),
    }


def active_parts(prog: moderngl.Program, arrays: dict[str, Any]) -> dict[str, Any]:
    """The `direct_uniforms` arrays cut to the lengths the compiled program keeps (a
    compiler drops the tail of an array that only constant indices below it read)."""
    out = {}
    for name, data in arrays.items():
        if name in prog and not isinstance(data, bytes):
            out[name] = data
        elif name in prog:
            declared = MAX_DIRECT_LIGHTS if name.startswith("u_direct") else MAX_DIRECT_TILES
            out[name] = data[:prog[name].array_length * (len(data) // declared)]
    return out


@dataclass
class DirectAtlas:
    """The per-pixel lights' shadow tiles in one depth texture (compared, bilinear), with
    an R32F copy of its depths for the sun's blocker search (`raw`); `key` says what they
    were drawn for, `uniforms` the shader's values for them."""

    depth: moderngl.Texture
    raw: moderngl.Texture
    fbo: moderngl.Framebuffer
    key: tuple[object, ...] | None = None
    uniforms: dict[str, bytes] = field(default_factory=dict)

    def release(self) -> None:
        self.fbo.release()
        self.raw.release()
        self.depth.release()


@dataclass
class ShadowMap:
    """The key light's depth map and what it was drawn for (`key`: mesh generation, light
    direction, scene sphere)."""

    depth: moderngl.Texture
    fbo: moderngl.Framebuffer
    view_proj: np.ndarray | None = None
    key: tuple[object, ...] | None = None

    @property
    def resolution(self) -> int:
        return self.depth.size[0]

    def release(self) -> None:
        self.fbo.release()
        self.depth.release()


class ShadowMaps:
    """The key light's `ShadowMap` and the per-pixel lights' `DirectAtlas` of one GL
    context, each drawn again only when the mesh, the lights or the scene sphere change.

    Args:
        ctx: the context.
        program: (kind, defines) → the renderer's compiled program of that kind.
        draw_mesh: draws the renderer's mesh with a program.
        park: a framebuffer that is always valid to bind, bound before a texture that may
            be bound is freed.
    """

    def __init__(self, ctx: moderngl.Context, program: Callable[[str, tuple], moderngl.Program],
                 draw_mesh: Callable[[moderngl.Program], None],
                 park: moderngl.Framebuffer) -> None:
        self.ctx = ctx
        self._program = program
        self._draw_mesh = draw_mesh
        self._park = park
        self._shadow: ShadowMap | None = None
        self._atlas: DirectAtlas | None = None

    def _ensure_shadow_map(self, resolution: int) -> ShadowMap:
        if self._shadow is not None and self._shadow.resolution == resolution:
            return self._shadow
        if self._shadow is not None:
            self._park.use()
            self._shadow.release()
        depth = self.ctx.depth_texture((resolution, resolution))
        depth.compare_func = "<="  # texture() returns the fraction with reference ≤ stored
        depth.filter = (moderngl.LINEAR, moderngl.LINEAR)  # bilinear 2×2 comparisons
        depth.repeat_x = depth.repeat_y = False
        self._shadow = ShadowMap(depth, self.ctx.framebuffer(depth_attachment=depth))
        return self._shadow

    def key_map(self, resolution: int, light: np.ndarray, sphere: tuple[np.ndarray, float],
                generation: int) -> ShadowMap:
        """The key light's depth map (`resolution` texels square) towards the unit vector
        `light` (3,) for mesh `generation` within the scene `sphere` (centre (3,),
        radius), drawn unless it shows just that."""
        shadow = self._ensure_shadow_map(resolution)
        centre, radius = sphere
        key = (generation, tuple(light), tuple(centre), radius)
        if shadow.key == key:
            return shadow
        shadow.view_proj = light_view_proj(light, centre, SHADOW_MARGIN * radius)
        prog = self._program("shadow", ())
        prog["u_light_view_proj"].write(shadow.view_proj.T.astype("f4").tobytes())
        shadow.fbo.use()
        self.ctx.clear(depth=1.0)
        self._draw_mesh(prog)
        shadow.key = key
        return shadow

    def _ensure_atlas(self, tile: int, tiles: int) -> DirectAtlas:
        """A depth atlas holding `tiles` square tiles of `tile` texels (reused when it
        has that size)."""
        cols = math.ceil(math.sqrt(tiles))
        size = (tile * cols, tile * math.ceil(tiles / cols))
        if self._atlas is not None and self._atlas.depth.size == size:
            return self._atlas
        if self._atlas is not None:
            self._park.use()
            self._atlas.release()
        depth = self.ctx.depth_texture(size)
        depth.compare_func = "<="
        depth.filter = (moderngl.LINEAR, moderngl.LINEAR)
        depth.repeat_x = depth.repeat_y = False
        raw = self.ctx.texture(size, 1, dtype="f4")  # the same depths as floats
        raw.filter = (moderngl.NEAREST, moderngl.NEAREST)
        raw.repeat_x = raw.repeat_y = False
        self._atlas = DirectAtlas(depth, raw, self.ctx.framebuffer(
            color_attachments=[raw], depth_attachment=depth))
        return self._atlas

    def atlas(self, lights: tuple[DirectLight, ...], resolution: int,
              sphere: tuple[np.ndarray, float], generation: int) -> DirectAtlas:
        """The per-pixel `lights`' shadow tiles (at most `resolution` texels square) for
        mesh `generation` within the scene `sphere` (centre (3,), radius), drawn unless it
        shows just that, and the shader's uniforms for them."""
        first = direct_tiles(lights)
        tiles = first[-1] + (6 if is_point(lights[-1]) else 1)
        cols = math.ceil(math.sqrt(tiles))
        tile = min(resolution, 8192 // cols)
        atlas = self._ensure_atlas(tile, tiles)
        centre, radius = sphere
        key = (generation, lights, tuple(centre), radius, tile)
        if atlas.key == key:
            return atlas
        width, height = atlas.depth.size
        matrices, planes, rects, ranges = [], [], [], []
        for light in lights:
            for view_proj, plane, span in light_tiles(light, centre, SHADOW_MARGIN * radius):
                i = len(matrices)
                x, y = (i % cols) * tile, (i // cols) * tile
                matrices.append(view_proj)
                planes.append(plane)
                rects.append((x / width, y / height, tile / width, tile / height))
                ranges.append(span)
        prog = self._program("depth", ())
        atlas.fbo.use()
        atlas.fbo.viewport = (0, 0, width, height)
        self.ctx.clear(1.0, 1.0, 1.0, 1.0, depth=1.0)
        for i, (view_proj, plane) in enumerate(zip(matrices, planes, strict=True)):
            atlas.fbo.viewport = (round(rects[i][0] * width), round(rects[i][1] * height),
                                  tile, tile)
            prog["u_view_proj"].write(view_proj.T.astype("f4").tobytes())
            prog["u_depth"].value = tuple(plane)
            self._draw_mesh(prog)
        atlas.fbo.viewport = (0, 0, width, height)
        atlas.uniforms = direct_uniforms(lights, matrices, planes, rects, ranges,
                                         [tile] * len(matrices))
        atlas.key = key
        return atlas

    def release(self) -> None:
        """Free the maps' GL objects (the caller binds a framebuffer that stays first)."""
        if self._shadow is not None:
            self._shadow.release()
        if self._atlas is not None:
            self._atlas.release()

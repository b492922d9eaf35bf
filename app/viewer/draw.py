"""The viewer's drawing: what is on the GPU, how a frame is lit and drawn.

`Drawing` owns the `app.render.renderer.SurfaceRenderer` of the window's context and everything the
picture depends on besides the camera and the user's choices (`ViewState`): the surface on
the GPU (the preview or the full-resolution one), the lattice textures and the re-upload of
lazily baked texels (`TexelUploader`, 8³ bricks within a per-frame budget), the light
(`Drawing.settings`: key light fixed to the camera or to the world, the environment
rotation of SH lattices), and the detail while the user moves the camera (`Quality`:
the preview mesh, then lower resolutions, scaled onto the window by `Blitter`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume import volumes
from isolume.app.render.bricks import BRICK, brick_grid, needed_bricks

if TYPE_CHECKING:
    import moderngl

    from isolume.app.render.camera import Camera
    from isolume.app.render.glcontext import Window
    from isolume.app.render.lattice_gl import LatticeTextures
    from isolume.app.render.renderer import SurfaceRenderer
    from isolume.app.render.settings import Frame, RenderSettings
    from isolume.baking.lattice import Lattice
    from isolume.baking.view_texels import HeldLattice

UPLOAD_BUDGET_S = 0.006
"""Seconds per frame spent re-uploading texels while the user moves the camera or light
(the rest waits for the next frame)."""
UPLOAD_FIRST_S = 0.05
"""The same for bricks that show their first light while the view rests (frames of Mesa's
llvmpipe take 50–1000 ms: a first preview of thousands of bricks goes up in seconds); the
light refined goes up at `UPLOAD_BUDGET_S` (more would take the processor from the bake,
which runs at the lowest priority)."""
UPLOAD_BATCH = 16
"""Bricks re-uploaded between two looks at the clock."""
FIRST_BATCH = 256
"""The same for bricks that show their first light: a brick's upload writes the bricks
whose aprons copy it too, which neighbours in one batch share."""
INTERACTIVE_MS = 33.0
"""Frame time aimed at while the camera or light moves (≈ 30 fps)."""
RENDER_SCALES = (1.0, 0.75, 0.5, 0.35)
"""Resolution factors tried, in order, while interacting and too slow."""
PREVIEW_TRIANGLES = 60_000
"""While interacting and too slow, the preview surface replaces a full one above this."""
EXPOSURE_ADAPT_S = 0.3
"""Time constant of the automatic exposure's adaptation (seconds; game engines' eye
adaptation takes a few tenths of a second): it moves smoothly, never jumps."""
EXPOSURE_PROBE = 64
"""The automatic exposure reads this many pixels across the HDR target (nearest samples)."""


def adapted_exposure(current: float, goal: float, seconds: float,
                     time_constant: float = EXPOSURE_ADAPT_S) -> float:
    """The exposure `seconds` after `current` when it moves towards `goal`: exponentially in
    log space (equal steps in stops), so it never overshoots and halves its distance in
    stops every ``time_constant · ln 2`` seconds."""
    k = 1.0 - math.exp(-max(seconds, 0.0) / time_constant)
    return current * (goal / current) ** k


@dataclass
class ViewState:
    """What the user controls (besides the camera)."""

    iso: float
    shading: str
    exposure: float
    light: tuple[float, float] | None = None  # None: key light fixed to the camera
    show_ui: bool = True


def frame_size(window: Window) -> tuple[int, int]:
    """(W, H) pixels of `window`'s framebuffer (an `app.render.glcontext.Window`), at
    least 1 × 1 (a minimised window has none)."""
    w, h = window.framebuffer_size
    return max(w, 1), max(h, 1)


class TexelUploader:
    """Tracks which bricks (`app.render.bricks.BRICK`³ texels) hold newly committed texels
    and re-uploads them (`LatticeTextures.write_bricks`) within a time budget, the bricks
    that show their first light before those that refine it."""

    def __init__(self, textures: LatticeTextures) -> None:
        self.textures: LatticeTextures = textures
        self.shape: tuple[int, ...] = tuple(textures.lattice.geometry.shape)
        self.dirty: np.ndarray = np.zeros(brick_grid(self.shape), bool)
        self.shown: np.ndarray = np.zeros(self.dirty.shape, bool)  # uploaded once since
        self.uploaded: int = 0
        self._watches: list[np.ndarray] = []

    def mark(self, flat_ids: np.ndarray) -> None:
        """Note (N,) flat texel ids whose values changed."""
        if len(flat_ids) == 0:
            return
        k, j, i = np.unravel_index(np.asarray(flat_ids, np.int64), self.shape)
        self.dirty[k // BRICK, j // BRICK, i // BRICK] = True

    @property
    def pending(self) -> int:
        """Bricks waiting for upload."""
        return int(self.dirty.sum())

    def watch(self) -> np.ndarray:
        """A mask of the bricks waiting for upload now, which each upload clears as it
        uploads them (whatever was marked since): all False once every texel marked so
        far is in GL, though a lazy bake keeps marking more."""
        watched = self.dirty.copy()
        self._watches.append(watched)
        return watched

    def upload(self, budget_s: float | None = UPLOAD_BUDGET_S,
               first_budget_s: float | None = None) -> int:
        """Upload dirty bricks, `UPLOAD_BATCH` at a time, until `budget_s` seconds are spent
        (None: all), one batch at least; with `first_budget_s`, those never uploaded (the
        first light there) first, `FIRST_BATCH` at a time, until `first_budget_s`. Returns
        how many were uploaded."""
        t0, n = time.perf_counter(), 0
        dirty = np.argwhere(self.dirty)
        fresh = ~self.shown[tuple(dirty.T)]
        first_light = ((dirty[fresh], budget_s, UPLOAD_BATCH) if first_budget_s is None
                       else (dirty[fresh], first_budget_s, FIRST_BATCH))
        for part, budget, batch in (first_light, (dirty[~fresh], budget_s, UPLOAD_BATCH)):
            for lo in range(0, len(part), batch):
                if n and budget is not None and time.perf_counter() - t0 > budget:
                    break  # (one batch at least a call)
                n += self._write(part[lo:lo + batch])
        self.uploaded += n
        return n

    def _write(self, batch: np.ndarray) -> int:
        """Upload the (B, 3) bricks `batch`; returns B. The bricks whose aprons copy their
        texels go up whole with them (`LatticeTextures.write_bricks`): those have shown
        their light since, but stay marked if they were, for their own texels are in the
        aprons of the bricks below them too."""
        written = self.textures.write_bricks(batch)
        self.shown[tuple(np.asarray(written, np.int64).T)] = True
        at = tuple(batch.T)
        self.dirty[at] = False
        self.shown[at] = True
        for watched in self._watches:
            watched[at] = False
        self._watches = [w for w in self._watches if w.any()]
        return len(batch)


def check_textures(textures: LatticeTextures) -> dict[str, Any]:
    """Read the GL atlases back and compare them with the lattice.

    Returns:
        {"texels": texels shown (computed or previewed), "computed": texels with samples,
        "missing_bricks": bricks a lookup can read a shown texel from that have no slot,
        "max_rel_error": largest |GL − lattice| / max(RGB) over the shown texels of the
        uploaded bricks (RGB9_E5 keeps 9 mantissa bits: ≤ 2⁻⁹ when rounding),
        "valid_mismatch": texels whose validity differs, "uncomputed_nonzero": texels not
        shown with a non-zero value, "facing_mismatch": texels whose facing code
        differs}; SH lattices: the validity and the facings only.
    """
    lat = textures.lattice
    shown = lat.shown(np.s_[:])
    needed = needed_bricks(lat.shown, textures.shape)
    bricks, got = textures.read_blocks()
    want = textures.blocks(bricks)
    valid = want[0][..., 0] > 127
    # a lattice dense over the box counts its samples; one held at texels (a file's
    # computed texels) its paths
    samples = lat.samples if hasattr(lat, "samples") else lat.paths
    result = {"texels": int(shown.sum()), "computed": int(np.count_nonzero(samples)),
              "missing_bricks": int((needed & (textures.slot == 0)).sum()),
              "valid_mismatch": int(((got[0][..., 0] > 127) != valid).sum()),
              "facing_mismatch": int((got[0][..., 1:] != want[0][..., 1:]).any(axis=-1).sum()),
              "max_rel_error": None, "uncomputed_nonzero": None}
    if textures.kind == "irradiance":  # SH packing is LatticeTextures' own: validity only
        gl_rgb, rgb = got[1].astype(np.float64), want[1].astype(np.float64)
        scale = np.maximum(rgb[valid].max(axis=1, keepdims=True), 1e-30)
        rel = np.abs(gl_rgb[valid] - rgb[valid]) / scale
        result.update(max_rel_error=float(rel.max()) if len(rel) else 0.0,
                      uncomputed_nonzero=int((gl_rgb[~valid] != 0).any(axis=-1).sum()))
    return result


@dataclass
class Quality:
    """Detail while the user moves the camera or light: the preview mesh first, then lower
    resolutions, until a frame takes about INTERACTIVE_MS (software GL needs both; a GPU
    needs neither). Kept between interactions; full detail returns when the motion stops."""

    level: int = 0
    coarse: bool = False

    @property
    def scale(self) -> float:
        return RENDER_SCALES[self.level]

    def adapt(self, frame_ms: float, full_triangles: int) -> None:
        """Adjust after an interactive frame that took `frame_ms`."""
        if frame_ms > 1.3 * INTERACTIVE_MS:
            if not self.coarse and full_triangles > PREVIEW_TRIANGLES:
                self.coarse = True
            elif self.level < len(RENDER_SCALES) - 1:
                self.level += 1
        elif frame_ms < 0.6 * INTERACTIVE_MS and self.level > 0:
            self.level -= 1


_GL_READ_FRAMEBUFFER, _GL_DRAW_FRAMEBUFFER = 0x8CA8, 0x8CA9
_GL_COLOR_BUFFER_BIT, _GL_LINEAR, _GL_NEAREST = 0x4000, 0x2601, 0x2600


class Blitter:
    """Scales an 8-bit render target onto the window (glBlitFramebuffer, linear filter),
    which moderngl's ``copy_framebuffer`` cannot do (it copies 1:1)."""

    def __init__(self, ctx: moderngl.Context) -> None:
        import ctypes

        proc = ctx.extra["proc_address"]
        self.ctx: moderngl.Context = ctx
        self._bind = ctypes.CFUNCTYPE(None, ctypes.c_uint, ctypes.c_uint)(
            proc("glBindFramebuffer"))
        self._blit = ctypes.CFUNCTYPE(None, *([ctypes.c_int] * 8), ctypes.c_uint,
                                      ctypes.c_uint)(proc("glBlitFramebuffer"))

    def blit(self, fbo: moderngl.Framebuffer, src: tuple[int, int],
             dst_fbo: moderngl.Framebuffer | None, dst: tuple[int, int],
             nearest: bool = False) -> None:
        """Scale `fbo`'s (W, H) `src` onto `dst_fbo` (None: the window) at `dst`."""
        self._bind(_GL_READ_FRAMEBUFFER, fbo.glo)
        self._bind(_GL_DRAW_FRAMEBUFFER, 0 if dst_fbo is None else dst_fbo.glo)
        self._blit(0, 0, src[0], src[1], 0, 0, dst[0], dst[1], _GL_COLOR_BUFFER_BIT,
                   _GL_NEAREST if nearest else _GL_LINEAR)
        screen = self.ctx.screen  # None in a headless context
        if dst_fbo is None:
            screen.viewport = (0, 0, dst[0], dst[1])
        (screen if screen is not None else dst_fbo).use()  # what moderngl believes bound


class Drawing:
    """The picture of the viewer's window (see the module docstring).

    Attributes:
        renderer: the `app.render.renderer.SurfaceRenderer` of the window's context.
        modes: every shading mode's name, in the keys' order.
        albedo: (3,) surface albedo, the lattice's when one is shown.
        meshes: the surfaces of the current isovalue by stage ("coarse", "full").
        on_gpu: the stage whose surface the renderer holds (None: none yet).
        uploader: re-uploads lazily baked texels (None: the lattice does not change).
        quality: the detail used while interacting.
        auto_exposure: expose by `app.render.exposure.auto_exposure_scale`, smoothed in time.
        auto: the automatic exposure now (None before the first frame).
        adapting: the automatic exposure is still moving (keep drawing frames).
    """

    ctx: moderngl.Context
    volume: volumes.Volume

    def __init__(self, ctx: moderngl.Context, volume: volumes.Volume,
                 auto_exposure: bool = True) -> None:
        from isolume.app.render.renderer import SurfaceRenderer
        from isolume.app.render.settings import SHADING_MODES, RenderSettings

        self.ctx, self.volume = ctx, volume
        self.renderer: SurfaceRenderer = SurfaceRenderer(ctx)
        self.renderer.set_bounds(*volume.box)  # shadows and fog do not follow the isovalue
        self._render_fields = {f.name for f in fields(RenderSettings)}
        self.modes: tuple[str, ...] = tuple(SHADING_MODES)
        self.albedo: tuple[float, float, float] = (0.8, 0.8, 0.8)
        self.meshes: dict[str, volumes.Mesh] = {}
        self.on_gpu: str | None = None
        self.uploader: TexelUploader | None = None
        self.quality: Quality = Quality()
        self.blitter: Blitter = Blitter(ctx)
        self._usable: tuple[str, ...] | None = None
        self.auto_exposure: bool = auto_exposure
        self.auto: float | None = None
        self.adapting: bool = False
        self._adapted_at = 0.0
        self._probe = None  # a small float framebuffer the HDR target is sampled into

    # -- the lattice ---------------------------------------------------------------------
    def show_lattice(self, lattice: Lattice | HeldLattice | None) -> str | None:
        """Upload `lattice` (and, for SH, the environment it was baked for); returns why
        it cannot be shown, or None."""
        self._usable = None
        try:
            self.renderer.set_lattice(lattice)
            if lattice.kind == "sh":
                from isolume.app.options import environment_coefficients

                self.renderer.set_environment(environment_coefficients(None, lattice, "none"))
        except ValueError as exc:
            self.renderer.set_lattice(None)
            return f"lattice not shown: {exc}"
        return None

    def track_uploads(self) -> None:
        """The lattice shown will change (a lazy bake): re-upload the texels marked."""
        self.uploader = TexelUploader(self.renderer.lattice)

    def usable_modes(self) -> tuple[str, ...]:
        """Shading modes that can be drawn now (`SurfaceRenderer.check_mode`); the
        closest-isovalue lookup counts as usable with an irradiance lattice, its texel
        isovalues are computed when it is first chosen."""
        if self._usable is None:
            from isolume.app.render.settings import SHADING_MODES

            lattice = self.renderer.lattice
            out = []
            for name in self.modes:
                try:
                    self.renderer.check_mode(name)
                except ValueError:
                    closest = getattr(SHADING_MODES[name], "lookup", "") == "closest"
                    if not (closest and lattice is not None and lattice.kind == "irradiance"):
                        continue
                out.append(name)
            self._usable = tuple(out)
        return self._usable

    def ensure_texel_isovalues(self, mode: str) -> None:
        """Upload the texel isovalues the closest-isovalue lookup needs (once)."""
        from isolume.app.render.settings import SHADING_MODES
        from isolume.baking.plan import texel_values

        textures = self.renderer.lattice
        closest = getattr(SHADING_MODES[mode], "lookup", "") == "closest"
        if not closest or textures is None or textures.texel_iso is not None:
            return
        lattice = textures.lattice
        self.renderer.set_lattice(lattice, texel_values(self.volume, lattice.geometry))
        if self.uploader is not None:  # fresh textures hold every texel computed so far
            self.uploader = TexelUploader(self.renderer.lattice)
        self._usable = None

    def mark_texels(self, flat_ids: np.ndarray) -> None:
        """Note (N,) flat ids of texels the bake changed."""
        if self.uploader is not None:
            self.uploader.mark(flat_ids)

    def upload_texels(self, budget_s: float | None = UPLOAD_BUDGET_S,
                      first_budget_s: float | None = None) -> bool:
        """Re-upload changed texels for `budget_s` seconds (None: all), the bricks never
        uploaded for `first_budget_s` (`TexelUploader.upload`); True when some were."""
        if self.uploader is None or not self.uploader.pending:
            return False
        self.uploader.upload(budget_s, first_budget_s)
        return True

    def check_lattice(self) -> dict[str, Any]:
        """Upload every pending texel, then compare the GL textures with the lattice
        (`check_textures`)."""
        self.upload_texels(budget_s=None)
        return check_textures(self.renderer.lattice)

    # -- the light -----------------------------------------------------------------------
    def settings(self, state: ViewState, size: tuple[int, int]) -> RenderSettings:
        """The `RenderSettings` of a frame of `size` (W, H) pixels in `state`."""
        from isolume.app.render.settings import RenderSettings
        from isolume.app.viewer.panel import direction_from_angles

        kw = {"size": size, "shading": state.shading, "exposure": state.exposure,
              "albedo": self.albedo}
        if state.light is not None:
            kw["key_dir"] = tuple(direction_from_angles(*state.light))
            moved = self._moved_lights(state)
            if moved is not None:
                kw["direct_lights"] = moved
        if "env_rotation" in self._render_fields:
            kw["env_rotation"] = state.light or (0.0, 0.0)
        return RenderSettings(**kw)

    def _moved_lights(self, state: ViewState) -> tuple | None:
        """The per-pixel lights of the lattice shown with the sun (or first directional
        light) turned to the user's light direction; None when there is none to turn."""
        from isolume.app.render.lights import aimed_lights, first_distant_light
        from isolume.app.viewer.panel import direction_from_angles

        lights = self.renderer.lattice_lights
        if state.light is None or first_distant_light(lights) is None:
            return None
        return aimed_lights(lights, direction_from_angles(*state.light))

    def light_note(self, state: ViewState, rebakes: bool = False) -> str | None:
        """What the light controls do to a lattice whose sun or lights are shaded per
        pixel, and whether its indirect light is stale; None for other lattices.
        `rebakes`: a lazy bake re-bakes the bounced light of a turned light."""
        from isolume.app.render.lights import first_distant_light
        from isolume.app.render.settings import LATTICE_MODES

        mode = LATTICE_MODES.get(state.shading)
        baked = first_distant_light(self.renderer.lattice_lights)
        if mode is None or mode.lattice != "irradiance" or baked is None:
            return None
        moved = self._moved_lights(state)
        shown = first_distant_light(moved) if moved is not None else baked
        turn = math.degrees(math.acos(float(np.clip(
            np.dot(shown.direction, baked.direction), -1.0, 1.0))))
        after = ("is re-baked once the light rests" if rebakes else "stays as baked")
        if turn < 0.5:
            return ("The sun and lights are shaded per pixel (exact shadows); turning the "
                    f"light moves them, their bounced light {after}.")
        until = "re-baked (once the light rests)" if rebakes else "the lattice is baked again"
        return (f"Light turned {turn:.0f}° from the bake: its direct light and shadows are "
                f"exact, its bounced light is stale until {until}.")

    def turned_light(self, state: ViewState) -> tuple[str, tuple[float, float, float]] | None:
        """("sun" or "light", (3,) unit vector towards it) of the light that the frames of
        `state` shade per pixel and the user turns (the sun or first directional light of
        an irradiance lattice, `light_note`): what a lazy bake's bounced light must
        follow (`baking.lazy.View.light`). None in other modes and for other lattices
        (an SH transfer turns its sun with itself)."""
        from isolume.app.render.lights import first_distant_light
        from isolume.baking.lights import SunLight

        if self.light_note(state) is None:
            return None
        moved = self._moved_lights(state)
        light = first_distant_light(moved if moved is not None
                                    else self.renderer.lattice_lights)
        name = "sun" if isinstance(light, SunLight) else "light"
        return name, tuple(float(v) for v in light.direction)

    def light_angles(self, state: ViewState, camera: Camera) -> tuple[float, float]:
        """The light's (azimuth, elevation) in degrees (from the camera-fixed light if need
        be)."""
        from isolume.app.render.lights import first_distant_light, key_direction
        from isolume.app.viewer.panel import angles_from_direction

        if state.light is not None:
            return state.light
        if state.shading == "sh":  # the environment starts as loaded
            return (0.0, 0.0)
        baked = first_distant_light(self.renderer.lattice_lights)
        if baked is not None and self.light_note(state) is not None:
            return angles_from_direction(np.asarray(baked.direction))  # the baked sun
        return angles_from_direction(key_direction(camera, self.settings(state, (1, 1))))

    # -- surfaces ------------------------------------------------------------------------
    def set_surface(self, stage: str, mesh: volumes.Mesh, new_iso: bool) -> None:
        """Keep `mesh` as the surface of `stage`; `new_iso` drops the other isovalue's."""
        if new_iso:
            self.meshes = {}
        self.meshes[stage] = mesh
        self.on_gpu = None

    def sync_mesh(self, preview: bool) -> None:
        """Put the preview or the full surface of the current isovalue on the GPU."""
        want = "coarse" if preview and "coarse" in self.meshes else "full"
        if want not in self.meshes:
            want = "coarse"
        if want == self.on_gpu or want not in self.meshes:
            return
        mesh = self.meshes[want]
        self.renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces, iso=mesh.iso)
        self.on_gpu = want

    # -- frames --------------------------------------------------------------------------
    def draw(self, camera: Camera, state: ViewState, size: tuple[int, int], scale: float,
             target: moderngl.Framebuffer | None = None) -> None:
        """Render at `scale` × the framebuffer `size` (W, H) and put it on the window, or
        into the framebuffer `target` of that size (a headless context's picture).

        Raises:
            ValueError: the shading mode lacks what it needs (`app.render.settings.RenderError`).
        """
        w, h = size
        small = (max(1, round(w * scale)), max(1, round(h * scale)))
        settings = self.exposed(self.settings(state, small))
        targets = self.renderer.draw_hdr(camera, settings)
        change = self._adapt(targets, small)
        if small == size:
            fbo = self.ctx.screen if target is None else target
            fbo.viewport = (0, 0, w, h)
            self.renderer.resolve(targets, settings, fbo=fbo, auto=change)
        else:
            self.renderer.resolve(targets, settings, auto=change)
            self.blitter.blit(targets.ldr, small, target, size)

    def exposed(self, settings: RenderSettings) -> RenderSettings:
        """`settings` with the automatic exposure (as it stands) folded into `exposure`."""
        if not self.auto_exposure or self.auto is None:
            return settings
        return replace(settings, exposure=settings.exposure * self.auto)

    def _adapt(self, targets, size: tuple[int, int]) -> float:
        """Move the automatic exposure towards the frame's own (`auto_exposure_scale` of
        `EXPOSURE_PROBE` pixels across the HDR target of `size`) with time constant
        `EXPOSURE_ADAPT_S`, or straight to it on the first frame that shows the surface
        (frames before it have none to meter); returns the factor by which the frame's
        exposure (`exposed` before this call) must change: on that first frame, the whole
        automatic exposure."""
        if not self.auto_exposure:
            return 1.0
        from isolume.app.render.exposure import auto_exposure_scale

        rgba = self._sample_hdr(targets, size)
        surface = rgba[..., 3] > 0
        now = time.perf_counter()
        before = self.auto
        if not surface.any():  # nothing to meter: keep the exposure (none yet: none)
            self._adapted_at, self.adapting = now, False
            return 1.0
        goal = auto_exposure_scale(rgba[..., :3], surface)
        self.auto = goal if before is None else adapted_exposure(before, goal,
                                                                 now - self._adapted_at)
        self._adapted_at = now
        self.adapting = abs(math.log(goal / self.auto)) > 0.01
        return self.auto if before is None else self.auto / before

    def _sample_hdr(self, targets, size: tuple[int, int]) -> np.ndarray:
        """(h, w, 4) float32 nearest samples of the HDR target of `size`, about
        `EXPOSURE_PROBE` across."""
        w, h = size
        k = EXPOSURE_PROBE / max(w, h)
        small = (max(1, min(w, round(w * k))), max(1, min(h, round(h * k))))
        if self._probe is None or self._probe[0] != small:
            if self._probe is not None:
                self._probe[1].release()
                self._probe[2].release()
            texture = self.ctx.texture(small, 4, dtype="f4")
            self._probe = (small, texture, self.ctx.framebuffer(color_attachments=[texture]))
        _, _, fbo = self._probe
        self.blitter.blit(targets.hdr, size, fbo, small, nearest=True)
        data = np.frombuffer(fbo.read(components=4, dtype="f4"), np.float32)
        return data.reshape(small[1], small[0], 4)

    def frame(self, camera: Camera, state: ViewState, size: tuple[int, int]) -> Frame:
        """An off-screen `app.render.renderer` frame (sRGB and linear radiance) of `size` (W, H),
        exposed as the window is (`metered`)."""
        return self.renderer.render(camera, self.metered(camera, state, size))

    def metered(self, camera: Camera, state: ViewState,
                size: tuple[int, int]) -> RenderSettings:
        """The `RenderSettings` of a frame of `size` exposed as the window is; while no
        window frame has shown the surface yet, the automatic exposure is first metered on
        this one (as the window's first frame with the surface would)."""
        settings = self.settings(state, size)
        if self.auto_exposure and self.auto is None:
            self._adapt(self.renderer.draw_hdr(camera, settings), size)
        return self.exposed(settings)

    def visible_points(self, camera: Camera, state: ViewState,
                       size: tuple[int, int]) -> np.ndarray:
        """(N, 3) world positions of the surface under the pixels of a view of `size`
        (W, H), read at most 512 pixels across."""
        w, h = size
        scale = min(1.0, 512.0 / max(w, h))
        small = (max(1, round(w * scale)), max(1, round(h * scale)))
        settings = replace(self.settings(state, small), shading="position")
        frame = self.renderer.render(camera, settings)
        return frame.linear[frame.mask]

    def release(self) -> None:
        self.uploader = None
        if self._probe is not None:
            self._probe[2].release()
            self._probe[1].release()
        self.renderer.release()

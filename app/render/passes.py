"""What a frame's passes draw into and read: the render targets (linear HDR colour with its
depth, the 8-bit display image, the G-buffer of ``gbuffer.glsl``) and the deferred pass's
eye rays (``deferred.frag``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import moderngl
import numpy as np

from isolume.app.render.camera import Camera

GBUFFER_UNIT = 16
"""Texture unit of the G-buffer the deferred pass reads (a unit of its own, so that no
program's texture is ever the one the surface pass draws into)."""


@dataclass
class Targets:
    """A frame's render targets: the linear HDR colour with its depth (`hdr`), the 8-bit
    display image (`ldr`) and, once a deferred frame is drawn, the G-buffer of
    ``gbuffer.glsl`` (`g_surface`, RGBA32F) with the framebuffers that draw it: alone
    (`deferred`) or beside the HDR colour (`forward_g`, for SH transfer with lights)."""

    size: tuple[int, int]
    hdr: moderngl.Framebuffer
    hdr_color: moderngl.Texture
    ldr: moderngl.Framebuffer
    depth: moderngl.Renderbuffer
    objects: list[moderngl.Framebuffer | moderngl.Texture | moderngl.Renderbuffer] = field(
        default_factory=list)
    g_surface: moderngl.Texture | None = None
    deferred: moderngl.Framebuffer | None = None
    forward_g: moderngl.Framebuffer | None = None

    @classmethod
    def new(cls, ctx: moderngl.Context, size: tuple[int, int]) -> Targets:
        """The HDR and display targets of `size` (width, height) pixels."""
        color = ctx.texture(size, 4, dtype="f4")
        depth = ctx.depth_renderbuffer(size)
        hdr = ctx.framebuffer(color_attachments=[color], depth_attachment=depth)
        ldr_color = ctx.texture(size, 4, dtype="f1")
        ldr = ctx.framebuffer(color_attachments=[ldr_color])
        return cls(size, hdr, color, ldr, depth, [hdr, color, depth, ldr, ldr_color])

    def gbuffer(self, ctx: moderngl.Context, with_hdr: bool) -> moderngl.Framebuffer:
        """The framebuffer drawing the G-buffer (made on first use), with the HDR colour
        as its first target when `with_hdr`."""
        if self.g_surface is None:
            self.g_surface = ctx.texture(self.size, 4, dtype="f4")
            self.deferred = ctx.framebuffer(color_attachments=[self.g_surface],
                                            depth_attachment=self.depth)
            self.forward_g = ctx.framebuffer(
                color_attachments=[self.hdr_color, self.g_surface], depth_attachment=self.depth)
            self.objects[:0] = [self.deferred, self.forward_g, self.g_surface]
        return self.forward_g if with_hdr else self.deferred

    def release(self) -> None:
        for obj in self.objects:
            obj.release()


def pixel_rays(camera: Camera, size: tuple[int, int]) -> dict[str, tuple[float, ...]]:
    """``deferred.frag``'s eye rays: the uniforms u_ray0, u_rayx, u_rayy (3,) such that
    the ray through the pixel centre at window coordinates (x, y) (gl_FragCoord: from the
    lower left, centres at half-integers) of a `size` (W, H) view runs along
    u_ray0 + x u_rayx + y u_rayy (not unit: the shader normalises it)."""
    w, h = size
    inverse = np.linalg.inv(camera.view_proj(w / h))
    eye = np.asarray(camera.eye, np.float64)

    def towards(x: float, y: float) -> np.ndarray:  # NDC (x, y) on the far plane
        p = inverse @ np.array([x, y, 1.0, 1.0])
        return p[:3] / p[3] - eye

    # the far plane's points are affine in NDC (a perspective inverse's w depends on z only)
    centre = towards(0.0, 0.0)
    dx, dy = towards(1.0, 0.0) - centre, towards(0.0, 1.0) - centre
    scale = 1.0 / np.linalg.norm(centre)
    return {"u_ray0": tuple(scale * (centre - dx - dy)), "u_rayx": tuple(scale * 2 / w * dx),
            "u_rayy": tuple(scale * 2 / h * dy)}

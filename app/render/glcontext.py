"""The one place that creates OpenGL contexts.

* ``egl``: Mesa/NVIDIA EGL through moderngl's standalone backend (no display needed).
* ``osmesa``: Mesa's off-screen renderer ``libOSMesa.so.8`` (Debian ``libosmesa6``),
  created with ctypes as a 3.3 core-profile context and bound with
  ``moderngl.init_context(loader=...)``. Bit-identical to EGL llvmpipe; used by the tests.
* windows: `create_window` (glfw, for the interactive viewer). glfw reports the *window*
  size in screen coordinates (mouse positions use them) and the *framebuffer* size in
  pixels; on HiDPI displays the two differ by the content scale. Everything drawn uses the
  framebuffer size; input uses window coordinates.

Headless renders draw into their own framebuffers, so the OSMesa drawable is a 1×1 dummy.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType

import moderngl
import numpy as np

from isolume.volumes.errors import IsolumeError

BACKENDS = ("egl", "osmesa")


class GLUnavailable(IsolumeError, RuntimeError):
    """No OpenGL 3.3 context could be created with the requested backend."""


@dataclass
class HeadlessContext:
    """A moderngl context plus what keeps it alive; call `release` when done."""

    ctx: moderngl.Context
    backend: str
    _keepalive: object = None

    def make_current(self) -> None:
        """Make this context current again on this thread (after another was created)."""
        if isinstance(self._keepalive, _OSMesa):
            self._keepalive.make_current()
        else:
            self.ctx.__enter__()

    def release(self) -> None:
        """Free the context (and the OSMesa context and buffer, if any)."""
        self.ctx.release()
        if isinstance(self._keepalive, _OSMesa):
            self._keepalive.destroy()


# OSMesa constants (GL/osmesa.h)
_OSMESA_FORMAT = 0x22
_OSMESA_RGBA = 0x1908
_OSMESA_DEPTH_BITS = 0x30
_OSMESA_STENCIL_BITS = 0x31
_OSMESA_PROFILE = 0x33
_OSMESA_CORE_PROFILE = 0x34
_OSMESA_CONTEXT_MAJOR_VERSION = 0x36
_OSMESA_CONTEXT_MINOR_VERSION = 0x37
_GL_UNSIGNED_BYTE = 0x1401


class _OSMesa:
    """ctypes binding of an OSMesa core-profile context; also the moderngl loader."""

    def __init__(self) -> None:
        name = "libOSMesa.so.8"
        try:
            self.lib = ctypes.CDLL(name)
        except OSError:
            found = ctypes.util.find_library("OSMesa")
            if found is None:
                raise GLUnavailable(
                    f"OSMesa is not installed ({name} not found; Debian: apt-get install "
                    "libosmesa6); try --gl egl"
                ) from None
            self.lib = ctypes.CDLL(found)
        lib = self.lib
        lib.OSMesaCreateContextAttribs.restype = ctypes.c_void_p
        lib.OSMesaCreateContextAttribs.argtypes = [ctypes.POINTER(ctypes.c_int), ctypes.c_void_p]
        lib.OSMesaMakeCurrent.restype = ctypes.c_int
        lib.OSMesaMakeCurrent.argtypes = [
            ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_int,
        ]
        lib.OSMesaGetProcAddress.restype = ctypes.c_void_p
        lib.OSMesaGetProcAddress.argtypes = [ctypes.c_char_p]
        lib.OSMesaDestroyContext.argtypes = [ctypes.c_void_p]
        attrs = (ctypes.c_int * 13)(
            _OSMESA_FORMAT, _OSMESA_RGBA, _OSMESA_DEPTH_BITS, 24, _OSMESA_STENCIL_BITS, 8,
            _OSMESA_PROFILE, _OSMESA_CORE_PROFILE,
            _OSMESA_CONTEXT_MAJOR_VERSION, 3, _OSMESA_CONTEXT_MINOR_VERSION, 3, 0,
        )
        self.handle = lib.OSMesaCreateContextAttribs(attrs, None)
        if not self.handle:
            raise GLUnavailable("OSMesa could not create a 3.3 core-profile context; try --gl egl")
        self.buffer = (ctypes.c_ubyte * 4)()
        self.make_current()

    def make_current(self) -> None:
        """Bind this context (with its 1×1 dummy drawable) to the calling thread."""
        if not self.lib.OSMesaMakeCurrent(self.handle, self.buffer, _GL_UNSIGNED_BYTE, 1, 1):
            raise GLUnavailable("OSMesaMakeCurrent failed; try --gl egl")

    def load_opengl_function(self, name: str) -> int:
        """Address of a GL entry point (the moderngl loader protocol)."""
        return self.lib.OSMesaGetProcAddress(name.encode()) or 0

    def release(self) -> None:
        """Part of the moderngl loader protocol; the context is destroyed in `destroy`."""

    def destroy(self) -> None:
        if self.handle:
            self.lib.OSMesaDestroyContext(self.handle)
            self.handle = None


def _egl_proc_address() -> Callable[[str], int]:
    lib = ctypes.CDLL("libEGL.so.1")
    lib.eglGetProcAddress.restype = ctypes.c_void_p
    lib.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    return lambda name: lib.eglGetProcAddress(name.encode()) or 0


def _create_egl() -> HeadlessContext:
    try:
        ctx = moderngl.create_standalone_context(require=330, backend="egl")
        proc = _egl_proc_address()
    except Exception as exc:  # moderngl/glcontext raise plain Exceptions
        raise GLUnavailable(
            f"EGL context failed ({exc}); install Mesa's EGL (libegl1 libegl-mesa0) "
            "or try --gl osmesa"
        ) from None
    ctx.extra = {"proc_address": proc}
    return HeadlessContext(ctx, "egl")


def _create_osmesa() -> HeadlessContext:
    osmesa = _OSMesa()
    try:
        moderngl.init_context(loader=osmesa)
        ctx = moderngl.get_context()
    except Exception as exc:
        osmesa.destroy()
        raise GLUnavailable(f"binding OSMesa to moderngl failed ({exc}); try --gl egl") from None
    if ctx.version_code < 330:
        raise GLUnavailable(f"OSMesa gave OpenGL {ctx.version_code}, 330 needed; try --gl egl")
    ctx.extra = {"proc_address": osmesa.load_opengl_function}
    return HeadlessContext(ctx, "osmesa", osmesa)


def create_headless(backend: str = "auto") -> HeadlessContext:
    """Create an off-screen OpenGL ≥ 3.3 context.

    Args:
        backend: "egl", "osmesa", or "auto" (EGL, then OSMesa).

    Raises:
        GLUnavailable: with a message naming the alternatives.
    """
    if backend == "egl":
        return _create_egl()
    if backend == "osmesa":
        return _create_osmesa()
    if backend != "auto":
        raise GLUnavailable(f"unknown GL backend {backend!r}; expected one of egl, osmesa, auto")
    try:
        return _create_egl()
    except GLUnavailable as egl_error:
        try:
            return _create_osmesa()
        except GLUnavailable as osmesa_error:
            raise GLUnavailable(
                f"no headless OpenGL: EGL: {egl_error}; OSMesa: {osmesa_error}"
            ) from None


_GL_TEXTURE_3D = 0x806F
_GL_RGB9_E5 = 0x8C3D
_GL_RGB = 0x1907
_GL_FLOAT = 0x1406
_TEX_IMAGE_3D = ctypes.CFUNCTYPE(
    None, ctypes.c_uint, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int,
    ctypes.c_int, ctypes.c_uint, ctypes.c_uint, ctypes.c_void_p,
)
_GET_TEX_IMAGE = ctypes.CFUNCTYPE(None, ctypes.c_uint, ctypes.c_int, ctypes.c_uint,
                                  ctypes.c_uint, ctypes.c_void_p)


def rgb9e5_texture(ctx: moderngl.Context, size: tuple[int, int, int]) -> moderngl.Texture3D:
    """A 3-D texture of `size` (width, height, depth) texels stored as GL_RGB9_E5 (4 bytes
    per texel, shared-exponent HDR), its contents undefined until written.

    moderngl cannot request that internal format: it makes a one-texel float RGB texture,
    whose storage glTexImage3D (through the context's own function loader) re-specifies at
    `size`, so no float storage of the whole size (12 bytes per texel) is ever allocated.
    ``texture.write`` of float RGB data with a viewport converts into it. moderngl keeps
    the texture's `size` as (1, 1, 1): read it back with `read_rgb9e5`.
    """
    texture = ctx.texture3d((1, 1, 1), 3, dtype="f4")
    width, height, depth = size
    texture.use(location=0)
    _TEX_IMAGE_3D(_gl_function(ctx, "glTexImage3D"))(
        _GL_TEXTURE_3D, 0, _GL_RGB9_E5, width, height, depth, 0, _GL_RGB, _GL_FLOAT, None)
    return texture


def read_rgb9e5(ctx: moderngl.Context, texture: moderngl.Texture3D,
                size: tuple[int, int, int]) -> np.ndarray:
    """(depth, height, width, 3) float32 contents of an `rgb9e5_texture` of `size`."""
    width, height, depth = size
    out = np.empty((depth, height, width, 3), np.float32)
    texture.use(location=0)
    _GET_TEX_IMAGE(_gl_function(ctx, "glGetTexImage"))(_GL_TEXTURE_3D, 0, _GL_RGB, _GL_FLOAT,
                                                       out.ctypes.data)
    return out


def _gl_function(ctx: moderngl.Context, name: str) -> int:
    """Address of the GL entry point `name` through `ctx`'s function loader.

    Raises:
        GLUnavailable: the context has no loader, or the loader lacks `name`.
    """
    proc = (ctx.extra or {}).get("proc_address")
    if proc is None:
        raise GLUnavailable(f"this GL context has no function loader for {name}")
    address = proc(name)
    if not address:
        raise GLUnavailable(f"{name} is not available")
    return address


# -- windows (the interactive viewer) ------------------------------------------------
GL_BACK = 0x0405
GL_RGB = 0x1907
GL_UNSIGNED_BYTE = 0x1401
GL_PACK_ALIGNMENT = 0x0D05

NO_DISPLAY_HINT = ("the viewer needs a display; render off-screen with `isolume render "
                   "[VOLUME] --out FILE.png` instead")


def import_glfw() -> ModuleType:
    """Import pyglfw, after imgui_bundle when it is installed.

    imgui_bundle ships its own libglfw and, when imported first, points pyglfw at it
    (PYGLFW_LIBRARY), so that one glfw library serves both. It does not matter for the UI
    used here (input is fed to ImGui from Python), but it avoids two glfw copies in one
    process.
    """
    try:
        import imgui_bundle  # noqa: F401
    except ImportError:
        pass
    import glfw

    return glfw


@dataclass
class Window:
    """A glfw window and its moderngl context.

    Attributes:
        handle: the glfw window.
        ctx: moderngl context of the window (``ctx.extra["proc_address"]`` resolves GL
            entry points, as `app.render.glcontext.rgb9e5_texture` needs).
        glfw: the glfw module.
    """

    handle: object
    ctx: object
    glfw: object

    @property
    def framebuffer_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return tuple(self.glfw.get_framebuffer_size(self.handle))

    @property
    def window_size(self) -> tuple[int, int]:
        """(width, height) in screen coordinates (mouse positions)."""
        return tuple(self.glfw.get_window_size(self.handle))

    @property
    def content_scale(self) -> float:
        """UI scale factor of the monitor the window is on (1 on standard displays)."""
        return float(self.glfw.get_window_content_scale(self.handle)[0])

    @property
    def ui_scale(self) -> float:
        """How much larger than nominal to draw UI sizes in window coordinates: the content
        scale where window coordinates are pixels (Windows, X11), 1 where the framebuffer is
        already denser than the window coordinates (macOS Retina, Wayland scaling)."""
        pixel_ratio = self.framebuffer_size[0] / max(self.window_size[0], 1)
        return max(1.0, self.content_scale / max(pixel_ratio, 1e-6))

    def should_close(self) -> bool:
        return bool(self.glfw.window_should_close(self.handle))

    def request_close(self) -> None:
        self.glfw.set_window_should_close(self.handle, True)

    def swap(self) -> None:
        self.glfw.swap_buffers(self.handle)

    def set_title(self, title: str) -> None:
        self.glfw.set_window_title(self.handle, title)

    def read_back(self) -> bytes:
        """RGB bytes of the back buffer (rows bottom to top), before `swap`.

        moderngl's ``ctx.screen.read`` selects a colour attachment as the read buffer,
        which the default framebuffer rejects (GL_INVALID_OPERATION); this reads GL_BACK.
        """
        w, h = self.framebuffer_size
        proc = self.ctx.extra["proc_address"]
        read_buffer = ctypes.CFUNCTYPE(None, ctypes.c_uint)(proc("glReadBuffer"))
        pixel_store = ctypes.CFUNCTYPE(None, ctypes.c_uint, ctypes.c_int)(proc("glPixelStorei"))
        read_pixels = ctypes.CFUNCTYPE(
            None, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_uint,
            ctypes.c_uint, ctypes.c_void_p)(proc("glReadPixels"))
        buffer = ctypes.create_string_buffer(w * h * 3)
        self.ctx.screen.use()
        read_buffer(GL_BACK)
        pixel_store(GL_PACK_ALIGNMENT, 1)
        read_pixels(0, 0, w, h, GL_RGB, GL_UNSIGNED_BYTE, buffer)
        return buffer.raw

    def close(self) -> None:
        """Destroy the window and terminate glfw."""
        self.ctx.release()
        self.glfw.destroy_window(self.handle)
        self.glfw.terminate()


def _display_available() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
                or os.name == "nt" or os.uname().sysname == "Darwin")


def create_window(size: tuple[int, int] = (1024, 768), title: str = "isolume",
                  visible: bool = True) -> Window:
    """Open a window with an OpenGL 3.3 core context and bind moderngl to it.

    Args:
        size: (width, height) in screen coordinates; the framebuffer may be larger on
            HiDPI displays.
        visible: False keeps the window hidden (benchmarks).

    Raises:
        app.render.glcontext.GLUnavailable: no display, glfw cannot start, or no 3.3 context —
            the message names `isolume render` as the alternative.
    """
    import moderngl

    from isolume.app.render.glcontext import GLUnavailable

    if not _display_available():
        raise GLUnavailable(f"no display (DISPLAY is not set): {NO_DISPLAY_HINT}")
    glfw = import_glfw()
    errors: list[str] = []
    glfw.set_error_callback(lambda code, text: errors.append(
        text.decode(errors="replace") if isinstance(text, bytes) else str(text)))
    if not glfw.init():
        reason = errors[-1] if errors else "glfw.init() failed"
        raise GLUnavailable(f"cannot open a window ({reason}): {NO_DISPLAY_HINT}")
    glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 3)
    glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
    glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
    glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
    glfw.window_hint(glfw.SCALE_TO_MONITOR, True)
    glfw.window_hint(glfw.VISIBLE, bool(visible))
    handle = glfw.create_window(int(size[0]), int(size[1]), title, None, None)
    if not handle:
        reason = errors[-1] if errors else "no OpenGL 3.3 core context"
        glfw.terminate()
        raise GLUnavailable(f"cannot open an OpenGL 3.3 window ({reason}): {NO_DISPLAY_HINT}")
    glfw.make_context_current(handle)
    glfw.swap_interval(1)
    try:
        ctx = moderngl.create_context(require=330)
    except Exception as exc:  # moderngl raises plain Exceptions
        glfw.destroy_window(handle)
        glfw.terminate()
        raise GLUnavailable(f"OpenGL 3.3 context failed ({exc}): {NO_DISPLAY_HINT}") from None
    ctx.extra = {"proc_address": lambda name: glfw.get_proc_address(name) or 0}
    return Window(handle, ctx, glfw)

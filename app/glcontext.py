"""The one place that creates OpenGL contexts.

* ``egl``: Mesa/NVIDIA EGL through moderngl's standalone backend (no display needed).
* ``osmesa``: Mesa's off-screen renderer ``libOSMesa.so.8`` (Debian ``libosmesa6``),
  created with ctypes as a 3.3 core-profile context and bound with
  ``moderngl.init_context(loader=...)``. Bit-identical to EGL llvmpipe; used by the tests.
* windows: `create_window` (glfw, for the interactive viewer).

Headless renders draw into their own framebuffers, so the OSMesa drawable is a 1×1 dummy.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from collections.abc import Callable
from dataclasses import dataclass

import moderngl

BACKENDS = ("egl", "osmesa")


class GLUnavailable(RuntimeError):
    """No OpenGL 3.3 context could be created with the requested backend."""


@dataclass
class HeadlessContext:
    """A moderngl context plus what keeps it alive; call `release` when done."""

    ctx: moderngl.Context
    backend: str
    _keepalive: object = None

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
        if not lib.OSMesaMakeCurrent(self.handle, self.buffer, _GL_UNSIGNED_BYTE, 1, 1):
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


def store_rgb9e5(ctx: moderngl.Context, texture: moderngl.Texture3D, rgb) -> None:
    """Re-specify a bound-able 3-D texture's storage as GL_RGB9_E5 (4 bytes per texel,
    shared-exponent HDR) filled from (Z, Y, X, 3) float32 `rgb`.

    moderngl cannot request that internal format, so this calls glTexImage3D through the
    context's own function loader; later ``texture.write`` of float RGB data converts into
    the same storage.
    """
    import numpy as np

    proc = (ctx.extra or {}).get("proc_address")
    if proc is None:
        raise GLUnavailable("this GL context has no function loader for glTexImage3D")
    address = proc("glTexImage3D")
    if not address:
        raise GLUnavailable("glTexImage3D is not available")
    data = np.ascontiguousarray(rgb, np.float32)
    depth, height, width = data.shape[:3]
    texture.use(location=0)
    _TEX_IMAGE_3D(address)(_GL_TEXTURE_3D, 0, _GL_RGB9_E5, width, height, depth, 0, _GL_RGB,
                           _GL_FLOAT, data.ctypes.data)

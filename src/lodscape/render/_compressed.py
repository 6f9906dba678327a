"""Compressed textures into the GL: moderngl allocates the texture, the blocks go in through
``glCompressedTexImage2D`` (moderngl has no call for it), found in the GL dispatch library of
the current context (libOpenGL through glvnd, else EGL's proc address)."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from typing import Any, TypeVar

import moderngl

from lodscape.imagery.compress import Compressed

__all__ = ["has_s3tc", "texture", "texture_array"]

_Tex = TypeVar("_Tex", moderngl.Texture, moderngl.TextureArray)
_TEXTURE_2D = 0x0DE1
_TEXTURE_2D_ARRAY = 0x8C1A
_ARGS = [
    ctypes.c_uint,
    ctypes.c_int,
    ctypes.c_uint,
    ctypes.c_int,
    ctypes.c_int,
    ctypes.c_int,
    ctypes.c_int,
    ctypes.c_void_p,
]


def has_s3tc(ctx: moderngl.Context) -> bool:
    """Whether ``ctx`` takes S3TC (BC1..BC3) textures and the upload call can be found."""
    ext = ctx.extensions
    ok = "GL_EXT_texture_compression_s3tc" in ext or "GL_S3_s3tc" in ext
    return ok and _upload() is not None


def _upload() -> Any:
    return _gl("glCompressedTexImage2D", tuple(_ARGS))


def _upload_3d() -> Any:
    return _gl("glCompressedTexImage3D", (*_ARGS[:5], ctypes.c_int, *_ARGS[5:]))


@functools.cache
def _gl(name: str, args: tuple[Any, ...]) -> Any:
    for lib in ("OpenGL", "GL"):
        path = ctypes.util.find_library(lib)
        if path is None:
            continue
        try:
            fn = getattr(ctypes.CDLL(path), name)
        except (OSError, AttributeError):
            continue
        fn.argtypes, fn.restype = list(args), None
        return fn
    path = ctypes.util.find_library("EGL")
    if path is None:
        return None
    try:
        egl = ctypes.CDLL(path)
    except OSError:
        return None
    egl.eglGetProcAddress.restype = ctypes.c_void_p
    egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    addr = egl.eglGetProcAddress(name.encode())
    return None if not addr else ctypes.CFUNCTYPE(None, *args)(addr)


def texture(ctx: moderngl.Context, data: Compressed) -> moderngl.Texture:
    """A mipmapped 2D texture holding ``data``'s levels as they are (the GPU samples blocks)."""
    fn = _upload()
    if fn is None:
        raise RuntimeError("glCompressedTexImage2D is not reachable in this process")
    w, h, _ = data.levels[0]
    components = 4 if data.format == 0x83F3 else 3
    _ = ctx.error  # an earlier call's error is not this upload's
    tex = ctx.texture((w, h), components, None, internal_format=data.format)
    tex.use(0)
    for level, (lw, lh, blocks) in enumerate(data.levels):
        fn(_TEXTURE_2D, level, data.format, lw, lh, 0, len(blocks), blocks)
    return _checked(ctx, tex)


def texture_array(ctx: moderngl.Context, layers: list[Compressed]) -> moderngl.TextureArray:
    """A mipmapped 2D texture array, a layer per ``Compressed`` (all of one size and format)."""
    fn = _upload_3d()
    if fn is None:
        raise RuntimeError("glCompressedTexImage3D is not reachable in this process")
    first = layers[0]
    size = first.levels[0][:2]
    if any(lay.format != first.format or lay.levels[0][:2] != size for lay in layers):
        raise ValueError("a compressed texture array needs layers of one size and format")
    w, h, _ = first.levels[0]
    _ = ctx.error
    tex = ctx.texture_array((w, h, len(layers)), 4)
    tex.use(0)
    for level in range(len(first.levels)):
        lw, lh, _ = first.levels[level]
        blocks = b"".join(lay.levels[level][2] for lay in layers)
        fn(_TEXTURE_2D_ARRAY, level, first.format, lw, lh, len(layers), 0, len(blocks), blocks)
    return _checked(ctx, tex)


def _checked(ctx: moderngl.Context, tex: _Tex) -> _Tex:
    """``tex`` mipmap-filtered, or released and an error if the upload failed."""
    err = ctx.error
    if err != "GL_NO_ERROR":
        tex.release()
        raise RuntimeError(f"compressed texture upload failed: {err}")
    tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
    return tex

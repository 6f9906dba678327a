"""Headless OpenGL contexts: made without a window, and made current before every use."""

from __future__ import annotations

from collections.abc import Callable

import moderngl

__all__ = ["create_context", "is_software", "make_current"]

#: GLSL 330 is all the terrain pass needs; Mesa's llvmpipe offers 4.5 through EGL.
REQUIRED_GL = 330
#: Versions asked for, newest first: some drivers (NVIDIA's EGL) give exactly the version asked
#: for, so asking for 3.3 alone would hide multi-draw-indirect (4.3) and tessellation (4.0).
WANTED_GL = (460, 450, 430, REQUIRED_GL)


def create_context() -> moderngl.Context:
    """A standalone context: EGL first (headless servers, CI), then the platform's default."""
    # moderngl's stubs type the keyword settings as dicts; the backend is a plain string
    standalone: Callable[..., moderngl.Context] = moderngl.create_standalone_context
    failures: list[str] = []
    for backend in ("egl", None):
        kwargs = {} if backend is None else {"backend": backend}
        for version in WANTED_GL:
            try:
                return standalone(require=version, **kwargs)
            except Exception as exc:  # moderngl raises bare Exception subclasses per backend
                if version == REQUIRED_GL:
                    failures.append(f"{backend or 'default'}: {exc}")
    raise RuntimeError(
        "cannot create a headless OpenGL 3.3 context (" + "; ".join(failures) + "); "
        "install Mesa's EGL and OpenGL drivers (e.g. libegl1 and libgl1-mesa-dri)"
    )


def make_current(ctx: moderngl.Context) -> None:
    """Bind ``ctx`` to the calling thread and leave it bound.

    moderngl never switches contexts by itself: with several standalone contexts in one thread
    (one per Scene, a test's shared one) GL calls go to whichever was bound last. The ``with ctx``
    form is not used because its exit re-binds the previous context, which glcontext's EGL backend
    does not do reliably; binding on entry alone costs about 2 µs.
    """
    ctx.__enter__()  # type: ignore[no-untyped-call]


def is_software(ctx: moderngl.Context) -> bool:
    """Whether ``ctx`` rasterises on the CPU (Mesa's llvmpipe, softpipe, swrast)."""
    renderer = str(ctx.info.get("GL_RENDERER", "")).lower()
    return any(name in renderer for name in ("llvmpipe", "softpipe", "swrast"))

"""Shared fixtures: one headless OpenGL context for the tests marked ``gl``."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

import pytest


def _on_ci() -> bool:
    """CI sets ``CI`` (``.ci/run`` exports ``CI=true``): there a skipped OpenGL test fails."""
    return os.environ.get("CI", "").lower() not in ("", "0", "false", "no")


@pytest.fixture(scope="session")
def gl_ctx() -> Iterator[Any]:
    """A standalone EGL context shared by the session; skips the test where EGL is missing."""
    import moderngl  # imported here so the pure tests never load OpenGL

    try:
        ctx = moderngl.create_standalone_context(backend="egl", require=330)
    except Exception as exc:  # a missing libEGL or driver surfaces as a bare Exception
        reason = f"no headless OpenGL 3.3 context through EGL: {exc}"
        if _on_ci():
            pytest.fail(f"{reason} (CI={os.environ['CI']}: the OpenGL tests must run here)")
        pytest.skip(reason)
    yield ctx
    ctx.release()


@pytest.fixture(autouse=True)
def _gl_errors_checked(request: pytest.FixtureRequest) -> Iterator[None]:
    """Tests marked ``gl`` skip without EGL and must leave the shared context error-free."""
    if request.node.get_closest_marker("gl") is None:
        yield
        return
    ctx = request.getfixturevalue("gl_ctx")
    ctx.__enter__()  # other contexts may have been bound since; rebind before reading errors
    ctx.clear_errors()
    yield
    ctx.__enter__()
    assert ctx.error == "GL_NO_ERROR"


@pytest.fixture(autouse=True, scope="session")
def _own_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The session's sidecars (overviews, tile statistics) in a folder of its own, not the
    user's cache."""
    old = os.environ.get("LODSCAPE_CACHE")
    os.environ["LODSCAPE_CACHE"] = str(tmp_path_factory.mktemp("lodscape-cache"))
    yield
    if old is None:
        os.environ.pop("LODSCAPE_CACHE", None)
    else:
        os.environ["LODSCAPE_CACHE"] = old

"""The public surface stays small and every exported name resolves (httpx exported-members)."""

from __future__ import annotations

import lodscape


def test_exported_members_resolve() -> None:
    import inspect

    assert lodscape.__all__ == sorted(set(lodscape.__all__))
    for name in lodscape.__all__:
        value = getattr(lodscape, name)  # raises for a name that does not resolve
        if name == "__version__":
            assert isinstance(value, str)
            assert value[0].isdigit()
            continue
        # every other export is lodscape's own class or function, documented
        assert inspect.isclass(value) or inspect.isfunction(value), name
        assert value.__module__.startswith("lodscape."), (name, value.__module__)
        assert (value.__doc__ or "").strip(), name
    public = {n for n in dir(lodscape) if not n.startswith("_")}
    # sub-packages may show up once imported; nothing else is public by accident
    assert public - set(lodscape.__all__) <= {
        "errors",
        "lod",
        "geo",
        "scene",
        "terrain",
        "imagery",
        "render",
        "store",
        "stream",
        "flight",
        "build",
        "data",
        "cli",
        "city",
        "view",
        "serve",
        "globe",
        "sources",
        "dataset",
        "widget",
        "frame",
        "picture",
        "options",
        "annotations",
    }


def test_pure_layers_import_without_gl_or_rasterio() -> None:
    import subprocess
    import sys

    code = (
        "import sys, lodscape, lodscape.geo, lodscape.lod; "
        "print(any(m in sys.modules for m in ('moderngl', 'rasterio')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"

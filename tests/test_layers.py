"""The import contract: the layer table of docs/ARCHITECTURE.md, read off the source with ast
(imports inside functions included), and no import cycle between modules."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import lodscape

ROOT = Path(lodscape.__file__).parent
#: Modules any layer may import: they hold no state of a layer's.
BASE = {"errors", "_lru", "_sqlite", "_cache", "_tmp"}
#: What each layer may import (besides BASE); the application modules may import anything.
LAYERS: dict[str, set[str]] = {
    "geo": set(),
    "lod": {"geo"},
    "terrain": {"geo"},
    "imagery": {"geo", "terrain"},
    "city": {"geo", "lod"},
    "store": {"geo", "terrain", "imagery", "city"},
    "build": {"geo", "terrain", "imagery", "city", "store"},
    "stream": {"geo", "lod", "terrain"},
    "frame": {"geo", "lod", "stream"},
    "render": {"geo", "lod", "terrain", "imagery", "city", "frame"},
}
APP = {
    "scene",
    "picture",
    "options",
    "_watch",
    "sources",
    "globe",
    "flight",
    "view",
    "serve",
    "cli",
    "__main__",
    "data",
    "dataset",
    "widget",
    "__init__",
}


def _modules() -> dict[str, Path]:
    out = {}
    for f in ROOT.rglob("*.py"):
        parts = f.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = f
    return out


def _imports(path: Path, name: str = "lodscape.m") -> set[str]:
    """The lodscape modules a file (module ``name``) imports, anywhere in it, relative imports
    resolved."""
    found = set()
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            base = package[: len(package) - (node.level - 1)]
            module = ".".join([*base, *([node.module] if node.module else [])])
            found.add(module)
            found.update(f"{module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            if node.module.startswith("lodscape"):
                found.add(node.module)
                # ``from lodscape.geo import keys`` imports the module lodscape.geo.keys
                found.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("lodscape"))
    return found


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


MODULES = _modules()


def test_every_module_has_a_layer() -> None:
    for name in MODULES:
        layer = _layer(name)
        assert layer in LAYERS or layer in APP or layer in BASE, f"{name}: no layer"


@pytest.mark.parametrize("name", sorted(n for n in MODULES if _layer(n) in LAYERS))
def test_layers_import_only_below(name: str) -> None:
    layer = _layer(name)
    allowed = LAYERS[layer] | BASE | {layer}
    for target in _imports(MODULES[name], name):
        if target not in MODULES:
            continue  # a name imported from a module, not a module
        assert _layer(target) in allowed, f"{name} imports {target} ({_layer(target)})"


def test_no_import_cycle() -> None:
    graph = {
        n: {t for t in _imports(p, n) if t in MODULES and t != n and not _is_parent(t, n)}
        for n, p in MODULES.items()
    }
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                cycle = [*stack[stack.index(m) :], m]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if m not in state:
                visit(m)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n)


def _is_parent(package: str, module: str) -> bool:
    """A package's ``__init__`` importing its own submodules is how packages re-export."""
    return module.startswith(package + ".")


def test_the_contract_sees_a_violation(tmp_path: Path) -> None:
    """The reader finds an import inside a function (where cycles hide)."""
    f = tmp_path / "m.py"
    f.write_text("def f():\n    from lodscape.render import Renderer\n")
    assert "lodscape.render" in _imports(f)
    # and a relative one, resolved against the module's package
    f.write_text("from ..render.terrain_pass import Renderer\nfrom . import keys\n")
    got = _imports(f, "lodscape.lod.view")
    assert {"lodscape.render.terrain_pass", "lodscape.lod.keys"} <= got

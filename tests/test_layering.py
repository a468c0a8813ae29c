"""The layers of DESIGN.md, checked on the import graph rather than described.

* The pure layers (core, protocols) import no I/O, event loops or clocks.
* Imports point only downward: core < protocols < pipeline, io < sim < eval < service. ``pipeline`` and ``io``
  are one level (capture sources fill pipeline rings; the detector finds its model in the io cache).
* No module-level import cycle inside mocapd, counting imports under ``if TYPE_CHECKING:`` too: a type that can
  only be named behind that guard is a sign the two modules are one concept or the dependency points the wrong way.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mocapd"
FORBIDDEN = {"asyncio", "socket", "serial", "gi", "onnxruntime", "ai_edge_litert", "time"}
PURE_LAYERS = ("core", "protocols")
#: layer -> rank; a module may import layers of its own rank or lower
RANKS = {"errors": 0, "data": 0, "web": 0, "core": 1, "protocols": 2, "pipeline": 3, "io": 3, "sim": 4, "eval": 5,
         "service": 6}  # fmt: skip


def _imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module is not None and node.level == 0:
            found.add(node.module)
    return found


def _module_level_imports(path: Path) -> set[str]:
    """mocapd modules ``path`` imports at module level (``if TYPE_CHECKING:`` blocks included), not in function
    bodies."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: set[str] = set()

    def visit(body: list[ast.stmt]) -> None:
        for node in body:
            if isinstance(node, ast.Import):
                found.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module is not None and node.level == 0:
                found.add(node.module)
                found.update(f"{node.module}.{a.name}" for a in node.names)
            elif isinstance(node, ast.If):
                visit(node.body)
                visit(node.orelse)
            elif isinstance(node, ast.Try):
                visit(node.body)

    visit(tree.body)
    return {m for m in found if m.split(".")[0] == "mocapd"}


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "mocapd" and len(parts) > 1 else None


def _all_files() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def _pure_files() -> list[Path]:
    return sorted(p for layer in PURE_LAYERS for p in (PACKAGE / layer).rglob("*.py"))


def test_pure_layers_exist() -> None:
    assert _pure_files(), "mocapd/core and mocapd/protocols must contain modules"


@pytest.mark.parametrize("path", _pure_files(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_pure_layer_imports_no_io(path: Path) -> None:
    bad = sorted(m for m in _imported_modules(path) if m.split(".")[0] in FORBIDDEN)
    assert not bad, f"{path.relative_to(PACKAGE)} imports {bad}; core/protocols must stay pure"


def test_checker_catches_forbidden_import(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("import time\nfrom asyncio import sleep\nimport numpy\n", encoding="utf-8")
    assert _imported_modules(bad) & FORBIDDEN == {"time", "asyncio"}


def test_every_package_has_a_rank() -> None:
    packages = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    modules = {p.stem for p in PACKAGE.glob("*.py") if p.stem not in ("__init__", "__main__")}
    unranked = sorted((packages | modules) - set(RANKS))
    assert not unranked, f"give {unranked} a place in RANKS (and in DESIGN.md's layer list)"


def _violations(path: Path) -> list[str]:
    """Upward imports of ``path`` (anywhere in the file, function bodies included)."""
    me = _layer(_module_name(path))
    if me is None or me not in RANKS:
        return []  # mocapd/__init__.py and __main__.py sit above every layer
    out = []
    for m in sorted(_imported_modules(path)):
        other = _layer(m)
        if other is not None and other in RANKS and RANKS[other] > RANKS[me]:
            out.append(f"{_module_name(path)} ({me}) imports {m} ({other})")
    return out


@pytest.mark.parametrize("path", _all_files(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_point_downward(path: Path) -> None:
    assert not _violations(path)


def test_layer_checker_catches_an_upward_import(tmp_path: Path) -> None:
    core = tmp_path / "mocapd" / "core"
    core.mkdir(parents=True)
    bad = core / "bad.py"
    bad.write_text("def f() -> None:\n    from mocapd.service.daemon import Daemon\n", encoding="utf-8")
    rel = bad.relative_to(tmp_path)
    assert _layer(".".join(rel.with_suffix("").parts)) == "core"
    assert "mocapd.service.daemon" in _imported_modules(bad)


def _graph() -> dict[str, set[str]]:
    names = {_module_name(p): p for p in _all_files()}
    graph: dict[str, set[str]] = {}
    for name, path in names.items():
        deps = set()
        for imported in _module_level_imports(path):
            # "from mocapd.service import daemon" names a module; "from mocapd.service.daemon import Daemon" a
            # member: keep the longest prefix that is a module of ours.
            m = imported
            while m and m not in names:
                m = m.rpartition(".")[0]
            if m and m != name:
                deps.add(m)
        graph[name] = deps
    return graph


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for d in sorted(graph.get(n, ())):
            if state.get(d) == 1:
                return [*stack[stack.index(d) :], d]
            if d not in state and (found := visit(d)) is not None:
                return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state and (found := visit(n)) is not None:
            return found
    return None


def test_no_module_level_import_cycle() -> None:
    graph = _graph()
    # A package's __init__ importing its own submodules is not a cycle to worry about; a submodule importing the
    # package that imports it back is (the app <-> config <-> metrics <-> udp_config cycle this test was made for).
    cycle = _find_cycle(graph)
    assert cycle is None, " -> ".join(cycle or [])


def test_cycle_finder_finds_a_cycle() -> None:
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b"}, "b": set()}) is None

"""The pure layers (core, protocols) must not import I/O, event loops or clocks (DESIGN.md, Layers)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mocapd"
FORBIDDEN = {"asyncio", "socket", "serial", "gi", "onnxruntime", "time"}
PURE_LAYERS = ("core", "protocols")


def _imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module is not None and node.level == 0:
            found.add(node.module)
    return found


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

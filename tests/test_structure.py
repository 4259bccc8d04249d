"""Checks anyone can run on the code's shape: modules a reader can hold, functions on one screen,
and no package that reaches up a layer (the adapters never import the training loop)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from external.paths import REPO_ROOT

PACKAGES = ("bench", "backbones", "encoders", "external")
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 60


def _modules() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (REPO_ROOT / pkg).rglob("*.py"))


def _rel(path: Path) -> str:
    return path.relative_to(REPO_ROOT).as_posix()


def test_no_module_is_over_400_lines():
    long = {_rel(p): n for p in _modules() if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_no_function_is_over_60_lines():
    long = []
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{_rel(path)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {long}"


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


@pytest.mark.parametrize("package, forbidden", [
    # Adapters and encoders are below the harness: they know LeRobot, timm, the hub and
    # external/, never anything of bench/ (what they need lives in external/ or is passed in).
    ("backbones", ("bench",)),
    ("encoders", ("bench", "backbones")),
    # external/ is the floor: the hub cache, cache paths, artifacts, LIBERO's feature format.
    ("external", ("bench", "backbones", "encoders")),
])
def test_lower_layers_do_not_import_upper_ones(package, forbidden):
    """Every import counts, those inside functions included (the whole AST is walked)."""
    bad = [f"{_rel(p)} imports {name}" for p in (REPO_ROOT / package).rglob("*.py")
           for name in _imports(p) if name.split(".")[0] in forbidden]
    assert not bad, bad

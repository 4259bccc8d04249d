"""Checks anyone can run on the code's shape: modules a reader can hold, functions on one screen,
every module in a named layer, and no import that climbs to a layer above its own (the adapters
never import the training loop; the records never import the cell that writes them)."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

from ondisk.paths import REPO_ROOT

PACKAGES = ("bench", "backbones", "encoders", "ondisk")
# The LeRobot plugin's packages sit under their own project folder: the import graph reads them
# too (a cycle there went unseen while only PACKAGES were scanned).
PLUGIN_ROOT = REPO_ROOT / "plugins" / "lerobot_policy_graft"
PLUGIN_PACKAGES = ("lerobot_policy_graft", "graftcore")
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
    # ondisk/, never anything of bench/ (what they need lives in ondisk/ or is passed in).
    ("backbones", ("bench",)),
    ("encoders", ("bench", "backbones")),
    # ondisk/ is the floor: the hub cache, cache paths, artifacts, LIBERO's feature format.
    ("ondisk", ("bench", "backbones", "encoders")),
])
def test_lower_layers_do_not_import_upper_ones(package, forbidden):
    """Every import counts, those inside functions included (the whole AST is walked)."""
    bad = [f"{_rel(p)} imports {name}" for p in (REPO_ROOT / package).rglob("*.py")
           for name in _imports(p) if name.split(".")[0] in forbidden]
    assert not bad, bad


def _plugin_modules() -> list[Path]:
    return sorted(p for pkg in PLUGIN_PACKAGES for p in (PLUGIN_ROOT / pkg).rglob("*.py"))


def _module_name(path: Path) -> str:
    root = PLUGIN_ROOT if path.is_relative_to(PLUGIN_ROOT) else REPO_ROOT
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@functools.cache  # three tests read it: parsed once
def _import_graph() -> dict[str, frozenset[str]]:
    """module -> the modules of ours it imports, anywhere in its AST (inside functions and under
    TYPE_CHECKING too); `from pkg import sub` counts as importing pkg.sub, not pkg."""
    modules = {_module_name(p): p for p in _modules() + _plugin_modules()}
    graph = {}
    for name, path in modules.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                deps |= {a.name for a in node.names if a.name in modules}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for alias in node.names:
                    sub = f"{node.module}.{alias.name}"
                    deps.add(sub if sub in modules else node.module)
        graph[name] = frozenset(d for d in deps if d in modules and d != name)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan, iterative)."""
    index, low, on_stack, stack, found, counter = {}, {}, set(), [], [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, edges = work[-1]
            nxt = next(edges, None)
            if nxt is not None:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter[0]
                    counter[0] += 1
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                elif nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def _sub_package(module: str) -> str:
    """bench.cell.freeze -> bench.cell; bench.session -> bench.session; backbones.pi05 -> backbones."""
    parts = module.split(".")
    if parts[0] == "bench" and len(parts) > 2:
        return ".".join(parts[:2])
    return module if parts[0] == "bench" else parts[0]


def test_no_import_cycle_between_modules():
    """No two modules import each other, directly or round a loop (imports in functions count),
    the plugin's included."""
    assert not _cycles(_import_graph())


def test_tiny_patches_know_every_paligemma_family():
    """tiny_paligemma spells its policy types (importing families.py would close a circle)."""
    from lerobot_policy_graft.families import FAMILIES, PaliGemmaFamily
    from lerobot_policy_graft.tiny_paligemma import POLICY_TYPES

    assert set(POLICY_TYPES) == {t for t, f in FAMILIES.items() if isinstance(f, PaliGemmaFamily)}


# Sub-package cycles known and owned elsewhere, each with why it is still there. The test fails
# when one goes away as well, so that this list is emptied, never stale.
KNOWN_PACKAGE_CYCLES: set[tuple[str, ...]] = set()  # none (the last, grid <-> results, is gone)


def test_no_import_cycle_between_sub_packages():
    """bench's sub-packages (and backbones, encoders, ondisk as wholes) import one way."""
    graph: dict[str, set[str]] = {}
    for module, deps in _import_graph().items():
        graph.setdefault(_sub_package(module), set()).update(
            _sub_package(d) for d in deps if _sub_package(d) != _sub_package(module))
    for deps in list(graph.values()):
        for d in deps:
            graph.setdefault(d, set())
    assert {tuple(c) for c in _cycles(graph)} == KNOWN_PACKAGE_CYCLES


# The layers, top to bottom (docs/ARCHITECTURE.md, "The layers"): a module imports modules of
# its own layer and of the layers below it, never of one above. Each entry is a file or a folder
# (ending in "/") relative to the repository or to the plugin's project folder; every module of
# ours must fall under exactly one, so a new module is placed on purpose, not by default.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("front: the pytest front", (
        "bench/plugin.py", "bench/session.py", "bench/options.py", "bench/scheduling.py",
        "bench/summary.py", "bench/test_grid.py", "bench/startup.py", "bench/memory.py",
        "bench/data_bounds.py", "bench/preflight.py")),
    ("study: what a study makes of its records", (
        "bench/analysis/", "bench/report/", "bench/regression/", "bench/export/",
        "bench/robust/", "bench/outputs.py")),
    ("cell: a cell's measurement", ("bench/cell/", "bench/resources/", "bench/loops/")),
    ("records: the record, its store and the screen's scores", (
        "bench/results/", "bench/screen/")),
    ("worlds: the data a cell reads", ("bench/suites/", "bench/sim/", "bench/offline_hub.py")),
    ("core: what a cell is, and the leaves", (
        "bench/__init__.py", "bench/grid/", "bench/option_values.py", "bench/table.py",
        "bench/stats.py", "bench/progress.py")),
    ("registries: the encoders and the policy adapters", ("encoders/", "backbones/")),
    ("floor: the disk and the standalone plugin", (
        "ondisk/", "lerobot_policy_graft/", "graftcore/")),
)


def _place(path: Path) -> str:
    """A module's path as the layer table spells it (the plugin's relative to its project)."""
    root = PLUGIN_ROOT if path.is_relative_to(PLUGIN_ROOT) else REPO_ROOT
    return path.relative_to(root).as_posix()


def layer_of(place: str) -> list[str]:
    """The layers whose entries hold `place` (a file as `_place` spells it): one, if placed."""
    return [name for name, entries in LAYERS
            if any(place == e or e.endswith("/") and place.startswith(e) for e in entries)]


def test_every_module_has_one_layer():
    modules = [_place(p) for p in _modules() + _plugin_modules()]
    unplaced = [m for m in modules if len(layer_of(m)) != 1]
    assert not unplaced, (
        f"modules in no layer or in several: {unplaced}; place each in ONE entry of LAYERS "
        "(tests/test_structure.py) and in docs/ARCHITECTURE.md's list of layers")
    stale = [e for _, entries in LAYERS for e in entries
             if not any(m == e or e.endswith("/") and m.startswith(e) for m in modules)]
    assert not stale, f"LAYERS entries that hold no module: {stale}"


def climbing_imports(graph: dict[str, set[str]], places: dict[str, str]) -> list[str]:
    """'A (layer a) imports B (layer b)' for every import of `graph` whose target's layer is
    above its importer's (LAYERS' order); `places`: module -> its place in the table."""
    rank = {name: i for i, (name, _) in enumerate(LAYERS)}
    layer = {m: found[0] for m, place in places.items() if len(found := layer_of(place)) == 1}
    climbs = []  # a module in no layer is test_every_module_has_one_layer's to name
    for module, deps in sorted(graph.items()):
        for dep in sorted(deps):
            if module in layer and dep in layer and rank[layer[dep]] < rank[layer[module]]:
                climbs.append(f"{module} ({layer[module]}) imports {dep} ({layer[dep]})")
    return climbs


def test_no_import_climbs_a_layer():
    """Every import counts, those inside functions and under TYPE_CHECKING included."""
    places = {_module_name(p): _place(p) for p in _modules() + _plugin_modules()}
    climbs = climbing_imports(_import_graph(), places)
    assert not climbs, "imports that climb to a layer above their own:\n" + "\n".join(climbs)


def test_a_climbing_import_is_named_with_both_layers():
    """The check itself, on a made-up graph: the records importing the cell that writes them."""
    places = {"bench.results.store": "bench/results/store.py",
              "bench.cell.service": "bench/cell/service.py"}
    graph = {"bench.results.store": {"bench.cell.service"},
             "bench.cell.service": {"bench.results.store"}}
    assert climbing_imports(graph, places) == [
        "bench.results.store (records: the record, its store and the screen's scores) imports "
        "bench.cell.service (cell: a cell's measurement)"]


def test_the_architecture_page_lists_the_same_layers():
    """docs/ARCHITECTURE.md's table of layers names LAYERS' layers, in their order."""
    text = (REPO_ROOT / "docs" / "ARCHITECTURE.md").read_text()
    table = text.split("## The layers", 1)[1].split("\n## ", 1)[0]
    rows = [line.split("|")[1].strip() for line in table.splitlines()
            if line.startswith("| ") and not line.startswith(("| layer |", "| --- |"))]
    assert rows == [name.split(":")[0] for name, _ in LAYERS]

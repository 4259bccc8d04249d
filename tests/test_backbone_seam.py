"""The backbone seam (backbones.seam.AdapterModule) and the registry that reads it: an entry
names its policy type, a module that lacks a member fails in one line, and the harness reads
families from the registry instead of naming them."""

from __future__ import annotations

import re
import sys
import types

import pytest

import backbones
from backbones import BACKBONES, BackboneEntry, adapter_for_policy_type, study_backbone
from backbones.seam import ADAPTER_MEMBERS
from ondisk.paths import REPO_ROOT


@pytest.fixture
def fake_registry(monkeypatch):
    """An empty registry and a throwaway adapter module named unlike its policy type."""
    monkeypatch.setattr(backbones, "BACKBONES", {})
    module = types.ModuleType("tests_fake_adapter")
    for member in ADAPTER_MEMBERS:
        setattr(module, member, object())
    monkeypatch.setitem(sys.modules, module.__name__, module)
    return module


def test_a_module_lacking_a_member_fails_in_one_line(fake_registry, monkeypatch):
    monkeypatch.delattr(fake_registry, "write_hub_release")
    monkeypatch.delattr(fake_registry, "RENAMES_CAMERAS")
    backbones.register(BackboneEntry("fake", "faketype", fake_registry.__name__, "o/r", "a fake"))
    with pytest.raises(TypeError) as info:
        backbones.adapter_module("fake")
    message = str(info.value)
    assert "\n" not in message and "'fake'" in message
    assert "RENAMES_CAMERAS, write_hub_release" in message


def test_the_entry_names_the_policy_type_not_the_file_name(fake_registry):
    backbones.register(BackboneEntry("fake", "faketype", fake_registry.__name__, "o/r", "a fake"))
    assert adapter_for_policy_type("faketype") is fake_registry
    with pytest.raises(ValueError, match="adapters exist for faketype"):
        adapter_for_policy_type("tests_fake_adapter")


def test_each_registry_entry_names_a_policy_type_its_module_serves():
    by_module = {}
    for entry in BACKBONES.values():
        by_module.setdefault(entry.module, set()).add(entry.policy_type)
    assert all(len(types_) == 1 for types_ in by_module.values()), by_module


def test_study_backbone_is_read_from_the_registry():
    assert study_backbone("pi05_libero") == "pi05" and study_backbone("smolvla_libero") == "smolvla"
    assert study_backbone("pi0") == "pi0"  # no study entry of its type
    assert study_backbone("smolvla_mine") == "smolvla_mine"  # a --policy name is itself


def test_the_study_tables_per_backbone_keys_are_the_registry_study_entries():
    from bench.report.study import STUDY_CONSTANTS

    study = {name for name, entry in BACKBONES.items() if entry.study}
    per_backbone = [c for c in STUDY_CONSTANTS if c.name in ("pooling grid", "checkpoints")]
    assert per_backbone and all(set(c.study) == study for c in per_backbone)


PLUGIN = REPO_ROOT / "plugins" / "lerobot_policy_graft"
PACKAGES = ("bench", "backbones", "encoders", "ondisk")


def _words(name: str) -> set[str]:
    """The words of a code name, lower case: "GraftPI0Policy" -> graft, pi0, policy;
    "lerobot.policies.pi0.configuration_pi0" -> lerobot, policies, pi0, configuration."""
    parts = re.split(r"[^A-Za-z0-9]+", name)
    return {w.lower() for part in parts
            for w in re.findall(r"[A-Z]+[0-9]*(?![a-z])|[A-Z]?[a-z]+[0-9]*|[0-9]+", part)}


def _names_family(path, family: str) -> bool:
    """Does the code of `path` name backbone `family`: as a name or a word of one (a variable,
    attribute, class, function, argument or imported module), or in a string that is not prose
    ("pi0", "graft_pi0"; docstrings and comments do not count)."""
    import ast

    for node in ast.walk(ast.parse(path.read_text())):
        names: list[str] = []
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            names = [] if any(c.isspace() for c in node.value) else [node.value]
        elif isinstance(node, ast.Name):
            names = [node.id]
        elif isinstance(node, ast.Attribute):
            names = [node.attr]
        elif isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names = [node.name]
        elif isinstance(node, ast.alias):
            names = [node.name, node.asname or ""]
        elif isinstance(node, ast.ImportFrom):
            names = [node.module or ""]
        elif isinstance(node, (ast.keyword, ast.arg)):
            names = [node.arg or ""]
        if any(family in _words(name) for name in names):
            return True
    return False


def test_names_family_finds_a_family_in_code_not_in_prose(tmp_path):
    code = tmp_path / "code.py"
    for text, names in (('x = "pi0"', True), ("class GraftPI0Policy: ...", True),
                        ("from lerobot.policies.pi0 import x", True), ("make_graft_pi0 = 1", True),
                        ("f(PI0)", True), ("import pi05", False), ('"""pi0 and pi0.5"""', False),
                        ("# pi0\nx = 1", False), ('y = "graft_pi05"', False)):
        code.write_text(text)
        assert _names_family(code, "pi0") is names, text


def test_extending_pi0_example_lists_every_file_that_names_pi0():
    """docs/EXTENDING.md's worked example: its "Files touched" are exactly the modules, of the
    harness and of the LeRobot plugin alike, whose code names pi0 (its registry name, its
    module, its family); the tests it lists name pi0 too."""
    text = (REPO_ROOT / "docs" / "EXTENDING.md").read_text()
    section = text.split("## Worked example: pi0", 1)[1].split("Files touched", 1)[1]
    listed = set(re.findall(r"`((?:backbones|bench|encoders|external|tests|plugins)/[\w/]+\.py)`",
                            section.split("\n\n", 1)[0]))
    sources = [p for pkg in PACKAGES for p in (REPO_ROOT / pkg).rglob("*.py")]
    sources += list((PLUGIN / "lerobot_policy_graft").rglob("*.py"))
    modules = {p.relative_to(REPO_ROOT).as_posix() for p in sources if _names_family(p, "pi0")}
    listed_modules = {f for f in listed if not f.startswith("tests/")}
    assert listed_modules == modules, (
        f"listed in EXTENDING.md, not naming pi0: {sorted(listed_modules - modules)}; naming "
        f"pi0, not listed: {sorted(modules - listed_modules)}")
    tests = sorted(f for f in listed if f.startswith("tests/"))
    assert tests and all(_names_family(REPO_ROOT / f, "pi0") for f in tests), tests

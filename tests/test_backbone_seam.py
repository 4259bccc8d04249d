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
from external.paths import REPO_ROOT


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


def _names_family(path, family: str) -> bool:
    """Does the code of `path` name backbone `family`: the string, its module or an attribute?"""
    import ast

    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Constant) and node.value == family:
            return True
        if isinstance(node, ast.Import) and any(a.name == f"backbones.{family}" for a in node.names):
            return True
        if isinstance(node, ast.ImportFrom) and (node.module == f"backbones.{family}" or (
                node.module == "backbones" and any(a.name == family for a in node.names))):
            return True
        if isinstance(node, ast.Attribute) and node.attr == family:
            return True
    return False


def test_extending_pi0_example_lists_every_file_that_names_pi0():
    """docs/EXTENDING.md's worked example: its "Files touched" are exactly the package modules
    whose code names pi0 (its registry name, its module); the tests it lists name pi0 too."""
    text = (REPO_ROOT / "docs" / "EXTENDING.md").read_text()
    section = text.split("## Worked example: pi0", 1)[1].split("Files touched", 1)[1]
    listed = set(re.findall(r"`((?:backbones|bench|encoders|external|tests)/[\w/]+\.py)`",
                            section.split("\n\n", 1)[0]))
    modules = {p.relative_to(REPO_ROOT).as_posix()
               for pkg in ("bench", "backbones", "encoders", "external")
               for p in (REPO_ROOT / pkg).rglob("*.py") if _names_family(p, "pi0")}
    listed_modules = {f for f in listed if not f.startswith("tests/")}
    assert listed_modules == modules, (
        f"listed in EXTENDING.md, not naming pi0: {sorted(listed_modules - modules)}; naming "
        f"pi0, not listed: {sorted(modules - listed_modules)}")
    tests = sorted(f for f in listed if f.startswith("tests/"))
    assert tests and all(_names_family(REPO_ROOT / f, "pi0") for f in tests), tests

"""The tiny size ladder (backbones.tiny_sizes): every size builds offline with its parameter count
and its family's token grid, sizes are matched across families, a size's release has a key of its
own while the families' base builds keep theirs, and a saved size reloads at its size."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from backbones import BACKBONES, adapter_module, get_entry
from backbones.tiny_sizes import (RUNGS, SIZES, build_args, ladder, matched_pairs, pi05_arch,
                                  smolvla_arch)
from bench.grid.protocol import SIM, TINY
from bench.resources.releases import release_key
from tests.backbone_data import CAMERAS, CHUNK, make_stats

# Each family's token grid per camera at every size: the family's, not the size's.
FAMILY_GRID = {"smolvla": (2, 2), "pi05": (4, 4)}


def _build(name: str, seed: int = 0):
    return adapter_module(name).build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK,
                                                  seed=seed, **build_args(name))


def _width(name: str) -> int:
    arch = SIZES[name].arch
    return arch.get("text.hidden_size", arch.get("vlm_width", 64))


@pytest.mark.parametrize("name", list(SIZES))
def test_each_size_builds_offline_with_its_parameters_and_its_familys_token_grid(name):
    backbone = _build(name)
    size = SIZES[name]
    assert sum(p.numel() for p in backbone.policy.parameters()) == size.params
    assert backbone.info.native_grid == FAMILY_GRID[size.family]
    assert backbone.info.lm_width == _width(name)
    assert get_entry(name).policy_type == get_entry(size.family).policy_type


def test_each_family_spans_at_least_8x_over_at_least_three_sizes():
    for family in FAMILY_GRID:
        sizes = ladder(family)
        assert len(sizes) >= 3, family
        assert sizes[-1].params >= 8 * sizes[0].params, family
        assert [s.params for s in sizes] == sorted(s.params for s in sizes)  # rungs grow


def test_matched_rungs_share_width_depth_and_attention_shapes():
    pairs = matched_pairs()
    assert [a.rung for a, _ in pairs] == ["s", "m", "l"]
    for smol, pi in pairs:
        assert (smol.family, pi.family) == ("smolvla", "pi05")
        # today's tiny SmolVLA is rung s: its numbers are smolvla_arch(64, 4)'s
        text = smol.arch or smolvla_arch(64, 4)
        width, depth = text["text.hidden_size"], text["text.num_hidden_layers"]
        assert pi.arch == pi05_arch(width, depth)
        heads, kv, head_dim = (text["text.num_attention_heads"], text["text.num_key_value_heads"],
                               text["text.head_dim"])
        assert heads * head_dim == 8 * pi.arch["head_dim"]  # query projections alike
        assert kv * head_dim == pi.arch["num_kv_heads"] * pi.arch["head_dim"]  # keys and values
        assert 1.15 < pi.params / smol.params < 1.3  # the family's own parts (module doc)


def test_todays_tiny_smolvla_is_rung_s_exactly():
    base, sized = _build("smolvla"), adapter_module("smolvla").build_tiny_policy(
        make_stats(), CAMERAS, chunk_size=CHUNK, arch=smolvla_arch(64, 4))
    a, b = base.policy.state_dict(), sized.policy.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_only_the_ladders_new_sizes_take_arch_and_none_is_on_the_hub():
    assert build_args("smolvla") == {} and build_args("pi05") == {} and build_args("pi0") == {}
    for name, size in SIZES.items():
        entry = BACKBONES[name]
        assert entry.on_hub == size.base, name
        assert (entry.tiny_size is None) == size.base and entry.repo_id == ("" if not size.base
                                                                            else entry.repo_id)
    assert all(s.rung in RUNGS for s in SIZES.values())


class _Suite:
    fingerprint = "abc"


def test_todays_release_keys_are_kept_and_each_size_has_its_own():
    # Known answers: the keys of main before the ladder (release 0 and 2), so records resume.
    assert release_key("smolvla", TINY, [_Suite()], 10, "arch") == "7212277859b2"
    assert release_key("pi05", SIM, [_Suite()], 10, "arch", 2) == "47d331753545"
    keys = {release_key(name, TINY, [_Suite()], 10, "arch") for name in SIZES}
    assert len(keys) == len(SIZES)  # even with the same architecture fingerprint


def test_a_saved_size_reloads_at_its_size(tmp_path):
    for name in ("smolvla_m", "pi05_s"):
        module = adapter_module(name)
        built = _build(name, seed=3)
        module.save_pretrained(built, tmp_path / name)
        loaded = module.load_policy(str(tmp_path / name))
        a, b = built.policy.state_dict(), loaded.policy.state_dict()
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a), name
        assert loaded.info.lm_width == _width(name)


def test_a_hub_profile_refuses_a_tiny_only_size():
    from bench.grid.protocol import PAPER
    from bench.startup import validate_names

    with pytest.raises(pytest.UsageError, match=r"'smolvla_m' is a size of the tiny ladder"):
        validate_names(dataclasses.replace(PAPER, backbones=("smolvla_m",), encoders=()))


def test_the_step_script_refuses_a_wrong_size_before_building_any(capsys, monkeypatch):
    """scripts/ladder_steps.py NAME...: a name not on the ladder, wherever it stands, is one line
    naming the near one (the case only differs here), exit 4; no size is measured first."""
    import importlib.util

    from ondisk.paths import REPO_ROOT

    spec = importlib.util.spec_from_file_location("ladder_steps",
                                                  REPO_ROOT / "scripts" / "ladder_steps.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    monkeypatch.setattr(script, "measure", lambda name: pytest.fail(f"{name} measured"))
    with pytest.raises(SystemExit) as stop:
        script.main(["pi05", "pi05_L"])
    err = capsys.readouterr().err
    assert stop.value.code == 4 and err.count("\n") == 1, err
    assert "NAME: unknown ladder size 'pi05_L' (did you mean 'pi05_l'?); valid sizes" in err

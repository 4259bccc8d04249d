"""A user's own encoder, `--encoders PKG.MODULE:FACTORY` (encoders.user_encoders): loaded from an
importable module, fed and frozen like a timm encoder, its weights id in the feature key and the
record, and every broken contract one line before any cell trains."""

from __future__ import annotations

import json
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F

from bench.grid.cells import CellSpec
from bench.resources.features import feature_key
from bench.startup import validate_names
from bench.grid.protocol import TINY, with_overrides
from encoders import UnknownEncoder, build_encoder, get_spec, user_encoders
from encoders.timm_encoders import weight_artifacts

MODULE = "graftbench_user_enc"  # unlikely to shadow anything on sys.path
SOURCE = textwrap.dedent('''
    import torch

    class Patches(torch.nn.Module):
        input_size = 32
        mean = (0.5, 0.5, 0.5)
        std = (0.25, 0.25, 0.25)
        channels = 12

        def __init__(self, weights_id="patches-a"):
            super().__init__()
            self.weights_id = weights_id
            self.conv = torch.nn.Conv2d(3, 12, kernel_size=8, stride=8)
            self.norm = torch.nn.BatchNorm2d(12)

        def forward(self, x):
            return self.norm(self.conv(x))

    def make():
        return Patches()

    def make_other():
        return Patches("patches-b")

    def make_for(source):
        return Patches(f"patches-{source}")

    class NoSize(torch.nn.Module):
        mean, std, channels, weights_id = (0.5,) * 3, (0.5,) * 3, 3, "x"

    def no_size():
        return NoSize()

    def bad_mean():
        net = Patches()
        net.mean = (0.5, 0.5)
        return net

    def wrong_channels():
        net = Patches()
        net.channels = 5
        return net

    def not_a_module():
        return lambda x: x

    NOT_CALLABLE = 3
''')


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """MODULE written into tmp_path, importable, with a fresh build cache."""
    (tmp_path / f"{MODULE}.py").write_text(SOURCE)
    monkeypatch.delitem(sys.modules, MODULE, raising=False)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(user_encoders, "_BUILT", {})
    yield tmp_path
    sys.modules.pop(MODULE, None)


def test_factory_is_loaded_fed_like_timm_and_frozen(user_module):
    enc = build_encoder(f"{MODULE}:make", "tiny")
    spec = enc.spec
    assert (spec.name, spec.timm_name, spec.input_size) == (f"{MODULE}:make", None, 32)
    assert spec.mean == (0.5, 0.5, 0.5) and spec.std == (0.25, 0.25, 0.25)
    assert enc.channels == 12 and enc.weights_id == "patches-a"
    images = torch.rand(2, 3, 64, 64)
    grid = enc(images)
    # Known answer: resized to 32 px, normalised by the declared mean/std, then the module.
    resized = F.interpolate(images, size=(32, 32), mode="bilinear", antialias=True,
                            align_corners=False)
    assert torch.equal(grid, enc.module((resized - 0.5) / 0.25))
    assert grid.shape == (2, 12, 4, 4) and grid.dtype == torch.float32
    assert not any(p.requires_grad for p in enc.parameters())
    enc.train()  # a parent's .train() must not switch its BatchNorm back on
    assert not any(m.training for m in enc.modules())
    assert get_spec(f"{MODULE}:make") is spec  # built once per name and source
    assert weight_artifacts(f"{MODULE}:make") == []  # its weights are its module's business


def test_factory_runs_seeded_and_leaves_the_global_rng_alone(user_module, monkeypatch):
    torch.manual_seed(7)
    expected_next = torch.rand(1)
    torch.manual_seed(7)
    first = build_encoder(f"{MODULE}:make", "tiny")
    assert torch.equal(torch.rand(1), expected_next)
    monkeypatch.setattr(user_encoders, "_BUILT", {})
    again = build_encoder(f"{MODULE}:make", "tiny")
    assert again is not first
    assert torch.equal(again.module.conv.weight, first.module.conv.weight)


def test_a_factory_with_a_source_parameter_gets_the_source(user_module):
    assert build_encoder(f"{MODULE}:make_for", "tiny").weights_id == "patches-tiny"
    assert build_encoder(f"{MODULE}:make_for", "hub").weights_id == "patches-hub"


def test_the_weights_id_is_in_the_feature_key(user_module):
    suite = SimpleNamespace(fingerprint="suite-fp", camera_keys=("image",))
    key = {n: feature_key(build_encoder(f"{MODULE}:{n}", s), suite, (4, 4))
           for n, s in (("make", "tiny"), ("make_other", "tiny"))}
    assert key["make"] != key["make_other"]
    # Same factory, same spec, only the weights id differs (its source): still two keys.
    tiny, hub = (build_encoder(f"{MODULE}:make_for", s) for s in ("tiny", "hub"))
    same = ("name", "timm_name", "input_size", "mean", "std", "num_prefix_tokens")
    assert [getattr(tiny.spec, f) for f in same] == [getattr(hub.spec, f) for f in same]
    assert feature_key(tiny, suite, (4, 4)) != feature_key(hub, suite, (4, 4))
    assert feature_key(tiny, suite, (4, 4)) == feature_key(tiny, suite, (4, 4))


@pytest.mark.parametrize("name, error, words", [
    ("no_such_pkg.enc:make", UnknownEncoder, ["'no_such_pkg.enc'", "PYTHONPATH"]),
    ("no_such_module_at_all:make", UnknownEncoder, ["unknown encoder", "PKG.MODULE:FACTORY"]),
    (f"{MODULE}:nope", UnknownEncoder, ["no factory 'nope'", MODULE, "def nope():", "make"]),
    (f"{MODULE}:NOT_CALLABLE", UnknownEncoder, ["non-callable factory 'NOT_CALLABLE'"]),
    (f"{MODULE}:no_size", ValueError, ["without input_size;", MODULE, "set it on it"]),
    (f"{MODULE}:bad_mean", ValueError, ["mean=(0.5, 0.5)", "3 floats"]),
    (f"{MODULE}:not_a_module", ValueError, ["not a torch.nn.Module"]),
    (f"{MODULE}:wrong_channels", ValueError, ["(1, 12, 4, 4)", "channels=5"]),
])
def test_a_broken_contract_is_one_line_naming_the_fix(user_module, name, error, words):
    with pytest.raises(error) as err:
        build_encoder(name, "tiny")
    message = str(err.value)
    assert "\n" not in message and name in message
    for w in words:
        assert w in message, message


def test_names_pass_validation_and_give_readable_cell_ids(user_module):
    validate_names(with_overrides(TINY, encoders=("pixels", f"{MODULE}:make")))
    with pytest.raises(pytest.UsageError, match="without input_size"):
        validate_names(with_overrides(TINY, encoders=(f"{MODULE}:no_size",)))
    cell = CellSpec("graft", "smolvla", "spatial", 0, "mypkg.enc:make")
    assert cell.id == "smolvla-spatial-mypkg.enc_make-seed0"


def test_bench_records_the_user_encoders_weights_id(user_module, bench_cli, tmp_path):
    """End to end: `pytest bench --encoders ...,MODULE:make`, the module's folder on sys.path;
    its record carries the encoder's weights id."""
    run = bench_cli(tmp_path / "R", "--encoders", f"pixels,blind,{MODULE}:make", "--backbones",
                    "pi05", "--suites", "spatial", "--seeds", "0", "--controls", "none",
                    "--steps", "5")
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    results = tmp_path / "R" / "results"
    record = json.loads((results / "cells" / f"pi05-spatial-{MODULE}_make-seed0.json").read_text())
    assert record["encoder"] == f"{MODULE}:make"
    assert record["encoder_weights"] == "patches-a"
    assert (tmp_path / "R" / "REPORT.md").exists()

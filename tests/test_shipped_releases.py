"""The shipped tiny releases (bench.resources.shipped): the default recipe's releases load from
the shipped copy into an empty cache without training, their files are the ones pinned (content
hash), weights and stats are safetensors only, and a changed file is refused before anything is
copied."""

from __future__ import annotations

import shutil

import pytest

from bench.grid.pinned_release import check_pinned
from bench.grid.protocol import TINY
from bench.progress import QUIET
from bench.resources import releases, shipped
from ondisk.hubcache import folder_revision

# The tests' world has a third backbone beside the default grid's two: its release is shipped too.
BACKBONES = TINY.backbones + ("pi0",)


def _world(tiny_ws):
    suites = [tiny_ws.suite(s) for s in tiny_ws.released_suites()]
    return suites, {s.name: tiny_ws.split(s.name).train_frames for s in suites}


def _no_training(name, *args, **kwargs):
    raise AssertionError(f"the tiny {name} was trained: its recipe's key is not in "
                         "bench/resources/shipped/index.json (ship it: python -m "
                         "bench.resources.shipped GRAFTBENCH_CACHE/released/<backbone>-<key>)")


@pytest.mark.parametrize("name", BACKBONES)
def test_the_default_recipe_loads_the_shipped_release_without_training(name, tiny_ws, tmp_path,
                                                                       monkeypatch,
                                                                       one_torch_thread):
    monkeypatch.setattr(releases, "train_tiny_release", _no_training)
    suites, train = _world(tiny_ws)
    policy, checkpoint = releases.load_released(name, TINY, suites, train, tmp_path,
                                                progress=QUIET)
    (folder,) = (p for p in (tmp_path / "released").iterdir() if p.is_dir())
    # Its saved stats are the ones this world's suites give: records name the same normaliser.
    expected = releases.normalizer_for(name, TINY, suites, train).fingerprint
    assert policy.normalizer_fingerprint() == expected
    source = shipped.SHIPPED_DIR / shipped.shipped()[folder.name]
    assert checkpoint["revision"] == folder_revision(source) is not None
    assert {p.relative_to(folder): p.read_bytes() for p in folder.rglob("*") if p.is_file()} == \
        {p.relative_to(source): p.read_bytes() for p in source.rglob("*") if p.is_file()}


def test_every_shipped_release_is_pinned_and_holds_no_pickle():
    index = shipped.shipped()
    assert sorted(index.values()) == sorted(p.name for p in shipped.SHIPPED_DIR.iterdir()
                                            if p.is_dir())
    for cache_name, pinned in index.items():
        folder = check_pinned(cache_name.rsplit("-", 1)[0], shipped.SHIPPED_DIR / pinned)
        suffixes = {p.suffix for p in folder.rglob("*") if p.is_file()}
        assert suffixes <= {".safetensors", ".json"}, (pinned, suffixes)
        assert (folder / "model.safetensors").is_file()


def test_a_changed_shipped_file_is_refused_and_nothing_is_copied(tmp_path, monkeypatch):
    cache_name, pinned = next(iter(shipped.shipped().items()))
    copy = tmp_path / "shipped"
    shutil.copytree(shipped.SHIPPED_DIR, copy)
    with open(copy / pinned / "model.safetensors", "r+b") as weights:
        weights.seek(-1, 2)
        last = weights.read(1)
        weights.seek(-1, 2)
        weights.write(bytes([last[0] ^ 1]))
    monkeypatch.setattr(shipped, "SHIPPED_DIR", copy)
    with pytest.raises(ValueError, match=r"shipped release of .* hash to .*git checkout"):
        shipped.shipped_release(cache_name)
    assert shipped.shipped_release("smolvla-000000000000") is None  # another recipe: trained


def test_a_shipped_copy_that_changes_on_the_way_is_not_kept(tmp_path, monkeypatch):
    cache_name, pinned = next(iter(shipped.shipped().items()))
    monkeypatch.setattr(shipped, "content_hash", lambda folder: "0" * 16)  # what the copy hashes to
    target = tmp_path / "released" / cache_name
    target.parent.mkdir()
    with pytest.raises(OSError, match="changed its files"):
        shipped.install_shipped(shipped.SHIPPED_DIR / pinned, target)
    assert list(target.parent.iterdir()) == []

"""Where the LIBERO suites are looked for (LeRobot's cache and the HF hub cache that
`hf download` fills), the dataset artifact the preflight lists, and one-line load failures."""

from __future__ import annotations

import json
import os
import shutil

import pytest
import torch

from bench.progress import QUIET
from bench.suites import libero, load_suite
from ondisk.libero_format import IMAGE_KEYS
from bench.suites.base import SuiteUnavailable

REPO = "lerobot/libero_spatial_image"
SHA = "0123456789abcdef0123456789abcdef01234567"
COMMAND = f"hf download --repo-type dataset {REPO}"


@pytest.fixture
def hf_home(tmp_path, monkeypatch):
    """An empty HF_HOME (hub cache and LeRobot's cache inside), offline, no GRAFTBENCH root.

    Both libraries read these variables at import time, so their module attributes are patched
    too; libero.lerobot_home() and hub_cache() read those attributes at call time.
    """
    from huggingface_hub import constants as hub_constants
    from lerobot.utils import constants as lerobot_constants

    home = tmp_path / "hf"
    for var, value in (("HF_HOME", home), ("HF_HUB_CACHE", home / "hub"),
                       ("HF_LEROBOT_HOME", home / "lerobot")):
        monkeypatch.setenv(var, str(value))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.delenv(libero.ROOT_ENV, raising=False)
    monkeypatch.setattr(hub_constants, "HF_HOME", str(home))
    monkeypatch.setattr(hub_constants, "HF_HUB_CACHE", str(home / "hub"))
    monkeypatch.setattr(hub_constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(lerobot_constants, "HF_LEROBOT_HOME", home / "lerobot")
    monkeypatch.setattr(lerobot_constants, "HF_LEROBOT_HUB_CACHE", home / "lerobot" / "hub")
    assert libero.hub_cache() == home / "hub" and libero.lerobot_home() == home / "lerobot"
    return home


def hub_snapshot(cache, sha: str = SHA, ref: str | None = "main", info: dict | None = None):
    """What `hf download --repo-type dataset REPO` leaves in hub cache `cache`: refs/<ref> holding
    the commit sha and snapshots/<sha>/ holding the files (here only meta/info.json)."""
    repo = cache / ("datasets--" + REPO.replace("/", "--"))
    snapshot = repo / "snapshots" / sha
    (snapshot / "meta").mkdir(parents=True)
    (snapshot / "meta" / "info.json").write_text(json.dumps(info or {"codebase_version": "v3.0"}))
    if ref is not None:
        (repo / "refs").mkdir(exist_ok=True)
        (repo / "refs" / ref).write_text(sha)
    return snapshot


def test_locate_finds_the_snapshot_refs_main_names_before_newer_ones(hf_home):
    named = hub_snapshot(hf_home / "hub")
    newer = hub_snapshot(hf_home / "hub", sha="f" * 40, ref=None)
    os.utime(newer, (named.stat().st_mtime + 60,) * 2)
    assert libero.locate(REPO) == named
    (named / "meta" / "info.json").unlink()  # no refs/main snapshot: the newest other one
    assert libero.locate(REPO) == newer


def test_dataset_artifact_reports_a_hub_cache_copy_present(hf_home):
    snapshot = hub_snapshot(hf_home / "hub")
    artifact = libero.dataset_artifact("spatial")
    assert (artifact.kind, artifact.repo_id, artifact.needed_by) == ("dataset", REPO, "suite spatial")
    assert artifact.present and artifact.where == str(snapshot) and artifact.fix == ""
    assert artifact.revision is None and artifact.line().startswith("ok ")


def test_absent_dataset_fix_is_the_command_that_makes_it_found(hf_home):
    artifact = libero.dataset_artifact("spatial")
    assert not artifact.present and artifact.fix == COMMAND
    assert str(hf_home / "lerobot" / REPO) in artifact.where and str(hf_home / "hub") in artifact.where
    with pytest.raises(SuiteUnavailable) as err:
        load_suite("spatial", "hub", progress=QUIET)
    message = str(err.value)
    assert "\n" not in message and f"`{COMMAND}`" in message
    assert str(hf_home / "lerobot" / REPO) in message and str(hf_home / "hub") in message
    assert f"--local-dir {hf_home / 'lerobot' / REPO}`" in message
    hub_snapshot(hf_home / "hub")  # what running the fix leaves behind
    assert libero.dataset_artifact("spatial").present


def test_local_dir_fix_is_found_too(hf_home):
    local = hf_home / "lerobot" / REPO  # `hf download ... --local-dir $HF_LEROBOT_HOME/REPO`
    (local / "meta").mkdir(parents=True)
    (local / "meta" / "info.json").write_text("{}")
    assert libero.locate(REPO) == local and libero.dataset_artifact("spatial").where == str(local)


def test_a_pinned_revision_is_only_found_at_that_revision(hf_home, monkeypatch):
    monkeypatch.setitem(libero.LIBERO_REVISIONS, "spatial", "v3.0")
    hub_snapshot(hf_home / "hub")  # refs/main only
    artifact = libero.dataset_artifact("spatial")
    assert not artifact.present and artifact.fix == f"{COMMAND} --revision v3.0"
    pinned = hub_snapshot(hf_home / "hub", sha="e" * 40, ref="v3.0")
    artifact = libero.dataset_artifact("spatial")
    assert artifact.present and artifact.where == str(pinned) and artifact.revision == "v3.0"
    assert f"{REPO}@v3.0" in artifact.line()


def test_hf_download_into_the_hub_cache_loads_as_the_hub_suite(hf_home):
    """End to end: a LeRobot dataset laid out as `hf download` writes it loads with no root."""
    tiny = load_suite("spatial", "tiny", progress=QUIET)
    snapshot = hf_home / "hub" / f"datasets--{REPO.replace('/', '--')}" / "snapshots" / SHA
    shutil.copytree(tiny.root, snapshot)
    (snapshot.parent.parent / "refs").mkdir()
    (snapshot.parent.parent / "refs" / "main").write_text(SHA)
    suite = load_suite("spatial", "hub", progress=QUIET)
    assert suite.root == str(snapshot) and torch.equal(suite.action, tiny.action)
    frames = torch.tensor([0, 5])
    assert torch.equal(suite.images(frames)[IMAGE_KEYS[0]], tiny.images(frames)[IMAGE_KEYS[0]])


class _LeadingNewlineError(Exception):
    """Like LeRobot's compatibility errors: the message starts with a newline."""


def test_an_error_whose_first_line_is_blank_still_gives_the_reason(hf_home, monkeypatch):
    import lerobot.datasets.lerobot_dataset as lerobot_dataset

    def refuse(repo_id, root=None, revision=None):
        raise _LeadingNewlineError(f"\nThe dataset you requested ({repo_id}) is in v2.1 format.\n\n"
                                   + "Please convert it. " * 40)

    hub_snapshot(hf_home / "hub")
    monkeypatch.setattr(lerobot_dataset, "LeRobotDataset", refuse)
    with pytest.raises(SuiteUnavailable) as err:
        load_suite("spatial", "hub", progress=QUIET)
    message = str(err.value)
    assert "\n" not in message
    assert f"(_LeadingNewlineError: The dataset you requested ({REPO}) is in v2.1 format. " \
           f"Please convert it." in message
    reason = message.split("_LeadingNewlineError: ")[1].split("); fix:")[0]
    assert len(reason) == libero.REASON_CHARS and reason.endswith("...")


def test_lerobots_own_version_error_gives_the_reason(hf_home):
    hub_snapshot(hf_home / "hub", info={"codebase_version": "v2.1", "fps": 10, "features": {}})
    with pytest.raises(SuiteUnavailable) as err:
        load_suite("spatial", "hub", progress=QUIET)
    message = str(err.value)
    assert "\n" not in message
    assert f"(BackwardCompatibilityError: The dataset you requested ({REPO}) is in 2.1" in message


def test_one_line_collapses_whitespace_and_trims():
    assert libero.one_line("\n a\n\n b\tc  ") == "a b c"
    assert libero.one_line("x" * 10, limit=8) == "xxxxx..."


def test_unknown_suite_names_the_valid_ones():
    with pytest.raises(ValueError, match=r"unknown LIBERO suite 'spatal'.*'spatial'"):
        libero.dataset_artifact("spatal")

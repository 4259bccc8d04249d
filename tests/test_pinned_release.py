"""Pinned releases (bench.grid.pinned_release): a committed study loads the release it was
measured on by content hash, refuses a pin whose files changed at start-up, and a record made on
another release is neither resumed nor mixed into a report silently."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from bench.grid.cells import CellSpec
from bench.grid.kinds import GRAFT
from bench.grid.pinned_release import check_pinned, content_hash, pin
from bench.grid.protocol import TINY
from bench.options import build_profile
from bench.progress import QUIET
from bench.report import build
from bench.report.sections import mixed_releases
from bench.results.current import RunConditions
from bench.results.store import ResultStore
from bench.cell.plan import plan
from bench.resources.workspace import Workspace
from tests.factories import make_record
from tests.test_gridfile import Config
from tests.test_report import write_grid
from tests.worlds import lent_workspace


def _fake_release(folder: Path, backbone: str = "pi05") -> Path:
    """A release folder's shape without torch: metadata and a weights file."""
    folder.mkdir(parents=True)
    (folder / "graftbench_release.json").write_text(json.dumps({"backbone": backbone}))
    (folder / "model.safetensors").write_bytes(bytes(range(256)))
    return folder


def test_the_content_hash_is_the_paths_and_bytes_of_every_file(tmp_path):
    """Known answer: sha256 over "path NUL sha256(bytes) NEWLINE" in path order, 16 hex."""
    (tmp_path / "sub").mkdir()
    (tmp_path / "b.txt").write_bytes(b"y")
    (tmp_path / "sub" / "a.txt").write_bytes(b"x")
    lines = "".join(f"{p}\0{hashlib.sha256(b).hexdigest()}\n"
                    for p, b in (("b.txt", b"y"), ("sub/a.txt", b"x")))
    assert content_hash(tmp_path) == hashlib.sha256(lines.encode()).hexdigest()[:16]
    (tmp_path / "sub" / "a.txt").rename(tmp_path / "sub" / "c.txt")  # same bytes, other name
    assert content_hash(tmp_path) != hashlib.sha256(lines.encode()).hexdigest()[:16]


def _study(tmp_path, pinned: Path, profile: str = "tiny") -> Path:
    path = tmp_path / "study.toml"
    path.write_text(f'profile = "{profile}"\n[releases]\npi05 = "pins/{pinned.name}"\n')
    return path


def test_a_pinned_release_is_read_from_the_grid_file_and_a_tampered_one_refused(tmp_path):
    pinned = pin(_fake_release(tmp_path / "cache" / "released" / "pi05-key"), tmp_path / "pins")
    assert pinned.name == f"pi05-{content_hash(pinned)}"
    assert pin(tmp_path / "cache" / "released" / "pi05-key", tmp_path / "pins") == pinned
    profile = build_profile(Config(grid=str(_study(tmp_path, pinned))))
    assert profile.releases == (("pi05", str(pinned.resolve())),)
    with pytest.raises(pytest.UsageError, match=r"\[releases\] pins tiny releases, and profile "
                                                r"'paper' loads real checkpoints"):
        build_profile(Config(grid=str(_study(tmp_path, pinned, "paper"))))
    weights = pinned / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:-1] + b"\0")  # one byte of the weights changed
    with pytest.raises(pytest.UsageError) as err:
        build_profile(Config(grid=str(_study(tmp_path, pinned))))
    message = str(err.value)
    assert "\n" not in message and "study.toml: [releases] pi05 = " in message
    assert f"hash to {content_hash(pinned)}, not the {pinned.name[5:]} its name claims" in message
    renamed = pinned.rename(pinned.with_name("smolvla-" + pinned.name[5:]))
    with pytest.raises(ValueError, match=r"not named pi05-<16 hex content hash>"):
        check_pinned("pi05", renamed)


def test_the_printed_releases_line_pasted_into_a_grid_file_beside_the_pins_loads_them(
        tmp_path, capsys):
    from bench.grid.pinned_release import main

    release = _fake_release(tmp_path / "cache" / "released" / "pi05_s-key", backbone="pi05_s")
    main([str(release), "--into", str(tmp_path / "study" / "releases")])
    line = capsys.readouterr().out.splitlines()[-1]
    assert f"for a grid file in {tmp_path / 'study'}/" in line
    entry = line[line.rindex(": ") + 2:]
    assert entry.startswith('pi05_s = "releases/pi05_s-')
    grid = tmp_path / "study" / "study.toml"
    grid.write_text(f'profile = "tiny"\n[releases]\n{entry}\n')
    [(backbone, path)] = build_profile(Config(grid=str(grid))).releases
    assert backbone == "pi05_s" and Path(path).parent == (tmp_path / "study" / "releases").resolve()


def test_a_bad_into_or_release_stops_in_one_line_with_exit_4(tmp_path, capsys):
    from bench.grid.pinned_release import main

    release = _fake_release(tmp_path / "cache" / "released" / "pi05-key")
    (tmp_path / "a_file").write_text("")
    for argv, says in (([str(release), "--into", str(tmp_path / "a_file")], "cannot pin there"),
                       ([str(tmp_path / "nothing"), "--into", str(tmp_path / "pins")],
                        "no graftbench_release.json")):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        err = capsys.readouterr().err
        assert stop.value.code == 4 and says in err and err.count("\n") == 1, err
    assert not (tmp_path / "pins").exists() and (tmp_path / "a_file").read_text() == ""


def test_pytest_bench_stops_on_a_tampered_pin_with_exit_4(bench_cli, tmp_path):
    pinned = pin(_fake_release(tmp_path / "release"), tmp_path / "pins")
    (pinned / "graftbench_release.json").write_text('{"backbone": "pi05", "x": 1}')
    out = bench_cli(tmp_path, "--grid", str(_study(tmp_path, pinned)), "--co")
    text = out.stdout + out.stderr
    assert out.returncode == 4 and "its name claims (edited since it was pinned)" in text
    assert "Traceback" not in text and "INTERNALERROR" not in text


def test_a_pinned_release_gives_the_same_policy_without_training(tmp_path):
    """A 2-step release pinned, then loaded by a run whose own protocol (3 native steps), empty
    cache and shifted suites would train another: the pinned weights, revision and normaliser,
    no training."""
    lent = lent_workspace(TINY, ResultStore(tmp_path / "lent"))

    def workspace(profile, cache: str, state_shift: float = 0.0) -> Workspace:
        ws = Workspace(profile, ResultStore(tmp_path / cache / "results"), progress=QUIET,
                       cache=tmp_path / cache)
        ws._suites.update({s: dataclasses.replace(lent.suite(s), state=lent.suite(s).state
                                                  + state_shift)
                           for s in ws.released_suites()})
        return ws

    small = TINY.protocol.replace(tiny_image_size=32)  # a 2 x 2 token grid: a faster release
    two = dataclasses.replace(TINY, protocol=small.replace(native_steps=2))
    trained = workspace(two, "cache")
    policy = trained.backbone("pi05", "spatial").policy.state_dict()
    (release,) = (p for p in (tmp_path / "cache" / "released").iterdir() if p.is_dir())
    pinned = pin(release, tmp_path / "pins")
    three = dataclasses.replace(TINY, protocol=small.replace(native_steps=3),
                                releases=(("pi05", str(pinned)),))
    # Another machine's suites (states rendered a little differently): the release's own
    # normaliser still, not one of these suites' stats.
    loaded = workspace(three, "empty", state_shift=1e-3)
    again = loaded.backbone("pi05", "spatial").policy.state_dict()
    assert list(again) == list(policy)
    assert all(torch.equal(again[k], policy[k]) for k in policy)
    assert loaded.checkpoint("pi05") == trained.checkpoint("pi05")
    assert (loaded.normalizer("pi05", "spatial").fingerprint
            == trained.normalizer("pi05", "spatial").fingerprint)
    assert not (tmp_path / "empty" / "released").exists()  # nothing was trained


def test_a_record_of_another_release_is_not_resumed_and_the_report_names_both(tmp_path):
    store = ResultStore(tmp_path / "results")
    ours, theirs = "sha256:00000000000000aa", "sha256:00000000000000bb"
    store.write(make_record(backbone="pi05", encoder="pixels",
                            checkpoint={"repo_id": "tiny:pi05", "revision": theirs}))
    cell = CellSpec(GRAFT, "pi05", "spatial", 0, "pixels")
    run = RunConditions(protocol_hash=TINY.protocol.hash)
    stored = store.load(cell.id)
    lent = stored.measured.checkpoint or {}  # the workspace lends this release's weights and normaliser
    normalizer = SimpleNamespace(fingerprint=lent.get("normalizer_fingerprint"))

    def workspace(revision):  # the workspace's lookups, as bench.cell.plan.on_weights makes them
        return lambda: SimpleNamespace(checkpoint=lambda *where: {**lent, "revision": revision},
                                       normalizer=lambda *where: normalizer)

    assert plan(cell, stored, run, workspace=workspace(ours)).resume is None
    assert plan(cell, stored, run, workspace=workspace(theirs)).resume is not None
    # Another item measured on this machine's release: the folder now holds both.
    store.write(make_record(backbone="pi05", encoder="blind",
                            checkpoint={"repo_id": "tiny:pi05", "revision": ours}))
    records = [make_record(backbone="pi05", encoder="pixels",
                           checkpoint={"repo_id": "tiny:pi05", "revision": theirs}),
               make_record(backbone="pi05", encoder="blind",
                           checkpoint={"repo_id": "tiny:pi05", "revision": ours})]
    assert mixed_releases(records) == {"pi05": {ours: ["pi05-spatial-blind-seed0"],
                                                theirs: ["pi05-spatial-pixels-seed0"]}}
    assert mixed_releases(records[:1]) == {}
    folder = write_grid(tmp_path / "report", records)
    text = build.build_report(folder, tmp_path / "REPORT.md", n_resamples=20,
                              plots=False).read_text()
    assert (f"**Warning: pi05's records were measured on 2 different releases** ({ours}: "
            f"pi05-spatial-blind-seed0 (1 cell(s)); {theirs}: pi05-spatial-pixels-seed0") in text

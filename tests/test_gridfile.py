"""A study in a file (`pytest bench --grid study.toml`, bench.grid.gridfile): the file gives the grid,
the command line overrides it, its hash goes into every record, and a bad file is one line."""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import json

import pytest

from bench.grid.gridfile import GridFileError, read_grid_file
from bench.options import build_profile
from ondisk.paths import REPO_ROOT
from bench.grid.protocol import TINY, TINY_FULL, with_overrides

STUDY = """\
profile = "tiny"
backbones = ["pi05"]
suites = ["spatial"]
encoders = ["pixels", "blind"]
seeds = [0]
controls = []
steps = 5
"""


def _write(tmp_path, text: str, name: str = "study.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


class Config:
    """What build_profile reads of pytest's config: the options given, None for the others."""

    def __init__(self, **given):
        self.given = {f"--{k.replace('_', '-')}": v for k, v in given.items()}

    def getoption(self, name):
        return self.given.get(name)


def test_a_file_gives_the_same_profile_as_the_same_overrides(tmp_path):
    path = _write(tmp_path, STUDY + 'control_encoders = ["blind"]\n[protocol]\nlr = 0.01\n'
                                    "heldout_episodes_per_task = 3\n")
    profile = build_profile(Config(grid=str(path)))
    expected = with_overrides(TINY, backbones=("pi05",), suites=("spatial",),
                              encoders=("pixels", "blind"), seeds=(0,), controls=(),
                              control_encoders=("blind",), steps=5)
    expected = dataclasses.replace(expected, protocol=expected.protocol.replace(
        lr=0.01, heldout_episodes_per_task=3))
    assert dataclasses.replace(profile, grid_file=None) == expected
    info = profile.grid_file
    assert info.path == str(path) and info.text == path.read_text()
    assert info.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    # The file's protocol values move the hash (they change numbers); the file itself does not.
    assert profile.protocol.hash == expected.protocol.hash != TINY.protocol.hash


def test_the_file_itself_leaves_the_protocol_hash_alone(tmp_path):
    profile = build_profile(Config(grid=str(_write(tmp_path, "seeds = [3]\n"))))
    assert profile.protocol == TINY.protocol and profile.protocol.hash == TINY.protocol.hash
    assert profile.seeds == (3,) and profile.encoders == TINY.encoders  # the rest: the base's
    assert build_profile(Config()).grid_file is None


def test_the_file_names_its_base_profile(tmp_path):
    profile = build_profile(Config(grid=str(_write(tmp_path, 'profile = "tiny-full"\n'))))
    assert dataclasses.replace(profile, grid_file=None) == TINY_FULL


def test_the_command_line_overrides_the_file(tmp_path):
    path = _write(tmp_path, STUDY + "[protocol]\nlr = 0.01\n")
    profile = build_profile(Config(grid=str(path), seeds="1,2", steps=7, encoders="pixels",
                                   controls="native", profile="tiny-full"))
    assert profile.name == "tiny-full"  # --profile replaces the file's base ...
    assert profile.backbones == ("pi05",) and profile.suites == ("spatial",)  # ... the file stays
    assert profile.seeds == (1, 2) and profile.encoders == ("pixels",)
    assert profile.controls == ("native",)
    assert profile.protocol == TINY_FULL.protocol.replace(lr=0.01, steps=7)
    assert profile.grid_file.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize("text, words", [
    ("seed = [0]\n", ["seed is not a key here", "did you mean 'seeds'", "known: profile"]),
    ("[policy]\nmine = \"me/policy\"\n", ["policy is not a key here", "policies",
                                           "[protocol]"]),
    ("[policies]\nmine = 3\n", ["policies = {'mine': 3}", "NAME = \"REPO_ID_OR_PATH\""]),
    ("[policies]\nMy-Policy = \"me/policy\"\n", ["[policies] My-Policy", "lower-case"]),
    ("[camera_map]\nfront = \"top\"\nwrist = 1\n", ["camera_map", "POLICY_CAMERA"]),
    ('seeds = "0,1"\n', ["seeds = '0,1'", "non-negative integers"]),
    ("seeds = [0, -1]\n", ["seeds", "non-negative integers"]),
    ('encoders = "pixels"\n', ["encoders = 'pixels'", "list of names"]),
    ("steps = 0\n", ["steps = 0 is out of range", "give steps >= 1"]),
    ('controls = ["none"]\n', ["controls", "['none']", "shuffled_image", "[] runs none"]),
    ('profile = "huge"\n', ["profile = 'huge'", "tiny-full"]),
    ("[protocol]\nlrr = 0.1\n", ["[protocol] lrr is not a key here", "did you mean 'lr'",
                                 "batch_size"]),
    # a key of the other place: named, with where it goes
    ("eval_stride = 30\n", ["eval_stride is not a key here", "a [protocol] key: move it"]),
    ("[protocol]\nreleases_per_backbone = 3\n", ["[protocol] releases_per_backbone is not a key",
                                                 "a top-level key: move it"]),
    ('[protocol]\nbatch_size = "16"\n', ["[protocol] batch_size = '16'", "expected an integer"]),
    ("[protocol]\nbatch_size = 16.0\n", ["[protocol] batch_size = 16.0", "expected an integer"]),
    ("[protocol]\nlr = \"fast\"\n", ["[protocol] lr = 'fast'", "expected a number"]),
    ("[protocol]\nlora_targets = \"q_proj\"\n", ["lora_targets", "a list of strings"]),
    ("steps = 5\n[protocol]\nsteps = 6\n", ["steps is given twice"]),
    ("[protocol]\nnative_image_shift = -4\n", ["native_image_shift = -4 is out of range", ">= 0"]),
    ("[protocol]\ngraft_image_shift = -1\n", ["graft_image_shift = -1 is out of range", ">= 0"]),
    ("[protocol]\nnative_state_dropout = 1.5\n", ["native_state_dropout = 1.5", "in [0, 1]"]),
    ("[protocol]\ntiny_image_size = 100\n", ["tiny_image_size = 100 is not a multiple",
                                             "give 96 or 112"]),
    ("seeds = [0\n", ["not valid TOML", "fix the file"]),
])
def test_a_bad_file_is_one_line_naming_the_file_and_the_key(tmp_path, text, words):
    path = _write(tmp_path, text)
    with pytest.raises(pytest.UsageError) as err:
        build_profile(Config(grid=str(path)))
    message = str(err.value)
    assert "\n" not in message and str(path) in message
    for w in words:
        assert w in message, message


def test_a_missing_file_is_one_line(tmp_path):
    with pytest.raises(GridFileError, match=r"^--grid .*nope\.toml: no such file; give the path"):
        read_grid_file(tmp_path / "nope.toml")


def test_pytest_bench_stops_on_a_bad_file_in_one_line(bench_cli, tmp_path):
    out = bench_cli(tmp_path, "--grid", str(_write(tmp_path, "seed = [0]\n")), "--co")
    text = out.stdout + out.stderr
    assert out.returncode == 4 and "study.toml: seed is not a key here" in text
    assert "INTERNALERROR" not in text and "Traceback" not in text


def test_the_offline_switch_reads_the_files_profile(tmp_path):
    spec = importlib.util.spec_from_file_location("graftbench_root_conftest",
                                                  REPO_ROOT / "conftest.py")
    root_conftest = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(root_conftest)
    paper = _write(tmp_path, 'profile = "paper"\n')
    assert root_conftest._profile_from_argv(["pytest", "bench", "--grid", str(paper)]) == "paper"
    assert root_conftest._profile_from_argv(["pytest", f"--grid={paper}", "--profile", "sim"]) \
        == "sim"
    assert root_conftest._profile_from_argv(["pytest", "--grid", str(tmp_path / "no")]) == "tiny"


def test_records_carrying_a_grid_file_are_valid_and_the_report_names_it(tmp_path):
    from bench.results.record import validate_record
    from tests.factories import make_record, save_record
    from bench.report.build import build_report

    grid_file = {"path": "study.toml", "sha256": "ab" * 32, "text": STUDY}
    filed = [make_record(encoder=e, grid_file=grid_file) for e in ("pixels", "blind")]
    for r in filed:
        validate_record(r)
        save_record(tmp_path / "filed", r)
    save_record(tmp_path / "typed", make_record(encoder="pixels"))
    text = build_report(tmp_path / "filed", n_resamples=50, plots=False).read_text()
    assert f"Grid file(s): `study.toml` sha256 `{'ab' * 32}` (2 cells)" in text
    assert "Grid file" not in build_report(tmp_path / "typed", n_resamples=50,
                                           plots=False).read_text()


def _records(results) -> dict[str, dict]:
    return {p.stem: json.loads(p.read_text()) for p in (results / "cells").glob("*.json")}


def test_a_study_file_runs_the_same_cells_and_records_its_hash(bench_cli, tmp_path):
    """End to end: `pytest bench --grid study.toml`, then the same options on the command line
    with no file: the same cells, the same MSE bits; only the first carries the file's hash."""
    study = _write(tmp_path, STUDY)
    from_file = bench_cli(tmp_path / "file", "--grid", str(study))
    assert from_file.returncode == 0, from_file.stdout[-3000:] + from_file.stderr[-3000:]
    by_hand = bench_cli(tmp_path / "cli", "--backbones", "pi05", "--suites", "spatial",
                        "--encoders", "pixels,blind", "--seeds", "0", "--controls", "none",
                        "--steps", "5")
    assert by_hand.returncode == 0, by_hand.stdout[-3000:] + by_hand.stderr[-3000:]
    filed, typed = _records(tmp_path / "file" / "results"), _records(tmp_path / "cli" / "results")
    assert sorted(filed) == sorted(typed) == ["pi05-spatial-blind-seed0", "pi05-spatial-pixels-seed0"]
    sha = hashlib.sha256(study.read_bytes()).hexdigest()
    for cell, record in filed.items():
        assert record["grid_file"] == {"path": str(study), "sha256": sha, "text": STUDY}
        assert "grid_file" not in typed[cell]
        assert record["protocol_hash"] == typed[cell]["protocol_hash"]
        assert record["mse"] == typed[cell]["mse"]
        assert record["per_window"] == typed[cell]["per_window"]
    report = (tmp_path / "file" / "REPORT.md").read_text()
    assert f"`{study}` sha256 `{sha}` (2 cells)" in report
    assert "Grid file(s)" not in (tmp_path / "cli" / "REPORT.md").read_text()


def test_the_committed_sim_recipe_is_the_protocol_of_the_committed_sim_report():
    """studies/sim/closed_loop.toml is the grid file studies/sim/REPORT.md's run used (a copy of
    it): its protocol hash is the one every record of that report carries."""
    profile = build_profile(Config(grid=str(REPO_ROOT / "studies" / "sim" / "closed_loop.toml")))
    summary = json.loads((REPO_ROOT / "studies" / "sim" / "REPORT_summary.json").read_text())
    assert profile.name == "sim" and summary["protocol_hashes"] == [profile.protocol.hash]
    assert profile.control_encoders == ("pixels_p16",)  # the report's LoRA item

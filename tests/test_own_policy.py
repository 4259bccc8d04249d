"""Your own policy and data (`--policy NAME=PATH`, `--dataset NAME=PATH`, bench.resources.user_policies),
end to end on a non-LIBERO world: a LeRobotDataset with another robot's layout (6-D state and
action, cameras front and wrist, 30 fps, the tiny suites' planted visual signal;
bench.suites.custom_world) and a tiny SmolVLA trained natively on it and saved with
save_pretrained into a folder. The known answers, each with a paired window-bootstrap interval
that excludes 0: a graft of raw pixels beats a blind graft on held-out episodes (the images reach
the graft), and the policy's own tower (`native`) beats the pixels graft (its cameras reach the
slots it was trained on: a swapped camera map breaks this one; docs/YOUR_OWN.md).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
from bench.progress import QUIET
import pytest

from bench.analysis.rankings import paired_window_bootstrap
from ondisk.paths import cache_dir
from tests.test_gridfile import Config

WORLD = dict(tasks=4, episodes_per_task=10)
NATIVE_STEPS = 600  # native training of the tiny policy on the world
STEPS = "150"  # projector steps of each graft cell
GRID = ["--encoders", "pixels,blind", "--seeds", "0", "--controls", "native", "--steps", STEPS]


def build_world(folder: Path) -> None:
    """folder/data: the dataset; folder/policy: the natively trained tiny SmolVLA."""
    import torch

    from backbones import smolvla
    from bench.grid.protocol import TINY
    from bench.resources.releases import train_tiny_release, union_stats
    from bench.suites.custom_world import ACTION_DIM, CAMERAS, STATE_DIM, generate_world
    from bench.suites.user import load_user_suite
    from bench.suites.windows import episode_frames, heldout_split

    generate_world(folder / "data", **WORLD)
    suite = load_user_suite("mydata", str(folder / "data"))
    profile = dataclasses.replace(TINY, protocol=TINY.protocol.replace(native_steps=NATIVE_STEPS))
    p = profile.protocol
    train, _ = heldout_split(suite, p.split_seed, p.heldout_episodes_per_task)  # as the grid's
    frames = {suite.name: episode_frames(suite, train)}
    untrained = smolvla.build_tiny_policy(union_stats([suite], frames), CAMERAS,
                                          state_dim=STATE_DIM, action_dim=ACTION_DIM,
                                          chunk_size=10, seed=0)
    with torch.random.fork_rng():
        train_tiny_release("smolvla", untrained, profile, [suite], frames, folder / "policy", 10,
                           progress=QUIET)


@pytest.fixture(scope="module")
def world() -> Path:
    """Built once and cached (keyed by this file's world and native steps)."""
    key = hashlib.sha256(json.dumps([WORLD, NATIVE_STEPS, "1"]).encode()).hexdigest()[:12]
    final = cache_dir() / "test-own-world" / key
    if not (final / "policy" / "graftbench_release.json").is_file():
        tmp = final.with_name(f".tmp-{key}-{os.getpid()}")
        shutil.rmtree(tmp, ignore_errors=True)
        build_world(tmp)
        shutil.rmtree(final, ignore_errors=True)
        os.replace(tmp, final)
    return final


def _records(results: Path) -> dict[str, dict]:
    return {r["encoder"] or r["kind"]: r for r in (json.loads(p.read_text())
                                                   for p in (results / "cells").glob("*.json"))}


def paired_gap(records: dict[str, dict], better: str, worse: str):
    """(worse - better mean normalised MSE, its 95% paired window-bootstrap interval)."""
    per_window = np.array([[records[better]["per_window"]["normalized"]],
                           [records[worse]["per_window"]["normalized"]]])
    result = paired_window_bootstrap(per_window, leader=0, n_resamples=2000)
    return float(result.diff[1]), (float(result.diff_lo[1]), float(result.diff_hi[1]))


def _beats(records: dict[str, dict], better: str, worse: str) -> None:
    gap, (lo, hi) = paired_gap(records, better, worse)
    print(f"{worse} - {better}: {gap:.4f} [{lo:.4f}, {hi:.4f}] ({better} "
          f"{records[better]['mse']['normalized']:.4f}, {worse} {records[worse]['mse']['normalized']:.4f})")
    assert lo > 0, f"{better} not better than {worse}: {worse} - {better} {gap:.4f} [{lo:.4f}, {hi:.4f}]"


def _check_known_answer(out, results: Path, policy: Path) -> dict[str, dict]:
    records = _check_records(out, results, policy)
    _beats(records, "pixels", "blind")
    _beats(records, "native", "pixels")
    return records


def _check_records(out, results: Path, policy: Path) -> dict[str, dict]:
    """The run passed and its records name the policy's weights and the dataset."""
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    records = _records(results)
    assert sorted(r["cell_id"] for r in records.values()) == [
        "mine-mydata-blind-seed0", "mine-mydata-native-seed0", "mine-mydata-pixels-seed0"]
    record = records["pixels"]
    weights = hashlib.sha256((policy / "model.safetensors").read_bytes()).hexdigest()[:16]
    assert record["checkpoint"]["repo_id"] == str(policy.resolve())
    assert record["checkpoint"]["revision"] == f"sha256:{weights}"
    assert record["checkpoint"]["policy_type"] == "smolvla"
    assert record["dataset"]["fps"] == 30
    assert record["dataset"]["cameras"] == ["observation.images.front", "observation.images.wrist"]
    return records


@pytest.mark.slow  # trains grafts on the world's natively trained policy
def test_your_policy_on_your_data_pixels_beat_blind(world, bench_cli, tmp_path):
    out = bench_cli(tmp_path, "--policy", f"mine={world / 'policy'}",
                    "--dataset", f"mydata={world / 'data'}", *GRID)
    records = _check_known_answer(out, tmp_path / "results", world / "policy")
    assert records["pixels"]["camera_map"] == {
        "observation.images.front": "observation.images.front",
        "observation.images.wrist": "observation.images.wrist"}
    assert "cameras of mine x mydata by identical names" in out.stdout


def test_the_same_through_a_grid_file(world, bench_cli, tmp_path):
    """The grid file's policy, dataset and camera map reach the records (5 steps: the known
    answer itself is the command line's test above)."""
    study = tmp_path / "study.toml"
    study.write_text('encoders = ["pixels", "blind"]\nseeds = [0]\ncontrols = ["native"]\n'
                     f'steps = 5\n[policies]\nmine = "{world / "policy"}"\n'
                     f'[datasets]\nmydata = "{world / "data"}"\n'
                     '[camera_map]\nfront = "front"\nwrist = "wrist"\n')
    out = bench_cli(tmp_path, "--grid", str(study))
    records = _check_records(out, tmp_path / "results", world / "policy")
    sha = hashlib.sha256(study.read_bytes()).hexdigest()
    assert {r["grid_file"]["sha256"] for r in records.values()} == {sha}
    assert "by the camera map" in out.stdout


@pytest.mark.slow  # trains grafts on the world's natively trained policy
def test_swapped_cameras_break_the_known_answer(world, bench_cli, tmp_path):
    """What the known answer guards: the wrist view fed into the front slot and back. The
    policy's own tower no longer beats a pixels graft (whose projector learns either order)."""
    out = bench_cli(tmp_path, "--policy", f"mine={world / 'policy'}",
                    "--dataset", f"mydata={world / 'data'}", "--camera-map",
                    "front=wrist,wrist=front", "--encoders", "pixels", *GRID[2:])  # blind sees none
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    with pytest.raises(AssertionError, match="native not better than pixels"):
        _beats(_records(tmp_path / "results"), "native", "pixels")
    assert _records(tmp_path / "results")["native"]["camera_map"] == {
        "observation.images.front": "observation.images.wrist",
        "observation.images.wrist": "observation.images.front"}


# --- one-line errors at collection, before anything trains ------------------------------------

def _copy_meta(world: Path, tmp_path: Path, edit) -> Path:
    """A dataset folder whose meta/ is the world's, edited (the checks read only meta/)."""
    data = tmp_path / "data"
    shutil.copytree(world / "data" / "meta", data / "meta")
    info = json.loads((data / "meta" / "info.json").read_text())
    edit(info, data)
    (data / "meta" / "info.json").write_text(json.dumps(info))
    return data


def _usage_error(**options) -> str:
    from bench.options import build_profile
    from bench.startup import check_user_world

    with pytest.raises(pytest.UsageError) as caught:
        check_user_world(build_profile(Config(**options)))
    message = str(caught.value)
    assert "\n" not in message
    return message


def test_mismatches_are_one_line_errors_naming_both_sides(world, tmp_path):
    policy, data = f"mine={world / 'policy'}", f"mydata={world / 'data'}"
    message = _usage_error(policy=[policy], dataset=[data], camera_map="front=top,wrist=wrist")
    assert "--policy mine (cameras" in message and "--dataset mydata (cameras" in message
    assert "['observation.images.top'] it lacks" in message and "fix: --camera-map" in message

    def seven_d(info, _):
        info["features"]["action"]["shape"] = [7]
    other = _copy_meta(world, tmp_path / "a", seven_d)
    message = _usage_error(policy=[policy], dataset=[f"mydata={other}"])
    assert "takes action 6-D, the dataset has 7-D" in message

    def no_tasks(info, folder):
        info["features"].pop("task_index")
        (folder / "meta" / "tasks.parquet").unlink()
    other = _copy_meta(world, tmp_path / "b", no_tasks)
    assert "no task column" in _usage_error(policy=[policy], dataset=[f"mydata={other}"])

    message = _usage_error(dataset=[data], backbones="smolvla")
    assert "backbone 'smolvla'" in message and "--policy" in message
    assert "NAME=REPO_ID_OR_PATH" in _usage_error(policy=["mine"], dataset=[data])


def test_a_mismatch_stops_pytest_bench_with_exit_4(world, bench_cli, tmp_path):
    out = bench_cli(tmp_path, "--policy", f"mine={world / 'policy'}", "--dataset",
                    f"mydata={world / 'data'}", "--camera-map", "front=top", "--co")
    assert out.returncode == 4, out.stdout[-2000:] + out.stderr[-2000:]
    assert "unmapped" in out.stderr and "--dataset mydata (cameras" in out.stderr
    assert not (tmp_path / "results" / "cells").exists()

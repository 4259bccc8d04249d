"""bench.export and the lerobot_policy_graft plugin: a tiny graft cell of each backbone family,
exported, read back by LeRobot's own loading (strictly), scored by graftbench's own scorer to
the record's MSE, trained two steps by `lerobot-train`, loaded again after the copy."""

from __future__ import annotations

import ast
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from backbones import adapter_module
from backbones.base import only_step
from bench.export import ExportError, export_cell
from bench.grid.cells import CellSpec
from bench.grid.protocol import TINY, with_overrides
from bench.results.store import ResultStore
from bench.loops.evaluate import score
from bench.cell.service import run_cell
from bench.sim.env import libero_available
from ondisk.paths import REPO_ROOT, cache_dir
from tests.factories import make_failed, make_record, save_record
from tests.worlds import lent_workspace

pytest.importorskip("lerobot_policy_graft", reason="install the plugin: scripts/install.sh")

FAMILIES = ("smolvla", "pi05", "pi0")
PROFILE = with_overrides(TINY, steps=4)
ENCODER = "dinov2_s"
PLUGIN = REPO_ROOT / "plugins" / "lerobot_policy_graft" / "lerobot_policy_graft"


@pytest.fixture(scope="module")
def world(tmp_path_factory, one_torch_thread):
    """One float32-feature graft cell per family (and an fp16 twin of smolvla's), exported. The
    lerobot-train interpreter starts first (its imports take longest) and is handed the
    exports when they exist; the tests below run while it trains."""
    root = tmp_path_factory.mktemp("export")
    train = start_lerobot(root, "train", TRAIN_SCRIPT)
    evaluate = start_lerobot(root, "eval", EVAL_SCRIPT) if libero_available() else None
    try:
        out = {}
        for dtype, families in (("float32", FAMILIES), ("fp16", ("smolvla",))):
            results = root / f"results-{dtype}"
            ws = lent_workspace(PROFILE, ResultStore(results), feature_dtype=dtype)
            for family in families:
                record = run_cell(CellSpec("graft", family, "spatial", 0, ENCODER), ws)
                folder = export_cell(results, record.cell_id, root / f"{family}-{dtype}",
                                     lend_from=ws)
                out[(family, dtype)] = (record, folder, results)
        world = {"root": root, "cells": out, "ws": ws, "train": train, "eval": evaluate}
        train.stdin.write(json.dumps(lerobot_train_argvs(world)))
        train.stdin.close()
        if evaluate is not None:
            evaluate.stdin.write(json.dumps([lerobot_eval_argv(world)]))
            evaluate.stdin.close()
        yield world
    finally:
        for process in (train, evaluate):
            if process is not None and process.poll() is None:
                process.kill()
                process.wait()


# One interpreter per LeRobot CLI, started before the cells run (its imports take longest),
# that runs the CLI's own entry point (`main`, which registers the plugins) once per argv list
# read from stdin. LIBERO's config (no prompt) and assets are set up first for lerobot-eval.
TRAIN_SCRIPT = "from lerobot.scripts.lerobot_train import main\n"
EVAL_SCRIPT = ("from bench.sim.env import configure\nconfigure()\n"
               "from lerobot.scripts.lerobot_eval import main\n")
RUN_ARGVS = ("import json, sys\nfor argv in json.loads(sys.stdin.read()):\n"
             "    sys.argv = argv\n    main()\n")


def start_lerobot(root: Path, name: str, script: str) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HF_HUB_OFFLINE": "1"}
    log = open(root / f"lerobot-{name}.log", "w")
    return subprocess.Popen([sys.executable, "-c", script + RUN_ARGVS], stdin=subprocess.PIPE,
                            stdout=log, stderr=subprocess.STDOUT, text=True, env=env,
                            cwd=REPO_ROOT)


def lerobot_eval_argv(world) -> list[str]:
    """One short LIBERO episode of the SmolVLA export (the env's wrist camera is image2)."""
    return ["lerobot-eval", f"--policy.path={world['cells'][('smolvla', 'float32')][1]}",
            "--env.type=libero", "--env.task=libero_spatial", "--env.task_ids=[0]",
            "--env.episode_length=2", "--env.observation_height=64",
            "--env.observation_width=64", "--eval.n_episodes=1", "--eval.batch_size=1",
            "--eval.use_async_envs=false", f"--output_dir={world['root'] / 'eval'}",
            '--rename_map={"observation.images.image2": "observation.images.wrist_image"}']


def lerobot_train_argvs(world) -> list[list[str]]:
    """`lerobot-train --policy.path=EXPORT --dataset.repo_id --dataset.root --steps=2` per family
    (+ where to write, and a small batch without workers for speed)."""
    suite = world["ws"].suite("spatial")
    return [["lerobot-train", f"--policy.path={world['cells'][(family, 'float32')][1]}",
             f"--dataset.repo_id={suite.repo_id}", f"--dataset.root={suite.root}", "--steps=2",
             f"--output_dir={world['root'] / f'train-{family}'}", "--batch_size=2",
             "--num_workers=0"] for family in FAMILIES]


def load_policy(folder: Path):
    """What lerobot-train / lerobot-eval do: the type from config.json, the class by
    LeRobot's convention, the processors from their JSON."""
    from lerobot.configs import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    config = PreTrainedConfig.from_pretrained(folder)
    policy = get_policy_class(config.type).from_pretrained(folder, config=config)
    pre, post = make_pre_post_processors(config, pretrained_path=str(folder))
    return policy, pre, post


def as_backbone(family: str, policy, pre, post):
    """The harness's adapter around a loaded policy (its own graft path: no feed spliced in)."""
    module = adapter_module(family)
    if module.RENAMES_CAMERAS:
        backbone = module.BACKBONE_CLASS(policy, pre, post)
    else:
        rename = dict(only_step(pre, "RenameObservationsProcessorStep").rename_map)
        dataset_key = {v: k for k, v in rename.items()}
        cameras = tuple(dataset_key.get(k, k) for k in policy.config.image_features)
        backbone = module.BACKBONE_CLASS(policy, pre, post, cameras, rename_map=rename)
    backbone.freeze()
    return backbone


def heldout_mse(world, family: str, folder: Path) -> dict:
    ws = world["ws"]
    p = ws.profile.protocol
    backbone = as_backbone(family, *load_policy(folder))
    return score(backbone, ws.suite("spatial"), ws.split("spatial").windows,
                 p.eval_batch_size, p.eval_noise_seed).mse


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_lerobot_loads_the_export_strictly(world, family):
    from safetensors.torch import load_model

    record, folder, _ = world["cells"][(family, "float32")]
    policy, _, _ = load_policy(folder)
    assert type(policy).__name__.startswith("Graft") and policy.config.type == f"graft_{family}"
    missing, unexpected = load_model(policy, folder / "model.safetensors", strict=False)
    assert (missing, unexpected) == (set(), set()) or (not missing and not unexpected)
    saved = set(json.loads((folder / "config.json").read_text()))
    assert {"encoder_timm_name", "graft_grid", "train_scope"} <= saved
    assert policy.config.graft_cell == record.cell_id
    trainable = {n for n, p in policy.named_parameters() if p.requires_grad}
    assert trainable == {"graft.projector.linear.weight", "graft.projector.linear.bias"}


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_loaded_export_scores_the_records_mse_bit_for_bit(world, family):
    record, folder, _ = world["cells"][(family, "float32")]
    assert heldout_mse(world, family, folder) == record.scores.mse


@pytest.mark.slow
def test_loaded_export_of_an_fp16_cell_is_within_the_fp16_tolerance(world):
    record, folder, _ = world["cells"][("smolvla", "fp16")]
    mse = heldout_mse(world, "smolvla", folder)
    for space, value in record.scores.mse.items():
        assert abs(mse[space] - value) <= 2e-4 * abs(value), (space, mse[space], value)


@pytest.mark.slow
@pytest.mark.parametrize("family", ["smolvla", "pi05"])  # LeRobot: strict=False / prints
def test_loading_refuses_a_missing_or_unexpected_key(world, tmp_path, family):
    from safetensors.torch import load_file, save_file

    _, folder, _ = world["cells"][(family, "float32")]
    state = load_file(folder / "model.safetensors")
    for name, changed in (("missing", {k: v for k, v in state.items()
                                       if k != "graft.projector.linear.bias"}),
                          ("unexpected", {**state, "graft.extra": torch.zeros(1)})):
        broken = tmp_path / name
        shutil.copytree(folder, broken)
        save_file(changed, broken / "model.safetensors")
        with pytest.raises(RuntimeError, match="graft.projector.linear.bias|graft.extra"):
            load_policy(broken)


@pytest.mark.slow
def test_a_copied_folder_loads_without_the_original(world, tmp_path):
    record, folder, _ = world["cells"][("smolvla", "float32")]
    original = shutil.copytree(folder, tmp_path / "here")  # lerobot-train reads `folder` now
    copy = shutil.copytree(original, tmp_path / "elsewhere" / "policy")
    shutil.rmtree(original)  # an absolute reference into the original would now fail
    for path in copy.rglob("*.json"):
        text = path.read_text()
        assert str(world["root"]) not in text and str(cache_dir()) not in text, path
    assert heldout_mse(world, "smolvla", copy) == record.scores.mse


@pytest.mark.slow
def test_lerobot_train_trains_each_export_and_its_checkpoint_loads_as_a_graft(world):
    assert world["train"].wait(timeout=300) == 0, \
        (world["root"] / "lerobot-train.log").read_text()[-3000:]
    for family in FAMILIES:
        checkpoint = (world["root"] / f"train-{family}" / "checkpoints" / "000002"
                      / "pretrained_model")
        policy, _, _ = load_policy(checkpoint)
        assert policy.config.type == f"graft_{family}"
        _, folder, _ = world["cells"][(family, "float32")]
        exported, _, _ = load_policy(folder)
        before, after = exported.state_dict(), policy.state_dict()
        assert set(before) == set(after)
        assert not torch.equal(before["graft.projector.linear.weight"],
                               after["graft.projector.linear.weight"])  # it trained
        assert torch.equal(before["graft.encoder.model.patch_embed.proj.weight"],
                           after["graft.encoder.model.patch_embed.proj.weight"])  # frozen


# -- bad input: one line each, nothing written ------------------------------------------------

def _export_fails(results, cell_id, out, match, out_existed=False):
    with pytest.raises(ExportError, match=match) as info:
        export_cell(results, cell_id, out)
    assert "\n" not in str(info.value)
    assert out.exists() == out_existed
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.partial")]


@pytest.mark.slow
def test_bad_input_is_one_line_and_writes_nothing(world, tmp_path):
    record, folder, results = world["cells"][("pi0", "float32")]
    out = tmp_path / "out"
    _export_fails(results, "pi0-spatial-dinov3-seed0", out, "no cell 'pi0-spatial-dinov3-seed0'")
    _export_fails(results, record.cell_id, folder, "already exists", out_existed=True)
    own = tmp_path / "results"
    save_record(own, make_failed(backbone="pi0", encoder="dinov2_s", error="RuntimeError: oom"))
    _export_fails(own, "pi0-spatial-dinov2_s-seed0", out, "failed .*oom.*run it again")
    save_record(own, make_record(backbone="smolvla", encoder="dinov2_s"))
    _export_fails(own, "smolvla-spatial-dinov2_s-seed0", out, "names no projector file")
    corrupt = tmp_path / "corrupt"
    shutil.copytree(results, corrupt)
    projector = corrupt / record.training.projector_file
    projector.write_bytes(projector.read_bytes()[:-1] + b"\0")
    _export_fails(corrupt, record.cell_id, out, "has sha256 .* the record .* says")


def test_plugin_is_light_and_below_the_harness():
    """No import of graftbench's packages anywhere, functions included (it stands alone:
    tests/test_plugin_standalone.py runs it so); no timm / modeling at import time (every
    LeRobot CLI imports the plugin at start)."""
    heavy = ("timm", "lerobot_policy_graft.modeling_graft")
    core = sorted((PLUGIN.parent / "graftcore").glob("*.py"))  # torch alone: no LeRobot at all
    assert core
    for path in sorted(PLUGIN.glob("*.py")) + core:
        tree = ast.parse(path.read_text())
        every = {n.module if isinstance(n, ast.ImportFrom) else a.name
                 for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))
                 for a in getattr(n, "names", [])}
        harness = ("bench", "encoders", "backbones", "ondisk")
        assert not [m for m in every if m and m.split(".")[0] in harness], path
        if path in core:
            assert not [m for m in every if m and m.startswith("lerobot")], path
        if path.name != "modeling_graft.py":
            top = {n.module if isinstance(n, ast.ImportFrom) else a.name
                   for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))
                   for a in getattr(n, "names", [])}
            assert not [m for m in top if m.startswith(heavy)], (path.name, top)


@pytest.mark.slow
def test_best_picks_the_report_winner_and_the_cli_lists_and_refuses(world, capsys, tmp_path):
    from bench.export import best_cell
    from bench.export.__main__ import main

    record, folder, results = world["cells"][("pi05", "float32")]
    best, note = best_cell(results, "pi05", "spatial")
    assert best.cell_id == record.cell_id and "rank 1 of 1" in note
    assert main(["--list", "--results-dir", str(results)]) == 0
    assert record.cell_id in capsys.readouterr().out
    assert main(["--best", "pi05", "spatial", "--results-dir", str(results),
                 "--out", str(folder)]) == 4
    assert capsys.readouterr().err.count("\n") == 1


@pytest.mark.slow
@pytest.mark.skipif(not libero_available(), reason="needs the libero extra")
def test_lerobot_eval_runs_one_short_libero_episode_of_the_export(world):
    assert world["eval"].wait(timeout=400) == 0, \
        (world["root"] / "lerobot-eval.log").read_text()[-3000:]
    log = (world["root"] / "lerobot-eval.log").read_text()
    assert "'n_episodes': 1" in log and "End of eval" in log


# --- the command line without a world: records alone (no projector is read) ---------------

def test_list_names_every_cell_with_why_it_does_not_export(tmp_path, capsys):
    """Before: `--list` printed nothing, exit 0; then only a summary of reasons, no cell named
    (docs/EXPORT.md says each is named). A user encoder's and a known-answer graft, a control
    and a failed cell."""
    from bench.export.__main__ import main

    save_record(tmp_path, make_record(encoder="mypkg.effl:pretrained"))
    save_record(tmp_path, make_record(encoder="pixels"))
    save_record(tmp_path, make_record(encoder="pixels", kind="shuffled_image"))
    save_record(tmp_path, make_failed(encoder="dinov2_s"))
    assert main(["--list", "--results-dir", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines == [
        "smolvla-spatial-mypkg.effl_pretrained-seed0  not exportable: its encoder "
        "'mypkg.effl:pretrained' is your own module's (PKG.MODULE:FACTORY), and the LeRobot "
        "plugin rebuilds encoders from timm by name only; export a graft of a registry or timm: "
        "encoder (docs/EXPORT.md)",
        "smolvla-spatial-pixels-seed0  not exportable: its encoder 'pixels' is a known-answer "
        "function, not a timm architecture: nothing for the plugin to rebuild",
        "smolvla-spatial-pixels-shuffled_image-seed0  not exportable: a shuffled_image cell: "
        "only graft cells export",
        "smolvla-spatial-dinov2_s-seed0  not exportable: it failed (RuntimeError: boom)",
        f"bench.export: nothing to export in {tmp_path}: 4 cell(s), none exportable"], lines


def test_a_user_encoders_graft_is_refused_before_anything_is_written(tmp_path, capsys):
    from bench.export.__main__ import main

    save_record(tmp_path / "results", make_record(encoder="mypkg.effl:pretrained"))
    cell = "smolvla-spatial-mypkg.effl_pretrained-seed0"
    assert main([cell, "--results-dir", str(tmp_path / "results"),
                 "--out", str(tmp_path / "out")]) == 4
    err = capsys.readouterr().err
    assert err.startswith(f"bench.export: cell {cell} cannot be exported: its encoder "
                          "'mypkg.effl:pretrained' is your own module's") and err.count("\n") == 1
    assert not (tmp_path / "out").exists()


def test_best_with_an_unknown_backbone_names_what_is_there(tmp_path, capsys):
    """Before: `--best nope spatial` suggested running `pytest bench -k "nope and spatial"`."""
    from bench.export.__main__ import main

    save_record(tmp_path, make_record(backbone="pi05", encoder="dinov2_s"))
    assert main(["--best", "nope", "spatial", "--results-dir", str(tmp_path), "--out",
                 str(tmp_path / "out")]) == 4
    assert capsys.readouterr().err == (
        f"bench.export: --best nope spatial: no backbone 'nope' in {tmp_path}; backbones there: "
        "pi05\n")
    assert main(["--best", "pi05", "spatail", "--results-dir", str(tmp_path), "--out",
                 str(tmp_path / "out")]) == 4
    assert "no suite 'spatail' in" in capsys.readouterr().err


def test_an_export_folder_is_readable_by_the_group(tmp_path):
    from bench.export.build import share_with_group

    folder = tmp_path / "export"
    (folder / "smolvlm").mkdir(parents=True)
    for path in (folder / "config.json", folder / "smolvlm" / "config.json"):
        path.write_text("{}")
        path.chmod(0o600)
    (folder / "smolvlm").chmod(0o700)
    share_with_group(folder)
    modes = {p.relative_to(folder).as_posix(): p.stat().st_mode & 0o777
             for p in [folder, *folder.rglob("*")]}
    assert modes == {".": 0o755, "smolvlm": 0o755, "config.json": 0o644,
                     "smolvlm/config.json": 0o644}


def test_the_cards_interval_draws_held_out_episodes():
    """Known answer: 4 held-out episodes whose windows sit at 0.5, 0.7, 1.3, 1.5 (8 windows
    each, a little spread within): the card's interval draws the episodes, so it is as wide as
    four values make it; drawn as 32 independent windows it would be about half as wide."""
    from bench.export.card import interval_words, mse_interval

    levels = [0.5, 0.7, 1.3, 1.5]
    episode = [i // 8 for i in range(32)]
    values = [levels[e] + 0.01 * (i % 8 - 3.5) for i, e in enumerate(episode)]
    record = make_record(per_window=values, n_tasks=1, window_episode=episode)
    mean, lo, hi = mse_interval(record, "normalized")
    windows = make_record(per_window=values, n_tasks=1)  # no episode ids: its windows
    _, w_lo, w_hi = mse_interval(windows, "normalized")
    assert mean == pytest.approx(1.0) and lo < mean < hi
    assert hi - lo > 1.6 * (w_hi - w_lo), (lo, hi, w_lo, w_hi)
    assert interval_words(record).startswith("95% bootstrap over its 4 held-out episodes, then "
                                             "their 32 windows")
    assert "carries no episode ids" in interval_words(windows)

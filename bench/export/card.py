"""README.md of an exported graft: what it is, the cell's record (MSE with its interval,
protocol, provenance, the study file if any) and the LeRobot commands that take it further."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bench.results.record import NORMALIZED, RAW, Record

# LeRobot's LIBERO env names the wrist camera image2 (lerobot/envs/libero.py); datasets wrist_image.
LIBERO_ENV_CAMERAS = {"observation.images.image": "observation.images.image",
                      "observation.images.wrist_image": "observation.images.image2"}


def mse_interval(record: Record, space: str) -> tuple[float, float, float]:
    """(mean, lo, hi): the cell's MSE with its 95% interval, the report's bootstrap on one cell
    (its held-out episodes drawn, then their windows)."""
    from bench.analysis.rankings import paired_bootstrap, record_units

    per_window = np.asarray(record.scores.per_window_in(space), dtype=float)
    boot = paired_bootstrap(per_window[None, None, None, :], record_units(record), 0)
    return float(boot.mean[0]), float(boot.mean_lo[0]), float(boot.mean_hi[0])


def interval_words(record: Record) -> str:
    """What the card's interval drew (a record without episode ids: its windows)."""
    from bench.analysis.rankings import record_units

    units = record_units(record)
    if units.source == "none":
        return (f"95% bootstrap over its {record.scores.n_windows} held-out windows (the record "
                "carries no episode ids)")
    return (f"95% bootstrap over its {len(units.episodes)} held-out episodes, then their "
            f"{record.scores.n_windows} windows; one cell: other releases and seeds not drawn")


def rename_flags(rename_map: dict[str, str]) -> tuple[str, str]:
    """(lerobot-train flag, lerobot-eval flag) pairing the data's cameras with the policy's."""
    train = {k: v for k, v in rename_map.items() if k != v}
    env = {LIBERO_ENV_CAMERAS.get(k, k): v for k, v in
           {**{k: k for k in LIBERO_ENV_CAMERAS}, **rename_map}.items()}
    env = {k: v for k, v in env.items() if k != v}
    flag = lambda m: f" --rename_map='{json.dumps(m)}'" if m else ""  # noqa: E731
    return flag(train), flag(env)


def _lines(record: Record, results_dir: Path, note: str | None, flags: tuple[str, str],
           dataset: tuple[str, str], policy_type: str) -> list[str]:
    mse = {space: mse_interval(record, space) for space in (NORMALIZED, RAW)}
    m, run = record.measured, record.run
    train_flag, eval_flag = flags
    repo_id, root = dataset
    lines = [
        f"# {record.encoder} grafted into {record.backbone} ({record.suite})", "",
        f"A graftbench graft exported as a LeRobot policy (type `{policy_type}`): the "
        "released backbone with its vision tower "
        f"replaced by `{record.encoder}` -> pooling to the {m.grid[0]}x"
        f"{m.grid[1]} token grid -> LayerNorm (no affine) -> the trained Linear "
        "projector. Load it with the `lerobot_policy_graft` plugin installed (`pip install "
        "plugins/lerobot_policy_graft` from graftbench's checkout: it needs LeRobot, timm and "
        "safetensors, not graftbench).", "",
        "## Its graftbench record", "",
        f"- cell: `{record.cell_id}` (seed {record.seed}), from `{results_dir}`",
        f"- offline action MSE, normalised: {mse[NORMALIZED][0]:.6g} "
        f"[{mse[NORMALIZED][1]:.6g}, {mse[NORMALIZED][2]:.6g}] ({interval_words(record)})",
        f"- raw units: {mse[RAW][0]:.6g} [{mse[RAW][1]:.6g}, {mse[RAW][2]:.6g}]",
        "- offline action MSE is a pre-commitment diagnostic on held-out demonstrations, not "
        "a closed-loop success rate",
        f"- profile `{m.profile}`, protocol {m.protocol_hash}: "
        f"`{json.dumps(m.protocol, sort_keys=True)}`",
        f"- backbone checkpoint and normaliser: `{json.dumps(m.checkpoint, sort_keys=True)}`",
        f"- features: {m.features_mode} ({m.stored_feature_dtype or 'encoder in the loop'}); "
        f"encoder weights {record.training.encoder_weights}",
        f"- measured with graftbench {run.git_commit} on {run.device}, {run.created}; "
        f"versions {json.dumps(run.versions, sort_keys=True)}",
    ]
    if m.grid_file:
        lines.append(f"- study file: `{json.dumps(m.grid_file, sort_keys=True)}`")
    if note:
        lines.append(f"- chosen as the best: {note}")
    lines += [
        "", "## Take it further", "",
        "Fine-tune (what trains: `--policy.train_scope` = projector | projector+encoder | "
        "projector+policy; LeRobot's own `--peft.*` options are not yet tested with graft "
        "types):", "", "```",
        f"lerobot-train --policy.path=THIS_FOLDER --dataset.repo_id={repo_id} "
        f"--dataset.root={root} --policy.train_scope=projector{train_flag} "
        "--output_dir=outputs/graft --steps=2000", "```", "",
        "Evaluate in LIBERO (needs LeRobot's libero extra):", "", "```",
        f"lerobot-eval --policy.path=THIS_FOLDER --env.type=libero "
        f"--env.task=libero_{record.suite} --eval.n_episodes=10 --eval.batch_size=1{eval_flag}",
        "```", "",
    ]
    return lines


def write_card(folder: Path, record: Record, results_dir: Path, note: str | None,
               policy_type: str, rename_map: dict[str, str] | None = None,
               dataset: tuple[str, str] = ("DATASET_REPO_ID", "DATASET_ROOT")) -> Path:
    """README.md in `folder`."""
    path = folder / "README.md"
    flags = rename_flags(rename_map or {})
    path.write_text("\n".join(_lines(record, results_dir, note, flags, dataset, policy_type)))
    return path

"""The five parts of a cell record (bench.results.record): what the cell is, what it was
measured under, its scores, what trained, where and when. Each field's name is its key in the
stored JSON: these classes and bench.results.record are the only places a record key is spelled.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

NORMALIZED, RAW = "normalized", "raw"  # the two action spaces every score is given in
SPACES = (NORMALIZED, RAW)
# Written only when set (absent from records that have none; every other field is always written).
_OMITTED_WHEN_NONE = {"feature_dtype", "feature_transform", "grid_file", "camera_map", "dataset",
                      "feature_runtime",
                      "rollouts", "projector_file", "projector_sha256", "train_steps",
                      "chunk_length", "n_action_steps", "per_window_executed", "window_critical",
                      "critical_rule", "window_episode"}


def flat(part) -> dict:
    """A part's fields by JSON name (optional ones left out when unset)."""
    return {f.name: getattr(part, f.name) for f in fields(part)
            if not (f.name in _OMITTED_WHEN_NONE and getattr(part, f.name) is None)}


@dataclass(frozen=True)
class Identity:
    """What a cell is: the first fields of both record forms."""

    cell_id: str
    kind: str
    backbone: str
    suite: str
    encoder: str | None
    seed: int
    variant: str | None = None
    reference: str | None = None  # the cell id a control is compared against
    # Which independently trained release of the backbone (0 in records made before releases
    # were a factor: they had one).
    release: int = 0

    @classmethod
    def of(cls, cell) -> Identity:
        """A bench.grid.cells.CellSpec's identity."""
        ref = cell.reference
        return cls(cell.id, cell.kind, cell.backbone, cell.suite, cell.encoder, cell.seed,
                   cell.variant, ref.id if ref else None, cell.release)

    @property
    def group(self) -> str:
        """The backbone x suite x (release x) seed a ranking is made in: smolvla-spatial-seed0,
        smolvla-spatial-rel1-seed0."""
        rel = f"-rel{self.release}" if self.release else ""
        return f"{self.backbone}-{self.suite}{rel}-seed{self.seed}"


@dataclass(frozen=True)
class MeasuredUnder:
    """What a record was measured under: the protocol, the weights and normaliser, features."""

    profile: str | None = None
    protocol: dict | None = None
    protocol_hash: str | None = None
    checkpoint: dict | None = None  # repo_id, revision, normalizer, normalizer_fingerprint
    grid: list | None = None  # the pooled token grid (rows, cols)
    features_mode: str | None = None  # "cache" | "loop" | None (no encoder)
    feature_dtype: str | None = None  # how cached features were stored (absent: float32)
    # What extracted the stored features (bench.resources.extraction): "torch" or an onnxruntime tag
    # such as "onnxruntime==1.31.1/opset17"; absent: no store read, or a record from before it.
    feature_runtime: str | None = None
    feature_transform: str | None = None  # a planted degradation: never resumed, never a baseline
    grid_file: dict | None = None
    camera_map: dict | None = None  # a --policy's camera pairing
    dataset: dict | None = None  # a --dataset's identity

    @property
    def revision(self) -> str | None:
        return checkpoint_revision(self.checkpoint)

    @property
    def normalizer_fingerprint(self) -> str | None:
        return (self.checkpoint or {}).get("normalizer_fingerprint")

    @property
    def stored_feature_dtype(self) -> str | None:
        """The dtype the features were read at; None when no feature cache was read."""
        if self.features_mode != "cache":
            return None
        return self.feature_dtype or "float32"  # records from before the option: float32


@dataclass(frozen=True)
class Scores:
    """Offline action MSE (bench.loops.evaluate): per window, per task, per horizon step, in both
    action spaces. per_window[space]: (n_windows,) aligned with window_ids."""

    mse: dict[str, float]
    per_window: dict[str, list[float]]
    window_ids: list[int]
    n_windows: int
    window_task: list[int] | None = None
    # (n_windows,) the held-out episode (the suite's episode index) each window comes from: the
    # unit the intervals draw (bench.analysis.hierarchy); None in records made before it.
    window_episode: list[int] | None = None
    tasks: list[str] | None = None
    per_task: dict[str, dict] | None = None  # task -> {space: mse, "n": windows}
    per_horizon: dict[str, list[float]] | None = None  # space -> (chunk,) per step
    # What the offline measures of bench.analysis.offline_measures read; None in records from
    # before them (those measures are then "not measured"). chunk_length: steps per predicted
    # chunk; n_action_steps: the steps of each chunk the policy executes before it replans.
    chunk_length: int | None = None
    n_action_steps: int | None = None
    # space -> (n_windows,) MSE over each window's first n_action_steps real steps; written only
    # when n_action_steps < chunk_length (otherwise it is per_window, bit for bit).
    per_window_executed: dict[str, list[float]] | None = None
    # (n_windows,) whether the window's scored span nears a gripper open/close event, and the
    # rule's parameters (bench.suites.critical), so records made under another rule never mix.
    window_critical: list[bool] | None = None
    critical_rule: dict | None = None

    def mse_in(self, space: str = NORMALIZED) -> float:
        return float(self.mse[space])

    def per_window_in(self, space: str = NORMALIZED) -> list[float]:
        return self.per_window[space]

    def per_horizon_in(self, space: str = NORMALIZED) -> list[float] | None:
        return (self.per_horizon or {}).get(space)

    def to_json(self) -> dict:
        return flat(self)


def task_score(mse: dict[str, float], n: int) -> dict:
    """One task's entry of `Scores.per_task`: its MSE per space over its `n` windows."""
    return {**mse, "n": n}


def checkpoint_revision(checkpoint: dict | None) -> str | None:
    """The weights' revision in a checkpoint dict (bench.resources.releases.checkpoint_id's)."""
    return (checkpoint or {}).get("revision")


def checkpoint_of(checkpoint: dict, normalizer: str, normalizer_fingerprint: str) -> dict:
    """`MeasuredUnder.checkpoint`: the policy's {repo_id, revision} (bench.resources.releases) and the
    normaliser's source and fingerprint."""
    return {**checkpoint, "normalizer": normalizer, "normalizer_fingerprint": normalizer_fingerprint}


@dataclass(frozen=True)
class Training:
    """What trained: parameter counts, the loss curve, the probe loss before and after."""

    trainable_params: int = 0
    projector_params: int = 0
    lora_params: int = 0
    projector_from: str | None = None  # the graft cell whose trained projector this cell took
    loss_curve: list = field(default_factory=list)  # [[step, loss], ...]
    probe_loss: dict | None = None  # {"before": float, "after": float}
    encoder_weights: str | None = None
    # The side (px) the encoder's input was resized to: its own (a pretrained encoder's, e.g.
    # 224), not the profile's; None: no encoder, or a record from before this field.
    encoder_input_size: int | None = None
    # The trained projector, kept for bench.export (bench.cell.projectors): its file relative to
    # the results dir and the file's sha256.
    projector_file: str | None = None
    projector_sha256: str | None = None
    # The optimiser steps the projector took (a short graft: a fraction of the protocol's steps);
    # None: trained nothing, or a record from before this field.
    train_steps: int | None = None

    @property
    def probe_before_after(self) -> tuple[float, float] | None:
        if not self.probe_loss:
            return None
        return float(self.probe_loss["before"]), float(self.probe_loss["after"])


@dataclass(frozen=True)
class RunInfo:
    """Where and when: timings (s), memory, device, versions, commit, closed-loop rollouts."""

    timings_s: dict = field(default_factory=dict)
    peak_memory_mb: Any = None
    device: str | None = None
    hardware: str | None = None
    versions: dict = field(default_factory=dict)
    git_commit: str | None = None
    created: str | None = None
    rollouts: dict | None = None

    @property
    def total_s(self) -> float | None:
        return self.timings_s.get("total")

    @property
    def rollout_action_steps(self) -> int | None:
        """Chunk steps the stored rollouts executed before replanning; None: no rollouts."""
        return ((self.rollouts or {}).get("spec") or {}).get("n_action_steps")

    def has_rollouts(self, episodes_per_task: int) -> bool:
        """Whether closed-loop episodes of this size (or the kind's skip line) are stored."""
        rollouts = self.rollouts or {}
        if "skipped" in rollouts:
            return True
        return (rollouts.get("spec") or {}).get("episodes_per_task") == episodes_per_task

"""Session-wide resources shared by all cells: loaded backbones, suites, splits, encoders,
pooled-feature caches. Built lazily, once per pytest session (or per worker under xdist)."""

from __future__ import annotations

import copy
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from backbones import get_entry
from bench.resources.releases import (
    Normalizer, checkpoint_id, load_released, normalizer_for, user_normalizer,
)
from bench.resources.features import FeatureStore
from ondisk.paths import cache_dir
from bench.progress import ProgressSink, say
from bench.grid.protocol import Profile
from bench.results.store import ResultStore
from bench.sim.batching import IN_PROCESS, Batching
from bench.suites import load_suite
from bench.suites.user import load_user_suite
from bench.resources.user_policies import load_user_policy
from bench.suites.windows import episode_frames, eval_windows, heldout_split
from encoders import build_encoder

TINY_CHUNK = 10  # tiny policies predict 10-step chunks (episodes are ~20-30 frames)


@dataclass
class Split:
    train_episodes: list[int]
    heldout_episodes: list[int]
    train_frames: torch.Tensor  # (N_train,) global frame indices
    windows: torch.Tensor  # (N_windows,) global frame indices of held-out windows


@dataclass(frozen=True)
class Lent:
    """What the workspace lends one cell, asked for once at its start (`Workspace.lend`): its
    suite and held-out split, the released policy, its checkpoint and normaliser."""

    suite: object  # bench.suites.Suite
    split: Split
    backbone: object  # the policy adapter (backbones.base.Backbone), frozen
    checkpoint: dict  # {repo_id, revision}
    normalizer: Normalizer
    user_policy: bool  # a --policy of the user's own (not the registry's)


@dataclass
class Workspace:
    profile: Profile
    store: ResultStore
    # Where every long step reports (bench.progress): required, so no step takes a default
    # sink that pytest captures.
    progress: ProgressSink
    # Closed-loop episodes per task for every cell (0: offline MSE only). LIBERO-backed suites.
    rollouts: int = 0
    # How they are run (bench.sim.rollout.Batching): envs per task at once, gym sync or async
    # vector env. Not part of what a cell measures: the same episodes whatever the batch.
    rollout_batching: Batching = IN_PROCESS
    cache: Path = field(default_factory=cache_dir)
    _suites: dict = field(default_factory=dict)
    _splits: dict = field(default_factory=dict)
    _released: dict = field(default_factory=dict)  # (name, release) -> policy adapter
    _checkpoints: dict = field(default_factory=dict)  # (name, release) -> checkpoint_id
    _backbones: dict = field(default_factory=dict)  # (name, normaliser fingerprint) -> adapter
    _normalizers: dict = field(default_factory=dict)
    _encoders: dict = field(default_factory=dict)
    # How stored features are kept on disk: "fp16" (default: closest to float32 of the half
    # dtypes, docs/PERFORMANCE.md), "bf16" (for encoders beyond fp16's range: the build says
    # so), or "float32" (the encoder's numbers bit for bit, 2x the disk).
    feature_dtype: str = "fp16"
    _features: FeatureStore | None = None  # opened lazily; keeps each stored file open
    # What one cell is measured with (a graft's trained projector to take, a planted feature
    # transform) is not kept here: bench.cell.plan's CellContext carries it.
    _session_dir: tempfile.TemporaryDirectory | None = None

    def session_dir(self) -> Path:
        """A private folder that lives as long as this workspace (removed at exit)."""
        if self._session_dir is None:
            self._session_dir = tempfile.TemporaryDirectory(prefix="graftbench-session-")
        return Path(self._session_dir.name)

    def suite(self, name: str):
        if (not self._suites and self.profile.data_source == "tiny"
                and name in self.released_suites() and name not in dict(self.profile.datasets)):
            self._prepare_tiny_suites()
        if name not in self._suites:
            why = ""
            if name not in self.profile.suites and self.profile.data_source == "tiny":
                why = ("; not selected, but the tiny release trains on both tiny suites, so "
                       "its numbers do not depend on the selection")
            say(self.progress, f"suite {name} ({self.profile.data_source}): loading "
                               f"(generated on first use, then cached{why})")
            start = time.monotonic()
            datasets = dict(self.profile.datasets)
            suite = (load_user_suite(name, datasets[name]) if name in datasets
                     else load_suite(name, self.profile.data_source,
                                     sim_spec=self._demos(name), progress=self.progress))
            say(self.progress, f"suite {name}: {len(suite.state)} frames, "
                               f"{len(set(suite.episode_index.tolist()))} episodes "
                               f"({time.monotonic() - start:.0f} s)")
            self._suites[name] = suite
        return self._suites[name]

    def _prepare_tiny_suites(self) -> None:
        """The tiny suites a release trains on, generated where missing before any is loaded:
        each xdist worker begins with another one, so that two workers generate both at once."""
        from bench.suites.synthetic import prepare_tiny_suites

        worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")  # xdist names its workers gwN
        first = int(worker[2:]) if worker[2:].isdigit() else 0
        prepare_tiny_suites(list(self.released_suites()), first, progress=self.progress)

    def _demos(self, name: str):
        """The sim suite's DemoSpec when --sim-tasks / --sim-demos change it, else None."""
        p = self.profile
        if p.data_source != "sim" or not (p.sim_tasks or p.sim_demos or p.sim_demo_noise
                                           or p.sim_demo_speed != 1.0):
            return None
        from bench.sim.demos import demo_spec

        return demo_spec(name, p.sim_tasks, p.sim_demos, p.sim_demo_noise, p.sim_demo_speed)

    def split(self, name: str) -> Split:
        if name not in self._splits:
            suite = self.suite(name)
            p = self.profile.protocol
            train_eps, heldout_eps = heldout_split(suite, p.split_seed, p.heldout_episodes_per_task)
            self._splits[name] = Split(
                train_eps, heldout_eps,
                episode_frames(suite, train_eps),
                eval_windows(suite, heldout_eps, p.eval_stride),
            )
        return self._splits[name]

    def normalizer(self, name: str, suite: str | None, release: int = 0) -> Normalizer:
        """Which stats backbone `name` (its release `release`) normalises `suite` with (no policy
        is loaded for this)."""
        if self.is_user_policy(name):  # its own saved stats, whatever the suite
            if (name, None) not in self._normalizers:
                self._normalizers[(name, None)] = user_normalizer(self.profile, name)
            return self._normalizers[(name, None)]
        per_suite = self.profile.source == "hub" and get_entry(name).stats == "dataset"
        if per_suite and suite is None:
            raise ValueError(f"backbone {name!r} normalises per suite: name the suite")
        names = (suite,) if per_suite else self.released_suites()
        key = (name, names, release)
        if key not in self._normalizers:
            suites = [self.suite(s) for s in names]
            train = {s.name: self.split(s.name).train_frames for s in suites}
            self._normalizers[key] = normalizer_for(name, self.profile, suites, train, release)
        return self._normalizers[key]

    def backbone(self, name: str, suite: str | None = None, release: int = 0):
        """The released policy (frozen, eval; its release `release`), normalising `suite` as
        `normalizer` says. The policy is loaded once per backbone and release; per-suite dataset
        stats only swap its processors."""
        norm = self.normalizer(name, suite, release)
        if self.is_user_policy(name):  # loaded per suite: the camera rule pairs per dataset
            return self._user_backbone(name, suite, norm)
        if (name, release) not in self._released:
            suites = [self.suite(s) for s in self.released_suites()]
            train = {s.name: self.split(s.name).train_frames for s in suites}
            chunk = TINY_CHUNK if self.profile.source == "tiny" else None
            kwargs = {"chunk_size": chunk} if chunk else {}
            bb, self._checkpoints[(name, release)] = load_released(
                name, self.profile, suites, train, self.cache, progress=self.progress,
                stats=norm.stats, release=release, **kwargs)
            bb.freeze()
            self._released[(name, release)] = bb
        key = (name, norm.fingerprint, release)
        if key not in self._backbones:
            bb = self._released[(name, release)]
            if bb.normalizer_fingerprint() != norm.fingerprint and norm.stats is not None:
                bb = bb.with_stats(norm.stats)
            if bb.normalizer_fingerprint() != norm.fingerprint:
                raise RuntimeError(
                    f"{name}: the loaded normaliser ({bb.normalizer_fingerprint()}) is not the "
                    f"expected {norm.source} one ({norm.fingerprint})"
                )
            self._backbones[key] = bb
        return self._backbones[key]

    def lend(self, name: str, suite: str, release: int = 0, *, fresh: bool = False) -> Lent:
        """What a cell of policy `name` (its release `release`) on `suite` reads, loaded in one
        pass: the suite, its split, the policy (`fresh`: a private copy, `fresh_backbone`), its
        checkpoint and normaliser."""
        loaded, split = self.suite(suite), self.split(suite)
        backbone = (self.fresh_backbone(name, suite, release) if fresh
                    else self.backbone(name, suite, release))
        return Lent(loaded, split, backbone, self.checkpoint(name, suite, release),
                    self.normalizer(name, suite, release), self.is_user_policy(name))

    def checkpoint(self, name: str, suite: str | None = None, release: int = 0) -> dict:
        """{repo_id, revision} of the policy `name` (release `release`) is measured on (loading
        it when needed: a tiny release's revision is its weights' hash)."""
        if self.is_user_policy(name):
            return checkpoint_id(name, self.profile)
        if (name, release) not in self._checkpoints:
            self.backbone(name, suite, release)
        return self._checkpoints[(name, release)]

    def is_user_policy(self, name: str) -> bool:
        return name in dict(self.profile.policies)

    def _user_backbone(self, name: str, suite: str, norm: Normalizer):
        """A `--policy` checkpoint on `suite`, through its adapter's load_policy (own stats)."""
        key = (name, suite, norm.fingerprint)
        if key not in self._backbones:
            say(self.progress, f"policy {name}: loading {dict(self.profile.policies)[name]}")
            bb = load_user_policy(self.profile, name, self.suite(suite))
            bb.freeze()
            if bb.normalizer_fingerprint() != norm.fingerprint:
                raise RuntimeError(f"{name}: the loaded normaliser ({bb.normalizer_fingerprint()}) "
                                   f"is not its saved one ({norm.fingerprint})")
            self._backbones[key] = bb
        return self._backbones[key]

    def fresh_backbone(self, name: str, suite: str | None = None, release: int = 0):
        """A private copy (the LoRA control modifies the LM in place)."""
        return copy.deepcopy(self.backbone(name, suite, release))

    def released_suites(self) -> tuple[str, ...]:
        # The tiny release is trained on both tiny suites whatever -k selects, so its cache key
        # (and every number measured on it) does not depend on the selection.
        # Hub: which suites does not matter (stats are per suite or the checkpoint's own).
        from bench.suites.synthetic import SUITE_PARAMS

        return tuple(SUITE_PARAMS) if self.profile.data_source == "tiny" else self.profile.suites[:1]

    def encoder(self, name: str):
        if name not in self._encoders:
            encoder = build_encoder(name, self.profile.source)
            if self.profile.source == "hub" and torch.cuda.is_available():
                encoder = encoder.to("cuda")
            self._encoders[name] = encoder
        return self._encoders[name]

    def features(self, encoder_name: str, suite_name: str, grid: tuple[int, int],
                 transform=None) -> dict:
        """{camera: view} of the stored features: `view[frames]` -> (B, rows*cols, C) float32 on
        the CPU, read from disk and pooled to `grid` per batch; `view.shape` is (N, rows*cols, C).
        The file is built on first use (resumable) and opened once per session. `transform`:
        a planted degradation applied to every batch read (bench.cell.plan.CellContext)."""
        return self.feature_store().pooled_features(
            self.encoder(encoder_name), self.suite(suite_name), grid,
            transform=transform)

    def feature_store(self) -> FeatureStore:
        """The session's feature store (opened lazily, in `feature_dtype`): sources other than a
        suite (the robustness tier's perturbed windows) are stored through it too."""
        if self._features is None or self._features.dtype != self.feature_dtype:
            self._features = FeatureStore(self.cache / "features", dtype=self.feature_dtype,
                                          progress=self.progress)
        return self._features

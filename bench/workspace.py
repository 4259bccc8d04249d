"""Session-wide resources shared by all cells: loaded backbones, suites, splits, encoders,
pooled-feature caches. Built lazily, once per pytest session (or per worker under xdist)."""

from __future__ import annotations

import copy
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import torch

from backbones.released import load_released
from bench.features import FeatureCache
from bench.paths import cache_dir
from bench.protocol import Profile
from bench.store import ResultStore
from bench.suites import load_suite
from bench.suites.windows import episode_frames, eval_windows, heldout_split
from encoders import build_encoder

TINY_CHUNK = 10  # tiny policies predict 10-step chunks (episodes are ~20-30 frames)


@dataclass
class Split:
    train_episodes: list[int]
    heldout_episodes: list[int]
    train_frames: torch.Tensor  # (N_train,) global frame indices
    windows: torch.Tensor  # (N_windows,) global frame indices of held-out windows


@dataclass
class Workspace:
    profile: Profile
    store: ResultStore
    progress: bool = True
    # Closed-loop episodes per task for every cell (0: offline MSE only). LIBERO-backed suites.
    rollouts: int = 0
    cache: Path = field(default_factory=cache_dir)
    _suites: dict = field(default_factory=dict)
    _splits: dict = field(default_factory=dict)
    _backbones: dict = field(default_factory=dict)
    _encoders: dict = field(default_factory=dict)
    _features: FeatureCache | None = None
    # graft cell id -> runner.TrainedProjector: its shuffled/zero-at-eval controls reuse it.
    trained_projectors: dict = field(default_factory=dict)
    _session_dir: tempfile.TemporaryDirectory | None = None
    # Test-only hook: name -> function(features dict) -> features dict (planted regressions).
    feature_transforms: dict = field(default_factory=dict)

    def session_dir(self) -> Path:
        """A private folder that lives as long as this workspace (removed at exit)."""
        if self._session_dir is None:
            self._session_dir = tempfile.TemporaryDirectory(prefix="graftbench-session-")
        return Path(self._session_dir.name)

    def suite(self, name: str):
        if name not in self._suites:
            self._suites[name] = load_suite(name, self.profile.data_source)
        return self._suites[name]

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

    def backbone(self, name: str):
        """The released policy (frozen, eval). Tiny: trained on every tiny suite of the profile."""
        if name not in self._backbones:
            suites = [self.suite(s) for s in self.released_suites()]
            train = {s.name: self.split(s.name).train_frames for s in suites}
            chunk = TINY_CHUNK if self.profile.source == "tiny" else None
            kwargs = {"chunk_size": chunk} if chunk else {}
            bb = load_released(name, self.profile, suites, train, self.cache,
                               progress=self.progress, **kwargs)
            bb.freeze()
            self._backbones[name] = bb
        return self._backbones[name]

    def fresh_backbone(self, name: str):
        """A private copy (the LoRA control modifies the LM in place)."""
        return copy.deepcopy(self.backbone(name))

    def released_suites(self) -> tuple[str, ...]:
        # The tiny release is trained on both tiny suites whatever -k selects, so its cache key
        # (and every number measured on it) does not depend on the selection.
        return ("spatial", "object") if self.profile.data_source == "tiny" else self.profile.suites

    def encoder(self, name: str):
        if name not in self._encoders:
            encoder = build_encoder(name, self.profile.source)
            if self.profile.source == "hub" and torch.cuda.is_available():
                encoder = encoder.to("cuda")
            self._encoders[name] = encoder
        return self._encoders[name]

    def features(self, encoder_name: str, suite_name: str, grid: tuple[int, int]) -> dict:
        if self._features is None:
            self._features = FeatureCache(self.cache / "features")
        feats = self._features.pooled_features(
            self.encoder(encoder_name), self.suite(suite_name), grid, progress=self.progress
        )
        transform = self.feature_transforms.get(encoder_name)
        return transform(feats) if transform else feats

"""Released checkpoints: the real ones from the HF cache, or tiny ones trained here natively.

A random-init tiny VLA has no meaningful native tower, so the offline world trains each tiny
policy natively (all of it, its own tower included) on the training episodes of the tiny suites,
saves it with save_pretrained and from then on loads it through the same from_pretrained path as
a real checkpoint. Deterministic, keyed by (config, data fingerprints, protocol), rebuilt only
when missing; the default recipe's releases are shipped (bench.resources.shipped) and copied in
instead of trained. The key does not hold the CPU's kernels or the thread count, which change
the weights (studies/sim/REBUILD.md): a committed study pins its release
(bench.grid.pinned_release).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import torch

from backbones import adapter_module, get_entry
from backbones.base import BackboneUnavailable, stats_fingerprint
from backbones.hub import saved_normalizer_stats
from backbones.tiny_sizes import build_args, size_of
from ondisk.filelock import exclusive
from ondisk.hubcache import download_command, folder_revision, resolved_revision
from bench.progress import ProgressSink, say
from bench.grid.pinned_release import check_pinned
from bench.grid.protocol import Profile, Protocol
from bench.results.provenance import stable_seed
from bench.loops.augment import shift_images
from ondisk.libero_format import STATE_KEY
from bench.loops.train import FitConfig, fit
from bench.resources.shipped import install_shipped, shipped_release
from bench.resources.user_policies import policy_facts, user_checkpoint_id

RELEASE_VERSION = "1"


def union_stats(suites, train_frames: dict[str, torch.Tensor]) -> dict:
    """LeRobot-style stats for state and action over the training frames of all suites, plus
    per-channel image stats (both policies keep images un-normalised, but the keys must exist)."""
    stats: dict = {}
    for key, attr in (("observation.state", "state"), ("action", "action")):
        values = torch.cat([getattr(s, attr)[train_frames[s.name]] for s in suites]).double()
        stats[key] = {
            "mean": values.mean(0), "std": values.std(0).clamp(min=1e-6),
            "min": values.min(0).values, "max": values.max(0).values,
            "q01": torch.quantile(values, 0.01, dim=0), "q99": torch.quantile(values, 0.99, dim=0),
        }
        stats[key] = {k: v.float() for k, v in stats[key].items()}
    for cam in suites[0].camera_keys:
        stats[cam] = {
            "mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25),
            "min": torch.zeros((3, 1, 1)), "max": torch.ones((3, 1, 1)),
            "q01": torch.zeros((3, 1, 1)), "q99": torch.ones((3, 1, 1)),
        }
    return stats


def architecture_fingerprint(backbone) -> str:
    """Parameter names and shapes of an (untrained) build: changes with any tiny-size change."""
    shapes = sorted((n, tuple(p.shape)) for n, p in backbone.policy.state_dict().items())
    return hashlib.sha256(repr(shapes).encode()).hexdigest()[:12]


def release_key(name: str, profile: Profile, suites, chunk_size: int, arch: str,
                release: int = 0) -> str:
    """The cache key of tiny `name`'s release `release`: its recipe, data, architecture
    fingerprint and, for a size of the tiny ladder, its rung (two sizes never share a key)."""
    p = profile.protocol
    size = size_of(name)
    blob = json.dumps({
        "v": RELEASE_VERSION, "backbone": name, "chunk": chunk_size, "arch": arch,
        "suites": sorted(s.fingerprint for s in suites),
        "native_steps": p.native_steps, "native_lr": p.native_lr, "batch": p.batch_size,
        "state_dropout": [p.native_state_dropout, p.native_state_dropout_warmup],
        "split_seed": p.split_seed, "heldout": p.heldout_episodes_per_task,
        # Only when set: the releases trained before the field existed keep their keys.
        **({"image_shift": p.native_image_shift} if p.native_image_shift else {}),
        **({"release": release} if release else {}),
        # Only for a ladder size beside its family's base build: the base keeps its key.
        **({"size": size.rung} if size is not None and not size.base else {}),
    }, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def tiny_release_dir(cache: Path, name: str, key: str) -> Path:
    return cache / "released" / f"{name}-{key}"


def drop_states(states: torch.Tensor, rate: float, mean: torch.Tensor,
                generator: torch.Generator) -> torch.Tensor:
    """(B, S) states with each row replaced by `mean` with probability `rate`."""
    if rate <= 0:
        return states
    drop = torch.rand(states.shape[0], generator=generator) < rate
    return torch.where(drop[:, None], mean.to(states.dtype), states)


def release_seed(name: str, stream: str, release: int) -> int:
    """The seed of one random stream of `name`'s native training: release 0 keeps the streams
    it had before releases were a factor (its weights unchanged), release r > 0 its own."""
    return stable_seed(stream, name) if release == 0 else stable_seed(stream, name, release)


def train_tiny_release(name: str, backbone, profile: Profile, suites, train_frames, folder: Path,
                       chunk_size: int, progress: ProgressSink, release: int = 0) -> None:
    """Train ALL of the untrained tiny `backbone` with its own loss, save it into `folder`.
    Release r draws its batches, dropout and shifts from seed r (its init: the caller's)."""
    from bench.suites.windows import raw_batch

    module = adapter_module(name)
    policy = backbone.policy
    policy.train()
    for p in policy.parameters():
        p.requires_grad_(True)
    # Alternate suites frame by frame: one frame list, tagged by suite.
    tagged = torch.cat([
        torch.stack([torch.full_like(train_frames[s.name], i), train_frames[s.name]], dim=1)
        for i, s in enumerate(suites)
    ])

    p = profile.protocol
    state_mean = torch.cat([s.state[train_frames[s.name]] for s in suites]).mean(0)
    dropout = torch.Generator().manual_seed(release_seed(name, "native-state-dropout", release))
    shifts = torch.Generator().manual_seed(release_seed(name, "native-image-shift", release))
    calls = [0]

    def next_batch(rows):
        raws = [raw_batch(suites[i], rows[rows[:, 0] == i][:, 1], chunk_size, with_images=True)
                for i in range(len(suites)) if (rows[:, 0] == i).any()]
        merged = {}
        for key in raws[0]:
            vals = [r[key] for r in raws]
            merged[key] = sum(vals, []) if isinstance(vals[0], list) else torch.cat(vals)
        calls[0] += 1  # one call per optimiser step (the probe never runs here)
        rate = 1.0 if calls[0] <= p.native_state_dropout_warmup else p.native_state_dropout
        merged[STATE_KEY] = drop_states(merged[STATE_KEY], rate, state_mean, dropout)
        for cam in suites[0].camera_keys:
            merged[cam] = shift_images(merged[cam], p.native_image_shift, shifts)
        return merged, None

    cfg = FitConfig(steps=p.native_steps, batch_size=p.batch_size, lr=p.native_lr,
                    weight_decay=0.0, warmup_steps=max(1, p.native_steps // 20), grad_clip=1.0,
                    log_every=max(1, p.native_steps // 20))
    curve = fit(backbone, list(policy.parameters()), tagged, next_batch, cfg, seed=release,
                label=f"native training of tiny {name}" + (f" release {release}" if release else ""),
                progress=progress)
    policy.eval()
    tmp = folder.with_name(folder.name + f".tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    module.save_pretrained(backbone, tmp)
    (tmp / "graftbench_release.json").write_text(json.dumps({
        "backbone": name, "loss_curve": curve, "suites": [s.name for s in suites],
        "fingerprints": [s.fingerprint for s in suites], "native_steps": p.native_steps,
        **({"release": release} if release else {}),
    }, indent=1))
    if folder.exists():
        shutil.rmtree(folder)
    os.replace(tmp, folder)


@dataclass(frozen=True)
class Normalizer:
    """Which stats a backbone x suite normalises with, known before the policy is loaded (a
    resume compares `fingerprint` with the record's: one report never mixes normalisers)."""

    source: str  # "dataset:<suite>" (its training episodes) or "checkpoint" (the release's own)
    stats: dict | None  # the dataset stats to load with; None: the checkpoint's saved stats
    fingerprint: str


def normalizer_for(name: str, profile: Profile, suites, train_frames,
                   release: int = 0) -> Normalizer:
    """The normaliser of backbone `name` (its release `release`) on `suites` (hub "dataset"
    stats: ONE suite, so that its numbers do not depend on which other suites a run selects)."""
    entry = get_entry(name)
    pinned = profile.pinned_release(name, release)
    if pinned is not None:  # its own stats: this machine's suites may render other frames
        return Normalizer("checkpoint", None, stats_fingerprint(saved_normalizer_stats(pinned)))
    if profile.source != "hub":  # the tiny release keeps what it was trained with: all suites
        stats = union_stats(suites, train_frames)
        return Normalizer("checkpoint", None, stats_fingerprint(stats))
    if entry.stats == "dataset":
        if len(suites) != 1:
            raise ValueError(f"dataset stats of {name} are per suite, got {[s.name for s in suites]}")
        stats = union_stats(suites, train_frames)
        return Normalizer(f"dataset:{suites[0].name}", stats, stats_fingerprint(stats))
    saved = saved_normalizer_stats(entry.repo_id, entry.revision)
    if saved is None:
        raise BackboneUnavailable(
            f"{entry.repo_id}@{entry.revision}: no saved normaliser stats in the HF cache, but the "
            f"backbone entry {name!r} keeps the checkpoint's own (stats='checkpoint'); fix: "
            f"`{download_command(entry.repo_id, entry.revision)}`"
        )
    return Normalizer("checkpoint", None, stats_fingerprint(saved))


def user_normalizer(profile: Profile, name: str) -> Normalizer:
    """A --policy checkpoint's normaliser: always its own saved stats."""
    facts = policy_facts(name, dict(profile.policies)[name])
    saved = saved_normalizer_stats(facts.source, facts.revision) or {}
    return Normalizer("checkpoint", None, stats_fingerprint(saved))


def checkpoint_id(name: str, profile: Profile, release_dir: Path | None = None) -> dict:
    """The checkpoint a record was measured on: repo id and the commit the cache resolves; a
    tiny release or a --policy folder: the sha256 of its weights (a folder has no commit, and
    the same key trained under another thread count gives other weights)."""
    if name in dict(profile.policies):
        return user_checkpoint_id(profile, name)
    entry = get_entry(name)
    if profile.source != "hub":
        return {"repo_id": f"tiny:{name}",
                "revision": folder_revision(release_dir) if release_dir else None}
    return {"repo_id": entry.repo_id, "revision": resolved_revision(entry.repo_id, entry.revision)}


def load_released(name: str, profile: Profile, suites, train_frames, cache: Path,
                  chunk_size: int = 10, *, progress: ProgressSink, stats: dict | None = None,
                  release: int = 0):
    """(the released policy for `name` in this profile's world, loaded with from_pretrained;
    its checkpoint_id). Hub: `stats` are the dataset stats to normalise with (None: the
    checkpoint's own). Tiny: `release` r is trained from seed r (init and batches)."""
    module = adapter_module(name)
    if profile.source == "hub":
        entry = get_entry(name)
        # a 3B checkpoint takes a while to read (and move to the GPU): said before, not after
        say(progress, f"policy {name}: loading {entry.repo_id} from the hub cache")
        backbone = module.load_policy(entry.repo_id, stats=stats, revision=entry.revision)
        return backbone, checkpoint_id(name, profile)
    if profile.pinned_release(name, release) is not None:
        return load_pinned(name, profile, progress, release)
    # The untrained build (seed r) both keys the cache and, on a miss, is what gets trained.
    side, tiny_stats = profile.protocol.tiny_image_size, union_stats(suites, train_frames)
    untrained = module.build_tiny_policy(tiny_stats, suites[0].camera_keys, image_hw=(side, side),
                                         chunk_size=chunk_size, seed=release, **build_args(name))
    if side != Protocol.tiny_image_size:
        default = module.build_tiny_policy(tiny_stats, suites[0].camera_keys, chunk_size=chunk_size,
                                           seed=0, **build_args(name))
        if default.info.native_grid == untrained.info.native_grid:  # a knob that moves nothing
            raise ValueError(f"[protocol] tiny_image_size = {side}: the tiny {name} reads "
                             f"{default.info.native_grid} image tokens at any size; remove it "
                             "for this backbone")
    key = release_key(name, profile, suites, chunk_size, architecture_fingerprint(untrained),
                      release)
    folder = tiny_release_dir(cache, name, key)
    if not (folder / "graftbench_release.json").exists():
        # xdist workers and array tasks sharing a cache: one trains, the others wait and load it.
        with exclusive(folder.with_name(folder.name + ".lock")):
            if not (folder / "graftbench_release.json").exists():
                shipped = shipped_release(folder.name)
                if shipped is not None:  # the default recipe's: ~1 min of training saved
                    say(progress, f"the tiny released {name} (release {release}): the shipped "
                                  f"{shipped.name}, not trained (content hash checked; cached "
                                  f"in {folder})")
                    install_shipped(shipped, folder)
                else:
                    say(progress, f"training the tiny released {name} (release {release}) "
                                  f"natively ({profile.protocol.native_steps} steps, once; "
                                  f"cached in {folder})")
                    train_tiny_release(name, untrained, profile, suites, train_frames, folder,
                                       chunk_size, progress, release)
    return module.load_policy(str(folder)), checkpoint_id(name, profile, folder)


def load_pinned(name: str, profile: Profile, progress: ProgressSink, release: int = 0):
    """(the pinned release `release` of `name` (the grid file's [releases]), its checkpoint_id),
    its content hash checked again: the folder may have changed since start-up."""
    folder = check_pinned(name, profile.pinned_release(name, release), "[releases]")
    say(progress, f"policy {name}: the pinned release {folder} (not trained, not the cache's)")
    return adapter_module(name).load_policy(str(folder)), checkpoint_id(name, profile, folder)

"""The fixed grafting protocol and the run profiles (tiny offline world vs. the paper grid).

Every constant that changes a number lives in `Protocol`; its hash goes into every record, so a
resumed or compared run never mixes numbers measured under different rules.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass

from backbones import BACKBONES
from bench.grid.kinds import default_controls


@dataclass(frozen=True)
class Protocol:
    """Constants of one grafting run. Bump `version` when a change moves numbers on purpose."""

    version: str = "1"
    # Projector training (the PAPER profile sets the study's lr and batch; schedule, warm-up and
    # clipping are ours where it is silent: bench/report/study.py, REPORT.md).
    steps: int = 2000
    batch_size: int = 32
    lr: float = 1e-3
    weight_decay: float = 0.0
    warmup_steps: int = 100
    grad_clip: float = 1.0
    loss_log_every: int = 10
    # Held-out split: whole episodes per task, drawn with a seed that never depends on the cell.
    split_seed: int = 1234
    heldout_episodes_per_task: int = 2
    # Evaluation windows: one window every `eval_stride` frames of each held-out episode.
    eval_stride: int = 10
    eval_batch_size: int = 16
    # Seed of the fixed per-window sampler noise (common random numbers across cells).
    eval_noise_seed: int = 4321
    # LoRA control: adapters on the frozen language model's attention projections.
    lora_rank: int = 8
    lora_alpha: int = 16
    lora_targets: tuple[str, ...] = ("q_proj", "v_proj")
    # Tuned-encoder control (bench.grid.kinds tuned_encoder): the encoder's weights train beside
    # the projector, at this AdamW learning rate under the same schedule (warm-up, cosine). 1e-5 is
    # LeRobot ACT's `optimizer_lr_backbone`, the usual rate for fine-tuning a pretrained vision
    # backbone: below every profile's projector lr (tiny 3e-3, paper 1e-4).
    encoder_lr: float = 1e-5
    # Released tiny checkpoints (offline world only): native training of the whole tiny policy.
    native_steps: int = 0
    native_lr: float = 3e-4
    # State dropout in that native training: each sample's state is replaced by the training
    # mean with probability `native_state_dropout` (1.0 for the first `native_state_dropout_warmup`
    # steps). Without it the tiny SmolVLA learns to act from its continuous state token alone and
    # never attends to the images (measured: native 0.31 vs shuffled-image 0.30 normalised MSE).
    native_state_dropout: float = 0.0
    native_state_dropout_warmup: int = 0
    # Random-shift augmentation in that native training (DrQ's pad-and-crop): every camera image
    # of every sample is moved by up to this many pixels in x and y (edges replicated). 0 = off.
    native_image_shift: int = 0
    # The same shift in graft (projector) training: the encoder then runs in the loop on the
    # shifted training images (stored features cannot be shifted); evaluation and rollouts read
    # images as they are. 0 = off.
    graft_image_shift: int = 0
    # Side of the square image the tiny released policies read (their config's image_resolution;
    # the suites' images are resized with padding to it). 64 px at patch 16 is a 4 x 4 grid of
    # tokens per camera: enough for the offline known answers, coarse for a centimetre grasp.
    tiny_image_size: int = 64

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @property
    def hash(self) -> str:
        """12 hex chars of sha256 over the canonical JSON of all fields; a field added after the
        first records leaves the hash alone at its default, so those records still resume."""
        values = {k: v for k, v in self.to_dict().items()
                  if not (k in _ADDED_LATER and v == _ADDED_LATER[k])}
        blob = json.dumps(values, sort_keys=True, default=list).encode()
        return hashlib.sha256(blob).hexdigest()[:12]

    def replace(self, **changes) -> "Protocol":
        return dataclasses.replace(self, **changes)


# Fields added after records existed, with the default that keeps the older hashes.
_ADDED_LATER = {"native_image_shift": 0, "graft_image_shift": 0, "tiny_image_size": 64,
                "encoder_lr": 1e-5}


@dataclass(frozen=True)
class Range:
    """The values a numeric Protocol field may take: low..high (None: unbounded), the low end
    itself excluded when `low_open` (a learning rate of 0 trains nothing)."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    why: str = ""  # why the top is where it is, for the message

    def __contains__(self, value) -> bool:
        if isinstance(value, float) and not math.isfinite(value):  # NaN passes every comparison
            return False
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return self.high is None or value <= self.high

    def text(self, value=None) -> str:
        """'>= 1', '> 0', 'in [0, 1]': the message's words; a top set by cost (`why`) is named
        with its reason only to a value above it."""
        if self.high is None or self.why and value is not None and not value > self.high:
            return f"{'>' if self.low_open else '>='} {self.low}"
        if self.why:
            return f"<= {self.high} ({self.why})"
        return f"in {'(' if self.low_open else '['}{self.low}, {self.high}]"


# ONE table of ranges: every int/float field of Protocol has its entry (tests/test_bad_inputs.py
# fails for a numeric field without one). Applied wherever a value comes in: --steps
# (bench.option_values.protocol_value), a grid file's `steps` and `[protocol]`
# (bench.grid.gridfile), each with range_error's one message.
# Adding a numeric field to Protocol: add its range here, in the same commit.
# A value whose cost grows with it has a top (steps run one after another; a LoRA rank or an
# image shift sizes tensors; a seed beyond 2**63 - 1 is refused by torch's generators).
# Held-out episodes and the batch are checked against the suite's data at start-up
# (bench.data_bounds). Infinity and NaN are outside every range.
MAX_STEPS = 1_000_000
_STEPS_WHY = "500x the study's 2,000 steps, which run one after another"
MAX_SEED = 2**63 - 1
_SHIFT_WHY = "it pads each image by as many pixels; past the largest side it moves nothing more"
PROTOCOL_RANGES: dict[str, Range] = {
    "steps": Range(1, MAX_STEPS, why=_STEPS_WHY), "batch_size": Range(1),
    "lr": Range(0, low_open=True), "weight_decay": Range(0),
    "warmup_steps": Range(0, MAX_STEPS, why=_STEPS_WHY), "grad_clip": Range(0),  # 0: no clipping
    "loss_log_every": Range(1), "split_seed": Range(0, MAX_SEED),
    "heldout_episodes_per_task": Range(1),
    "eval_stride": Range(1), "eval_batch_size": Range(1), "eval_noise_seed": Range(0, MAX_SEED),
    "lora_rank": Range(1, 4096), "lora_alpha": Range(1),  # a rank above any LM's width
    "encoder_lr": Range(0, low_open=True),  # 0 would train nothing: the frozen graft
    "native_steps": Range(0, MAX_STEPS, why=_STEPS_WHY),  # 0 steps: no native training
    "native_lr": Range(0, low_open=True),
    "native_state_dropout": Range(0, 1),
    "native_state_dropout_warmup": Range(0, MAX_STEPS, why=_STEPS_WHY),
    "native_image_shift": Range(0, 512, why=_SHIFT_WHY),
    "graft_image_shift": Range(0, 512, why=_SHIFT_WHY),
    "tiny_image_size": Range(16, 512),
}


def range_error(field: str, value, where: str) -> str | None:
    """The one message for a Protocol value out of its range (None: in range), the same from
    every entry: `where` names where the value came in ('--steps', 'study.toml [protocol]')."""
    allowed = PROTOCOL_RANGES.get(field)
    if allowed is None or value in allowed:
        return None
    finite = value == value and value not in (_INF, -_INF)
    what = "is out of range" if finite else "is not a finite number"
    return f"{where}: {field} = {value!r} {what}; give {field} {allowed.text(value)}"


_INF = float("inf")


PAPER_ENCODERS = ("siglip", "dinov2_s", "fastvit", "repvit")
# The study's two backbones, as the registry marks them (its base releases).
STUDY_BACKBONES = tuple(name for name, entry in BACKBONES.items() if entry.study)
# The kinds of bench.grid.kinds's table, graft and the opt-in ones (tuned_encoder) aside
ALL_CONTROLS = default_controls()


@dataclass(frozen=True)
class GridFileInfo:
    """Where a profile came from: the file as given, sha256 of its bytes, and its text."""

    path: str
    sha256: str
    text: str

    def provenance(self) -> dict:
        """The record's `grid_file` field."""
        return {"path": self.path, "sha256": self.sha256, "text": self.text}


@dataclass(frozen=True)
class Profile:
    """Which world a run lives in and the default grid selected in it."""

    name: str
    # "tiny": tiny LeRobot policies, random-init timm architectures and generated suites, all
    # built locally; "hub": real checkpoints, pretrained weights and LIBERO from the HF cache.
    source: str
    offline: bool
    protocol: Protocol
    backbones: tuple[str, ...]
    suites: tuple[str, ...]
    encoders: tuple[str, ...]
    seeds: tuple[int, ...]
    controls: tuple[str, ...] = ALL_CONTROLS
    # Encoders the control cells (lora, pooling, zero/shuffled image) are run for.
    control_encoders: tuple[str, ...] = ("pixels",)
    # Where the suites come from when not `source`: "sim" = scripted demonstrations in real
    # LIBERO scenes (bench.sim, needs the libero extra) for the tiny policies.
    suite_source: str | None = None
    # The study file (`--grid`) this profile was read from: provenance for every record. Not part
    # of `protocol`, so not of its hash: the file's [protocol] values are, through `protocol`.
    grid_file: GridFileInfo | None = None
    # Your own policies and datasets (bench.grid.user_specs): (NAME, PATH_OR_REPO_ID[@REV]) pairs,
    # and the camera map, (POLICY_CAMERA, DATASET_CAMERA) pairs. Not part of `protocol`: the
    # records carry the checkpoint's id and revision and the dataset's fingerprint instead.
    policies: tuple[tuple[str, str], ...] = ()
    datasets: tuple[tuple[str, str], ...] = ()
    camera_map: tuple[tuple[str, str], ...] = ()
    # Sim suites only (--sim-tasks, --sim-demos): the LIBERO task ids demonstrated and rolled out,
    # and successful demonstrations per task; empty / 0: bench.sim.demos.DEFAULT_SPECS. Not part
    # of `protocol`: the data they make changes the suite fingerprint and the tiny releases.
    sim_tasks: tuple[int, ...] = ()
    sim_demos: int = 0
    sim_demo_noise: float = 0.0  # --sim-demo-noise: DemoSpec.action_noise (DART-style)
    sim_demo_speed: float = 1.0  # --sim-demo-speed: DemoSpec.expert_speed (1: the original)
    # The robustness tier (--robustness, the grid file's `robustness`): perturbations as
    # "kind:severity" (bench.robust.perturbations), () = off. Not part of `protocol`: it adds cases
    # (test_robust) and their own records; the cells' numbers do not depend on it.
    robustness: tuple[str, ...] = ()
    # Pinned tiny releases (the grid file's [releases], bench.grid.pinned_release): (BACKBONE,
    # FOLDER) pairs loaded instead of training or reusing the cached release. Not part of
    # `protocol`: the records carry the weights' sha256 (checkpoint revision) instead.
    # A backbone named several times holds its releases in order (release 0 first).
    releases: tuple[tuple[str, str], ...] = ()
    # Independently seeded native trainings of the same recipe per tiny backbone (the grid file's
    # `releases_per_backbone`): release r trains from seed r, and every cell is measured on each,
    # so intervals can draw what two trainings of one choice move. 1: today's single release.
    releases_per_backbone: int = 1

    @property
    def data_source(self) -> str:
        return self.suite_source or self.source

    @property
    def release_indices(self) -> tuple[int, ...]:
        return tuple(range(self.releases_per_backbone))

    def pinned_release(self, backbone: str, release: int = 0) -> str | None:
        """The pinned folder of `backbone`'s release `release` (None: trained or cached here)."""
        folders = [folder for name, folder in self.releases if name == backbone]
        return folders[release] if release < len(folders) else None


TINY_FULL = Profile(
    name="tiny-full",
    source="tiny",
    offline=True,
    protocol=Protocol(
        # pi0.5 needs the steps (generator 5, spatial seed 0, pixels vs blind graft, 4 held-out
        # episodes per task): +5.2% at 400 steps (Wilcoxon p 0.07), +7.3% at 600 (p 0.0015),
        # +9.0% at 800; SmolVLA clears it at 400. lr 1e-3 or 6e-3 was no better than 3e-3.
        # docs/TINY_SMOLVLA.md has the measurements.
        steps=600,
        batch_size=16,
        lr=3e-3,
        warmup_steps=30,
        loss_log_every=10,
        # 4 of 16 episodes per task: ~150 windows per suite from 16 independent episodes (with 2
        # of 10, gaps of 9-11% read Wilcoxon p 0.01-0.03: too few episodes to tell).
        heldout_episodes_per_task=4,
        # Episodes are ~20-30 frames. At stride 6 the same SmolVLA cells read a pixels-blind gap
        # of 2.1%, at stride 3 11.1% (2 held-out episodes per task): window noise.
        eval_stride=3,
        eval_batch_size=32,
        native_steps=1500,
        native_lr=1e-3,
        native_state_dropout=0.5,
    ),
    backbones=STUDY_BACKBONES,
    suites=("spatial", "object"),
    encoders=PAPER_ENCODERS + ("pixels", "blind"),
    seeds=(0, 1),
)

# The default run: the tiny world's smallest grid in which every report section has something to
# say (both backbones, a paper encoder beside the two known-answer encoders, the native
# references, the wrapper control and a vision control), on ONE seed so that a first run from
# empty caches takes about 3 minutes on 2 cores (docs/PERFORMANCE.md): its intervals draw the
# held-out episodes and say that seeds are not drawn; `--seeds 0,1` adds the second seed (28
# cells, the earlier default). Same protocol and tiny releases as `tiny-full` (136 cells, one
# flag away): every cell here is bit-identical to its twin there.
TINY = dataclasses.replace(
    TINY_FULL,
    name="tiny",
    suites=("spatial",),
    encoders=("dinov2_s", "pixels", "blind"),
    seeds=(0,),
    # zero_image is in tiny-full: here `blind` and shuffled_image answer "does it use vision".
    controls=("native", "native_wrapped", "shuffled_image"),
)

PAPER = Profile(
    name="paper",
    source="hub",
    offline=False,
    # The study's settings where its summaries give them (bench/report/study.py; REPORT.md marks which
    # constants are the study's and which are ours): 2,000 steps, AdamW lr 1e-4, effective batch
    # 8, bf16 on CUDA (bench.loops.train.frozen_autocast). Warm-up, cosine decay, grad clip, split and
    # window stride are ours.
    protocol=Protocol(steps=2000, batch_size=8, lr=1e-4),
    backbones=STUDY_BACKBONES,
    suites=("spatial", "object"),
    encoders=PAPER_ENCODERS,
    seeds=(0, 1, 2),
    control_encoders=PAPER_ENCODERS,
)

# Tiny policies on LIBERO scenes: trained natively on the scripted demonstrations, so cells can
# also be rolled out in the simulator (--rollouts N). Few demos: one held-out episode per task.
SIM = Profile(
    name="sim",
    source="tiny",
    suite_source="sim",
    offline=True,
    protocol=TINY_FULL.protocol.replace(heldout_episodes_per_task=1),
    backbones=STUDY_BACKBONES,
    suites=("spatial",),
    encoders=("dinov2_s", "pixels", "blind"),
    seeds=(0,),
    controls=("native", "zero_image"),
)

PROFILES: dict[str, Profile] = {p.name: p for p in (TINY, TINY_FULL, PAPER, SIM)}


def get_profile(name: str) -> Profile:
    try:
        return PROFILES[name]
    except KeyError:
        raise ValueError(
            f"unknown profile {name!r}; choose one of {sorted(PROFILES)} (--profile NAME)"
        ) from None


def with_overrides(profile: Profile, **changes) -> Profile:
    """A copy of `profile` with grid fields (and `steps`, routed into the protocol) replaced."""
    steps = changes.pop("steps", None)
    if steps is not None:
        changes["protocol"] = profile.protocol.replace(steps=int(steps))
    changes = {k: v for k, v in changes.items() if v is not None}
    return dataclasses.replace(profile, **changes)



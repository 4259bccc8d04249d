"""Cell kinds: one table entry per kind declares everything the grid, the runner, the records and
the report know about it. Adding a control kind is one `register_kind(CellKind(...))`.

What a cell feeds the frozen policy is declared as an *input rule* for training and one for
evaluation, each one of `INPUT_RULES` (implemented once, in bench.cell.inputs):

- "same": the cell's own frames (pooled encoder features, the native tower's grid, or the images
  as recorded);
- "zero": all-zero images (for a graft: the encoder's features of a blank image);
- "shuffled": another held-out window's images (a fixed derangement of the windows).

This module imports nothing heavy: records, analysis and report read it without torch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from bench.table import Table

SAME, ZERO, SHUFFLED = "same", "zero", "shuffled"
INPUT_RULES = (SAME, ZERO, SHUFFLED)
# Why a rule has no closed-loop counterpart: "another window's images" needs a recorded episode
# to borrow from, and a live scene has none.
NO_CLOSED_LOOP = {SHUFFLED: "shuffled images have no closed-loop counterpart"}

# The encoder slot of an encoder-optional cell run without an encoder (the released policy).
NATIVE_SLOT = "native"


def _same_grid(native: tuple[int, int], variant: str | None) -> tuple[int, int]:
    return native


def _pooling_grid(native: tuple[int, int], variant: str | None) -> tuple[int, int]:
    rows, cols = native
    return {
        "half": (max(1, rows // 2), max(1, cols // 2)),
        "double": (rows * 2, cols * 2),
        "global": (1, 1),
    }[variant]


# Steps to compare training fractions at: divisible by every fraction of the table.
_FRACTION_PROBE = 1000


@dataclass(frozen=True)
class CellKind:
    """One kind of cell. `encoder`: "required" (a graft of the named encoder), "none" (the
    released policy's own tower: native, native_wrapped) or "optional" (either: an image control
    of a graft or of the released policy)."""

    name: str
    summary: str  # one line: what the cell measures (--help, report, docs)
    encoder: str = "required"
    variants: tuple[str | None, ...] = (None,)
    # Variants allowed without an encoder ("optional" kinds): the released policy is not retrained.
    native_variants: tuple[str | None, ...] = (None,)
    # The native tower's grid through the wrapper instead of an encoder's (native_wrapped).
    tower: bool = False
    # LoRA adapters on the frozen LM train beside the projector (the cell gets a private copy).
    lora: bool = False
    # The encoder's weights train beside the projector, at Protocol.encoder_lr (the cell gets a
    # private copy of the encoder, run in the training loop: stored features are the frozen
    # encoder's). Its question is per encoder, so it runs for every grid encoder with weights to
    # train (bench.grid.cells.tunable_encoders), not for the control encoders.
    tune_encoder: bool = False
    # The encoder runs in the training and evaluation loop at full precision without training
    # (the tuned control's zero-learning-rate twin): the tuned cell's feature path with its
    # weights held, so tuned - twin is what moving the encoder does and twin - graft what the
    # live path does against the stored fp16 features. Per encoder, as tune_encoder.
    live_encoder: bool = False
    # Left out of the profiles' default controls (bench.grid.protocol ALL_CONTROLS): measured
    # only when --controls or a grid file names it (a tuned encoder costs several times a frozen
    # graft's steps; the default grids and their committed records stay as they were).
    opt_in: bool = False
    # The cell's token grid per camera from the backbone's native grid and the variant.
    grid: Callable[[tuple[int, int], str | None], tuple[int, int]] = _same_grid
    # Input rule in training, per variant (missing variant: SAME), and in evaluation.
    train_inputs: tuple[tuple[str | None, str], ...] = ()
    eval_inputs: str = SAME
    # Id tag: None -> the kind's name; "{variant}" is filled in (pool_{variant}).
    tag: str | None = None
    # A control kind (compared against its reference) or a cell of the rankings (graft, native).
    control: bool = True
    # Training steps per variant as a fraction (numerator, denominator) of the protocol's (missing
    # variant: all of them); the warm-up shrinks with them (one whole schedule, compressed).
    train_fraction: tuple[tuple[str | None, tuple[int, int]], ...] = ()
    # A tier of the --screen ladder (short_graft): runs only under --screen, for every screened
    # encoder whatever the selection; not a control (--controls cannot name it, no control delta).
    tier: bool = False

    def __post_init__(self) -> None:
        if self.encoder not in ("required", "none", "optional"):
            raise ValueError(f"kind {self.name!r}: encoder={self.encoder!r}")
        if self.eval_inputs not in INPUT_RULES:
            raise ValueError(f"kind {self.name!r}: eval rule {self.eval_inputs!r} not in "
                             f"{INPUT_RULES}")
        for _, rule in self.train_inputs:  # shuffling needs held-out windows: evaluation only
            if rule not in (SAME, ZERO):
                raise ValueError(f"kind {self.name!r}: training rule {rule!r} not in "
                                 f"{(SAME, ZERO)}")

    # --- what a cell of this kind is --------------------------------------------------------
    def check(self, encoder: str | None, variant: str | None) -> None:
        """ValueError naming the problem when (encoder, variant) is not a cell of this kind."""
        if encoder is None and self.encoder == "required":
            raise ValueError(f"cell kind {self.name!r} needs an encoder")
        if encoder is not None and self.encoder == "none":
            raise ValueError(f"cell kind {self.name!r} runs the policy's own tower: no encoder")
        allowed = self.variants if encoder is not None else self.native_variants
        if variant not in allowed:
            what = "" if encoder is not None else " without an encoder (the policy is not retrained)"
            raise ValueError(f"{self.name} variant {variant!r}{what} not in {allowed}")

    def trains_projector(self, encoder: str | None) -> bool:
        """A projector is trained for a graft or the native tower; the released policy as is
        (native, its image controls) trains nothing."""
        return self.tower or encoder is not None

    def train_rule(self, variant: str | None) -> str:
        return dict(self.train_inputs).get(variant, SAME)

    @property
    def encoder_in_loop(self) -> bool:
        """Its encoder runs on every batch (tuned or live): a question per tunable encoder, never
        packed, never the stored features."""
        return self.tune_encoder or self.live_encoder

    def scaled_steps(self, steps: int, variant: str | None) -> int:
        """`steps` (the protocol's steps or warm-up) at the variant's fraction, rounded up; 0 stays
        0, anything else trains at least one step: 600 at 1/8 -> 75, 12 at 1/8 -> 2."""
        numerator, denominator = dict(self.train_fraction).get(variant, (1, 1))
        return 0 if steps <= 0 else max(1, math.ceil(steps * numerator / denominator))

    def shares_graft_training(self, encoder: str | None, variant: str | None) -> bool:
        """Trains exactly its graft's projector (same encoder, grid, inputs, LM): it takes the
        graft's trained projector instead of training it again; only evaluation differs."""
        return (encoder is not None and not (self.lora or self.tower or self.encoder_in_loop)
                and self.grid is _same_grid and self.train_rule(variant) == SAME
                and self.scaled_steps(_FRACTION_PROBE, variant) == _FRACTION_PROBE)

    def reference(self, encoder: str | None) -> str | None:
        """The kind of the cell a control is compared against: its graft, or the native policy."""
        if not self.control:
            return None
        return GRAFT if encoder is not None else NATIVE

    def reference_cell(self, encoder: str | None,
                       variant: str | None) -> tuple[str, str | None] | None:
        """(kind, variant) of the cell a control is compared against: a control trained for a
        fraction of the steps (tuned_encoder_1_8) against the short graft of as many steps, not
        the full graft; a tier (the short graft itself) against the graft it stands for."""
        ref = self.reference(encoder)
        if ref is None:
            return None
        steps = self.scaled_steps(_FRACTION_PROBE, variant)
        if ref != GRAFT or self.tier or steps == _FRACTION_PROBE:
            return ref, None
        short = CELL_KINDS[SHORT_GRAFT]
        matched = [v for v in short.variants if short.scaled_steps(_FRACTION_PROBE, v) == steps]
        return (SHORT_GRAFT, matched[0]) if matched else (GRAFT, None)

    def id_parts(self, encoder: str | None, variant: str | None) -> list[str]:
        """The middle of the cell id (between backbone-suite and seed)."""
        if self.encoder == "none":
            return [self.name]
        slot = encoder_slot(encoder or NATIVE_SLOT)
        if not self.control:
            return [slot]
        tag = (self.tag or self.name).format(variant=variant)
        return [slot, tag]

    def label(self, encoder: str | None, variant: str | None) -> str:
        """How the report names a cell of this kind, seeds aside: 'pooling[half] of pixels'."""
        if not self.control:
            return encoder or self.name
        if self.encoder == "none":
            return self.name
        what = self.name + (f"[{variant}]" if variant else "")
        return f"{what} of {encoder or NATIVE_SLOT}"


GRAFT = "graft"
NATIVE = "native"
NATIVE_WRAPPED = "native_wrapped"
CELL_KINDS: Table[CellKind] = Table("cell kind", "kinds")
register_kind = CELL_KINDS.register
unregister_kind = CELL_KINDS.unregister
get_kind = CELL_KINDS.get_entry


def control_kinds() -> tuple[str, ...]:
    """The kinds `--controls` may name, in table order."""
    return tuple(k.name for k in CELL_KINDS.values() if k.name != GRAFT and not k.tier)


def default_controls() -> tuple[str, ...]:
    """The control kinds a profile runs unless told otherwise: `control_kinds` but the opt-in."""
    return tuple(k for k in control_kinds() if not get_kind(k).opt_in)


def tier_kinds() -> tuple[CellKind, ...]:
    """The kinds that are tiers of the --screen ladder (run under --screen only), in table order."""
    return tuple(k for k in CELL_KINDS.values() if k.tier)


# Table order is the order of control cells in the grid (and of --controls' help).
register_kind(CellKind(GRAFT, "the encoder grafted through the projector", control=False))
register_kind(CellKind(NATIVE, "the released policy as is (no training)", encoder="none",
                       control=False))
register_kind(CellKind(NATIVE_WRAPPED, "the policy's own tower through the wrapper: a "
                       "projector trained on the native grid (wrapper neutrality)",
                       encoder="none", tower=True))
register_kind(CellKind("lora", "the graft plus LoRA on the frozen LM (does a frozen LM cap it?)",
                       lora=True))
register_kind(CellKind("tuned_encoder", "the graft with its encoder's weights trained too, at "
                       "the protocol's encoder_lr (does tuning the encoder beat freezing it?)",
                       tune_encoder=True, opt_in=True))
# The same question at an eighth of the steps (whole schedule compressed, as short_1_8): its
# frozen twin is the short_1_8 graft. A tuned cell runs its encoder forward and backward inside
# every step (studies/real/REPORT.md's tuned section gives the measured cost per step of a Lite
# and a ViT-S at 224 px on one CPU thread), so this is the cheapest question.
register_kind(CellKind("tuned_encoder_1_8", "the tuned-encoder control trained for 1/8 of the "
                       "steps, against the short_1_8 graft (the frozen twin at the same steps)",
                       tune_encoder=True, opt_in=True, train_fraction=((None, (1, 8)),)))
# tuned_encoder's zero-learning-rate twin: the same live path, its encoder held. The held encoder
# takes no gradient: at rate 0 its weights cannot move, and the clip then sees the projector's
# gradients alone, as the frozen graft's does (so tuned - twin also holds what the encoder's
# gradients do to the shared clip: part of what tuning is).
register_kind(CellKind("tuned_encoder_lr0", "tuned_encoder's twin at encoder learning rate 0: "
                       "the encoder run live in full precision, its weights held (does the live "
                       "path alone differ from the stored features?)",
                       live_encoder=True, opt_in=True))
register_kind(CellKind("pooling", "the graft pooled to another token grid",
                       variants=("half", "double", "global"), grid=_pooling_grid,
                       tag="pool_{variant}"))
register_kind(CellKind("zero_image", "all-zero images at evaluation (eval) or also in training "
                       "(train): does the policy use vision?",
                       encoder="optional", variants=("eval", "train"), native_variants=("eval",),
                       train_inputs=(("train", ZERO),), eval_inputs=ZERO,
                       tag="zero_image_{variant}"))
register_kind(CellKind("shuffled_image", "another held-out window's images at evaluation",
                       encoder="optional", eval_inputs=SHUFFLED))
# The short-graft tier of the --screen ladder: the graft trained for 1/8 or 1/4 of its steps.
SHORT_GRAFT = "short_graft"
# The fraction `--screen-by short` ranks by: the longer one (the closer to the graft it stands
# for; twice 1/8's cost, still a quarter of a graft's training). 1/8's agreement is reported too.
SHORT_BY_VARIANT = "1_4"
register_kind(CellKind(SHORT_GRAFT, "the graft trained for 1/8 or 1/4 of its steps (--screen's "
                       "short-graft tier)", variants=("1_8", SHORT_BY_VARIANT),
                       train_fraction=(("1_8", (1, 8)), (SHORT_BY_VARIANT, (1, 4))),
                       tag="short_{variant}", tier=True))


def encoder_slot(encoder: str) -> str:
    """An encoder name as ids spell it (cell ids, screen ids: one spelling): "timm:resnet18"
    -> "timm_resnet18", a user's "pkg.mod:make" -> "pkg.mod_make"; a hub name's '/' too."""
    return encoder.replace(":", "_").replace("/", "_")


def cell_id(kind: str, backbone: str, suite: str, encoder: str | None, seed: int,
            variant: str | None = None, release: int = 0) -> str:
    """smolvla-spatial-dinov2_s-seed0, smolvla-spatial-native-seed0,
    smolvla-spatial-pixels-pool_half-seed0, smolvla-spatial-native-zero_image_eval-seed0;
    on a backbone's release r > 0: smolvla-spatial-dinov2_s-rel2-seed0 (release 0 keeps the
    ids it had before releases were a factor, so its records resume)."""
    parts = [backbone, suite, *get_kind(kind).id_parts(encoder, variant),
             *([f"rel{release}"] if release else []), f"seed{seed}"]
    return "-".join(parts)


# The helpers below take a bench.results.record.Record (or Failure): anything with the identity
# fields kind, encoder and variant (this module sits below the record, which imports it).
def kind_of(record) -> CellKind | None:
    """The kind of a record, or None for a kind this code does not know."""
    return CELL_KINDS.get(record.kind)


def record_label(record) -> str:
    """What a record's cell is, seeds aside: 'dinov2_s', 'native', 'pooling[half] of pixels'."""
    kind = kind_of(record)
    if kind is None:
        return str(record.kind)
    return kind.label(record.encoder, record.variant)


def column_label(record) -> str | None:
    """Its column in per-task and per-horizon tables: grafts by encoder, the released policy's
    own-tower cells (native, native_wrapped) by kind; None for the other controls."""
    kind = kind_of(record)
    if kind is None or not (kind.name == GRAFT or kind.encoder == "none"):
        return None
    return record.encoder if kind.name == GRAFT else kind.name


def is_native_like(record) -> bool:
    """Compared against the native policy (no encoder of its own)."""
    return record.encoder in (None, NATIVE_SLOT)

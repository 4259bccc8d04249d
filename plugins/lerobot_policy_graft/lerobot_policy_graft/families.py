"""One class per backbone family: which LeRobot policy it is and where that policy embeds each
camera's image (the graft point). graftbench's adapters (backbones/) splice a graft in there for
a block (`grafted`); this plugin's grafted policies install theirs for good (`install`), so the
graft point is written once, here, for both.

Light on purpose (LeRobot's CLIs import the plugin at start): LeRobot's classes are imported
when asked for (`lerobot_class`), the tiny build's patches when a tiny graft is built.
"""

from __future__ import annotations

import contextlib
import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, ClassVar, Iterator

from torch import Tensor, nn

ImageEmbedder = Callable[[Tensor], Tensor]  # (B, 3, H, W) image -> (B, N_tokens, lm_width)


@dataclass(frozen=True)
class GraftFamily:
    """A LeRobot policy family and its graft point (subclasses: one per family's code)."""

    policy_type: str  # LeRobot's config type: lerobot.policies.<type>.modeling_<type>
    class_prefix: str  # "PI05" -> PI05Config, PI05Policy, PI05Pytorch
    label: str  # how messages name it: "SmolVLA", "pi0.5", "pi0"

    # The policy method that turns a batch's cameras into the images its embed_image is called
    # with, once per camera: a grafted policy encodes the batch's own pixels there.
    images_method: ClassVar[str]

    def lerobot_class(self, kind: str, suffix: str):
        """LeRobot's class, e.g. ("modeling", "Policy") -> PI05Policy."""
        module = importlib.import_module(
            f"lerobot.policies.{self.policy_type}.{kind}_{self.policy_type}")
        return getattr(module, f"{self.class_prefix}{suffix}")

    # -- the graft point ---------------------------------------------------------------------
    def embed_owner(self, policy: nn.Module) -> nn.Module:
        """The module whose `embed_image` (pixels -> LM input embeddings) the policy calls."""
        raise NotImplementedError

    def lm_width(self, policy: nn.Module) -> int:
        """Width of the LM input embeddings a graft must produce."""
        raise NotImplementedError

    def to_lm(self, policy: nn.Module, tokens: Tensor) -> Tensor:
        """A graft's tokens as the policy takes them from embed_image (as they are by default)."""
        return tokens

    def graft_point(self, policy: nn.Module, fn: ImageEmbedder) -> ImageEmbedder:
        """`fn` as the policy's embed_image: its output's shape checked, then `to_lm`."""
        width = self.lm_width(policy)

        def embed_image(image: Tensor) -> Tensor:
            tokens = fn(image)
            if tokens.ndim != 3 or tokens.shape[0] != image.shape[0] or tokens.shape[-1] != width:
                raise ValueError(f"image embedder returned {tuple(tokens.shape)}; {self.label} "
                                 f"needs ({image.shape[0]}, N_tokens, {width})")
            return self.to_lm(policy, tokens)

        return embed_image

    def install(self, policy: nn.Module, fn: ImageEmbedder) -> None:
        """From now on the policy embeds each camera's image with `fn`."""
        # An instance attribute shadows the method. object.__setattr__, because
        # nn.Module.__setattr__ would register an nn.Module `fn` as a submodule of the policy.
        object.__setattr__(self.embed_owner(policy), "embed_image", self.graft_point(policy, fn))

    @contextlib.contextmanager
    def grafted(self, policy: nn.Module, fn: ImageEmbedder) -> Iterator[None]:
        """Within the block the policy embeds each camera's image with `fn`; restored after."""
        owner = self.embed_owner(policy)
        previous = owner.__dict__.get("embed_image")  # set when grafts are nested
        self.install(policy, fn)
        try:
            yield
        finally:
            if previous is None:
                del owner.__dict__["embed_image"]
            else:
                object.__setattr__(owner, "embed_image", previous)

    # -- building a grafted policy (modeling_graft) ------------------------------------------
    def building(self, config, resolve: Callable[[str], str]):
        """Context in which LeRobot's policy class builds from `config`; `resolve` maps a
        config's relative asset name to the checkpoint's folder."""
        return contextlib.nullcontext()

    def bundled_assets(self, config) -> list[str]:
        """Folders the config names relative to the checkpoint: they travel with it."""
        return []


@dataclass(frozen=True)
class SmolVLAFamily(GraftFamily):
    """SmolVLA: `SmolVLMWithExpertModel.embed_image` (smolvlm_with_expert.py ~202-215), vision
    tower -> connector; `embed_prefix` scales its output by sqrt(width) afterwards, so a graft
    keeps that scaling. Images reach it from `prepare_images` (modeling_smolvla.py ~334-380)."""

    images_method: ClassVar[str] = "prepare_images"

    def embed_owner(self, policy: nn.Module) -> nn.Module:
        return policy.model.vlm_with_expert

    def lm_width(self, policy: nn.Module) -> int:
        return policy.model.vlm_with_expert.config.text_config.hidden_size

    def to_lm(self, policy: nn.Module, tokens: Tensor) -> Tensor:
        # The LM's own dtype, read per call: the policy may have been cast since installing.
        text = policy.model.vlm_with_expert.get_vlm_model().text_model
        return tokens.to(text.get_input_embeddings().weight.dtype)

    @contextlib.contextmanager
    def building(self, config, resolve: Callable[[str], str]):
        # The (bundled tiny) VLM folder: AutoConfig/AutoProcessor read it at construction only.
        saved = config.vlm_model_name
        config.vlm_model_name = resolve(saved)
        try:
            yield
        finally:
            config.vlm_model_name = saved

    def bundled_assets(self, config) -> list[str]:
        name = config.vlm_model_name
        return [] if Path(name).is_absolute() else [name]


@dataclass(frozen=True)
class PaliGemmaFamily(GraftFamily):
    """LeRobot's PaliGemma policies (pi0.5, pi0): `PaliGemmaWithExpertModel.embed_image`
    (modeling_pi05.py:284-293, modeling_pi0.py:287-296), SigLIP -> multi_modal_projector, with
    no scaling of image embeddings afterwards; images reach it from `_preprocess_images`. The
    fields below tell the two apart for graftbench's adapters (backbones.paligemma)."""

    normalization: str  # of state and action, as in the config's normalization_mapping
    stat_names: tuple[str, ...]  # the dataset stats that normalisation reads
    state_token: bool  # the inner forward takes the (padded, normalised) state

    images_method: ClassVar[str] = "_preprocess_images"

    def embed_owner(self, policy: nn.Module) -> nn.Module:
        return policy.model.paligemma_with_expert

    def lm_width(self, policy: nn.Module) -> int:
        return policy.model.paligemma_with_expert.paligemma.config.text_config.hidden_size

    def building(self, config, resolve: Callable[[str], str]):
        if not config.tiny_arch:
            return contextlib.nullcontext()
        # graftbench's tiny test world only: LeRobot builds the tiny sizes under these patches.
        from lerobot_policy_graft.tiny_paligemma import TinyPaliGemmaArch, tiny_paligemma_patches

        return tiny_paligemma_patches(TinyPaliGemmaArch.from_json(config.tiny_arch), None,
                                 self.policy_type)


SMOLVLA = SmolVLAFamily("smolvla", "SmolVLA", "SmolVLA")
PI05 = PaliGemmaFamily("pi05", "PI05", "pi0.5", normalization="QUANTILES",
                       stat_names=("q01", "q99"), state_token=False)
# pi0: the state is ONE continuous token (state_proj, modeling_pi0.py:529-549); MEAN_STD
# normalisation (configuration_pi0.py:71-77).
PI0 = PaliGemmaFamily("pi0", "PI0", "pi0", normalization="MEAN_STD", stat_names=("mean", "std"),
                      state_token=True)
FAMILIES: dict[str, GraftFamily] = {f.policy_type: f for f in (SMOLVLA, PI05, PI0)}

"""Loading a saved LeRobot PaliGemma policy (pi0.5, pi0): a local folder (tiny or real) or a hub
repo from the Hugging Face cache, with its saved processors made to fit the LIBERO view.

A hub release's config names its own cameras and state/action widths (`adapt_real_config` maps
LIBERO's onto them); its saved processors may carry `"features": {}`, no stats and a foreign
device (backbones.hub.saved_processor_overrides fixes all three); LeRobot keeps random weights
with only a printed line when the weights do not load (`_policy_from_pretrained` refuses that).
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple

from lerobot_policy_graft.configuration_graft import config_from_pretrained
from lerobot_policy_graft.families import PaliGemmaFamily

from backbones import hub, hub_release, paligemma
from backbones.base import BackboneInfo, only_step
from backbones.paligemma import (
    ACTION_KEY,
    PALIGEMMA_TOKENIZER_REPO,
    STATE_KEY,
    TOKENIZER_SUBDIR,
    PaliGemmaBackbone,
)
from backbones.tiny_paligemma import TinyPaliGemmaArch, require_pinned_lerobot, tiny_paligemma_patches
from ondisk.hubcache import cached_file, hub_artifact


def load_policy(backbone_cls: type[PaliGemmaBackbone], path_or_repo_id: str,
                stats: dict | None = None, *, revision: str | None = None,
                device: str | None = None) -> PaliGemmaBackbone:
    """A saved folder (tiny or real) or a hub repo id from the HF cache, on `device` (default: the
    checkpoint's own for a folder, CUDA when available for a hub id). `stats` (dataset stats)
    replace the saved ones; without them the checkpoint's own saved stats are used, and must cover
    the state and action."""
    require_pinned_lerobot()
    folder = Path(path_or_repo_id).expanduser()
    if folder.is_dir():
        return _load(backbone_cls, str(folder), stats, marker_dir=folder, revision=None, device=device)
    if path_or_repo_id.startswith(("/", ".", "~")) or path_or_repo_id.count("/") != 1:
        raise FileNotFoundError(
            f"no {backbone_cls.family.label} checkpoint folder at {path_or_repo_id!r} (and it is "
            "not an owner/name hub id)"
        )
    _require_cached(path_or_repo_id, revision)
    return _load(backbone_cls, path_or_repo_id, stats, marker_dir=None, revision=revision,
                 device=device or hub.default_device())


def _read_marker(family: PaliGemmaFamily, source: str, marker_dir: Path | None,
                 revision: str | None) -> dict:
    """graftbench's marker: a saved folder's (tiny arch, cameras, rename map) or, for a hub repo,
    only its tiny arch (the offline hub-cache world; a real release has no marker)."""
    if marker_dir is not None:
        path = marker_dir / paligemma.marker_file(family)
        return json.loads(path.read_text()) if path.is_file() else {}
    path = cached_file(source, paligemma.marker_file(family), revision)
    return {"tiny_arch": json.loads(path.read_text()).get("tiny_arch")} if path else {}


def _load(backbone_cls: type[PaliGemmaBackbone], source: str, stats: dict | None,
          marker_dir: Path | None, revision: str | None, device: str | None) -> PaliGemmaBackbone:
    from lerobot.policies.factory import make_pre_post_processors

    family = backbone_cls.family
    marker = _read_marker(family, source, marker_dir, revision)
    arch = TinyPaliGemmaArch.from_dict(marker["tiny_arch"]) if marker.get("tiny_arch") else None
    with _hub_errors_as_unavailable(source, revision):
        config = config_from_pretrained(source, revision)
    _check_config(config, family, source)
    if device is not None:
        config.device = device
    if marker.get("camera_keys"):
        rename_map, camera_keys = marker["rename_map"], tuple(marker["camera_keys"])
    else:
        rename_map, camera_keys = adapt_real_config(config, stats, family)
    # A saved tiny folder carries its tokenizer; a hub repo reads google/paligemma-3b-pt-224's.
    tokenizer_dir = marker_dir / TOKENIZER_SUBDIR if arch and marker_dir else None
    patches = (tiny_paligemma_patches(arch, tokenizer_dir, family.policy_type) if arch
               else contextlib.nullcontext())
    with patches, _hub_errors_as_unavailable(source, revision):
        policy = _policy_from_pretrained(family, source, config, revision)
        policy.to(config.device)
        if marker_dir is not None or cached_file(source, "policy_preprocessor.json", revision):
            pre_over, post_over = hub.saved_processor_overrides(
                policy.config, config.device, stats, rename_map)
            if tokenizer_dir is not None:
                pre_over["tokenizer_processor"] = {"tokenizer_name": str(tokenizer_dir)}
            pre, post = make_pre_post_processors(
                policy.config, pretrained_path=source, pretrained_revision=revision,
                preprocessor_overrides=pre_over, postprocessor_overrides=post_over,
            )
        else:  # a hub checkpoint saved before LeRobot's processor pipelines
            if stats is None:
                raise ValueError(f"{source} has no saved processors: pass dataset stats to load_policy")
            pre, post = make_pre_post_processors(policy.config, dataset_stats=stats)
            if rename_map:
                only_step(pre, "RenameObservationsProcessorStep").rename_map = dict(rename_map)
    hub.check_normalizer_covers(pre, source)
    hub.check_normalizer_covers(post, source)
    return backbone_cls(policy, pre, post, camera_keys, tiny_arch=arch, rename_map=rename_map)


def _check_config(config, family: PaliGemmaFamily, source: str) -> None:
    """Refuse a checkpoint of another policy type, or one trained on relative actions (pi0:
    action - state, undone in the post-processor, which the harness's action MSE bypasses)."""
    if config.type != family.policy_type:
        raise ValueError(
            f"{source} is a {config.type!r} checkpoint, not {family.policy_type!r}: register it "
            f"with the backbone module for {config.type!r}"
        )
    if getattr(config, "use_relative_actions", False):
        raise ValueError(
            f"{source} was trained on relative actions (use_relative_actions=true): graftbench "
            "scores absolute actions in the normaliser's space; use a checkpoint with "
            "use_relative_actions=false"
        )


def adapt_real_config(config, stats: dict | None,
                      family: PaliGemmaFamily) -> tuple[dict[str, str], tuple[str, ...]]:
    """LIBERO view of a released config: rename map, cameras kept, state/action width (in place)."""
    from lerobot.configs import FeatureType, PolicyFeature

    image_keys = list(config.image_features)
    rename_map = hub.libero_rename_map(image_keys, config.type)
    policy_keys = list(rename_map.values())
    for key in image_keys:  # unmapped cameras are dropped, not masked (see the note above)
        if key not in policy_keys:
            del config.input_features[key]
    rename_map = {src: dst for src, dst in rename_map.items() if src != dst}
    dims = {key: len(stats[key][family.stat_names[0]]) if stats else default
            for key, default in ((STATE_KEY, 8), (ACTION_KEY, 7))}  # LIBERO's 8 / 7 real dims
    config.input_features[STATE_KEY] = PolicyFeature(FeatureType.STATE, (dims[STATE_KEY],))
    config.output_features[ACTION_KEY] = PolicyFeature(FeatureType.ACTION, (dims[ACTION_KEY],))
    return rename_map, hub.LIBERO_CAMERAS


def _policy_from_pretrained(family: PaliGemmaFamily, source: str, config, revision: str | None = None):
    """<Family>Policy.from_pretrained, failing loudly where lerobot would keep random weights."""
    # modeling_pi05.py:810-813 and :859-860 (modeling_pi0.py:846, :895) print and return
    # the randomly initialised model when the weights cannot be read or do not match; we refuse.
    captured = io.StringIO()
    with contextlib.redirect_stdout(captured):
        policy = family.lerobot_class("modeling", "Policy").from_pretrained(
            source, config=config, revision=revision)
    if "Could not load" in captured.getvalue():
        raise RuntimeError(
            f"{type(policy).__name__}.from_pretrained({source!r}) kept random weights:\n"
            f"{captured.getvalue()}"
        )
    return policy


# config.json too: transformers 5.5's AutoTokenizer reads the repo's model config first (found
# offline by the hub-cache world: without it the tokenizer does not load).
TOKENIZER_INCLUDE = ("config.json", "tokenizer*", "special_tokens_map.json", "added_tokens.json")
TOKENIZER_NOTE = (
    "gated: accept the licence at https://huggingface.co/google/paligemma-3b-pt-224 and run "
    "`hf auth login` first; the --include patterns fetch the ~22 MB tokenizer, not 11.7 GB of weights"
)


def artifacts(repo_id: str, revision: str | None, needed_by: str) -> list:
    """What loading `repo_id` reads from the hub: the checkpoint and the PaliGemma tokenizer
    (LeRobot reads the tokenizer at its main revision: processor_pi0(5).py ~141 takes no revision)."""
    return [
        hub_artifact("policy", repo_id, ("config.json", "model.safetensors"), needed_by, revision),
        hub_artifact("tokenizer", PALIGEMMA_TOKENIZER_REPO,
                         ("config.json", "tokenizer_config.json", "tokenizer.json"), needed_by,
                         include=TOKENIZER_INCLUDE, note=TOKENIZER_NOTE),
    ]


def _require_cached(repo_id: str, revision: str | None = None) -> None:
    """Fail fast, in one line, when offline and the checkpoint or its tokenizer is not cached."""
    hub.require_present(artifacts(repo_id, revision, f"backbone {repo_id}"))


def _hub_errors_as_unavailable(repo_id: str, revision: str | None):
    return hub.errors_as_unavailable(repo_id, lambda: artifacts(repo_id, revision, repo_id),
                                     what=" or its tokenizer")


class PaliGemmaAdapter(NamedTuple):
    """What an adapter module offers the harness (backbones.seam.AdapterModule) for one PaliGemma
    family: pi0.py and pi05.py are each one of these, by composition (`paligemma_adapter`)."""

    FAMILY: PaliGemmaFamily
    INFO_REAL: BackboneInfo
    BACKBONE_CLASS: type[PaliGemmaBackbone]
    RENAMES_CAMERAS: bool  # False: a checkpoint is loaded with its saved camera names
    MARKER_FILE: str
    build_tiny_policy: Callable[..., PaliGemmaBackbone]
    save_pretrained: Callable[..., Path]
    load_policy: Callable[..., PaliGemmaBackbone]
    check_real_shapes: Callable[[], dict[str, int]]
    artifacts: Callable[..., list]
    write_hub_release: Callable[..., None]


def paligemma_adapter(family: PaliGemmaFamily, module: str,
                      hub_release_device: str) -> PaliGemmaAdapter:
    """The adapter of `family`, its Backbone class named <Prefix>Backbone in `module` (the
    adapter module's name); `hub_release_device`: the device the hub release saved its
    pre-processor with (docs/HUB_FACTS.md), which the offline hub world copies."""
    name = f"{family.class_prefix}Backbone"
    backbone_cls = type(name, (PaliGemmaBackbone,), {
        "__module__": module, "__qualname__": name, "family": family,
        "__doc__": f"A real LeRobot {family.label} policy with its own pre/post processors."})

    def build_tiny_policy(stats: dict, camera_keys=hub.LIBERO_CAMERAS,
                          image_hw: tuple[int, int] = (64, 64), state_dim: int = 8,
                          action_dim: int = 7, chunk_size: int = 10, seed: int = 0, *,
                          arch: Mapping[str, Any] | None = None):
        """A real LeRobot policy of this family with tiny sizes (~0.2M parameters), offline,
        deterministic from `seed`; `arch`: another size of the tiny ladder (TinyPaliGemmaArch
        fields, backbones.tiny_sizes)."""
        return paligemma.build_tiny_policy(backbone_cls, stats, camera_keys, image_hw,
                                           state_dim, action_dim, chunk_size, seed, arch)

    def load(path_or_repo_id: str, stats: dict | None = None, *, revision: str | None = None,
             device: str | None = None):
        """A saved folder (tiny or real) or a hub repo id from the HF cache (load_policy above)."""
        return load_policy(backbone_cls, path_or_repo_id, stats, revision=revision, device=device)

    def check_real_shapes() -> dict[str, int]:
        """The REAL model on the meta device (no weights), one 224 px image embedded."""
        return paligemma.check_real_shapes(family)

    def write_hub_release(hub_cache: Path, repo_id: str, revision: str | None) -> None:
        """The base release shaped as the hub's (backbones.hub_release)."""
        hub_release.write_paligemma_release(adapter, hub_cache, repo_id, revision,
                                          device=hub_release_device)

    adapter = PaliGemmaAdapter(
        FAMILY=family, INFO_REAL=paligemma.real_info(family), BACKBONE_CLASS=backbone_cls,
        RENAMES_CAMERAS=False, MARKER_FILE=paligemma.marker_file(family),
        build_tiny_policy=build_tiny_policy, save_pretrained=paligemma.save_pretrained,
        load_policy=load, check_real_shapes=check_real_shapes, artifacts=artifacts,
        write_hub_release=write_hub_release)
    return adapter

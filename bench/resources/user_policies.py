"""Your own policy and data (`--policy`, `--dataset`, `--camera-map`): what they are, whether a
policy can take a dataset (checked at start-up, one line naming both sides and the fix), and
loading through the same adapter `load_policy` as the registry's checkpoints.

Camera rule (one line printed for every user policy x dataset pair):
1. an explicit map (`--camera-map POLICY_CAMERA=DATASET_CAMERA,...`, `[camera_map]`) wins; it
   must cover every camera of the policy, each onto a camera the dataset has;
2. else identical names, when every camera of the policy is a camera of the dataset;
3. else, when the counts match, the dataset's cameras in its order onto the policy's in its order;
4. else an error.
Stats: a user policy keeps its own saved normaliser stats (like the registry's stats="checkpoint"
entries); they must have the dataset's state and action widths.
Provenance: a hub id records the commit the cache resolves; a local folder records
"sha256:<16 hex>" of its model.safetensors (a folder has no commit; its weights' hash names it).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from backbones import adapter_for_policy_type
from backbones.hub import saved_normalizer_stats
from ondisk.hubcache import cached_file, folder_revision, resolved_revision
from bench.grid.user_specs import split_revision
from ondisk.libero_format import ACTION_KEY, STATE_KEY
from bench.suites.user import DatasetFacts, check_dataset, dataset_facts


@dataclass(frozen=True)
class PolicyFacts:
    name: str
    source: str  # absolute folder, or the hub repo id
    revision: str | None  # as asked (None: the cache's main)
    policy_type: str
    cameras: tuple[str, ...]
    state_dim: int | None
    action_dim: int | None
    stats_widths: tuple[int | None, int | None]  # saved normaliser's (state, action) widths

    def describe(self) -> str:
        return (f"--policy {self.name} (cameras {list(self.cameras)}, state {self.state_dim}, "
                f"action {self.action_dim})")


def _is_folder(target: str) -> bool:
    return Path(target).expanduser().is_dir()


def _not_a_repo_id(source: str) -> str | None:
    """Why `source` (no folder) cannot be a hub repo id, or None when it can be one."""
    from huggingface_hub.errors import HFValidationError
    from huggingface_hub.utils import validate_repo_id

    if Path(source).expanduser().is_file():
        return "a file, not a folder (a checkpoint is the folder holding config.json)"
    if source.startswith(("/", "./", "../", "~")) or source.count("/") > 1:
        return "no such folder"
    try:
        validate_repo_id(source)
    except HFValidationError:
        return "neither a folder nor a hub repo id (OWNER/NAME)"
    return None


def policy_facts(name: str, target: str) -> PolicyFacts:
    """A checkpoint's type, cameras, state/action widths and saved stats' widths, from its
    config.json and saved pre-processor (no policy is built)."""
    source, revision = (target, None) if _is_folder(target) else split_revision(target)
    folder = Path(source).expanduser()
    why = None if folder.is_dir() else _not_a_repo_id(source)
    if why:
        raise ValueError(f"--policy {name}={target}: {why}; fix: give the folder save_pretrained "
                         "wrote (config.json, model.safetensors) or a cached hub repo id "
                         "OWNER/NAME[@REVISION]")
    config_path = folder / "config.json" if folder.is_dir() else cached_file(source, "config.json", revision)
    if config_path is None or not Path(config_path).is_file():
        raise ValueError(f"--policy {name}={target}: no LeRobot checkpoint there (no config.json "
                         "in the folder or the HF cache); give a save_pretrained folder or a "
                         "cached repo id (`hf download REPO_ID`)")
    source = str(folder.resolve()) if folder.is_dir() else source
    config = json.loads(Path(config_path).read_text())
    inputs, outputs = config.get("input_features", {}), config.get("output_features", {})
    stats = saved_normalizer_stats(source, revision) or {}

    def width(features, key):
        shape = features.get(key, {}).get("shape")
        return int(shape[0]) if shape else None

    def stats_width(key):
        mean = stats.get(key, {}).get("mean")
        return int(mean.shape[0]) if mean is not None and mean.ndim else None

    return PolicyFacts(
        name=name, source=source, revision=revision, policy_type=str(config.get("type")),
        cameras=tuple(k for k, f in inputs.items() if f.get("type") == "VISUAL"),
        state_dim=width(inputs, STATE_KEY), action_dim=width(outputs, ACTION_KEY),
        stats_widths=(stats_width(STATE_KEY), stats_width(ACTION_KEY)))


def _describe(name: str, facts: DatasetFacts) -> str:
    return (f"--dataset {name} (cameras {list(facts.cameras)}, state {facts.state_dim}, "
            f"action {facts.action_dim})")


def pair_cameras(policy: PolicyFacts, dataset_name: str, data: DatasetFacts,
                 explicit: dict[str, str]) -> tuple[dict[str, str], str]:
    """({policy camera: dataset camera}, the rule that chose it) or a one-line ValueError."""
    both = f"{policy.describe()} x {_describe(dataset_name, data)}"
    fix = "fix: --camera-map " + ",".join(f"{p.rsplit('.', 1)[-1]}=DATASET_CAMERA"
                                          for p in policy.cameras)
    if explicit:
        unknown = [p for p in explicit if p not in policy.cameras]
        unmapped = [p for p in policy.cameras if p not in explicit]
        absent = [d for p, d in explicit.items() if p in policy.cameras and d not in data.cameras]
        if unknown or unmapped or absent:
            problem = (f"the camera map names policy camera(s) {unknown} it lacks" if unknown else
                       f"the camera map leaves policy camera(s) {unmapped} unmapped" if unmapped
                       else f"the camera map names dataset camera(s) {absent} it lacks")
            raise ValueError(f"{both}: {problem}; {fix}")
        return {p: explicit[p] for p in policy.cameras}, "the camera map"
    if all(p in data.cameras for p in policy.cameras):
        return {p: p for p in policy.cameras}, "identical names"
    if len(policy.cameras) == len(data.cameras):
        return dict(zip(policy.cameras, data.cameras)), "the dataset's cameras in order"
    missing = [p for p in policy.cameras if p not in data.cameras]
    raise ValueError(f"{both}: missing camera(s) {missing} and the counts differ; {fix}")


def check_pair(policy: PolicyFacts, dataset_name: str, data: DatasetFacts,
               explicit: dict[str, str]) -> tuple[dict[str, str], str]:
    """Can `policy` take dataset `data`? Its camera pairing and rule, else a one-line error."""
    check_dataset(dataset_name, data)
    both = f"{policy.describe()} x {_describe(dataset_name, data)}"
    # A type without an adapter: its own line, before the others.
    renames = adapter_for_policy_type(policy.policy_type).RENAMES_CAMERAS
    for what, theirs, mine, saved in (("state", data.state_dim, policy.state_dim, policy.stats_widths[0]),
                                      ("action", data.action_dim, policy.action_dim, policy.stats_widths[1])):
        if mine != theirs:
            raise ValueError(f"{both}: the policy takes {what} {mine}-D, the dataset has {theirs}-D; "
                             f"fix: a checkpoint trained on this {what} layout, or a dataset that "
                             f"records {mine}-D {what}")
        if saved != theirs:
            raise ValueError(f"{both}: the policy's saved normaliser covers {what} {saved}-D, not "
                             f"{theirs}-D; fix: save the checkpoint with its pre/post-processors "
                             "(save_pretrained of the policy's processors, with the dataset's stats)")
    mapping, rule = pair_cameras(policy, dataset_name, data, explicit)
    if not renames and any(p != d for p, d in mapping.items()):
        raise ValueError(f"{both}: a {policy.policy_type} checkpoint is loaded with its saved "
                         f"camera names, the pairing {mapping} renames; fix: name the dataset's "
                         "cameras as the policy's (its adapter renames no cameras)")
    return mapping, rule


def _check_names(policies: dict, datasets: dict) -> None:
    """A user name must not shadow a registry backbone or a built-in suite."""
    from backbones import BACKBONES
    from bench.suites import SUITES

    for option, names, taken in (("--policy", policies, BACKBONES), ("--dataset", datasets, SUITES)):
        clash = sorted(set(names) & set(taken))
        if clash:
            raise ValueError(f"{option} {clash[0]}: the name of a built-in one; give yours "
                             f"another name (built-in: {', '.join(taken)})")


def _check_each(policies: dict, datasets: dict, explicit: dict) -> None:
    """Each --policy and --dataset on its own, before any pair: there, readable, of a type with
    an adapter; the camera map's policy cameras are cameras of a --policy."""
    cameras = set()
    for name, target in policies.items():
        facts = policy_facts(name, target)
        try:
            adapter_for_policy_type(facts.policy_type)
        except ValueError as e:
            raise ValueError(f"--policy {name}={target}: {e}") from None
        cameras.update(facts.cameras)
    for name, target in datasets.items():
        check_dataset(name, dataset_facts(target, name))
    unknown = [p for p in explicit if p not in cameras]
    if unknown:
        raise ValueError(f"--camera-map: policy camera(s) {unknown} are no camera of "
                         f"{', '.join(f'--policy {n}' for n in policies)} (cameras "
                         f"{sorted(cameras)}); fix: map those cameras")


def check_world(profile) -> list[str]:
    """Every user policy x suite and backbone x user dataset pair of the grid, at start-up;
    the camera pairing of each, one line per pair. A registry backbone cannot take a user
    dataset (its release is LIBERO's): an error."""
    lines = []
    policies, datasets = dict(profile.policies), dict(profile.datasets)
    _check_names(policies, datasets)
    explicit = dict(profile.camera_map)
    _check_each(policies, datasets, explicit)
    for backbone in profile.backbones:
        for suite in profile.suites:
            if suite in datasets and backbone not in policies:
                raise ValueError(f"backbone {backbone!r} (a registry release, LIBERO's cameras "
                                 f"and dims) x --dataset {suite}: not a pair it can take; fix: "
                                 "--backbones with your --policy names only")
            if backbone in policies and suite in datasets:
                mapping, rule = check_pair(policy_facts(backbone, policies[backbone]), suite,
                                           dataset_facts(datasets[suite], suite), explicit)
                lines.append(f"[graftbench] cameras of {backbone} x {suite} by {rule}: " + ", ".join(
                    f"{p} <- {d}" for p, d in mapping.items()))
    return lines


def camera_mapping(profile, backbone: str, suite) -> dict[str, str]:
    """{policy camera: dataset camera} for a user policy on a loaded suite (any suite)."""
    facts = policy_facts(backbone, dict(profile.policies)[backbone])
    data = DatasetFacts(source=suite.root, root=Path(suite.root), repo_id=suite.repo_id,
                        cameras=tuple(suite.camera_keys), state_dim=int(suite.state.shape[1]),
                        action_dim=int(suite.action.shape[1]), fps=suite.fps, has_tasks=True,
                        video=False)
    return check_pair(facts, suite.name, data, dict(profile.camera_map))[0]


def load_user_policy(profile, backbone: str, suite):
    """The user's checkpoint through its adapter's `load_policy`, its own saved stats, its
    cameras fed from the suite's as the camera rule pairs them."""
    facts = policy_facts(backbone, dict(profile.policies)[backbone])
    module = adapter_for_policy_type(facts.policy_type)
    mapping = camera_mapping(profile, backbone, suite)
    if not module.RENAMES_CAMERAS:
        return module.load_policy(facts.source, None, revision=facts.revision)
    return module.load_policy(
        facts.source, None, rename_map={d: p for p, d in mapping.items() if p != d},
        camera_keys=tuple(mapping[p] for p in facts.cameras),
        state_dim=int(suite.state.shape[1]), action_dim=int(suite.action.shape[1]),
        revision=facts.revision)


def user_checkpoint_id(profile, backbone: str) -> dict:
    """{repo_id: folder or hub id, revision: the resolved commit or sha256 of the weights}."""
    facts = policy_facts(backbone, dict(profile.policies)[backbone])
    revision = (folder_revision(facts.source) if Path(facts.source).is_dir()
                else resolved_revision(facts.source, facts.revision))
    return {"repo_id": facts.source, "revision": revision, "policy_type": facts.policy_type}

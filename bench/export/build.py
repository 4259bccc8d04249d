"""Write a graft cell as a LeRobot pretrained_model folder: config.json (type graft_<family>),
model.safetensors (backbone + encoder + projector), the pre/post processors with the suite's
normalisation stats, README.md. Staged in a temp folder beside OUT and renamed: whole or absent.

The cell is rebuilt from its record: the same profile and protocol (so the same release, suite
split and normaliser, each checked against the record), the encoder built as the cell built it,
and the projector file the cell kept (checksummed)."""

from __future__ import annotations

import copy
import dataclasses
import json
import shutil
import tempfile
from pathlib import Path

from bench.export.card import write_card
from bench.export.locate import ExportError, find_record, why_not_exportable
from bench.grid.protocol import Protocol, get_profile
from bench.results.record import Record, checkpoint_revision
from bench.results.store import ResultStore
from bench.cell.projectors import ProjectorFileError, load_projector

BUNDLED_VLM = "smolvlm"  # a local VLM folder (the tiny SmolVLM) travels under this name


def export_cell(results_dir: str | Path, cell_id: str, out: str | Path, *,
                note: str | None = None, progress: bool = False, lend_from=None) -> Path:
    """Export graft cell `cell_id` of `results_dir` to the new folder `out`; returns `out`.
    `lend_from`: a Workspace of the same world whose loaded suites and releases are reused."""
    from bench.outputs import export_refusal

    out = Path(out)
    problem = export_refusal("--out", out)
    if problem:
        raise ExportError(problem)
    if not out.parent.is_dir():
        raise ExportError(f"--out {out}: its parent folder {out.parent} does not exist")
    record = find_record(results_dir, cell_id)
    why = why_not_exportable(record)
    if why is not None:  # said before anything is rebuilt or written
        raise ExportError(f"cell {cell_id} cannot be exported: {why}")
    try:
        projector = load_projector(results_dir, cell_id, record.training.projector_file,
                                   record.training.projector_sha256)
    except ProjectorFileError as err:
        raise ExportError(str(err)) from None
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    staging.chmod(0o755)  # mkdtemp makes it private; a checkpoint folder is for sharing
    try:
        backbone, encoder, suite = rebuild_cell(results_dir, record, progress, lend_from)
        policy_type = write_folder(staging, record, backbone, encoder, projector)
        write_card(staging, record, Path(results_dir), note, policy_type,
                   getattr(backbone, "rename_map", None) or {},
                   (suite.repo_id or f"local/{suite.name}", str(suite.root or "DATASET_ROOT")))
        check_relocatable(staging)
        share_with_group(staging)
        staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out


def rebuild_cell(results_dir: str | Path, record: Record, progress: bool = False,
                 lend_from=None):
    """(backbone adapter normalising the cell's suite, encoder) as the cell had them, checked
    against the record's checkpoint revision and normaliser fingerprint."""
    from bench.resources.workspace import Workspace

    measured = record.measured
    try:
        profile = get_profile(measured.profile)
    except ValueError as err:
        raise ExportError(f"cell {record.cell_id}: {err}") from None
    if measured.camera_map or measured.dataset:
        raise ExportError(f"cell {record.cell_id} was measured on a --policy/--dataset of your "
                          "own: exporting those is not supported yet; export a registry cell")
    fields = dict(measured.protocol)
    fields["lora_targets"] = tuple(fields.get("lora_targets", ()))
    protocol = Protocol(**fields)
    if protocol.hash != measured.protocol_hash:
        raise ExportError(f"cell {record.cell_id}: its protocol does not hash to its "
                          f"protocol_hash ({protocol.hash} vs {measured.protocol_hash})")
    profile = dataclasses.replace(profile, protocol=protocol)
    store = ResultStore(results_dir)
    same_world = (lend_from is not None and lend_from.profile.data_source == profile.data_source
                  and lend_from.profile.source == profile.source
                  and lend_from.profile.protocol.replace(steps=0) == protocol.replace(steps=0))
    ws = (dataclasses.replace(lend_from, profile=profile, store=store) if same_world
          else Workspace(profile, store, progress=progress))
    backbone = ws.backbone(record.backbone, record.suite, record.release)
    now = checkpoint_revision(ws.checkpoint(record.backbone, record.suite, record.release))
    if measured.revision and now != measured.revision:
        raise ExportError(f"cell {record.cell_id} was measured on weights {measured.revision}, "
                          f"this machine has {now}: fetch that revision or run the cell again")
    found = backbone.normalizer_fingerprint()
    if measured.normalizer_fingerprint not in (None, found):
        raise ExportError(f"cell {record.cell_id}'s normaliser was "
                          f"{measured.normalizer_fingerprint}, rebuilt it is {found}: "
                          "run the cell again here")
    return backbone, ws.encoder(record.encoder), ws.suite(record.suite)


def graft_config(record: Record, backbone, encoder, staging: Path):
    """The plugin's config for this graft: the base policy's own config values + the graft."""
    from lerobot.configs import PreTrainedConfig

    from lerobot_policy_graft import GRAFT_TYPES

    base = backbone.policy.config
    values = {f.name: copy.deepcopy(getattr(base, f.name))
              for f in dataclasses.fields(base) if f.init}
    values.update(push_to_hub=False, repo_id=None, pretrained_path=None)
    vlm = values.get("vlm_model_name")
    if vlm and Path(vlm).is_dir():  # a local VLM folder (tiny): bundled, named relatively
        shutil.copytree(vlm, staging / BUNDLED_VLM)
        values["vlm_model_name"] = BUNDLED_VLM
    spec = encoder.spec
    tiny_arch = getattr(backbone, "tiny_arch", None)
    values.update(
        encoder_name=record.encoder, encoder_timm_name=spec.timm_name,
        encoder_timm_kwargs=json.dumps(encoder.timm_kwargs, sort_keys=True),
        encoder_input_size=int(encoder.input_size), encoder_mean=list(spec.mean),
        encoder_std=list(spec.std), encoder_num_prefix_tokens=spec.num_prefix_tokens,
        encoder_layout=spec.layout, encoder_channels=int(encoder.channels),
        graft_grid=[int(x) for x in record.measured.grid], train_scope="projector",
        graft_cell=record.cell_id,
        tiny_arch=json.dumps(tiny_arch.to_dict(), sort_keys=True) if tiny_arch else "")
    config_cls = PreTrainedConfig.get_choice_class(GRAFT_TYPES[base.type])
    return config_cls(**values)


def write_folder(staging: Path, record: Record, backbone, encoder, projector: dict) -> str:
    """config.json, model.safetensors, processors into `staging`; the policy type."""
    from lerobot.policies.factory import get_policy_class

    from lerobot_policy_graft.modeling_graft import assets_at
    from lerobot_policy_graft.processor_graft import bundle_tokenizer

    config = graft_config(record, backbone, encoder, staging)
    with assets_at(staging):
        policy = get_policy_class(config.type)(config)
    state = dict(backbone.policy.state_dict())
    state.update({f"graft.encoder.{k}": v for k, v in encoder.state_dict().items()})
    state.update({f"graft.projector.{k}": v for k, v in projector.items()})
    policy.load_state_dict(state, strict=True)
    policy.save_pretrained(staging)
    for pipeline, bundle in ((backbone.preprocessor, True), (backbone.postprocessor, False)):
        clone = copy.copy(pipeline)
        clone.steps = list(pipeline.steps)  # the harness's pipeline stays as it was
        if bundle:
            bundle_tokenizer(clone)
        clone.save_pretrained(staging)
    return config.type


def share_with_group(folder: Path) -> None:
    """Folders 0755, files 0644, as LeRobot's own saves under the usual umask: copied cache
    files (the bundled VLM: atomic temp files) came 0600 in 0700 folders, which a teammate
    reading a shared copy could not open."""
    for path in [folder, *folder.rglob("*")]:
        if path.is_dir():
            path.chmod(0o755)
        elif path.is_file():
            path.chmod(0o644)


def check_relocatable(folder: Path) -> None:
    """No absolute path in any JSON of the folder: it must load after a copy elsewhere."""
    def walk(value, where):
        if isinstance(value, dict):
            for k, v in value.items():
                walk(v, f"{where}.{k}")
        elif isinstance(value, list):
            for i, v in enumerate(value):
                walk(v, f"{where}[{i}]")
        elif isinstance(value, str) and value.startswith(("/", "~")) and Path(value).exists():
            raise ExportError(f"{where} holds the absolute path {value}: the folder would not "
                              "load elsewhere (a bug of bench.export: report it)")

    for path in sorted(folder.rglob("*.json")):
        if BUNDLED_VLM in path.relative_to(folder).parts[:1]:
            continue
        walk(json.loads(path.read_text()), path.relative_to(folder).as_posix())

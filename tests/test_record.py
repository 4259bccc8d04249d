"""The typed record (bench.results.record, bench.results.parts): JSON in and out, old records,
the freshness rule, and that no record key is spelled outside the record modules."""

from __future__ import annotations

import ast
import json
from dataclasses import fields

import pytest

from bench.results.current import RunConditions, differences, is_current
from bench.results.parts import SPACES
from bench.results.record import (
    Failure, Identity, MeasuredUnder, Record, RunInfo, Scores, Training, from_snapshot,
    snapshot_json,
)
from bench.results.store import ResultStore, load_results
from ondisk.paths import REPO_ROOT
from tests.factories import make_failed, make_record

RECORD_MODULES = {"bench/results/record.py", "bench/results/parts.py"}
# Dicts that share a name with a record key but are not records: the keys each may spell.
NOT_RECORDS = {
    "bench/grid/gridfile.py": {"camera_map", "profile", "protocol"},  # a grid file's own fields
    "bench/grid/protocol.py": {"protocol"},  # a profile's own dict
    "bench/grid/user_specs.py": {"camera_map"},  # a --policy's config
    "bench/resources/releases.py": {"backbone", "loss_curve", "revision", "release"},  # release metadata, checkpoint id
    "bench/analysis/hierarchy.py": {"release", "seed"},  # the variance budget's level names
    "bench/analysis/budget.py": {"backbone", "suite", "encoder", "error", "release", "seed"},  # its summary
    "bench/grid/pinned_release.py": {"backbone"},  # a pinned release's metadata
    "bench/resources/user_policies.py": {"revision"},  # a --policy's checkpoint id
    "bench/resources/features.py": {"encoder", "grid", "suite"},  # the feature store's manifest
    "bench/resources/feature_file.py": {"grid"},  # the feature file's manifest
    "bench/sim/rollout.py": {"per_task"},  # the rollouts' own summary
    "bench/analysis/sequential_records.py": {"rollouts", "tasks"},  # the rollouts' spec, the plan's keys
    "bench/suites/synthetic.py": {"seed"},  # a suite's generation parameters
    "bench/analysis/transfer.py": {"suite"},  # a rank-transfer comparison row
    "bench/report/sections.py": {"suite"},  # the same row, rendered
    "bench/analysis/family_scale.py": {"suite"},  # a suite's family-or-scale verdict row
    # The robustness tier's own formats: its summary rows, its perturbation's JSON, the feature
    # store key of perturbed windows, and the robustness record's `base` (what it rescored).
    "bench/analysis/robustness.py": {"backbone", "suite", "n_windows"},
    "bench/report/robustness.py": {"suite"},
    "bench/robust/perturbations.py": {"kind", "seed"},
    "bench/robust/rescore.py": {"suite"},
    "bench/results/robust.py": {"protocol_hash", "created", "projector_sha256", "kind"},
}


def record_keys() -> set[str]:
    """Every key a stored record has: the parts' field names, the score spaces, the checkpoint's
    keys the record module adds."""
    parts = (Identity, MeasuredUnder, Scores, Training, RunInfo)
    return ({f.name for p in parts for f in fields(p)} | set(SPACES)
            | {"normalizer", "normalizer_fingerprint", "revision", "status", "error"})


def key_spellings(tree: ast.AST, keys: set[str]) -> list[tuple[int, str]]:
    """(line, key) of every record key used as a literal: x["key"], x.get("key"), {"key": ...}."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant):
            out.append((node.lineno, node.slice.value))
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr in ("get", "pop", "setdefault") and node.args
              and isinstance(node.args[0], ast.Constant)):
            out.append((node.lineno, node.args[0].value))
        elif isinstance(node, ast.Dict):
            out += [(k.lineno, k.value) for k in node.keys if isinstance(k, ast.Constant)]
    return [(line, key) for line, key in out if key in keys]


def spellings_by_module() -> dict[str, list[tuple[int, str]]]:
    keys, found = record_keys(), {}
    for path in sorted((REPO_ROOT / "bench").rglob("*.py")):
        rel = path.relative_to(REPO_ROOT).as_posix()
        if rel not in RECORD_MODULES:
            hits = key_spellings(ast.parse(path.read_text()), keys)
            if hits:
                found[rel] = hits
    return found


def test_no_record_key_is_spelled_outside_the_record_modules():
    """Readers use the typed parts (record.encoder, record.scores.mse_in()); the record has no
    mapping view left for a spelled key to go through."""
    found = spellings_by_module()
    offenders = {m: hits for m, hits in found.items()
                 if not {k for _, k in hits} <= NOT_RECORDS.get(m, set())}
    assert not offenders, offenders
    assert not hasattr(Record, "__getitem__") and not hasattr(Record, "get")


def test_the_count_sees_a_spelled_key():
    tree = ast.parse('r["mse"]["normalized"]; r.get("cell_id"); {"seed": 0}; r["other"]')
    assert sorted(k for _, k in key_spellings(tree, record_keys())) == [
        "cell_id", "mse", "normalized", "seed"]


def test_json_round_trip_is_exact(tmp_path):
    record = make_record(kind="pooling", encoder="pixels", variant="half", feature_dtype="fp16",
                         grid=[4, 4], rollouts={"skipped": "no image"})
    data = json.loads(json.dumps(record.to_json()))
    assert Record.from_json(data).to_json() == data
    ResultStore(tmp_path).write(record)
    assert load_results(tmp_path).records[0].to_json() == data


def test_unset_optional_fields_are_absent_others_always_written():
    data = make_record().to_json()
    assert "feature_dtype" not in data and "rollouts" not in data and "dataset" not in data
    assert data["features_mode"] is None and data["probe_loss"] is None


def test_a_record_from_before_the_typing_still_loads():
    """An older record lacks the fields added since (lora_params, checkpoint, grid, ...) and may
    hold keys this code does not know: it loads, and writes back what it read."""
    data = json.loads(json.dumps(make_record().to_json()))
    for key in ("lora_params", "checkpoint", "grid", "features_mode", "projector_from",
                "encoder_weights", "window_task", "per_horizon"):
        data.pop(key)
    data["retired_field"] = 1
    record = Record.from_json(data)
    assert record.training.lora_params == 0 and record.measured.revision is None
    assert record.to_json()["retired_field"] == 1


@pytest.mark.parametrize("change, problem", [
    ({"schema": 2}, "schema 2"), ({"cell_id": "x"}, "is not what its fields say"),
    ({"n_windows": 3}, "per_window.normalized has 24 values"),
])
def test_an_invalid_record_names_its_problem(change, problem):
    with pytest.raises(ValueError, match=problem):
        Record.from_json({**make_record().to_json(), **change})


def test_a_failure_carries_its_protocol_hash():
    failure = make_failed()
    assert failure.to_json()["protocol_hash"] and Failure.from_json(failure.to_json()) == failure


def test_snapshot_keeps_what_a_baseline_compares():
    record = make_record()
    cell = from_snapshot(json.loads(json.dumps(snapshot_json(record))))
    assert cell.scores.per_window == record.scores.per_window
    assert cell.measured.protocol_hash == record.measured.protocol_hash


def test_is_current_checks_only_what_the_run_states():
    record = make_record(checkpoint={"revision": "r1", "normalizer_fingerprint": "n1"},
                         features_mode="cache")
    assert is_current(record, RunConditions(protocol_hash=record.measured.protocol_hash))
    assert differences(record, RunConditions(revision="r2")) == ["revision r1 (this run r2)"]
    assert differences(record, RunConditions(feature_dtype="fp16")) == [
        "feature_dtype float32 (this run fp16)"]  # stored before the option: float32
    assert not is_current(record, RunConditions(rollouts=5))
    assert is_current(record.replace(rollouts={"spec": {"episodes_per_task": 5}}),
                      RunConditions(rollouts=5))

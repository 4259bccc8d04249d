"""The study's constants against a record's protocol: known answers on hand-made dicts, records."""

from __future__ import annotations

import dataclasses

from bench.progress import QUIET
import pytest

from bench.grid.protocol import PAPER_ENCODERS, Protocol
from tests.factories import make_record
from bench.report.study import (
    DISAGREES, MAPPED_FIELDS, NOT_RECORDED, OUR_CODE, OURS, STUDY, STUDY_CONSTANTS, as_text,
    compare_protocol, compare_records, observed_from_records,
)

STUDY_PROTOCOL = Protocol(steps=2000, lr=1e-4, batch_size=8).to_dict()
# What paper-profile records on a GPU would say, for every constant the study gives.
STUDY_OBSERVED = {
    "optimiser": "AdamW", "precision": "bf16",
    "preprocessing: input px": {"siglip": 224, "dinov2_s": 224},
    "pooling grid": {"smolvla": "8x8", "pi05": "16x16"},
    "held-out windows": {"spatial": 3000, "object": 3457},  # 6,457 in total
    "seeds": {"smolvla x spatial": 2, "pi05 x spatial": 3},
    "checkpoints": {"smolvla": "lerobot/smolvla_base", "pi05": "lerobot/pi05_base"},
}


def statuses(rows) -> dict[str, str]:
    return {r.constant: r.status for r in rows}


def test_a_protocol_matching_the_study_disagrees_nowhere():
    rows = compare_protocol(STUDY_PROTOCOL, STUDY_OBSERVED)
    assert [r for r in rows if r.status == DISAGREES] == []
    by = statuses(rows)
    assert all(by[c.name] == STUDY for c in STUDY_CONSTANTS)
    assert by["warmup_steps"] == OURS and by["split_seed"] == OURS


def test_a_changed_lr_disagrees_exactly_once():
    for observed in (STUDY_OBSERVED, None):
        rows = compare_protocol(dict(STUDY_PROTOCOL, lr=3e-4), observed)
        (row,) = [r for r in rows if r.status == DISAGREES]
        assert (row.constant, row.field, row.study, row.ours) == (
            "learning rate", "lr", "0.0001", "0.0003")


def test_protocol_alone_leaves_the_other_constants_not_recorded():
    by = statuses(compare_protocol(STUDY_PROTOCOL))
    assert by["projector steps"] == by["effective batch"] == STUDY
    assert by["precision"] == by["held-out windows"] == by["checkpoints"] == NOT_RECORDED


def test_every_protocol_field_is_listed_once_and_mapped_fields_exist():
    fields = [f.name for f in dataclasses.fields(Protocol)]
    assert MAPPED_FIELDS <= set(fields), "a study constant maps to a field Protocol lacks"
    listed = [r.field for r in compare_protocol(STUDY_PROTOCOL) if r.field]
    assert sorted(listed) == sorted(fields)


def test_comparison_reads_the_dict_it_is_given():
    # Any protocol dict, even one with fields Protocol does not have (yet): listed as ours.
    rows = compare_protocol({"steps": 1000, "lr": 1e-4, "batch_size": 8, "ema": 0.99})
    by = statuses(rows)
    assert by["projector steps"] == DISAGREES and by["ema"] == OURS


@pytest.mark.parametrize("windows, agrees", [
    ({"spatial": 6457}, True), ({"spatial": 3000, "object": 3457}, True),
    ({"smolvla x spatial": 3000, "smolvla x object": 3457, "pi05 x spatial": 10,
      "pi05 x object": 5}, True),
    ({"spatial": 150, "object": 148}, False),
])
def test_held_out_windows_per_suite_or_in_total(windows, agrees):
    by = statuses(compare_protocol(STUDY_PROTOCOL, dict(STUDY_OBSERVED,
                                                        **{"held-out windows": windows})))
    assert by["held-out windows"] == (STUDY if agrees else DISAGREES)


def test_seed_counts_and_pooling_and_input_sizes():
    changed = dict(STUDY_OBSERVED, seeds={"smolvla x spatial": 1},
                   **{"pooling grid": {"smolvla": "4x4"},
                      "preprocessing: input px": {"siglip": 224, "fastvit": 256}})
    by = statuses(compare_protocol(STUDY_PROTOCOL, changed))
    assert by["seeds"] == by["pooling grid"] == by["preprocessing: input px"] == DISAGREES


def test_observed_from_paper_records_on_gpu():
    records = [make_record(backbone=b, encoder=e, seed=s, profile="paper", device="cuda:0",
                           grid=grid, checkpoint=f"lerobot/{b}_base",
                           protocol=STUDY_PROTOCOL, protocol_hash="study")
               for b, grid in (("smolvla", [8, 8]), ("pi05", [16, 16]))
               for e in ("siglip", "dinov2_s") for s in (0, 1)]
    observed = observed_from_records(records)
    assert observed["pooling grid"] == {"pi05": "16x16", "smolvla": "8x8"}
    assert observed["held-out windows"] == {"spatial": 24}
    assert observed["seeds"] == {"pi05 x spatial": 2, "smolvla x spatial": 2}
    (rows,) = compare_records(records).values()
    by = statuses(rows)
    assert by["held-out windows"] == DISAGREES  # 24 fabricated windows, not 6,457
    assert [r.constant for r in rows if r.status == DISAGREES] == ["held-out windows"]


def test_libero_releases_are_not_the_study_base_checkpoints():
    observed = dict(STUDY_OBSERVED, checkpoints={"pi05_libero": "lerobot/pi05_libero"},
                    **{"pooling grid": {"pi05_libero": "16x16"}})
    by = statuses(compare_protocol(STUDY_PROTOCOL, observed))
    assert by["checkpoints"] == DISAGREES and by["pooling grid"] == STUDY
    records = [make_record(backbone="pi05_libero", encoder="siglip", profile="paper",
                           checkpoint={"repo_id": "lerobot/pi05_libero", "revision": "abc"})]
    assert observed_from_records(records)["checkpoints"] == {"pi05_libero": "lerobot/pi05_libero"}


def test_observed_from_tiny_records_disagrees_where_the_tiny_world_differs():
    records = [make_record(encoder=e, seed=s, grid=[4, 4], encoder_input_size=64)
               for e in ("siglip", "blind")
               for s in (0, 1)]
    (rows,) = compare_records(records).values()
    by = statuses(rows)
    for constant in ("projector steps", "learning rate", "precision", "pooling grid",
                     "preprocessing: input px", "checkpoints"):
        assert by[constant] == DISAGREES, constant
    assert by["optimiser"] == by["seeds"] == STUDY


def test_as_text():
    assert as_text(1e-4) == "0.0001" and as_text(range(2, 4)) == "2-3"
    assert as_text({"smolvla": "8x8", "pi05": "16x16"}) == "smolvla: 8x8, pi05: 16x16"
    assert as_text(None) == "not recorded" and as_text(["q_proj", "v_proj"]) == "q_proj, v_proj"


def _fitted_weight(optimiser_steps: int, weight_decay: float):
    """One weight w fitted by bench.loops.train.fit on loss w * 1 (gradient 1 every step), and the
    same weight after AdamW with fit's schedule, one optimiser step per batch."""
    from types import SimpleNamespace

    import torch

    from bench.loops.train import FitConfig, fit, lr_factor

    cfg = FitConfig(steps=optimiser_steps, batch_size=2, lr=0.1, weight_decay=weight_decay,
                    warmup_steps=1, grad_clip=0.0, log_every=1)
    weight = torch.nn.Parameter(torch.ones(1))
    toy = SimpleNamespace(
        info=SimpleNamespace(chunk_size=1, max_action_dim=1), policy=torch.nn.Linear(1, 1),
        preprocess=lambda raw: raw, sample_time=lambda n, g: torch.rand(n, generator=g),
        loss=lambda batch, noise, time: (weight * batch["x"]).expand(len(time)))
    fit(toy, [weight], torch.arange(8), lambda rows: ({"x": torch.tensor(1.0)}, None), cfg,
        seed=0, progress=QUIET)
    reference = torch.nn.Parameter(torch.ones(1))
    optimiser = torch.optim.AdamW([reference], lr=cfg.lr, weight_decay=weight_decay)
    for step in range(optimiser_steps):
        optimiser.param_groups[0]["lr"] = cfg.lr * lr_factor(step, cfg)
        optimiser.zero_grad()
        reference.sum().backward()
        optimiser.step()
    return weight.detach(), reference.detach()


def test_our_code_facts_match_the_code():
    """OUR_CODE states facts no record carries; these fail when the code moves under them: the
    optimiser is AdamW (decoupled weight decay: one step of lr 0.1, decay 0.5 from w = 1 gives
    0.85, where Adam's L2 decay would give 0.9), stepped once per batch (no accumulation)."""
    from encoders.registry import get_spec

    one_step, _ = _fitted_weight(1, weight_decay=0.5)
    assert OUR_CODE["optimiser"] == "AdamW" and abs(one_step.item() - 0.85) < 1e-6
    fitted, adamw = _fitted_weight(3, weight_decay=0.0)
    assert OUR_CODE["gradient accumulation"] is False and fitted.equal(adamw)
    assert set(OUR_CODE["input sizes"]) == set(PAPER_ENCODERS)
    for name, size in OUR_CODE["input sizes"].items():
        assert get_spec(name).input_size == size, f"update OUR_CODE['input sizes'][{name!r}]"

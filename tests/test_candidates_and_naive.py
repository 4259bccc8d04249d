"""Agreement on the candidates (bench.analysis.candidates) and the naive baselines a proxy must
beat (bench.screen.proxies' ENCODER entries, bench.analysis.tiers' paired difference): known
answers on planted grafts."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bench.analysis.agreement import Interval, kendall_tau_b
from bench.analysis.candidates import candidate_items
from bench.analysis.rollouts import rollout_agreement
from bench.analysis.tiers import ALL, CANDIDATES, tier_agreement
from bench.grid.kinds import NATIVE
from tests.factories import make_record
from tests.test_analysis_rollouts import rollouts

# Seven grafts, best first (normalised MSE 0.05 .. 0.11).
ENCODERS = [f"timm:model_{i}" for i in range(7)]
LEVELS = {e: 0.05 + 0.01 * i for i, e in enumerate(ENCODERS)}
GOOD = {e: -level for e, level in LEVELS.items()}  # a score in the graft's order


def grafts():
    return [make_record(encoder=e, level=level, seed=s, noise=0.002)
            for e, level in LEVELS.items() for s in (0, 1)]


def _planted(order: list[int]) -> dict[str, float]:
    """Scores that rank ENCODERS[order[0]] first, then order[1], ..."""
    return {ENCODERS[i]: float(len(order) - rank) for rank, i in enumerate(order)}


def test_a_perfect_naive_baseline_keeps_a_noisy_proxy_from_being_recommended():
    """Parameter count orders the grafts exactly, the proxy swaps two pairs: its tau-b minus the
    baseline's is negative in every replicate, so it is not recommended."""
    noisy = _planted([1, 0, 2, 3, 5, 4, 6])  # tau-b (21 - 2*2) / 21
    baselines = {"param_count": GOOD, "resolution": _planted([6, 0, 5, 1, 4, 2, 3])}
    out = tier_agreement(noisy, grafts(), "smolvla", "spatial", "logme", n_resamples=200,
                         baselines=baselines)
    assert out.point.tau_b == pytest.approx(17 / 21)
    assert out.best_naive == "param_count" and out.naive_tau_b["param_count"] == pytest.approx(1.0)
    assert out.naive_gap == pytest.approx(17 / 21 - 1)
    gap = out.naive_gap_interval
    assert isinstance(gap, Interval) and gap.high < 0
    assert not out.recommended


def test_an_exact_proxy_beats_an_unrelated_parameter_count_and_is_recommended():
    unrelated = _planted([3, 6, 0, 5, 2, 4, 1])
    out = tier_agreement(GOOD, grafts(), "smolvla", "spatial", "ridge", n_resamples=200,
                         baselines={"param_count": unrelated})
    assert out.point.tau_b == pytest.approx(1.0)
    expected = 1.0 - kendall_tau_b([unrelated[e] for e in ENCODERS], [GOOD[e] for e in ENCODERS])
    assert out.naive_gap == pytest.approx(expected) and expected > 0.5
    assert out.naive_gap_interval.low > 0 and out.recommended


def test_the_difference_is_drawn_on_the_same_replicates_as_the_tier():
    """Grafts noisy enough that their order moves from draw to draw, a baseline equal to the
    proxy: the two differ by exactly 0 only where both meet the same draw of the graft."""
    noisy = _planted([1, 0, 2, 3, 5, 4, 6])
    records = [make_record(encoder=e, level=level, seed=s, noise=0.05)
               for e, level in LEVELS.items() for s in (0, 1)]
    out = tier_agreement(noisy, records, "smolvla", "spatial", "logme", n_resamples=100,
                         baselines={"param_count": noisy})
    assert out.intervals["tau_b"].high - out.intervals["tau_b"].low > 0.2  # the order moves
    ci = out.naive_gap_interval
    assert (ci.low, ci.high, ci.undefined) == (0.0, 0.0, 0) and not out.recommended


# The studies/real world in small: the wheels' trained encoders beside random twins, known-answer
# encoders and the tiny world's random-init stand-ins, all in the tiny profile's records.
TRAINED = ["dinov2_s_focus", "effnet_lite0", "effnet_lite0_s4", "effnet_lite1", "effnet_lite2"]
REFERENCES = ["blind", "dinov2_s", "effnet_lite0_random", "pixels", "pixels_p16", "siglip"]


def test_the_candidates_are_the_registrys_trained_encoders_and_the_native_policy():
    records = [make_record(encoder=e) for e in TRAINED + REFERENCES]
    records.append(make_record(kind=NATIVE))
    assert candidate_items(records) == frozenset(TRAINED + ["native"])
    hub = [r.replace(profile="paper") for r in records]  # timm's encoders built from the hub
    assert candidate_items(hub) == frozenset(TRAINED + ["native", "dinov2_s", "siglip"])


def test_agreement_on_the_candidates_reads_those_items_only():
    """A proxy exact on the five trained encoders and reversed on the six others: tau-b 1 on
    the candidates (5 items, the others left out saying why), below 0.5 over all 11."""
    levels = {e: 0.05 + 0.01 * i for i, e in enumerate(TRAINED + REFERENCES)}
    records = [make_record(encoder=e, level=level, noise=0.002) for e, level in levels.items()]
    scores = {e: -levels[e] for e in TRAINED} | {e: levels[e] for e in REFERENCES}
    items = candidate_items(records)
    every = tier_agreement(scores, records, "smolvla", "spatial", "logme", n_resamples=50)
    mine = tier_agreement(scores, records, "smolvla", "spatial", "logme", n_resamples=50,
                          items=items, item_set=CANDIDATES)
    assert (every.item_set, len(every.encoders)) == (ALL, 11) and every.point.tau_b < 0.5
    assert mine.encoders == TRAINED and mine.point.tau_b == pytest.approx(1.0)
    assert mine.left_out["pixels"] == "not among the candidates"
    assert mine.intervals["tau_b"].low == pytest.approx(1.0)


def test_the_closed_loop_agreement_on_the_candidates():
    """Offline order = success order among the trained items, a failing reference (pixels) rolled
    out beside them reads well offline and fails: the candidates' tau-b is 1, all items' less."""
    planted = {"effnet_lite0": (0.10, 0.9), "effnet_lite1": (0.12, 0.6),
               "effnet_lite2": (0.14, 0.3), "pixels": (0.08, 0.0)}
    records = [make_record(encoder=e, seed=s, level=level, noise=0.002, rollouts=rollouts(rate))
               for e, (level, rate) in planted.items() for s in (0, 1)]
    out = rollout_agreement(records, "smolvla", "spatial", n_resamples=100,
                            candidates=candidate_items(records))
    assert out.candidates == ["effnet_lite0", "effnet_lite1", "effnet_lite2"]
    assert out.candidate_agreement["tau_b"] == pytest.approx(1.0)
    assert out.agreement["tau_b"] == pytest.approx(0.0)  # pixels first offline, last in success
    assert out.candidate_interval_of("tau_b")[0] > 0
    full = out.measures[0]  # the offline measures' table, on the candidates' rows as well
    assert full.on_candidates.labels == out.candidates
    assert full.on_candidates.value["tau_b"] == pytest.approx(1.0)


class _Patchify(torch.nn.Module):
    """A 4x4-stride convolution 3 -> 8 channels fed 16 px: 8 * 4 * 4 outputs of 3 * 16 inputs."""

    input_size = 16

    def __init__(self) -> None:
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 8, kernel_size=4, stride=4)

    def forward(self, images):
        return self.conv(images)


def test_the_encoders_cost_is_counted_from_the_module_built():
    from encoders import build_encoder
    from encoders.cost import encoder_cost

    cost = encoder_cost(_Patchify())
    assert cost.params == 8 * 3 * 16 + 8 and cost.input_size == 16
    assert cost.flops == 2 * (8 * 4 * 4) * (3 * 4 * 4)  # 2 FLOPs per multiply-add
    blind = encoder_cost(build_encoder("pixels", "tiny"))
    assert (blind.params, blind.flops, blind.input_size) == (0, 0, 64)
    assert np.isclose(encoder_cost(build_encoder("effnet_lite0", "tiny")).params, 3_371_008)


def test_the_bootstraps_pair_count_is_scipys_tau_b():
    """naive_gap counts pairs itself (speed); it must be Kendall tau-b, ties and all."""
    from bench.analysis.agreement import Undefined, pairwise_tau_b

    rng = np.random.default_rng(0)
    for _ in range(200):
        n = int(rng.integers(2, 12))
        x, y = rng.integers(0, 4, n).astype(float), np.round(rng.normal(size=n), 1)
        mine, scipys = pairwise_tau_b(x, y), kendall_tau_b(x, y)
        if isinstance(scipys, Undefined):
            assert mine == scipys
        else:
            assert mine == pytest.approx(scipys, abs=1e-12)

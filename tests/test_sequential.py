"""The sequential closed-loop design (bench.analysis.sequential): known answers by hand, then
simulated Bernoulli studies (no simulator): its error rate stays under its nominal level and it
reaches the uniform allocation's resolution with fewer episodes; resumable from stored rows.
~5 s in all on 2 shared cores (numpy: the replicate studies advance together)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.analysis.sequential import (
    SequentialDesign, adjacent_open, advance, declare, discordant_wins, initial_state,
    items_to_run, log_evidence, next_round, order_by_success, study_state, study_summary,
)


def test_discordant_wins_and_evidence_by_hand():
    success = np.array([[1, 1, 0, 1], [0, 1, 1, 0], [1, 1, 1, 1]], bool)
    ran = np.array([[1, 1, 1, 1], [1, 1, 1, 1], [1, 1, 0, 0]], bool)  # item 2 ran units 0, 1
    wins = discordant_wins(success, ran)
    np.testing.assert_array_equal(wins, [[0, 2, 0], [1, 0, 0], [0, 1, 0]])
    # w wins of n discordant, Beta(1, 1): M = B(1 + w, 1 + n - w) * 2**n
    evidence = log_evidence(np.array([[0, 5], [0, 0]]))
    assert evidence[0, 1] == pytest.approx(math.log(32 / 6)) == evidence[1, 0]
    assert log_evidence(np.array([[0, 1], [1, 0]]))[0, 1] == pytest.approx(math.log(4 / 6))
    assert log_evidence(np.zeros((2, 2), int))[0, 1] == 0.0


def test_a_declaration_takes_the_side_of_the_wins_and_stays():
    design = SequentialDesign(alpha=0.05, budget=100, units_per_round=1)
    threshold = design.log_threshold(2)  # log(1 / 0.05): one pair
    assert threshold == pytest.approx(math.log(20))
    wins = np.array([[0, 0], [8, 0]])  # 8 of 8 to item 1: M = 256 / 9 > 20
    declared = declare(np.zeros((2, 2), np.int8), wins, threshold)
    np.testing.assert_array_equal(declared, [[0, -1], [1, 0]])
    later = declare(declared, np.zeros((2, 2), int), threshold)  # no evidence now: kept
    np.testing.assert_array_equal(later, declared)
    assert SequentialDesign(0.05, 100, 1).log_threshold(4) == pytest.approx(math.log(6 / 0.05))


def test_racing_runs_only_the_items_with_an_open_neighbour():
    state = initial_state(4)._replace(successes=np.array([9, 1, 5, 4]),
                                      episodes=np.array([10, 10, 10, 10]), rounds=3)
    np.testing.assert_array_equal(order_by_success(state.successes, state.episodes), [0, 2, 3, 1])
    declared = np.zeros((4, 4), np.int8)
    declared[0, 2], declared[2, 0] = 1, -1  # 0 over 2 declared; 2-3 and 3-1 open
    state = state._replace(declared=declared)
    np.testing.assert_array_equal(adjacent_open(np.array([0, 2, 3, 1]), declared),
                                  [False, True, True])
    design = SequentialDesign(alpha=0.1, budget=1000, units_per_round=2)
    np.testing.assert_array_equal(items_to_run(state, design), [False, True, True, True])
    uniform = SequentialDesign(alpha=0.1, budget=1000, units_per_round=2, allocation="uniform")
    assert items_to_run(state, uniform).all()
    assert items_to_run(state, SequentialDesign(0.1, 46, 2)).sum() == 3  # 40 + 3 x 2 = 46
    assert not items_to_run(state, SequentialDesign(0.1, 45, 2)).any()  # over the budget


def simulate(p, design: SequentialDesign, replicates: int, seed: int, shared: float = 0.5):
    """Replicate studies of Bernoulli items at once; each unit has a common difficulty that an
    item follows with probability `shared` (paired outcomes, as init states make them).
    Returns the final states and the episodes each replicate spent when its last round ended."""
    rng, p = np.random.default_rng(seed), np.asarray(p, float)
    k, u = len(p), design.units_per_round
    state = initial_state(k, (replicates,))
    while True:
        run = items_to_run(state, design)
        if not run.any():
            return state
        common = rng.random((replicates, 1, u))
        own = rng.random((replicates, k, u))
        draw = np.where(rng.random((replicates, k, u)) < shared, common, own)
        ran = np.broadcast_to(run[..., None], draw.shape)
        state = advance(state, draw < p[:, None], ran, design)


def wrong_declarations(state, p) -> np.ndarray:
    """(R,) bool: a replicate declared some i over j with p_i <= p_j."""
    p = np.asarray(p)
    wrong = (state.declared == 1) & (p[:, None] <= p[None, :])
    return wrong.any(axis=(-1, -2))


def test_over_many_replicates_the_error_rate_stays_under_its_nominal_level():
    # Two true ties and one close pair: every tie declared is an error.
    p = [0.6, 0.6, 0.7, 0.7]
    design = SequentialDesign(alpha=0.1, budget=4 * 4 * 150, units_per_round=4)
    state = simulate(p, design, replicates=600, seed=1)
    rate = wrong_declarations(state, p).mean()
    assert rate <= design.alpha
    # A lone tie at a loose level: the test is anytime-valid, not merely conservative.
    tie = SequentialDesign(alpha=0.3, budget=2 * 4 * 200, units_per_round=4)
    lone = simulate([0.5, 0.5], tie, replicates=1000, seed=2)
    assert 0 < wrong_declarations(lone, [0.5, 0.5]).mean() <= tie.alpha


def test_racing_reaches_the_uniform_resolution_with_fewer_episodes():
    p = [0.1, 0.45, 0.7, 0.9]  # every adjacent pair separable
    race = SequentialDesign(alpha=0.05, budget=100_000, units_per_round=4)
    uniform = SequentialDesign(alpha=0.05, budget=100_000, units_per_round=4,
                               allocation="uniform")
    raced = simulate(p, race, replicates=300, seed=3)
    flat = simulate(p, uniform, replicates=300, seed=3)
    for state in (raced, flat):  # both resolve every adjacent pair, in the true order
        order = order_by_success(state.successes, state.episodes)
        assert not adjacent_open(order, state.declared).any()
        assert (order == [3, 2, 1, 0]).mean() >= 0.95
    spent_race, spent_flat = raced.episodes.sum(-1), flat.episodes.sum(-1)
    assert spent_race.mean() < 0.85 * spent_flat.mean()
    assert (spent_race <= spent_flat).mean() >= 0.7


def test_a_study_resumes_from_its_stored_rows_and_records_its_rule():
    design = SequentialDesign(alpha=0.1, budget=60, units_per_round=2)
    items = ["native", "lite0", "lite1"]
    truth = {"native": [1, 1], "lite0": [0, 0], "lite1": [1, 0]}  # per unit, every round

    def played(plan):
        return [{"item": item, "round": plan["round"], "unit": u, "success": truth[item][u]}
                for item, units in plan["run"].items() for u in units]

    rows = played(next_round(design, items, []))
    assert len(rows) == 6  # round 0 runs every item
    first = next(iter(next_round(design, items, rows)["run"]))
    rows.append({"item": first, "round": 1, "unit": 0, "success": truth[first][0]})
    partial = next_round(design, items, rows)  # killed after one episode of round 1
    assert partial["round"] == 1 and partial["run"][first] == [1]
    assert sum(map(len, partial["run"].values())) == 5
    while (plan := next_round(design, items, rows))["stop"] is None:
        rows += played(plan)
    state, in_flight = study_state(design, items, rows)
    summary = study_summary(design, items, state)
    assert not in_flight and plan["stop"] == "resolved"
    # Pairs with one discordant unit a round: 2**n / (n + 1) first reaches 3 / 0.1 at n = 9.
    assert state.rounds == 9 and summary["spent"] == len(rows) == 54 <= design.budget
    assert summary["order"] == ["native", "lite1", "lite0"]
    assert [pair["declared"] for pair in summary["pairs"]] == [1, 1]
    assert summary["design"]["rule"] == design.rule and summary["design"]["alpha"] == 0.1
    stray = {"item": "lite0", "round": plan["round"], "unit": 0, "success": 0}
    with pytest.raises(ValueError, match="did not run"):
        study_state(design, items, rows + [stray])


def test_the_records_cli_orders_cells_by_their_stored_episodes(tmp_path, capsys):
    import json

    from bench.analysis.sequential_records import main
    from bench.results.store import ResultStore
    from tests.factories import make_record

    def rollouts(wins_per_task: int) -> dict:  # 2 tasks x 12 episodes; the first ones succeed
        return {"spec": {"tasks": [0, 1]}, "episodes": [
            {"task": t, "episode": e, "init_state": 49 - e, "success": e < wins_per_task,
             "steps": 50} for t in (0, 1) for e in range(12)]}

    store = ResultStore(tmp_path)
    for encoder, wins in (("pixels", 12), ("blind", 0)):
        store.write(make_record(encoder=encoder, rollouts=rollouts(wins)))
    with pytest.raises(ValueError, match="round 4 holds episodes"):  # rolled out uniformly
        main([str(tmp_path), "--budget", "1000", "--alpha", "0.1"])
    assert main([str(tmp_path), "--budget", "1000", "--alpha", "0.1", "--unplanned",
                 "ignore"]) == 0
    out = json.loads(capsys.readouterr().out)
    # Both units of a round are discordant: 2**n / (n + 1) first reaches 10 at n = 8.
    assert out["order"][0].endswith("pixels-seed0") and out["rounds"] == 4
    assert out["pairs"][0]["declared"] == 1 and out["next"]["stop"] == "resolved"
    assert out["spent"] == 16 and out["design"]["units_per_round"] == 2

"""A pre-declared sequential design for a closed-loop study: episodes go where the order is open.

Items (policies) are rolled out in rounds. Every item that runs in a round meets the same
`units_per_round` units (task, init state, env seed), so two items' outcomes on a unit are
paired. After each round the items are ordered by success rate; an adjacent pair is resolved
once an anytime-valid test says which of the two succeeds more often, and the next round runs
only the items with an unresolved neighbour (racing). The study stops when every adjacent pair
is resolved, or when the next round would spend more than the study's episode budget.

The test of a pair (i, j): on the units both ran, only the discordant ones (one succeeded, the
other failed) carry information on p_i - p_j. Given discordance, i wins with probability
q = p(i only) / (p(i only) + p(j only)), and q > 1/2 exactly when p_i > p_j. With w wins of i
in n discordant units, the beta-binomial mixture of likelihood ratios against q = 1/2,

    M_n = B(a + w, a + n - w) / B(a, a) * 2**n,

is a nonnegative martingale when q = 1/2 (whichever rounds the pair was run in, since that
choice depends on the past only); by Ville's inequality it ever reaches 1 / alpha_pair with
probability at most alpha_pair, and when q < 1/2 reaching it on i's side is rarer still. The
order of a pair is declared (for good) the first time M_n >= 1 / alpha_pair, with
alpha_pair = alpha / (K choose 2): the chance that ANY declared order of a K-item study is
wrong is then at most alpha, whichever pairs end up adjacent. Assumed: the units are
exchangeable draws (init states and seeds of the tasks in every round alike), so the success
rates compared are over the suite's init-state distribution.

Every function is pure numpy/scipy; arrays may carry leading batch axes (`...`, e.g.
replicate studies), so one call advances many simulated studies at once.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import NamedTuple

import numpy as np
from scipy.special import betaln, comb

ALLOCATIONS = ("racing", "uniform")


@dataclass(frozen=True)
class SequentialDesign:
    """The stop rule of a study, declared before its first episode and stored with it."""

    alpha: float  # bound on the chance that any declared order is wrong
    budget: int  # episodes the whole study may spend (all items, all rounds)
    units_per_round: int  # episodes per running item in a round (e.g. one per task)
    prior: float = 1.0  # a of the Beta(a, a) mixture over q: 1 is uniform
    allocation: str = "racing"  # "uniform": every item every round (the comparator)
    rule: str = "paired beta-binomial mixture, Bonferroni over all pairs, racing, v1"

    def __post_init__(self) -> None:
        if not 0 < self.alpha < 1:
            raise ValueError(f"alpha={self.alpha}: give a level in (0, 1), e.g. 0.05")
        if self.budget < 1 or self.units_per_round < 1 or self.prior <= 0:
            raise ValueError(f"budget={self.budget}, units_per_round={self.units_per_round}, "
                             f"prior={self.prior}: give budget and units >= 1, prior > 0")
        if self.allocation not in ALLOCATIONS:
            raise ValueError(f"allocation={self.allocation!r}; choose one of {ALLOCATIONS}")

    def log_threshold(self, items: int) -> float:
        """log(1 / alpha_pair): a pair is declared once its log evidence reaches this."""
        return float(np.log(comb(max(items, 2), 2) / self.alpha))

    def as_dict(self) -> dict:
        return asdict(self)


class RaceState(NamedTuple):
    """What the study knows after its rounds so far (K items)."""

    wins: np.ndarray  # (..., K, K) int: units where i succeeded and j failed, both ran
    declared: np.ndarray  # (..., K, K) int8: +1 i over j, -1 j over i, 0 open; antisymmetric
    successes: np.ndarray  # (..., K) int
    episodes: np.ndarray  # (..., K) int
    rounds: int  # rounds played


def initial_state(items: int, batch: tuple = ()) -> RaceState:
    """A study of `items` items before its first round (`batch`: leading axes)."""
    return RaceState(np.zeros((*batch, items, items), np.int64),
                     np.zeros((*batch, items, items), np.int8),
                     np.zeros((*batch, items), np.int64), np.zeros((*batch, items), np.int64), 0)


def discordant_wins(success: np.ndarray, ran: np.ndarray) -> np.ndarray:
    """(..., K, U) bool outcomes and whether each item ran each unit -> (..., K, K) int: the
    units both i and j ran where i succeeded and j failed."""
    mine = success & ran
    lost = ~success & ran
    return np.einsum("...iu,...ju->...ij", mine.astype(np.int64), lost.astype(np.int64))


def log_evidence(wins: np.ndarray, prior: float = 1.0) -> np.ndarray:
    """(..., K, K) wins -> (..., K, K) float: log M_n of each pair against q = 1/2 (symmetric;
    0 on the diagonal and where no unit was discordant)."""
    n = wins + np.swapaxes(wins, -1, -2)
    return betaln(prior + wins, prior + n - wins) - betaln(prior, prior) + n * np.log(2.0)


def declare(declared: np.ndarray, wins: np.ndarray, log_threshold: float,
            prior: float = 1.0) -> np.ndarray:
    """(..., K, K) declarations after new evidence: a pair whose evidence reaches the threshold
    is declared in the direction of its wins; a declared pair stays declared."""
    reached = log_evidence(wins, prior) >= log_threshold
    side = np.sign(wins - np.swapaxes(wins, -1, -2)).astype(np.int8)
    return np.where((declared == 0) & reached, side, declared).astype(np.int8)


def order_by_success(successes: np.ndarray, episodes: np.ndarray) -> np.ndarray:
    """(..., K) counts -> (..., K) item indices, highest success rate first (ties: lower
    index first; an item without episodes counts as rate 0)."""
    rate = np.divide(successes, episodes, out=np.zeros(successes.shape, float),
                     where=episodes > 0)
    return np.argsort(-rate, axis=-1, kind="stable")


def adjacent_open(order: np.ndarray, declared: np.ndarray) -> np.ndarray:
    """(..., K) order and (..., K, K) declarations -> (..., K-1) bool: is the pair of ranks
    (r, r+1) still undeclared."""
    rows = np.take_along_axis(declared, order[..., :-1, None], axis=-2)  # (..., K-1, K)
    return np.take_along_axis(rows, order[..., 1:, None], axis=-1)[..., 0] == 0


def items_to_run(state: RaceState, design: SequentialDesign) -> np.ndarray:
    """(..., K) bool: the items the next round runs; none once every adjacent pair is declared
    or the round would overspend the budget. Racing runs the items with an open neighbour;
    uniform runs all of them while any adjacent pair is open."""
    order = order_by_success(state.successes, state.episodes)
    open_pairs = adjacent_open(order, state.declared)
    if design.allocation == "uniform":
        run = np.broadcast_to(open_pairs.any(-1, keepdims=True), order.shape)
    else:
        at_rank = np.zeros(order.shape, bool)
        at_rank[..., :-1] |= open_pairs
        at_rank[..., 1:] |= open_pairs
        run = np.zeros(order.shape, bool)
        np.put_along_axis(run, order, at_rank, axis=-1)
    cost = run.sum(-1) * design.units_per_round
    affordable = state.episodes.sum(-1) + cost <= design.budget
    return run & np.asarray(affordable)[..., None]


def advance(state: RaceState, success: np.ndarray, ran: np.ndarray,
            design: SequentialDesign) -> RaceState:
    """The state after one round: `success`, `ran` (..., K, U) bool (U = units_per_round; an
    item that did not run has ran all False)."""
    wins = state.wins + discordant_wins(success, ran)
    threshold = design.log_threshold(wins.shape[-1])
    return RaceState(wins, declare(state.declared, wins, threshold, design.prior),
                     state.successes + (success & ran).sum(-1), state.episodes + ran.sum(-1),
                     state.rounds + 1)


def study_state(design: SequentialDesign, items: list[str], rows: list[dict],
                unplanned: str = "refuse"):
    """Replay a study's stored per-episode rows ({"item", "round", "unit", "success"}) round by
    round: (RaceState after its complete rounds, {item: units stored} of a round in flight).
    Rows the design would not have run (another design's, or another order's) are refused, or
    left out with unplanned="ignore" (what the design would have spent on rows run uniformly)."""
    index, units = {name: k for k, name in enumerate(items)}, design.units_per_round
    rounds = 1 + max((int(r["round"]) for r in rows), default=-1)
    success = np.zeros((rounds, len(items), units), bool)
    ran = np.zeros_like(success)
    for row in rows:
        if row["item"] not in index or not 0 <= int(row["unit"]) < units:
            raise ValueError(f"row {row}: item not in {items} or unit not in 0..{units - 1}")
        at = (int(row["round"]), index[row["item"]], int(row["unit"]))
        if ran[at]:
            raise ValueError(f"row {row}: its item, round and unit are stored twice")
        ran[at], success[at] = True, bool(row["success"])
    state = initial_state(len(items))
    for r in range(rounds):
        chosen = items_to_run(state, design)
        extra = ran[r].any(-1) & ~chosen
        if unplanned == "ignore":
            ran[r][extra] = False
        elif extra.any():
            raise ValueError(f"round {r} holds episodes of {np.asarray(items)[extra].tolist()}, "
                             "which this design did not run: rows of another study or design")
        if not chosen.any():  # the study had stopped here
            break
        if not ran[r][chosen].all():  # the last round, interrupted: resume it
            if r != rounds - 1 and unplanned != "ignore":
                raise ValueError(f"round {r} is incomplete but round {rounds - 1} exists")
            return state, {items[k]: np.flatnonzero(ran[r, k]).tolist()
                           for k in np.flatnonzero(chosen)}
        state = advance(state, success[r], ran[r], design)
    return state, {}


def next_round(design: SequentialDesign, items: list[str], rows: list[dict],
               unplanned: str = "refuse") -> dict:
    """What the study runs next, from its stored rows: {"round", "run": {item: [units still
    to run]}, "stop": None, "resolved" or "budget"} (`unplanned`: study_state's)."""
    state, in_flight = study_state(design, items, rows, unplanned)
    if in_flight:
        units = range(design.units_per_round)
        return {"round": state.rounds, "stop": None,
                "run": {k: [u for u in units if u not in done] for k, done in in_flight.items()}}
    run = items_to_run(state, design)
    if run.any():
        return {"round": state.rounds, "stop": None,
                "run": {items[k]: list(range(design.units_per_round)) for k in np.flatnonzero(run)}}
    order = order_by_success(state.successes, state.episodes)
    stop = "budget" if adjacent_open(order, state.declared).any() else "resolved"
    return {"round": state.rounds, "stop": stop, "run": {}}


def study_summary(design: SequentialDesign, items: list[str], state: RaceState) -> dict:
    """The order with each adjacent pair's evidence, episodes per item, the design: what a
    report or a rerun reads."""
    order = order_by_success(state.successes, state.episodes)
    evidence, threshold = log_evidence(state.wins, design.prior), design.log_threshold(len(items))
    pairs = [{"upper": items[i], "lower": items[j], "declared": int(state.declared[i, j]),
              "discordant": int(state.wins[i, j] + state.wins[j, i]),
              "upper_wins": int(state.wins[i, j]), "log_evidence": float(evidence[i, j])}
             for i, j in zip(order[:-1], order[1:])]
    return {"design": design.as_dict(), "log_threshold": threshold, "rounds": state.rounds,
            "order": [items[k] for k in order], "pairs": pairs,
            "successes": {items[k]: int(state.successes[k]) for k in order},
            "episodes": {items[k]: int(state.episodes[k]) for k in order},
            "spent": int(state.episodes.sum())}

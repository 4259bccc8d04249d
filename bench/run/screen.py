"""The screen tier: zero-training proxies of one (encoder, backbone, suite), from stored features.

Inputs, per window (a frame): per camera the stored pooled features averaged over the token grid,
(cameras x channels), and the robot state (8); targets: the action chunk from that frame,
normalised by the backbone's own normaliser step (the one its graft is scored in), real action
dims only, flattened to (chunk x 7). Padded chunk steps keep LeRobot's repeated last action as
target (the graft's score masks them; the screen does not). Fitted on the training episodes'
frames (what the graft trains on), scored on the SAME held-out windows as the grafts.

Each supervised proxy is computed for [state] and [state, features]; the gain of the features
(LogME: evidence with minus without; ridge and k-NN: MSE without minus with) is the proxy's score,
higher is better. k-NN weighs the state and each camera's block equally in its distance
(block_weights): unweighted, hundreds of feature columns drown the 8 state columns. The label-free norm entropy is over the tokens of all cameras' grids (the
backbone's native grid, as stored), per held-out window, averaged.
Memory: LogME and ridge read chunked `Moments`; k-NN keeps the (N_train, D) training inputs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from bench.analysis.agreement import Measure, Undefined, is_defined
from bench.analysis.screening import (Moments, knn_heldout, logme_moments, norm_entropy,
                                      ridge_heldout)
from bench.results.screen import ScreenScores  # noqa: F401  (re-exported: the screen's output)
from bench.results.screen import ScreenSelection
from bench.suites.windows import action_chunks

FOLDS = 5  # episode folds of the training episodes that choose the ridge penalty and the k
CHUNK = 2048  # windows read at a time
SUPERVISED = ("logme", "ridge", "knn")
INPUT_SETS = ("state", "state+features")


@dataclass
class _Inputs:
    """What one pass over a set of windows yields (train: with folds and kept arrays)."""

    moments: dict[str, list[Moments]]  # input set -> per fold (held out: one)
    arrays: dict[str, list[np.ndarray]]  # input set -> chunks of inputs (for k-NN)
    targets: list[np.ndarray]
    folds: list[np.ndarray]
    norms: list[np.ndarray]


def window_inputs(views: dict, suite, frames: torch.Tensor, normalize_actions, chunk_size: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(state (B, S), features (B, cameras*C), targets (B, chunk*7), token norms (B, cameras*T))
    of windows starting at `frames` (B,); views: {camera: view[frames] -> (B, T, C)}."""
    grids = [views[k][frames].float() for k in sorted(views)]
    features = torch.cat([g.mean(dim=1) for g in grids], dim=1).numpy()
    norms = torch.cat([g.norm(dim=2) for g in grids], dim=1).numpy()
    raw, _ = action_chunks(suite, frames, chunk_size)
    targets = normalize_actions(raw).float()[..., : raw.shape[-1]].reshape(len(frames), -1)
    return (suite.state[frames].float().numpy(), features, targets.numpy(), norms)


def _read(views, suite, frames: torch.Tensor, fold_of: np.ndarray, n_folds: int,
          normalize_actions, chunk_size: int, keep_arrays: bool) -> _Inputs:
    out = _Inputs({}, {s: [] for s in INPUT_SETS}, [], [], [])
    for start in range(0, len(frames), CHUNK):
        part = frames[start:start + CHUNK]
        state, features, targets, norms = window_inputs(views, suite, part, normalize_actions,
                                                        chunk_size)
        sets = {"state": state, "state+features": np.concatenate([state, features], axis=1)}
        fold = fold_of[start:start + CHUNK]
        for name, x in sets.items():
            per_fold = out.moments.setdefault(
                name, [Moments(x.shape[1], targets.shape[1]) for _ in range(n_folds)])
            for f in range(n_folds):
                inside = fold == f
                if inside.any():
                    per_fold[f].add(x[inside], targets[inside])
            if keep_arrays:
                out.arrays[name].append(x.astype(np.float32))
        out.targets.append(targets)
        out.folds.append(fold)
        out.norms.append(norms)
    return out


def episode_folds(suite, frames: torch.Tensor, episodes: list[int], n_folds: int) -> np.ndarray:
    """(N,) fold of each frame: its episode's position among the sorted `episodes` mod n_folds."""
    position = {e: i for i, e in enumerate(sorted(episodes))}
    return np.array([position[e] % n_folds for e in suite.episode_index[frames].tolist()])


def screen_features(views: dict, suite, split, normalize_actions, chunk_size: int,
                    names: tuple[str, str, str]) -> ScreenScores:
    """Screen one (encoder, backbone, suite) = `names` from its feature `views` (see module doc).

    split: .train_frames (N,), .train_episodes, .windows (M,); normalize_actions: (B, T, 7) raw
    -> normalised, the backbone's own. numpy's BLAS runs on torch's thread count: its own
    default (every CPU) made a serial run's LogME and ridge differ from an xdist worker's in the
    13th digit (CI, test_xdist). One knob for the screen's bits, as for a cell's."""
    with threadpool_limits(torch.get_num_threads(), user_api="blas"):
        return _screen(views, suite, split, normalize_actions, chunk_size, names)


def _screen(views: dict, suite, split, normalize_actions, chunk_size: int,
            names: tuple[str, str, str]) -> ScreenScores:
    t0 = time.perf_counter()
    out = ScreenScores(*names)
    n_folds = min(FOLDS, len(split.train_episodes))
    train_folds = episode_folds(suite, split.train_frames, split.train_episodes, n_folds)
    train = _read(views, suite, split.train_frames, train_folds, n_folds, normalize_actions,
                  chunk_size, keep_arrays=True)
    held = _read(views, suite, split.windows, np.zeros(len(split.windows), int), 1,
                 normalize_actions, chunk_size, keep_arrays=True)
    out.n_train, out.n_heldout = len(split.train_frames), len(split.windows)
    y_train, y_held = np.concatenate(train.targets), np.concatenate(held.targets)
    folds = np.concatenate(train.folds)
    state_dim = int(suite.state.shape[1])
    blocks = {"state": [state_dim],
              "state+features": [state_dim] + [int(views[k].shape[-1]) for k in sorted(views)]}
    for name in INPUT_SETS:
        out.dims[name] = train.moments[name][0].dim
        total = train.moments[name][0]
        for m in train.moments[name][1:]:
            total = total.plus(m)
        ridge, penalty = ridge_heldout(train.moments[name], held.moments[name][0])
        knn, k = knn_heldout(np.concatenate(train.arrays[name]), y_train, folds,
                             np.concatenate(held.arrays[name]), y_held,
                             weights=block_weights(blocks[name]))
        for proxy, value in (("logme", logme_moments(total)), ("ridge", ridge), ("knn", knn)):
            out.proxies.setdefault(proxy, {})[name] = value
        out.chosen[name] = {"ridge_penalty_ratio": penalty, "knn_k": k}
    for proxy in SUPERVISED:
        out.proxies[proxy]["gain"] = _gain(proxy, out.proxies[proxy])
    out.entropy = norm_entropy(np.concatenate(held.norms))
    out.seconds = time.perf_counter() - t0
    return out


def block_weights(sizes: list[int]) -> np.ndarray:
    """(sum(sizes),) k-NN distance factors: 1/sqrt(size) on each block's standardised columns,
    so the state and each camera weigh the same in the distance whatever their widths."""
    return np.concatenate([np.full(n, 1.0 / np.sqrt(n)) for n in sizes])


def _gain(proxy: str, values: dict[str, Measure]) -> Measure:
    """What the features add to the state, higher is better (undefined if either side is)."""
    without, with_ = values["state"], values["state+features"]
    for side, v in (("state", without), ("state+features", with_)):
        if not is_defined(v):
            return Undefined(f"{proxy} on [{side}] is {v}")
    return with_ - without if proxy == "logme" else without - with_


def screen_cell(ws, encoder: str, backbone: str, suite: str) -> ScreenScores:
    """The screen of `encoder` on `backbone` x `suite` from the workspace's feature store (built
    on first use), at the backbone's native token grid, normalised as the backbone does."""
    bb = ws.backbone(backbone, suite)
    views = ws.features(encoder, suite, tuple(bb.info.native_grid))
    return screen_features(views, ws.suite(suite), ws.split(suite), bb.normalize_actions,
                           bb.info.chunk_size, (encoder, backbone, suite))


SHORT = "short"  # --screen-by short: the short-graft tier (bench.grid.kinds SHORT_BY_VARIANT)
SCREEN_BY = SUPERVISED + ("entropy", SHORT)
DEFAULT_SCREEN_BY = "logme"
# Grafted whatever the screen says: the known-answer anchors (all the information in the images,
# none of it) every ranking of a --screen run is read against.
REFERENCES = ("pixels", "blind")


@dataclass(frozen=True)
class ScreenOptions:
    """A --screen run: graft the `keep` best encoders (None: all) by proxy `by`; `calibration`:
    the results dir of the calibration study whose agreement its report quotes (checked at
    start-up: bench.results.store.load_calibration)."""

    keep: int | None
    by: str = DEFAULT_SCREEN_BY
    calibration: str | None = None


@dataclass(frozen=True)
class ShortScores:
    """An encoder's short-graft score for `select_for_graft`: its normalised held-out MSE at the
    ranking fraction, mean over seeds (lower is better; the score is -MSE, higher is better)."""

    encoder: str
    mse: Measure

    def score(self, proxy: str) -> Measure:
        return -self.mse if is_defined(self.mse) else self.mse


def _shown(by: str, score: float) -> str:
    return f"MSE {-score:.4g}" if by == SHORT else f"{score:.4g}"


def parse_screen_keep(value: str) -> int | None:
    """`--screen-keep` as a count (None: "all"); ValueError with one line for anything else."""
    text = str(value).strip().lower()
    if text == "all":
        return None
    try:
        keep = int(text)
    except ValueError:
        keep = 0
    if keep < 1 or str(keep) != text.lstrip("+"):
        raise ValueError(f"--screen-keep {value}: give a whole number >= 1, or all")
    return keep


def parse_screen_by(value: str) -> str:
    """`--screen-by` checked against SCREEN_BY; ValueError with one line naming the valid ones."""
    if value not in SCREEN_BY:
        raise ValueError(f"--screen-by {value}: unknown proxy; choose one of "
                         f"{', '.join(SCREEN_BY)}")
    return value


def select_for_graft(backbone: str, suite: str, screens: list[ScreenScores],
                     options: ScreenOptions, references: tuple[str, ...] = (),
                     failed: dict[str, str] | None = None) -> ScreenSelection:
    """What to graft on `backbone` x `suite`: the `options.keep` best non-reference screens by
    `options.by` (anything with `.encoder` and `.score(by)`: ScreenScores, or ShortScores for
    --screen-by short; higher is better; ties: the encoder name), every reference, and each dropped
    encoder with why: its rank and score, its undefined score's reason, or its screen's failure
    (`failed`: {encoder: error}). keep > screened is allowed and noted."""
    by, keep = parse_screen_by(options.by), options.keep
    candidates = [s for s in screens if s.encoder not in references]
    defined = [(s.encoder, s.score(by)) for s in candidates if is_defined(s.score(by))]
    dropped = {s.encoder: f"{by} {s.score(by)}" for s in candidates if not is_defined(s.score(by))}
    dropped |= {e: f"its screen failed: {why}" for e, why in (failed or {}).items()
                if e not in references}
    ranked = sorted(defined, key=lambda item: (-item[1], item[0]))
    count = len(ranked) if keep is None else min(keep, len(ranked))
    note = (f"--screen-keep {keep} is more than the {len(ranked)} encoder(s) with a defined "
            f"{by} score: all are grafted" if keep is not None and keep > len(ranked) else None)
    for rank, (encoder, score) in enumerate(ranked[count:], start=count + 1):
        dropped[encoder] = (f"{by} rank {rank} of {len(ranked)} ({_shown(by, score)}), below "
                            f"the top {count}")
    kept = tuple(e for e, _ in ranked[:count])
    return ScreenSelection(backbone, suite, by, keep, kept, tuple(references), dropped, note,
                           options.calibration)

"""One screen: the proxies of the table (bench.screen.proxies) for one (encoder, backbone, suite),
from stored features, with no training.

Inputs, per window (a frame): per camera the stored pooled features averaged over the token grid,
(cameras x channels), and the robot state (8); targets: the action chunk from that frame,
normalised by the backbone's own normaliser step (the one its graft is scored in), real action
dims only, flattened to (chunk x 7). Padded chunk steps keep LeRobot's repeated last action as
target (the graft's score masks them; the screen does not). Fitted on the training episodes'
frames (what the graft trains on), scored on the SAME held-out windows as the grafts.

Each supervised proxy is computed for [state] and [state, features]; the gain of the features
(LogME: evidence with minus without; ridge and k-NN: MSE without minus with) is the proxy's score,
higher is better. k-NN weighs the state and each camera's block equally in its distance
(block_weights): unweighted, hundreds of feature columns drown the 8 state columns. The
label-free proxies (norm entropy) read the tokens of all cameras' grids (the backbone's native
grid, as stored) of the held-out windows.
Memory: the (N_train, D) training and (M, D) held-out inputs as float64, plus float64 centred
and standardised copies, the cheaper of a D x D or N x N matrix (bench.screen.spectral) and
k-NN's N x N distances (up to estimators.KNN_GRAM_MAX windows); stored grids are read CHUNK
windows at a time.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from bench.screen.proxies import (INPUT_SETS, FitInputs, label_free_proxies, naive_proxies,
                                  supervised_proxies)
from bench.screen.records import (GAIN, VALUE, ScreenConditions, ScreenFailure, ScreenRecord,
                                  ScreenScores, new_screen_record)
from bench.stats import Undefined
from encoders.cost import EncoderCost, encoder_cost
from bench.suites.windows import action_chunks

FOLDS = 5  # episode folds of the training episodes that choose the ridge penalty and the k
# Windows read at a time: each batch is read as float16, widened to float32 and pooled per
# window, so a small batch stays in the CPU's caches; 2,048 (the whole split) made ~180 MB of
# float32 per camera of a 1280 x 7 x 7 store and read at a third of the speed (same bits: every
# step is per window).
CHUNK = 64


@dataclass
class _Inputs:
    """What one pass over a set of windows yields: per input set the inputs (N, D) and the
    targets (N, C), float64 (the proxies' precision: widened once here instead of by each proxy;
    float32 values widen exactly, so the same numbers), and the token norms' chunks."""

    arrays: dict[str, np.ndarray]
    targets: np.ndarray
    norms: list[np.ndarray | None]


def window_inputs(views: dict, suite, frames: torch.Tensor, normalize_actions, chunk_size: int,
                  with_norms: bool = True
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """(state (B, S), features (B, cameras*C), targets (B, chunk*7), token norms (B, cameras*T),
    or None without `with_norms`) of windows starting at `frames` (B,); views: {camera:
    view[frames] -> (B, T, C)}."""
    grids = [views[k][frames].float() for k in sorted(views)]
    features = torch.cat([g.mean(dim=1) for g in grids], dim=1).numpy()
    norms = torch.cat([g.norm(dim=2) for g in grids], dim=1).numpy() if with_norms else None
    raw, _ = action_chunks(suite, frames, chunk_size)
    targets = normalize_actions(raw).float()[..., : raw.shape[-1]].reshape(len(frames), -1)
    return (suite.state[frames].float().numpy(), features, targets.numpy(), norms)


def _read(views, suite, frames: torch.Tensor, normalize_actions, chunk_size: int,
          with_norms: bool) -> _Inputs:
    inputs = targets = None
    norms = []
    for start in range(0, len(frames), CHUNK):
        part = frames[start:start + CHUNK]
        state, features, y, n = window_inputs(views, suite, part, normalize_actions, chunk_size,
                                              with_norms)
        if inputs is None:  # [state, features] written in place: no per-chunk concatenation
            inputs = np.empty((len(frames), state.shape[1] + features.shape[1]))
            targets = np.empty((len(frames), y.shape[1]))
        rows = slice(start, start + len(part))
        inputs[rows, :state.shape[1]], inputs[rows, state.shape[1]:] = state, features
        targets[rows] = y
        norms.append(n)
    width = int(suite.state.shape[1])
    return _Inputs({"state": np.ascontiguousarray(inputs[:, :width]), "state+features": inputs},
                   targets, norms)


def episode_folds(suite, frames: torch.Tensor, episodes: list[int], n_folds: int) -> np.ndarray:
    """(N,) fold of each frame: its episode's position among the sorted `episodes` mod n_folds."""
    position = {e: i for i, e in enumerate(sorted(episodes))}
    return np.array([position[e] % n_folds for e in suite.episode_index[frames].tolist()])


def screen_features(views: dict, suite, split, normalize_actions, chunk_size: int,
                    names: tuple[str, str, str], cost: EncoderCost | None = None
                    ) -> ScreenScores:
    """Screen one (encoder, backbone, suite) = `names` from its feature `views` (see module doc);
    `cost`: the encoder's (encoders.cost), what the naive baselines read (None: undefined).

    split: .train_frames (N,), .train_episodes, .windows (M,); normalize_actions: (B, T, 7) raw
    -> normalised, the backbone's own. numpy's BLAS runs on torch's thread count: its own
    default (every CPU) made a serial run's LogME and ridge differ from an xdist worker's in the
    13th digit (CI, test_xdist). One knob for the screen's bits, as for a cell's."""
    with threadpool_limits(torch.get_num_threads(), user_api="blas"):
        out = _screen(views, suite, split, normalize_actions, chunk_size, names)
    for proxy in naive_proxies():
        value = (proxy.compute(cost) if cost is not None
                 else Undefined("the encoder's cost was not measured"))
        out.keep_label_free(proxy.name, value, proxy.oriented(value), VALUE)
    return out


def _screen(views: dict, suite, split, normalize_actions, chunk_size: int,
            names: tuple[str, str, str]) -> ScreenScores:
    t0 = time.perf_counter()
    out = ScreenScores(*names)
    n_folds = min(FOLDS, len(split.train_episodes))
    train_folds = episode_folds(suite, split.train_frames, split.train_episodes, n_folds)
    # The label-free proxies read the held-out windows' token norms only.
    train = _read(views, suite, split.train_frames, normalize_actions, chunk_size,
                  with_norms=False)
    held = _read(views, suite, split.windows, normalize_actions, chunk_size, with_norms=True)
    out.n_train, out.n_heldout = len(split.train_frames), len(split.windows)
    state_dim = int(suite.state.shape[1])
    blocks = {"state": [state_dim],
              "state+features": [state_dim] + [int(views[k].shape[-1]) for k in sorted(views)]}
    for name in INPUT_SETS:
        out.dims[name] = int(train.arrays[name].shape[1])
        fit = FitInputs(train.arrays[name], train.targets, train_folds, held.arrays[name],
                        held.targets, block_weights(blocks[name]))
        out.chosen[name] = {}
        for proxy in supervised_proxies():
            value, chosen = proxy.compute(fit)
            out.proxies.setdefault(proxy.name, {})[name] = value
            if proxy.chooses:
                out.chosen[name][proxy.chooses] = chosen
    for proxy in supervised_proxies():
        out.proxies[proxy.name][GAIN] = proxy.gain(out.proxies[proxy.name])
    norms = np.concatenate(held.norms)
    for proxy in label_free_proxies():
        value = proxy.compute(norms)
        out.keep_label_free(proxy.name, value, proxy.oriented(value))
    out.seconds = time.perf_counter() - t0
    return out


def block_weights(sizes: list[int]) -> np.ndarray:
    """(sum(sizes),) k-NN distance factors: 1/sqrt(size) on each block's standardised columns,
    so the state and each camera weigh the same in the distance whatever their widths."""
    return np.concatenate([np.full(n, 1.0 / np.sqrt(n)) for n in sizes])


def measure_screen(ws, encoder: str, backbone: str, suite: str,
                   conditions: ScreenConditions) -> ScreenRecord | ScreenFailure:
    """The screen of `encoder` on `backbone` x `suite`: every proxy of the table from the
    workspace's feature store (built on first use: its time is the record's feature_seconds), at
    the backbone's native token grid, targets normalised as the backbone does. `conditions`:
    what it is measured under, kept in the record. A build or extraction error is a failure."""
    bb = ws.backbone(backbone, suite)
    start = time.perf_counter()
    try:
        views = ws.features(encoder, suite, tuple(bb.info.native_grid))
    except Exception as e:  # noqa: BLE001 - any encoder may fail; the screen goes on
        return ScreenFailure(backbone, suite, encoder, " ".join(f"{type(e).__name__}: {e}".split()))
    feature_seconds = time.perf_counter() - start
    cost = encoder_cost(ws.encoder(encoder))  # built for the features: one forward more
    # The stored file's own extraction time, whoever built it (the graft, an earlier screen).
    built = [v.stored.manifest.get("build_s") for v in views.values()]
    extraction = max((float(b) for b in built if b is not None), default=None)
    scores = screen_features(views, ws.suite(suite), ws.split(suite), bb.normalize_actions,
                             bb.info.chunk_size, (encoder, backbone, suite), cost)
    # What extracted them (bench.resources.features.PooledView.runtime; read here by name: bench.run
    # imports bench.results, which imports bench.screen).
    runtimes = {getattr(v, "runtime", None) for v in views.values()}
    return new_screen_record(scores, conditions, feature_seconds, extraction,
                             runtimes.pop() if len(runtimes) == 1 else None)

"""Packed grafts (bench.cell.packed): K graft cells trained through one frozen-backbone pass a step
are the cells they would be alone (loss curves and trained projectors), deterministic per
packing, each follows its own draws, and a cell that fails fails alone.

Tolerance: on CPU with one torch thread the packed cells measured bit-identical to their twins
(max abs diff 0.0 on curves and weights, both tiny backbones, K=2 and 3); TOL leaves room for the
rounding of batched kernels elsewhere (other thread counts, BLAS, devices)."""

from __future__ import annotations

import pytest
import torch

from bench.grid.cells import CellSpec
from bench.progress import QUIET
from bench.grid.protocol import TINY, with_overrides
from bench.cell.packed import PackedCell, PackedFeed, fit_packed, stack_raw, train_pack
from bench.cell.plan import CellContext
from bench.cell.runner import build_graft, cell_inputs, train_graft
from bench.loops.train import FitConfig, NonFiniteLoss, fit

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TOL = 1e-5  # absolute, on losses (~0.1-1) and projector weights (~0.01-0.1)
STEPS = 4


def config(ws, steps: int = STEPS) -> FitConfig:
    p = ws.profile.protocol
    return FitConfig(steps, p.batch_size, p.lr, p.weight_decay, 1, p.grad_clip, log_every=1)


def graft_cell(ws, spec: CellSpec, cfg: FitConfig | None = None, seed: int | None = None):
    """(backbone, PackedCell, projector) of a graft cell, built as the runner builds it: its
    projector initialised from the cell's seed; `seed` replaces the seed of its draws only."""
    backbone = ws.backbone(spec.backbone, spec.suite)
    split = ws.split(spec.suite)
    inputs = cell_inputs(spec, ws.profile.protocol, ws.suite(spec.suite), split, backbone,
                         torch.device("cpu"))
    graft = build_graft(spec, ws, backbone, inputs, CellContext())
    cell = PackedCell(spec.id, list(graft.projector.parameters()), graft.feed, split.train_frames,
                      inputs.train_batches(spec.spec.train_rule(spec.variant)),
                      spec.seed if seed is None else seed, cfg)
    return backbone, cell, graft.projector


def alone(ws, spec: CellSpec, cfg: FitConfig, seed: int | None = None):
    """(loss curve, trained projector state) of the cell trained by `fit`, unpacked."""
    backbone, cell, projector = graft_cell(ws, spec, cfg, seed)
    curve = fit(backbone, cell.params, cell.frames, cell.next_batch, cfg, cell.seed,
                feed=cell.feed, label=cell.label, progress=QUIET)
    return curve, projector.state_dict()


def packed(ws, specs, cfg: FitConfig, cfgs=None, seeds=None):
    """[(PackedFit, trained projector state)] of the cells trained in one pack."""
    cfgs, seeds = cfgs or [None] * len(specs), seeds or [None] * len(specs)
    built = [graft_cell(ws, s, c, seed) for s, c, seed in zip(specs, cfgs, seeds)]
    fits = fit_packed(built[0][0], [cell for _, cell, _ in built], cfg, progress=QUIET)
    return [(f, projector.state_dict()) for f, (_, _, projector) in zip(fits, built)]


def max_diff(curve_a, state_a, curve_b, state_b) -> float:
    """Largest absolute difference over the loss curves and the projectors' weights."""
    assert [s for s, _ in curve_a] == [s for s, _ in curve_b]  # the same steps logged
    curves = max(abs(a - b) for (_, a), (_, b) in zip(curve_a, curve_b))
    return max([curves] + [(state_a[k] - state_b[k]).abs().max().item() for k in state_a])


def cells(backbone: str) -> list[CellSpec]:
    """Three grafts of one backbone x suite: two encoders (channels 3 and 384), two seeds."""
    return [CellSpec("graft", backbone, "spatial", 0, "pixels"),
            CellSpec("graft", backbone, "spatial", 0, "dinov2_s"),
            CellSpec("graft", backbone, "spatial", 1, "pixels")]


@pytest.mark.parametrize("backbone", ["smolvla", "pi05"])
def test_packed_cells_equal_their_unpacked_twins(tiny_ws, backbone):
    """K=3, one of them a short graft's schedule (2 steps: it leaves the pack early)."""
    cfg, short = config(tiny_ws), config(tiny_ws, steps=2)
    specs, cfgs = cells(backbone), [None, None, short]
    twins = [alone(tiny_ws, s, c or cfg) for s, c in zip(specs, cfgs)]
    for (fitted, state), (curve, twin_state) in zip(packed(tiny_ws, specs, cfg, cfgs), twins):
        assert fitted.error is None
        assert len(fitted.curve) == len(curve)
        assert max_diff(fitted.curve, state, curve, twin_state) <= TOL, fitted.label


def test_the_same_packing_gives_the_same_bits(tiny_ws):
    specs, cfg = cells("smolvla")[:2], config(tiny_ws)
    first, second = packed(tiny_ws, specs, cfg), packed(tiny_ws, specs, cfg)
    for (fit_a, state_a), (fit_b, state_b) in zip(first, second):
        assert fit_a.curve == fit_b.curve
        assert all(torch.equal(state_a[k], state_b[k]) for k in state_a)


def test_a_packed_cell_follows_its_own_draws_known_answer(tiny_ws):
    """Swap the draws' seeds of two packed cells (projectors keep their own init): each cell is
    then the unpacked run of its projector on the OTHER seed's data order, noise and time, and
    far from its own twin. Packing is no pass-through: what a cell learns is its slice's."""
    a, b = cells("smolvla")[0], cells("smolvla")[2]  # pixels, seeds 0 and 1
    cfg = config(tiny_ws)
    swapped = packed(tiny_ws, [a, b], cfg, seeds=[b.seed, a.seed])
    (fit_a, state_a), (fit_b, state_b) = swapped
    on_other = alone(tiny_ws, a, cfg, seed=b.seed)
    assert max_diff(fit_a.curve, state_a, *on_other) <= TOL
    own = alone(tiny_ws, a, cfg)
    assert max_diff(fit_a.curve, state_a, *own) > 1000 * TOL


def test_a_non_finite_cell_fails_alone_and_named(tiny_ws):
    a, b = cells("smolvla")[:2]
    cfg = config(tiny_ws)
    backbone, good, good_projector = graft_cell(tiny_ws, a, cfg)
    _, bad, _ = graft_cell(tiny_ws, b, cfg)
    healthy = bad.next_batch

    def nan_features(frames):
        raw, features = healthy(frames)
        return raw, {k: torch.full_like(v, float("nan")) for k, v in features.items()}

    bad.next_batch = nan_features
    fit_good, fit_bad = fit_packed(backbone, [good, bad], cfg, progress=QUIET)
    assert isinstance(fit_bad.error, NonFiniteLoss) and fit_bad.curve == []
    assert b.id in str(fit_bad.error) and "at step 0 of 4" in str(fit_bad.error)
    assert fit_good.error is None
    assert max_diff(fit_good.curve, good_projector.state_dict(), *alone(tiny_ws, a, cfg)) <= TOL


def test_train_pack_gives_each_grid_cell_what_train_graft_gives_it_alone(tiny_workspace):
    """Grid cells (a short graft among them: 8 steps at 1/8 -> 1) built and trained as the
    runner does, packed: the same curve, probe losses, steps and projector as alone."""
    ws = tiny_workspace(with_overrides(TINY, steps=8))
    specs = cells("smolvla")[:2] + [CellSpec("short_graft", "smolvla", "spatial", 0, "pixels",
                                             "1_8")]
    contexts = [CellContext()] * len(specs)
    items = train_pack(specs, ws, contexts)
    assert [item.fitted.steps for item in items] == [8, 8, 1]
    for item, spec in zip(items, specs):
        backbone = ws.backbone(spec.backbone, spec.suite)
        inputs = cell_inputs(spec, ws.profile.protocol, ws.suite(spec.suite),
                             ws.split(spec.suite), backbone, torch.device("cpu"))
        graft = build_graft(spec, ws, backbone, inputs, CellContext())
        fitted = train_graft(spec, ws, backbone, graft, CellContext())
        assert item.error is None and item.fitted.steps == fitted.steps
        assert item.fitted.probe_losses == pytest.approx(fitted.probe_losses, abs=TOL)
        assert max_diff(item.fitted.curve, item.graft.projector.state_dict(),
                        fitted.curve, graft.projector.state_dict()) <= TOL
    with pytest.raises(ValueError, match="LoRA changes the backbone"):
        train_pack([CellSpec("lora", "smolvla", "spatial", 0, "pixels")], ws, contexts[:1])


class _Tagged:
    """A stand-in feed: tokens = its slice of the image + its tag, so routing can be read off."""

    def __init__(self, tag: float) -> None:
        self.tag, self.calls = tag, 0

    def __call__(self, image):
        self.calls += 1
        return image + self.tag

    def assert_consumed(self) -> None:
        pass


def test_packed_feed_routes_slice_k_to_feed_k_and_checks_the_batch():
    feeds = [_Tagged(100.0), _Tagged(200.0)]
    route = PackedFeed(feeds, [2, 3])
    out = route(torch.arange(5.0).reshape(5, 1))
    assert out.flatten().tolist() == [100.0, 101.0, 202.0, 203.0, 204.0]
    assert [f.calls for f in feeds] == [1, 1]
    with pytest.raises(RuntimeError, match="packed image batch 4"):
        route(torch.zeros(4, 1))


def test_stack_raw_joins_tensors_and_tasks_in_cell_order():
    one = {"action": torch.zeros(1, 2), "task": ["a"]}
    two = {"action": torch.ones(2, 2), "task": ["b", "c"]}
    stacked = stack_raw([one, two])
    assert stacked["action"][:, 0].tolist() == [0.0, 1.0, 1.0] and stacked["task"] == ["a", "b", "c"]
    with pytest.raises(ValueError, match="differ in keys"):
        stack_raw([one, {"task": ["x"]}])

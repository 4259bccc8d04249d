import torch

from bench.loops.evaluate import derangement, masked_sq_error, window_noise
from bench.loops.train import FitConfig, batch_order, lr_factor

CFG = FitConfig(steps=10, batch_size=4, lr=1e-3, weight_decay=0.0, warmup_steps=2,
                grad_clip=1.0, log_every=1)


def test_lr_schedule_warms_up_then_decays_to_zero():
    f = [lr_factor(s, CFG) for s in range(CFG.steps)]
    assert f[0] == 0.5 and f[1] == 1.0 and f[2] == 1.0
    assert all(a >= b for a, b in zip(f[2:], f[3:])) and f[-1] < 0.05


def test_batch_order_depends_on_the_seed_only():
    a, b, c = (list(batch_order(10, CFG, seed)) for seed in (0, 0, 1))
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert not all(torch.equal(x, y) for x, y in zip(a, c))
    assert len(a) == 10 and all(len(x) == 4 for x in a)
    # Within an epoch no frame repeats.
    assert len(set(torch.cat(a[:2]).tolist())) == 8


def test_window_noise_is_per_window_whatever_the_batch():
    ids = torch.tensor([5, 9, 11])
    full = window_noise(ids, 4, 6, seed=1)
    torch.testing.assert_close(full[1:], window_noise(ids[1:], 4, 6, seed=1))
    assert not torch.equal(full, window_noise(ids, 4, 6, seed=2))


def test_masked_error_ignores_padded_steps_known_answer():
    pred = torch.zeros(1, 3, 2)
    target = torch.tensor([[[1.0, 1.0], [2.0, 2.0], [100.0, 100.0]]])
    valid = torch.tensor([[True, True, False]])
    per_window, per_step = masked_sq_error(pred, target, valid)
    assert per_window.item() == (1.0 + 4.0) / 2
    assert per_step[0, 2] == 0


def test_derangement_has_no_fixed_point_and_is_fixed():
    d = derangement(7, seed=3)
    assert sorted(d.tolist()) == list(range(7)) and not (d == torch.arange(7)).any()
    assert torch.equal(d, derangement(7, seed=3))

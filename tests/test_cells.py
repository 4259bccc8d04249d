import pytest

from bench.grid.cells import CellSpec, control_cells, graft_cells
from bench.grid.protocol import TINY, TINY_FULL, get_profile, with_overrides


def test_ids_read_as_the_cell():
    assert CellSpec("graft", "smolvla", "spatial", 0, "dinov2_s").id == "smolvla-spatial-dinov2_s-seed0"
    assert CellSpec("native_wrapped", "pi05", "object", 1).id == "pi05-object-native_wrapped-seed1"
    assert CellSpec("pooling", "pi05", "object", 1, "pixels", "half").id == "pi05-object-pixels-pool_half-seed1"
    assert CellSpec("zero_image", "smolvla", "spatial", 0, None, "eval").id == "smolvla-spatial-native-zero_image_eval-seed0"
    assert CellSpec("graft", "smolvla", "spatial", 0, "timm:resnet18").id == "smolvla-spatial-timm_resnet18-seed0"


def test_references_point_at_the_right_cell():
    assert CellSpec("native_wrapped", "pi05", "object", 1).reference.id == "pi05-object-native-seed1"
    assert CellSpec("lora", "pi05", "object", 1, "pixels").reference.id == "pi05-object-pixels-seed1"
    assert CellSpec("shuffled_image", "pi05", "object", 1).reference.id == "pi05-object-native-seed1"
    assert CellSpec("graft", "pi05", "object", 1, "pixels").reference is None


@pytest.mark.parametrize("kwargs, match", [
    (dict(kind="graft", encoder=None), "needs an encoder"),
    (dict(kind="nonsense", encoder="x"), "unknown cell kind"),
    (dict(kind="pooling", encoder="x", variant="triple"), "pooling variant"),
    (dict(kind="zero_image", encoder=None, variant="train"), "not retrained"),
])
def test_bad_cells_are_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        CellSpec(backbone="smolvla", suite="spatial", seed=0, **kwargs)


@pytest.mark.parametrize("profile", [TINY, TINY_FULL], ids=["tiny", "tiny-full"])
def test_every_graft_cell_once_and_ids_unique(profile):
    grafts = graft_cells(profile)
    keys = [(c.backbone, c.suite, c.encoder, c.seed) for c in grafts]
    assert len(keys) == len(set(keys)) and all(c.kind == "graft" for c in grafts)
    assert {c.encoder for c in grafts} == set(profile.encoders)
    ids = [c.id for c in grafts + control_cells(profile)]
    assert len(ids) == len(set(ids))


def test_a_seed_more_adds_that_seeds_cells_and_nothing_else():
    grafts = {c.id for c in graft_cells(with_overrides(TINY, seeds=(0, 1)))}
    more = {c.id for c in graft_cells(with_overrides(TINY, seeds=(0, 1, 2)))}
    added = sorted(more - grafts)
    assert grafts < more and all(i.endswith("-seed2") for i in added)
    assert added == ["pi05-spatial-blind-seed2", "pi05-spatial-dinov2_s-seed2",
                     "pi05-spatial-pixels-seed2", "smolvla-spatial-blind-seed2",
                     "smolvla-spatial-dinov2_s-seed2", "smolvla-spatial-pixels-seed2"]


def test_default_grid_is_the_full_tiny_grid_cut_down_on_the_same_protocol():
    assert TINY.protocol == TINY_FULL.protocol and TINY.seeds == (0,) and TINY_FULL.seeds == (0, 1)
    full = {c.id for c in graft_cells(TINY_FULL) + control_cells(TINY_FULL)}
    small = [c.id for c in graft_cells(TINY) + control_cells(TINY)]
    assert set(small) < full and len(small) == 14 and len(full) == 136
    # --seeds 0,1: the earlier default's 28 cells, each still its tiny-full twin.
    two = [c.id for c in graft_cells(with_overrides(TINY, seeds=(0, 1)))
           + control_cells(with_overrides(TINY, seeds=(0, 1)))]
    assert set(two) < full and len(two) == 28 and set(small) < set(two)


def test_profile_overrides_and_errors():
    p = with_overrides(TINY, steps=7, seeds=(3,))
    assert p.protocol.steps == 7 and p.seeds == (3,) and p.protocol.hash != TINY.protocol.hash
    with pytest.raises(ValueError, match="unknown profile 'papr'"):
        get_profile("papr")


def test_a_screen_id_spells_the_encoder_as_its_grafts_cell_id_does():
    """Graft ids said effl_pretrained where screen ids said effl:pretrained."""
    from bench.grid.cells import ScreenCase

    for encoder in ("effl:pretrained", "timm:resnet18", "dinov2_s"):
        graft = CellSpec("graft", "smolvla", "spatial", 0, encoder).id
        assert ScreenCase("smolvla", "spatial", encoder).id + "-seed0" == graft


def test_staggered_sends_two_backbones_workers_round_the_encoders_in_opposite_directions():
    """Two workers, one backbone each: the second goes round the encoders backwards, so the two
    need the same encoder's features at most once, where their queues cross (features are shared
    per suite: the same order made one worker wait on the other's extraction, and a rotation
    made a worker whose half was cheap wait behind the other at every extraction); one worker, or
    one backbone: the order is kept."""
    from bench.grid.cells import staggered
    from bench.grid.kinds import GRAFT

    profile = with_overrides(TINY, backbones=("pi05", "smolvla"),
                             encoders=("dinov2_s", "siglip", "pixels", "blind"), seeds=(0, 1))
    cells = graft_cells(profile) + control_cells(profile)
    order = staggered(cells, workers=2)
    assert sorted(order, key=lambda c: c.id) == sorted(cells, key=lambda c: c.id)
    queues = {b: [c for c in order if c.backbone == b] for b in ("pi05", "smolvla")}
    rounds = {b: list(dict.fromkeys(c.encoder for c in q if c.encoder)) for b, q in queues.items()}
    assert rounds["smolvla"] == rounds["pi05"][::-1] and len(rounds["pi05"]) == 4
    grafts = {b: [c.encoder for c in q if c.kind == GRAFT] for b, q in queues.items()}
    assert grafts["pi05"] == ["dinov2_s", "dinov2_s", "siglip", "siglip", "pixels", "pixels",
                              "blind", "blind"]
    assert grafts["smolvla"] == grafts["pi05"][::-1]
    assert staggered(cells, workers=1) == cells
    one = [c for c in cells if c.backbone == "pi05"]
    assert staggered(one, workers=2) == one

"""`--pack-grafts K`: a run's graft cells trained K at a time through one frozen-backbone pass
(bench.cell.packed), each still its own record, claim, outcome and failure.

The cell service (bench.cell.service) owns the pack's way; this module measures and writes nothing
of its own. For a cell its plan measures, the service asks `can_lead` (the cell is packable,
bench.cell.packed.packable, and takes no graft's projector), then picks its mates among up to K-1
cells the session offers (`CellService.pack_candidates`: `candidates`, the selection in run
order, of its backbone x suite and tier, in the tiny world of its unit, `pack_units`; none the
screen dropped) that `may_join` (packable, of the lead's backbone, suite and release, not a
control that takes its graft's projector) and that it has not measured or failed yet; any seed:
each cell keeps its own seed, data order, noise and schedule in the pack, so a seed is no reason
to keep cells apart, and more cells fill a pack. Each mate is
claimed on the results store WITHOUT waiting: one another process holds is left to it; one with a
current record (its plan: resume) is left out and resumed by its own case, and so is one whose
record lacks only closed-loop episodes (its plan: extend, bench.cell.extend). The pack trains
(`train`: None when it cannot, then the lead is measured alone and the mates when reached), then
every cell is scored as it is alone (`scored`: runner.score_cell) and written by the service,
mates first, the lead last (like a runner's result), the claims held until all are written. A mate
that fails gets its failure record, and its case fails with that error when reached; the others go
on. The mates' records and outcomes go into the service's caches, so their cases take them
without measuring again and report "measured" (this process measured them; an xdist worker that
waited on a mate's claim resumes it: "resumed"). No mate found: the cell is measured alone, as
without the option.
"""

from __future__ import annotations

from typing import Sequence

from bench.grid.cells import CellSpec
from bench.progress import say
from bench.cell.plan import CellPlan, CellResult


def can_lead(lead: CellPlan) -> bool:
    """May `lead`'s cell lead a pack: packable, and taking no graft's trained projector."""
    from bench.cell.packed import packable

    return packable(lead.cell) is None and lead.context.reuse is None


def may_join(mate: CellSpec, lead: CellSpec, features_mode: str) -> bool:
    """May `mate` train in `lead`'s pack: packable, on the lead's backbone, suite and release,
    and not a control that takes its graft's projector."""
    from bench.cell.packed import packable

    return ((mate.backbone, mate.suite, mate.release) == (lead.backbone, lead.suite, lead.release)
            and packable(mate) is None and not _takes_graft_projector(mate, features_mode))


def pack_units(cells: Sequence[CellSpec], k: int, features_mode: str) -> dict[str, str]:
    """{cell id: its pack's unit} for the `cells` (run order) that may lead or join a pack: those
    of one backbone x suite x release and tier, K at a time. Where packs are scheduling units
    (the tiny world: bench.scheduling.cell_units) a unit goes to one worker and a lead's mates are
    drawn from its unit alone (`candidates`): drawn from the whole selection, every pack of a
    backbone had to stay on one worker, which idled the other core once one backbone was left."""
    from bench.cell.packed import packable

    filling: dict[tuple, list[str]] = {}
    units = {}
    for cell in cells:
        if packable(cell) is not None or _takes_graft_projector(cell, features_mode):
            continue
        key = (cell.backbone, cell.suite, cell.release, cell.spec.tier)
        if len(filling.get(key, ())) == k:
            del filling[key]
        members = filling.setdefault(key, [])
        members.append(cell.id)
        units[cell.id] = f"pack:{members[0]}"
    return units


def run_units(options, protocol_hash: str, per_cell: bool, selected: Sequence[CellSpec], store
              ) -> dict[str, str] | None:
    """`pack_units` of a run's `selected` cells less those with a current record in `store` (they
    resume; a failed cell, or one whose record another protocol made, is measured again, so it
    packs; with --rerun every cell) where packs are scheduling units (cells go out a unit at a
    time, `per_cell`: the tiny world, bench.scheduling.units_per_cell; --pack-grafts K > 1; no
    --executor), else None."""
    if options.pack_grafts == 1 or options.executor != "local" or not per_cell:
        return None
    from bench.results.current import RunConditions

    run = RunConditions(protocol_hash=protocol_hash, feature_dtype=options.feature_dtype,
                        rollouts=options.rollouts)
    measured = [c for c in selected if options.rerun or store.current(c.id, run) is None]
    return pack_units(measured, options.pack_grafts, options.features_mode)


def candidates(lead: CellSpec, selected: Sequence[CellSpec], units: dict[str, str] | None
               ) -> list[CellSpec]:
    """Of the `selected` cells (run order), those that may share `lead`'s pack: of its backbone x
    suite and tier and, where packs are scheduling units (`units`: `run_units`), of its unit;
    none when the lead is in no unit (stored when the units were drawn: its rerun goes alone)."""
    where = (lead.backbone, lead.suite, lead.spec.tier)
    alike = [c for c in selected if (c.backbone, c.suite, c.spec.tier) == where]
    if units is None:
        return alike
    if lead.id not in units:
        return []
    return [c for c in alike if units.get(c.id) == units[lead.id]]


def _takes_graft_projector(cell: CellSpec, features_mode: str) -> bool:
    """A control that trains exactly its graft's projector takes the graft's once measured
    (bench.cell.plan); packed beside or before its graft it would train a copy, and its record
    would lose `projector_from`: never a mate (as a lead, its plan is the unpacked one)."""
    from bench.grid.kinds import GRAFT
    from bench.cell.plan import shared_projector_key

    return cell.kind != GRAFT and shared_projector_key(cell, features_mode) is not None


def train(ws, plans: list[CellPlan]) -> list | None:
    """The pack of `plans` (the lead first) trained on `ws`: one item per plan (bench.cell.packed
    train_pack: its training, or its error), or None when the pack as a whole could not train
    (a graft that cannot be built, ...), saying so: the lead is then measured alone."""
    from bench.results.provenance import reset_peak_memory
    from bench.cell.packed import train_pack

    lead = plans[0].cell
    policy = ws.backbone(lead.backbone, lead.suite, lead.release).policy
    reset_peak_memory(next(policy.parameters()).device)
    try:
        return train_pack([p.cell for p in plans], ws, [p.context for p in plans],
                          label=f"{lead.backbone}-{lead.suite} pack")
    except Exception as e:  # not one cell's training: the mates, unclaimed, meet it alone
        say(ws.progress, f"the pack led by {lead.id} could not train ({type(e).__name__}: "
                         f"{e}); {lead.id} is measured alone, its mates when reached")
        return None


def scored(ws, plan: CellPlan, item) -> CellResult:
    """One packed cell scored as runner.measure does alone (its training's error raised here)."""
    from bench.cell.runner import score_cell

    if item.error is not None:
        raise item.error
    cell, graft = plan.cell, item.graft
    return score_cell(cell, ws, plan.context, ws.lend(cell.backbone, cell.suite, cell.release),
                      graft.inputs, graft, item.fitted, dict(item.timings),
                      spent=sum(item.timings.values()))

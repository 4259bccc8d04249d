"""`--pack-grafts K`: a run's graft cells trained K at a time through one frozen-backbone pass
(bench.cell.packed), each still its own record, claim, outcome and failure.

The cell service (bench.cell.service) calls `measure_packed` for a cell its plan measures. That cell
leads a pack when it is packable (bench.cell.packed.packable) and takes no graft's projector. Its
mates are up to K-1 cells the session offers (`CellService.pack_candidates`: the selection in run
order, of its backbone x suite and tier, none the screen dropped) that are packable, not yet
measured or failed by this service, and not a control that takes its graft's projector; any seed:
each cell keeps its own seed, data order, noise and schedule in the pack, so a seed is no reason to
keep cells apart, and more cells fill a pack. Each mate is claimed on the results store WITHOUT
waiting: one another process holds is left to it; one with a current record (its plan: resume) is
left out and resumed by its own case, and so is one whose record lacks only closed-loop episodes
(its plan: extend, bench.cell.extend). The pack trains (train_pack), then every cell is scored as it
is alone (runner.score_cell) and written by the service, mates first, the lead last (returned to the
service like a runner's result), the claims held until all are written. A mate that fails gets its
failure record, and its case fails with that error when reached; the others go on. The mates'
records and outcomes go into the service's caches, so their cases take them without measuring again
and report "measured" (this process measured them; an xdist worker that waited on a mate's claim
resumes it: "resumed"). No mate found: the cell is measured alone, as without the option.
"""

from __future__ import annotations

import contextlib

from bench.progress import say
from bench.cell.outcome import MEASURED
from bench.cell.plan import CellPlan, CellResult


def measure_packed(service, lead: CellPlan) -> CellResult:
    """`lead`'s result, its cell trained in a pack with the mates it finds (their records written
    and kept by `service`), or alone when it cannot lead one or finds no mate. Raises what the
    lead's own training or scoring raised (the service writes its failure)."""
    from bench.cell.packed import packable

    cell, ws = lead.cell, service.workspace()
    if packable(cell) is not None or lead.context.reuse is not None:
        return service.runner(cell, ws, lead.context)
    with contextlib.ExitStack() as claims:
        plans = [lead] + claim_mates(service, lead, claims)
        if len(plans) == 1:
            return service.runner(cell, ws, lead.context)
        say(service.progress(), f"pack of {len(plans)} grafts through one {cell.backbone} pass "
                                f"({cell.suite}): {', '.join(p.cell.id for p in plans)}")
        return _train_and_write(service, plans)


def claim_mates(service, lead: CellPlan, claims: contextlib.ExitStack) -> list[CellPlan]:
    """Plans of up to K-1 mates for `lead`, each claimed (the claims entered on `claims`)."""
    from bench.cell.packed import packable

    cell, wanted = lead.cell, service.settings.pack_grafts - 1
    mates: list[CellPlan] = []
    for mate in service.pack_candidates(cell):
        if len(mates) == wanted:
            break
        if (mate.id == cell.id or mate.id in service.records or mate.id in service.pack_failures
                or (mate.backbone, mate.suite, mate.release)
                != (cell.backbone, cell.suite, cell.release)
                or packable(mate) is not None or _takes_graft_projector(mate, service)):
            continue
        one = contextlib.ExitStack()
        if not one.enter_context(service.store.try_cell_lock(mate.id)):
            one.close()  # another process measures it: its record is its claimant's
            continue
        service.set_aside(mate)
        plan = service.plan(mate)
        if plan.resume is not None or plan.extend is not None or plan.context.reuse is not None:
            one.close()  # its case resumes / extends it, takes its graft's projector, as unpacked
            continue
        claims.enter_context(one.pop_all())
        mates.append(plan)
    return mates


def _takes_graft_projector(cell, service) -> bool:
    """A control that trains exactly its graft's projector takes the graft's once measured
    (bench.cell.plan); packed beside or before its graft it would train a copy, and its record
    would lose `projector_from`: never a mate (as a lead, its plan is the unpacked one)."""
    from bench.grid.kinds import GRAFT
    from bench.cell.plan import shared_projector_key

    return (cell.kind != GRAFT
            and shared_projector_key(cell, service.settings.features_mode) is not None)


def _train_and_write(service, plans: list[CellPlan]) -> CellResult:
    """Train the pack, then score and write each cell; the lead's (plans[0]) result last."""
    from bench.results.provenance import reset_peak_memory
    from bench.cell.packed import train_pack

    ws = service.workspace()
    for plan in plans:
        if plan.discard:  # a degraded record never outlives its run
            ws.store.forget(plan.cell.id)
    lead = plans[0].cell
    policy = ws.backbone(lead.backbone, lead.suite, lead.release).policy
    reset_peak_memory(next(policy.parameters()).device)
    try:
        items = train_pack([p.cell for p in plans], ws, [p.context for p in plans],
                           label=f"{lead.backbone}-{lead.suite} pack")
    except Exception as e:  # not one cell's training (a graft that cannot be built, ...):
        # the lead alone, as unpacked; the mates, unclaimed, each meet their own error alone
        say(service.progress(), f"the pack led by {lead.id} could not train ({type(e).__name__}: "
                                f"{e}); {lead.id} is measured alone, its mates when reached")
        return service.runner(lead, ws, plans[0].context)
    for plan, item in list(zip(plans, items))[1:]:
        try:
            record = service.write(plan, _score(ws, plan, item))
        except Exception as e:  # this mate alone fails; the pack's others go on
            service.note_failure(plan.cell, e)
            service.pack_failures[plan.cell.id] = e
            continue
        service.records[plan.cell.id], service.outcomes[plan.cell.id] = record, MEASURED
    return _score(ws, plans[0], items[0])


def _score(ws, plan: CellPlan, item) -> CellResult:
    """One packed cell scored as runner.measure does alone (its training's error raised here)."""
    from bench.cell.runner import score_cell

    if item.error is not None:
        raise item.error
    cell, graft = plan.cell, item.graft
    return score_cell(cell, ws, plan.context, ws.backbone(cell.backbone, cell.suite, cell.release),
                      graft.inputs, graft, item.fitted, dict(item.timings),
                      spent=sum(item.timings.values()))

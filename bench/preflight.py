"""Preflight: every artifact a selected hub grid reads, present or missing, on one screen, with
the exact commands that put the missing ones where graftbench looks. Run before any cell.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Iterable, Sequence

from ondisk.artifacts import Artifact

def grid_artifacts(backbones: Iterable[str], encoders: Iterable[str],
                   suites: Iterable[str]) -> list[Artifact]:
    """Artifacts of a hub grid, one per (kind, repo, revision), `needed_by` merged."""
    from backbones import adapter_module, get_entry
    from bench.suites import libero
    from encoders.timm_encoders import weight_artifacts

    found: list[Artifact] = []
    for name in dict.fromkeys(backbones):
        entry = get_entry(name)
        found += adapter_module(name).artifacts(entry.repo_id, entry.revision, f"backbone {name}")
    for name in dict.fromkeys(encoders):
        found += weight_artifacts(name)
    for name in dict.fromkeys(suites):
        found.append(libero.dataset_artifact(name, revision=libero.LIBERO_REVISIONS.get(name)))
    return _merged(found)


def _merged(artifacts: Sequence[Artifact]) -> list[Artifact]:
    by_key: dict[tuple, Artifact] = {}
    for a in artifacts:
        key = (a.kind, a.repo_id, a.revision)
        if key in by_key:
            have = by_key[key]
            if a.needed_by not in have.needed_by.split(", "):
                by_key[key] = replace(have, needed_by=f"{have.needed_by}, {a.needed_by}")
        else:
            by_key[key] = a
    return list(by_key.values())


def cells_artifacts(cells) -> list[Artifact]:
    """Artifacts of the selected cells (after -k): their backbones, encoders and suites."""
    cells = list(cells)
    encoders = [c.encoder for c in cells if c.encoder]
    return grid_artifacts([c.backbone for c in cells], encoders, [c.suite for c in cells])


def render(artifacts: Sequence[Artifact]) -> str:
    """The preflight screen: one line per artifact, then the fix commands for the missing."""
    missing = [a for a in artifacts if not a.present]
    lines = [f"graftbench preflight: {len(artifacts)} artifacts, {len(missing)} missing"]
    lines += ["  " + a.line() for a in artifacts]
    if missing:
        lines.append("fetch the missing ones (on a machine with network, same HF_HOME):")
        for a in missing:
            lines.append(f"  {a.fix}")
            if a.note:
                lines.append(f"    # {a.note}")
    return "\n".join(lines)


def missing_summary(artifacts: Sequence[Artifact]) -> str:
    """One line naming every missing artifact (for the error that stops the run)."""
    missing = [a for a in artifacts if not a.present]
    names = ", ".join(f"{a.kind} {a.repo_id}" for a in missing)
    return (f"preflight: {len(missing)} artifact(s) missing ({names}); nothing was run. "
            "The list above gives the commands that fetch them.")


def stop_on_missing(cells, config, store) -> None:
    """Hub grids: list every artifact the selected `cells` read; stop (UsageError, no cell run,
    the results `store` removed if unused) when one is missing. --collect-only shows the list and
    stops anyway."""
    import sys

    import pytest

    artifacts = cells_artifacts(cells)
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    screen = render(artifacts)
    if reporter is not None:
        reporter.write_line(screen)
    else:
        sys.stderr.write(screen + "\n")
    if any(not a.present for a in artifacts) and not config.option.collectonly:
        store.remove_if_unused()
        raise pytest.UsageError(missing_summary(artifacts))

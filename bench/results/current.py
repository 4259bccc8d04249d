"""May a stored record stand for this run? The one rule, used by resume (bench.session) and by
the baseline comparison (bench.regression.baseline).

A run states the conditions it measures under (`RunConditions`); a record is current when it
matches every condition the run states (None: not asked). Resume states them all; a baseline
states what its cell was measured under (protocol, normaliser, package versions).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from bench.results.record import Record


@dataclass(frozen=True)
class RunConditions:
    """What a run measures under, as far as a stored record must match it."""

    protocol_hash: str | None = None
    revision: str | None = None  # the checkpoint's weights (a tiny release: their sha256)
    normalizer_fingerprint: str | None = None
    feature_dtype: str | None = None  # the feature store's dtype (cells that read it)
    rollouts: int = 0  # closed-loop episodes per task the run wants (0: none)
    versions: dict | None = None  # packages that must match (those both sides name)
    label: str = "this run"  # how differences name the run's side


def differences(record: Record, run: RunConditions) -> list[str]:
    """One line per condition of `run` that `record` was not measured under."""
    m, out = record.measured, []

    def differ(what: str, have, want) -> None:
        if want is not None and have != want:
            out.append(f"{what} {have} ({run.label} {want})")

    differ("protocol_hash", m.protocol_hash, run.protocol_hash)
    differ("revision", m.revision, run.revision)
    differ("normalizer", m.normalizer_fingerprint, run.normalizer_fingerprint)
    if m.stored_feature_dtype is not None:  # features stored at another precision
        differ("feature_dtype", m.stored_feature_dtype, run.feature_dtype)
    if run.rollouts and not record.run.has_rollouts(run.rollouts):
        out.append(f"rollouts not of {run.rollouts} episodes per task ({run.label})")
    have_versions = record.run.versions or {}
    for pkg in sorted(set(run.versions or {}) & set(have_versions)):
        differ(pkg, have_versions[pkg], run.versions[pkg])
    return out


def fewer_episodes(record: Record, run: RunConditions) -> bool:
    """Whether `record` stands for `run` in everything but holding fewer closed-loop episodes
    per task than the run wants (none counts as 0): its episodes can be kept and the rest
    rolled out (bench.cell.extend), where another count or condition measures it again."""
    if not run.rollouts or differences(record, replace(run, rollouts=0)):
        return False
    rollouts = record.run.rollouts or {}
    if "skipped" in rollouts:
        return False
    have = (rollouts.get("spec") or {}).get("episodes_per_task", 0) \
        if rollouts.get("episodes") else 0
    return have < run.rollouts


def is_current(record: Record, run: RunConditions) -> bool:
    """Whether `record` may stand for `run`: measured under every condition `run` states."""
    return not differences(record, run)

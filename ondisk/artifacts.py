"""What a grid needs from the outside world: one `Artifact` per repo (policy, VLM, tokenizer,
encoder weights, dataset), present or missing, with the exact command that fetches it.

The providers live beside the code that loads each artifact (backbone adapters, the timm
encoders, the LIBERO suites); bench.preflight gathers and prints them before any cell runs.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Artifact:
    """One external thing a run reads. `fix` is empty when `present`."""

    kind: str  # "policy" | "vlm config" | "tokenizer" | "encoder weights" | "dataset"
    repo_id: str
    needed_by: str  # e.g. "backbone smolvla", "encoder dinov2_s", "suite spatial"
    present: bool
    where: str  # the path it was found at, or where it was looked for
    fix: str = ""  # exact shell command(s) that put it where graftbench looks
    revision: str | None = None  # pinned hub revision, when there is one
    note: str = ""  # gating, licence, size

    def line(self) -> str:
        """One screen line: status, kind, repo[@revision], who needs it, where."""
        mark = "ok     " if self.present else "MISSING"
        rev = f"@{self.revision}" if self.revision else ""
        return f"{mark} {self.kind:<16} {self.repo_id}{rev}  ({self.needed_by}) {self.where}"

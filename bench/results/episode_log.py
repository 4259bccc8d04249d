"""The closed-loop episodes of a cell still rolling out (the store hands one out per cell)."""

from __future__ import annotations

from pathlib import Path

from bench.results.jsonfile import atomic_write_json, read_json

_LOG_KEY, _LOG_EPISODES = "key", "episodes"


class EpisodeLog:
    """The finished closed-loop episodes of one cell while its rollouts run, so a killed run
    resumes per episode: one JSON file rewritten atomically after every episode (a kill loses
    at most the episode in flight; an episode is a few hundred bytes, so rewriting stays cheap).

    `key` names the policy and rollout spec the episodes belong to: episodes stored under
    another key (a retrained policy, another spec) are never resumed, they are started over.
    The store removes the file when the cell's record is written (the record holds them)."""

    def __init__(self, path: Path, key: str) -> None:
        self.path, self.key = Path(path), key

    def finished(self) -> list[dict]:
        """Episodes stored under this key, in the order they finished; [] when none is usable."""
        try:
            data = read_json(self.path)
        except (OSError, ValueError):
            return []  # absent, or unreadable: roll out again rather than trust it
        if not isinstance(data, dict) or data.get(_LOG_KEY) != self.key:
            return []
        return list(data.get(_LOG_EPISODES) or [])

    def add(self, episode: dict) -> None:
        """Store one more finished episode (atomically, with those before it)."""
        atomic_write_json(self.path, {_LOG_KEY: self.key,
                                      _LOG_EPISODES: [*self.finished(), episode]})

    def clear(self) -> None:
        self.path.unlink(missing_ok=True)

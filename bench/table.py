"""A table where adding a thing is one entry (cell kinds: bench.grid.kinds; screen proxies:
bench.screen.proxies; suites: bench.suites; perturbations: bench.robust.perturbations): a dict by
name, in registration order, that refuses a name twice and, asked for an unknown one, refuses it
in one shape: "unknown <what> 'x' (did you mean 'y'?); valid <plural>: a, b". The registries
below bench (backbones/, encoders/: they import nothing of bench) refuse in the same shape."""

from __future__ import annotations

import difflib
from typing import Generic, TypeVar

T = TypeVar("T")


class Table(dict, Generic[T]):
    """{name: entry}; `what` and `plural` name entries in errors ("cell kind", "kinds")."""

    def __init__(self, what: str, plural: str) -> None:
        super().__init__()
        self.what, self.plural = what, plural

    def register(self, entry: T) -> T:
        if entry.name in self:
            raise ValueError(f"{self.what} {entry.name!r} registered twice")
        self[entry.name] = entry
        return entry

    def unregister(self, name: str) -> None:
        """Tests that register an entry of their own take it out again."""
        self.pop(name)

    def refusal(self, name: str) -> str:
        """The one line that refuses an unknown `name`, with the nearest valid one."""
        close = ([n for n in self if n.lower() == str(name).lower()]  # only the case differs
                 or difflib.get_close_matches(str(name), list(self), n=1, cutoff=0.7))
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        return f"unknown {self.what} {name!r}{hint}; valid {self.plural}: {', '.join(self)}"

    def get_entry(self, name: str) -> T:
        try:
            return self[name]
        except KeyError:
            raise ValueError(self.refusal(name)) from None

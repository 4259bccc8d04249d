"""A table where adding a thing is one entry (cell kinds: bench.grid.kinds; screen proxies:
bench.screen.proxies): a dict by name, in registration order, that refuses a name twice and
names the valid ones when asked for an unknown one. Imports nothing, so any floor may hold one."""

from __future__ import annotations

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

    def get_entry(self, name: str) -> T:
        try:
            return self[name]
        except KeyError:
            raise ValueError(f"unknown {self.what} {name!r}; valid {self.plural}: "
                             f"{', '.join(self)}") from None

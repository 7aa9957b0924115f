"""Driver registries with lazy imports (after python-can's interface map).

Each kind of driver (camera, robot, bus) keeps a map `name -> DriverEntry`. A
backend module is imported only when its name is selected, so a missing
optional dependency fails then, with an error that names the extra to install.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from supervisor.errors import DriverUnavailable


@dataclass(frozen=True)
class DriverEntry:
    module: str
    cls: str
    extra: str | None = None  # pip extra that provides the vendor library
    doc: str = ""


class DriverRegistry:
    """Name -> lazily imported driver class, for one kind of driver."""

    def __init__(self, kind: str, entries: dict[str, DriverEntry]) -> None:
        self.kind = kind
        self._entries = dict(entries)

    def names(self) -> list[str]:
        return sorted(self._entries)

    def entry(self, name: str) -> DriverEntry:
        try:
            return self._entries[name]
        except KeyError:
            raise DriverUnavailable(
                f"unknown {self.kind} driver {name!r}; available: {', '.join(self.names())}"
            ) from None

    def load(self, name: str) -> type:
        """Import and return the driver class registered as `name`."""
        entry = self.entry(name)
        try:
            module = importlib.import_module(entry.module)
        except ImportError as exc:
            hint = (
                f"; install it with: pip install 'panda-localization-supervisor[{entry.extra}]'"
                if entry.extra
                else ""
            )
            raise DriverUnavailable(
                f"{self.kind} driver {name!r} needs a library that is not installed ({exc}){hint}"
            ) from exc
        return getattr(module, entry.cls)

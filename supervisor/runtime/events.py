"""Structured run events, written as JSON lines and kept in memory for the summary.

Every decision the supervisor takes (prediction updates, gate brakes, faults,
stage switches) is one event with the clock time, a kind and SI-unit fields.
The file is flushed per event so a crash leaves every event up to the crash.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import IO, Any

import numpy as np


def _plain(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, np.integer):
        return int(v)
    if hasattr(v, "value") and hasattr(v, "name"):  # enums
        return v.name
    return v


class EventLog:
    """Append-only event list, mirrored to `path` (JSON lines) when given."""

    def __init__(self, path: str | Path | None = None) -> None:
        self.events: list[dict[str, Any]] = []
        self.path = Path(path) if path is not None else None
        self._fh: IO[str] | None = None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = self.path.open("w", encoding="utf-8")

    def emit(self, t: float, kind: str, **fields: Any) -> dict[str, Any]:
        ev = {"t": float(t), "kind": kind, **{k: _plain(v) for k, v in fields.items()}}
        self.events.append(ev)
        if self._fh is not None:
            self._fh.write(json.dumps(ev, sort_keys=True) + "\n")
            self._fh.flush()
        return ev

    def of_kind(self, kind: str) -> list[dict[str, Any]]:
        return [e for e in self.events if e["kind"] == kind]

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self) -> EventLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""Structured run events: kept in memory for the summary, written as JSON lines by a writer thread.

Every decision the supervisor takes (prediction updates, gate brakes, faults,
stage switches) is one event with the clock time, a kind and SI-unit fields.

The control loop never waits for the disk (STYLE 15): `emit` appends to the
in-memory list and puts the serialized line on a bounded queue; a writer thread
writes and flushes each line. A full queue drops the line, a failing write
(disk full, file too large, I/O error) drops it too; either raises the log's
`alarm` (with the reason) and is counted, never raised into the caller.
`close()` drains the queue (bounded wait) so a clean shutdown loses nothing.
"""

from __future__ import annotations

import json
import math
import queue
import threading
from pathlib import Path
from typing import IO, Any

import numpy as np

QUEUE_LINES = 4096  # lines buffered for the writer; beyond this, lines are dropped (counted)
_STOP = object()


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
    """Append-only event list, mirrored to `path` (JSON lines) by a writer thread when given."""

    def __init__(self, path: str | Path | None = None, *, queue_lines: int = QUEUE_LINES) -> None:
        self.events: list[dict[str, Any]] = []
        self.path = Path(path) if path is not None else None
        self.dropped = 0  # lines that never reached the file
        self.alarm: str | None = None  # first reason lines were dropped
        self._fh: IO[bytes] | None = None
        self._queue: queue.Queue[object] = queue.Queue(maxsize=queue_lines)
        self._writer: threading.Thread | None = None
        self._lock = threading.Lock()
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = self.path.open("wb", buffering=0)
            self._writer = threading.Thread(target=self._write_loop, name="event-writer", daemon=True)
            self._writer.start()

    def emit(self, t: float, kind: str, **fields: Any) -> dict[str, Any]:
        """Record one event; never blocks on the disk and never raises for it."""
        ev = {"t": float(t), "kind": kind, **{k: _plain(v) for k, v in fields.items()}}
        line = None if self._writer is None else json.dumps(ev, sort_keys=True)
        full = False
        with self._lock:  # the file gets the events in the order of the list, whichever threads emit them
            self.events.append(ev)
            if line is not None:
                try:
                    self._queue.put_nowait(line)
                except queue.Full:
                    full = True
        if full:
            self._drop("event queue full (the disk is not keeping up)")
        return ev

    def _drop(self, reason: str) -> None:
        self.dropped += 1
        if self.alarm is None:
            self.alarm = reason

    def _write_loop(self) -> None:
        fh = self._fh
        assert fh is not None
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            if isinstance(item, threading.Event):  # a flush marker: everything before it is written
                item.set()
                continue
            data = memoryview((item + "\n").encode("utf-8"))  # type: ignore[operator]
            try:
                while data:  # unbuffered: a failed write keeps nothing back for later lines
                    n = fh.write(data)
                    data = data[n or 0:]
            except (OSError, ValueError) as exc:  # ENOSPC, EFBIG, EIO; ValueError: closed file
                self._drop(f"cannot write {self.path}: {exc}")

    def of_kind(self, kind: str) -> list[dict[str, Any]]:
        with self._lock:
            return [e for e in self.events if e["kind"] == kind]

    def flush(self, timeout: float = 2.0) -> bool:
        """Wait (at most `timeout`) until every line queued so far was handed to the file."""
        if self._writer is None:
            return True
        done = threading.Event()
        try:
            self._queue.put(done, timeout=timeout)
        except queue.Full:
            return False
        return done.wait(timeout)

    def close(self, timeout: float = 2.0) -> None:
        """Drain the queue (at most `timeout`), stop the writer, close the file. Idempotent."""
        if self._writer is not None:
            try:
                self._queue.put(_STOP, timeout=timeout)
            except queue.Full:
                self._drop("event queue still full at close")
            self._writer.join(timeout)
            self._writer = None
        if self._fh is not None:
            try:
                self._fh.close()
            except OSError as exc:
                self._drop(f"cannot close {self.path}: {exc}")
            self._fh = None

    def __enter__(self) -> EventLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

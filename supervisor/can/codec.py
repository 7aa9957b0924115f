"""The side channel's messages: the DBC read with cantools, frame ids and data IDs from configuration.

`encode(name, values)` fills in the alive counter and the CRC (E2E) and refuses values outside
the DBC's ranges (`FrameError`); `decode(name, data)` returns the signals without checks (the
receivers run `e2e.Checker` first).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cantools

from supervisor.can.e2e import COUNTER_MODULO, Checker, frame_crc
from supervisor.can.settings import DEFAULT_DATA_IDS, DEFAULT_DBC, DEFAULT_FRAMES, MESSAGES
from supervisor.errors import ConfigError, SupervisorError

DBC_NAMES = {"heartbeat": "HEARTBEAT", "stop": "STOP", "external_stop": "EXTERNAL_STOP", "status": "STATUS"}
E2E_SIGNALS = ("Crc", "AliveCounter")
# `setup`: a setup move under way (a model build's views, a run's move to its start) outside a gated run
STATES = ("idle", "armed", "moving", "halted", "fault", "setup")
STOP_REASONS = ("other", "end_of_path", "boundary", "gate", "stop_request", "external_stop", "fault", "consistency",
                "error_bound", "inlier_ratio")


class FrameError(SupervisorError):
    """A message that cannot be encoded or decoded (unknown message, value out of range, bad bytes)."""


def stop_reason_code(halt_reason: str) -> str:
    """The STOP frame's Reason for a loop halt reason (`gate:...`, `stop:operator`, `fault:...`, ...)."""
    head = halt_reason.split(":", 1)[0]
    if head == "stop":
        return "stop_request"
    if head in STOP_REASONS:
        return head
    return "other"


class Codec:
    """Encode and decode the four messages of the shipped DBC, under configured ids."""

    def __init__(self, dbc: str | Path = DEFAULT_DBC, frames: Mapping[str, int] = DEFAULT_FRAMES,
                 data_ids: Mapping[str, int] = DEFAULT_DATA_IDS) -> None:
        try:
            self.db = cantools.database.load_file(str(dbc), strict=True)
        except (OSError, cantools.database.UnsupportedDatabaseFormatError, ValueError) as exc:
            raise ConfigError(dbc, "", f"cannot read the DBC: {exc}") from exc
        self.messages = {}
        for key in MESSAGES:
            try:
                msg = self.db.get_message_by_name(DBC_NAMES[key])
            except KeyError:
                raise ConfigError(dbc, "", f"the DBC has no message {DBC_NAMES[key]}") from None
            missing = [s for s in E2E_SIGNALS if s not in {x.name for x in msg.signals}]
            if missing or msg.length != 8:
                raise ConfigError(dbc, "", f"{msg.name} needs 8 bytes and the signals {', '.join(E2E_SIGNALS)}")
            self.messages[key] = msg
        self.frames = dict(frames)
        self.data_ids = dict(data_ids)
        self.by_id = {fid: key for key, fid in self.frames.items()}
        self._counters = dict.fromkeys(MESSAGES, 0)

    def choices(self, name: str, signal: str) -> set[str]:
        """The named values a signal of a message has in this DBC (empty when it has none or no such signal)."""
        for s in self.messages[name].signals:
            if s.name == signal and s.choices:
                return {str(v) for v in s.choices.values()}
        return set()

    def signals(self, name: str) -> list[str]:
        """The payload signals of a message (without Crc and AliveCounter)."""
        return [s.name for s in self.messages[name].signals if s.name not in E2E_SIGNALS]

    def encode(self, name: str, values: Mapping[str, Any], *, counter: int | None = None) -> tuple[int, bytes]:
        """(CAN id, 8 bytes) of one message; the counter advances per message unless given."""
        if name not in self.messages:
            raise FrameError(f"unknown message {name!r}; known: {', '.join(self.messages)}")
        if counter is None:
            counter = self._counters[name]
            self._counters[name] = (counter + 1) % COUNTER_MODULO
        msg = self.messages[name]
        try:
            data = bytearray(msg.encode({"Crc": 0, "AliveCounter": counter, **values}, strict=True))
        except (cantools.database.EncodeError, KeyError, ValueError, TypeError) as exc:
            raise FrameError(f"{msg.name}: {exc}") from exc
        data[0] = frame_crc(self.data_ids[name], data)
        return self.frames[name], bytes(data)

    def decode(self, name: str, data: bytes) -> dict[str, Any]:
        """The signals of one frame (choices as names); FrameError if the bytes do not decode."""
        try:
            return dict(self.messages[name].decode(bytes(data), decode_choices=True, scaling=True))
        except (cantools.database.DecodeError, ValueError, KeyError) as exc:
            raise FrameError(f"{self.messages[name].name}: {exc}") from exc

    def checker(self, name: str, max_jump: int = 3) -> Checker:
        """A receiver's E2E checks for `name` (other messages' data IDs classify misrouted frames)."""
        return Checker(self.data_ids[name], length=self.messages[name].length, max_jump=max_jump,
                       other_ids=tuple(self.data_ids.values()))

    @classmethod
    def from_settings(cls, settings) -> Codec:
        return cls(settings.dbc, settings.frames, settings.data_ids)

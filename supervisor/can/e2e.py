"""End-to-end protection of safety frames (after AUTOSAR E2E profile 1, CANopen Safety).

Byte 0 of every frame is a CRC-8/SAE-J1850 (poly 0x1D, init 0xFF, xorout 0xFF; check value
0x4B for b"123456789") over the message's 16-bit data ID (low byte, then high byte) and
payload bytes 1..7. The data ID is never sent: a frame meant for another message or another
cell fails the CRC. The low nibble of byte 1 is a 4-bit alive counter, bumped per frame by
the sender; a receiver requires it to advance strictly (by 1..max_jump, modulo 16), so a
repeated or replayed frame is stale. Monitoring starts at the first valid frame.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

COUNTER_MODULO = 16
REJECT_REASONS = ("bad_crc", "wrong_data_id", "stale_counter", "bad_length", "undecodable")


def _table() -> tuple[int, ...]:
    out = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        out.append(crc)
    return tuple(out)


_TABLE = _table()


def crc8_sae_j1850(data: bytes, init: int = 0xFF) -> int:
    """CRC-8/SAE-J1850 of `data`."""
    crc = init
    for b in data:
        crc = _TABLE[crc ^ b]
    return crc ^ 0xFF


def frame_crc(data_id: int, frame: bytes) -> int:
    """The CRC a frame must carry in byte 0, for `data_id`."""
    return crc8_sae_j1850(bytes((data_id & 0xFF, (data_id >> 8) & 0xFF)) + bytes(frame[1:]))


def counter_of(frame: bytes) -> int:
    return frame[1] & 0x0F


@dataclass
class Verdict:
    ok: bool
    reason: str = ""  # one of REJECT_REASONS when not ok
    counter: int = -1


class Checker:
    """The receiver's checks for one message: CRC with its data ID, then a strictly advancing counter.

    `other_ids` are data IDs of other messages on the same bus: a frame whose CRC matches one of
    them is counted as `wrong_data_id` (misrouted or replayed from another message), any other CRC
    mismatch as `bad_crc`. Rejected frames never change the state.
    """

    def __init__(self, data_id: int, *, length: int = 8, max_jump: int = 3, other_ids: tuple[int, ...] = ()) -> None:
        if not 1 <= max_jump < COUNTER_MODULO:
            raise ValueError(f"max_jump must be in 1..{COUNTER_MODULO - 1}, got {max_jump}")
        self.data_id = data_id
        self.length = length
        self.max_jump = max_jump
        self.other_ids = tuple(i for i in other_ids if i != data_id)
        self.last: int | None = None
        self.accepted = 0
        self.rejected: Counter[str] = Counter()

    def check(self, frame: bytes) -> Verdict:
        v = self._verdict(bytes(frame))
        if v.ok:
            self.accepted += 1
            self.last = v.counter
        else:
            self.rejected[v.reason] += 1
        return v

    def _verdict(self, frame: bytes) -> Verdict:
        if len(frame) != self.length:
            return Verdict(False, "bad_length")
        if frame[0] != frame_crc(self.data_id, frame):
            wrong = any(frame[0] == frame_crc(i, frame) for i in self.other_ids)
            return Verdict(False, "wrong_data_id" if wrong else "bad_crc")
        c = counter_of(frame)
        if self.last is not None:
            jump = (c - self.last) % COUNTER_MODULO
            if not 1 <= jump <= self.max_jump:
                return Verdict(False, "stale_counter", c)
        return Verdict(True, "", c)

    def reset(self) -> None:
        """Forget the last counter (monitoring restarts at the next valid frame)."""
        self.last = None

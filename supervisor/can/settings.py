"""The `can:` configuration section, parsed once (absent or `can: null`: no side channel).

    can:
      interface: virtual          # a name from drivers.bus.BUSES (python-can interface)
      channel: cell0              # python-can channel (can0, a multicast group, a virtual name)
      bitrate: 500000             # optional (interfaces that set it)
      dbc: cell.dbc               # optional: another DBC with the same messages and signals
      heartbeat_period_ms: 20
      consumer_timeout_ms: 100    # `supervisor can monitor`'s default
      max_counter_jump: 3         # a receiver accepts a counter advance of 1..this (lost frames)
      frames:   {heartbeat: 0x100, stop: 0x101, external_stop: 0x080, status: 0x102}
      data_ids: {heartbeat: 0x5301, stop: 0x5302, external_stop: 0x5303, status: 0x5304}
      status_period_ms: 100       # STATUS frames at most this often (0: never)

`dbc` is resolved against the config file's folder; default the shipped config/can/supervisor.dbc.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from supervisor.paths import CONFIG_DIR
from supervisor.yamlschema import Ambiguous, Node

DEFAULT_DBC = CONFIG_DIR / "can" / "supervisor.dbc"
MESSAGES = ("heartbeat", "stop", "external_stop", "status")
DEFAULT_FRAMES = MappingProxyType({"heartbeat": 0x100, "stop": 0x101, "external_stop": 0x080, "status": 0x102})
DEFAULT_DATA_IDS = MappingProxyType({"heartbeat": 0x5301, "stop": 0x5302, "external_stop": 0x5303,
                                     "status": 0x5304})


@dataclass(frozen=True)
class CanSettings:
    interface: str
    channel: str
    bitrate: int | None = None
    dbc: Path = DEFAULT_DBC
    heartbeat_period: float = 0.02  # s
    consumer_timeout: float = 0.1  # s
    max_counter_jump: int = 3
    status_period: float = 0.1  # s; 0 = no STATUS frames
    frames: MappingProxyType = field(default_factory=lambda: DEFAULT_FRAMES)  # message -> CAN id
    data_ids: MappingProxyType = field(default_factory=lambda: DEFAULT_DATA_IDS)  # message -> 16-bit data ID
    options: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))  # extra python-can kwargs

    @classmethod
    def from_node(cls, n: Node, config_file: Path | None) -> CanSettings:
        from drivers.bus import BUSES

        dbc = DEFAULT_DBC
        name = n.optional_string("dbc")
        if name is not None:
            dbc = ((config_file.parent if config_file else Path.cwd()) / name).resolve()
            if not dbc.is_file():
                raise n.error("dbc", f"file not found: {dbc}")
        bitrate = None if n.is_null("bitrate") else n.integer("bitrate", min=5000, max=8_000_000)
        period = n.number("heartbeat_period_ms", 20.0, min=1.0, max=10000.0) / 1000.0
        timeout = n.number("consumer_timeout_ms", 100.0, min=1.0, max=60000.0) / 1000.0
        if timeout <= period:
            raise n.error("consumer_timeout_ms", f"must exceed heartbeat_period_ms ({period * 1000:g}), "
                                                 f"got {timeout * 1000:g}")
        out = cls(
            interface=n.string("interface", choices=tuple(BUSES.names())),
            channel=str(n.string("channel")),
            bitrate=bitrate,
            dbc=dbc,
            heartbeat_period=period,
            consumer_timeout=timeout,
            max_counter_jump=n.integer("max_counter_jump", 3, min=1, max=14),
            status_period=n.number("status_period_ms", 100.0, min=0.0, max=60000.0) / 1000.0,
            frames=_ids(n.child("frames", {}), DEFAULT_FRAMES, 0x1FFFFFFF, "a CAN id (0..0x1FFFFFFF)"),
            data_ids=_ids(n.child("data_ids", {}), DEFAULT_DATA_IDS, 0xFFFF, "a 16-bit data ID (0..0xFFFF)"),
            options=MappingProxyType(_options(n.child("options", {}))),
        )
        if len(set(out.frames.values())) != len(out.frames):
            raise n.error("frames", f"every message needs its own CAN id, got {dict(out.frames)}")
        if len(set(out.data_ids.values())) != len(out.data_ids):
            raise n.error("data_ids", f"every message needs its own data ID, got {dict(out.data_ids)}")
        n.done()
        return out


def _ids(n: Node, defaults: MappingProxyType, top: int, what: str) -> MappingProxyType:
    out = {m: n.integer(m, defaults[m], min=0, max=top) for m in MESSAGES}
    n.done()
    return MappingProxyType(out)


def _options(n: Node) -> dict[str, Any]:
    """Extra python-can keyword arguments: scalars only (strings, integers, booleans)."""
    out: dict[str, Any] = {}
    for key in n.keys():
        value = n.data[key]
        n._seen.add(key)  # noqa: SLF001 - read as raw scalars below
        if isinstance(value, (bool, int, str)) and not isinstance(value, (float, Ambiguous)):
            out[key] = value
        else:
            raise n.error(key, f"expected a string, an integer or true/false, got {type(value).__name__}")
    n.done()
    return out


def parse_can(root: Node, config_file: Path | None) -> CanSettings | None:
    """The `can:` section of a config, or None when absent or null (no side channel)."""
    if root.is_null("can"):
        return None
    return CanSettings.from_node(root.child("can"), config_file)

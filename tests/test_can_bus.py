"""The bus driver (python-can's virtual bus is the fake) and the side channel's fault detection."""

from __future__ import annotations

import time

import pytest

from drivers.bus import BUSES
from drivers.bus.base import BusFault, BusUnavailable, Frame
from drivers.bus.pythoncan import CAN_ERR_BUSOFF, PythonCanBus
from supervisor.can.channel import SideChannel
from supervisor.can.codec import Codec
from supervisor.can.e2e import frame_crc
from supervisor.can.settings import CanSettings
from supervisor.errors import DriverUnavailable


def _settings(channel: str, **kw) -> CanSettings:
    return CanSettings(interface="virtual", channel=channel, **kw)


def _wait(cond, timeout: float = 2.0) -> bool:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():
            return True
        time.sleep(0.005)
    return cond()


def test_registry_lists_the_fake_and_refuses_unknown_interfaces():
    assert {"virtual", "socketcan", "udp_multicast"} <= set(BUSES.names())
    with pytest.raises(DriverUnavailable, match="unknown bus driver 'warp'"):
        BUSES.load("warp")


def test_the_bus_opens_lazily_and_close_is_idempotent():
    bus = PythonCanBus("virtual", "lazy")
    assert bus._bus is None  # noqa: SLF001 - nothing opened at construction
    other = PythonCanBus("virtual", "lazy")
    other.open()
    bus.send(0x123, b"\x01\x02")  # first use opens it
    f = other.recv(1.0)
    assert isinstance(f, Frame) and f.arbitration_id == 0x123 and f.data == b"\x01\x02"
    assert abs(f.t - time.monotonic()) < 1.0  # arrival on the monotonic clock, not the frame's wall-clock stamp
    for b in (bus, other):
        b.close()
        b.close()


def test_socketcan_is_unavailable_here_and_the_vendor_error_is_translated():
    # PF_CAN sockets fail on these machines (no kernel modules): the error a missing bus gives anywhere
    bus = PythonCanBus("socketcan", "vcan0")
    with pytest.raises(BusUnavailable, match="socketcan:vcan0 cannot be opened") as err:
        bus.open()
    assert isinstance(err.value, DriverUnavailable) and err.value.__cause__ is not None
    ch = SideChannel(CanSettings(interface="socketcan", channel="vcan0"))
    with pytest.raises(BusUnavailable):
        ch.open()
    assert not ch.heartbeat(0.0) and ch.problem() and not ch.healthy  # never "sent" on a bus that is not open


class _Rig:
    def __init__(self, name: str, plc_queue: int = 0) -> None:
        self.settings = _settings(name)
        self.faults: list[BusFault] = []
        self.stops: list[float] = []
        self.ch = SideChannel(self.settings, on_external_stop=self.stops.append, on_fault=self.faults.append)
        self.ch.open()
        self.plc = PythonCanBus("virtual", name, options={"rx_queue_size": plc_queue})
        self.plc.open()
        self.plc_codec = Codec.from_settings(self.settings)

    def close(self) -> None:
        self.ch.close()
        self.plc.close()


def test_a_full_send_buffer_is_a_fault_reported_once_and_never_raises():
    rig = _Rig("full", plc_queue=3)  # a node that stops draining its queue
    try:
        sent = [rig.ch.stop(0.0, "gate:x") for _ in range(6)]
        assert sent[:3] == [True] * 3 and sent[3:] == [False] * 3
        assert [f.kind for f in rig.faults] == ["send_buffer_full"]
        assert "send buffer" in rig.ch.problem() and not rig.ch.healthy
        assert rig.ch.sent["stop"] == 3
    finally:
        rig.close()


def test_bus_off_error_frame_is_a_fault_and_stops_the_receiver():
    rig = _Rig("busoff")
    try:
        import can

        raw = can.Bus(interface="virtual", channel="busoff")
        raw.send(can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, data=bytes(8)))
        raw.shutdown()
        assert _wait(lambda: rig.faults)
        assert rig.faults[0].kind == "bus_off"
        assert _wait(lambda: not rig.ch._receiver.alive())  # noqa: SLF001
        assert not rig.ch.healthy
    finally:
        rig.close()


def test_a_dead_notifier_is_a_fault_once_and_it_does_not_spin():
    rig = _Rig("dead")
    try:
        rig.ch.bus._bus.shutdown()  # noqa: SLF001 - the vendor bus dies under the receive thread
        assert _wait(lambda: rig.faults)
        assert [f.kind for f in rig.faults] == ["receiver_dead"]
        assert _wait(lambda: not rig.ch._receiver.alive())  # noqa: SLF001 - stopped, not spinning on errors
        time.sleep(0.1)
        assert len(rig.faults) == 1
    finally:
        rig.close()


def test_external_stop_frames_are_checked_before_they_stop_and_rejects_are_counted():
    rig = _Rig("ext")
    try:
        c = rig.plc_codec
        fid, good0 = c.encode("external_stop", {"Stop": 0}, counter=4)
        _, good1 = c.encode("external_stop", {"Stop": 1}, counter=5)
        _, good2 = c.encode("external_stop", {"Stop": 1}, counter=6)
        bad_crc = bytearray(good2)
        bad_crc[0] ^= 0xFF
        wrong = bytearray(good2)
        wrong[0] = frame_crc(c.data_ids["heartbeat"], wrong)  # consistent, but protected for another message
        for data in (good0, bytes(bad_crc), bytes(wrong), good0, good1, good1):
            rig.plc.send(fid, data)
        assert _wait(lambda: sum(rig.ch.rejected.values()) + rig.ch.external.accepted >= 6)
        assert rig.ch.rejected == {"bad_crc": 1, "wrong_data_id": 1, "stale_counter": 2}
        assert len(rig.stops) == 1 and rig.ch.external_stops == 1  # only the valid Stop=1
        assert not rig.faults
    finally:
        rig.close()


def test_status_frames_are_rate_limited_and_carry_theta_allowance_and_inliers():
    import math

    rig = _Rig("status")
    try:
        assert rig.ch.status(10.0, math.radians(12.345), None, 57)
        assert not rig.ch.status(10.05, math.radians(13.0), None, 50)  # within status_period (100 ms)
        assert rig.ch.status(10.2, math.radians(700.0), math.radians(20.0), 70000)  # saturated, never refused
        got = []
        for _ in range(2):
            f = rig.plc.recv(1.0)
            assert f is not None and f.arbitration_id == rig.settings.frames["status"]
            assert rig.plc_codec.checker("status").check(f.data).ok
            got.append(rig.plc_codec.decode("status", f.data))
        assert got[0]["Theta"] == pytest.approx(12.35, abs=0.006) and got[0]["ThetaAllowed"] == "unknown"
        assert got[0]["NInliers"] == 57
        assert got[1]["Theta"] == pytest.approx(655.34) and got[1]["ThetaAllowed"] == pytest.approx(20.0)
        assert got[1]["NInliers"] == 65535 and not rig.faults
    finally:
        rig.close()


def test_can_monitor_command_needs_a_can_section_and_exits_0_when_never_tripped(tmp_path, capsys):
    from supervisor.cli import main
    from supervisor.paths import DEFAULT_CONFIG

    assert main(["can", "monitor"]) == 2
    assert "no CAN side channel" in capsys.readouterr().err
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(DEFAULT_CONFIG.read_text() + "\ncan:\n  interface: virtual\n  channel: mon-cli\n")
    assert main(["--config", str(cfg), "can", "monitor", "--duration", "0.2"]) == 0  # no heartbeat yet: no trip
    assert "not tripped" in capsys.readouterr().out
    assert main(["--config", str(cfg), "can", "monitor", "--timeout-ms", "0", "--duration", "0.1"]) == 2

"""The DBC through cantools, the E2E protection (counter + CRC-8 over data ID and payload), the `can:` config."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from supervisor.can.codec import STATES, STOP_REASONS, Codec, FrameError, stop_reason_code
from supervisor.can.e2e import Checker, crc8_sae_j1850, frame_crc
from supervisor.can.settings import DEFAULT_DBC
from supervisor.config import load_config
from supervisor.errors import ConfigError
from supervisor.paths import DEFAULT_CONFIG


@pytest.fixture(scope="module")
def codec() -> Codec:
    return Codec()


def test_crc8_sae_j1850_check_value():
    assert crc8_sae_j1850(b"123456789") == 0x4B  # the catalogued check value of CRC-8/SAE-J1850
    assert crc8_sae_j1850(b"") == 0x00


def _extremes(codec: Codec, name: str):
    """Every signal at its minimum, its maximum and a middle value, with the named choices."""
    msg = codec.messages[name]
    for sig in msg.signals:
        if sig.name in ("Crc", "AliveCounter"):
            continue
        values = [sig.minimum, sig.maximum, round((sig.minimum + sig.maximum) / 2 / sig.scale) * sig.scale]
        if sig.choices:
            values += [str(c) for c in sig.choices.values()]
        yield sig.name, values


@pytest.mark.parametrize("name", ["heartbeat", "stop", "external_stop", "status"])
def test_every_message_round_trips_through_the_dbc(codec, name):
    sigs = dict(_extremes(codec, name))
    assert set(sigs) == set(codec.signals(name))
    for combo in itertools.islice(itertools.product(*sigs.values()), 400):
        values = dict(zip(sigs, combo))
        for counter in (0, 7, 15):
            fid, data = codec.encode(name, values, counter=counter)
            assert fid == codec.frames[name] and len(data) == 8
            back = codec.decode(name, data)
            assert back["AliveCounter"] == counter
            assert data[0] == frame_crc(codec.data_ids[name], data) == back["Crc"]
            numeric = codec.messages[name].decode(data, decode_choices=False)
            for k, v in values.items():
                assert numeric[k] == pytest.approx(_physical(codec, name, k, v), abs=1e-9), (k, v, back[k])
            assert codec.encode(name, {k: back[k] for k in values}, counter=counter)[1] == data


def _physical(codec: Codec, name: str, signal: str, value):
    """A signal value as a number (a choice name becomes its raw value, scaled)."""
    sig = codec.messages[name].get_signal_by_name(signal)
    if isinstance(value, str):
        raw = next(r for r, c in sig.choices.items() if str(c) == value)
        return raw * sig.scale + sig.offset
    return value


@pytest.mark.parametrize("name,values,what", [
    ("heartbeat", {"State": 6, "Stage": 0, "Fault": 0}, "State"),
    ("heartbeat", {"State": "flying", "Stage": 0, "Fault": 0}, "flying"),
    ("heartbeat", {"State": "idle", "Stage": 256, "Fault": 0}, "Stage"),
    ("heartbeat", {"State": "idle", "Stage": 0, "Fault": 2}, "Fault"),
    ("heartbeat", {"State": "idle", "Stage": -1, "Fault": 0}, "Stage"),
    ("stop", {"Reason": 10}, "Reason"),
    ("external_stop", {"Stop": 2}, "Stop"),
    ("status", {"Theta": 655.36, "ThetaAllowed": 1.0, "NInliers": 0}, "Theta"),
    ("status", {"Theta": 1.0, "ThetaAllowed": -0.01, "NInliers": 0}, "ThetaAllowed"),
    ("status", {"Theta": 1.0, "ThetaAllowed": 1.0, "NInliers": 65536}, "NInliers"),
    ("status", {"Theta": 1.0, "NInliers": 3}, "ThetaAllowed"),  # a missing signal
])
def test_out_of_range_values_are_refused(codec, name, values, what):
    with pytest.raises(FrameError, match=what):
        codec.encode(name, values)


def test_counter_out_of_range_and_unknown_message_are_refused(codec):
    with pytest.raises(FrameError, match="AliveCounter"):
        codec.encode("stop", {"Reason": "gate"}, counter=16)
    with pytest.raises(FrameError, match="unknown message"):
        codec.encode("launch", {})


def test_the_heartbeat_states_are_the_dbcs_and_a_cells_dbc_without_setup_is_read_as_such(codec, tmp_path):
    """Every state the daemon sends has its value in the shipped DBC (`setup`: 5, a setup move); a cell's own
    DBC from before `setup` still loads, and says it lacks the value (the daemon then keeps the state)."""
    assert codec.choices("heartbeat", "State") == set(STATES)
    for state in STATES:
        _, data = codec.encode("heartbeat", {"State": state, "Stage": 0, "Fault": 0})
        assert codec.decode("heartbeat", data)["State"] == state
    old = tmp_path / "old.dbc"
    text = DEFAULT_DBC.read_text()
    assert ' 5 "setup"' in text and "[0|5]" in text
    old.write_text(text.replace(' 5 "setup"', "").replace("State : 12|4@1+ (1,0) [0|5]", "State : 12|4@1+ (1,0) [0|4]"))
    old_codec = Codec(old)
    assert old_codec.choices("heartbeat", "State") == set(STATES) - {"setup"}
    with pytest.raises(FrameError):
        old_codec.encode("heartbeat", {"State": "setup", "Stage": 0, "Fault": 0})
    assert old_codec.choices("heartbeat", "NoSuchSignal") == set()


def test_stop_reason_codes_cover_the_loop_halt_reasons():
    assert stop_reason_code("gate:brake_now") == "gate"
    assert stop_reason_code("stop:operator") == "stop_request"
    assert stop_reason_code("external_stop") == "external_stop"
    assert stop_reason_code("fault:state_gap") == "fault"
    assert stop_reason_code("end_of_path") == "end_of_path"
    assert stop_reason_code("something new") == "other"
    assert set(STOP_REASONS) >= {"boundary", "consistency", "error_bound"} and "moving" in STATES
    assert stop_reason_code("error_bound") == "error_bound"
    assert stop_reason_code("inlier_ratio") == "inlier_ratio"
    # every reason the loop can send is one the shipped DBC names, and it goes through the wire and back
    codec = Codec()
    for reason in STOP_REASONS:
        _, data = codec.encode("stop", {"Reason": reason}, counter=1)
        assert codec.decode("stop", data)["Reason"] == reason


def _frames(codec: Codec, name: str, n: int, values: dict, start: int = 0):
    return [codec.encode(name, values, counter=(start + i) % 16)[1] for i in range(n)]


def test_the_receiver_rejects_bad_crc_wrong_data_id_and_stale_counters_and_counts_them(codec):
    hb = {"State": "moving", "Stage": 1, "Fault": 0}
    chk = codec.checker("heartbeat", max_jump=3)
    good = _frames(codec, "heartbeat", 20, hb)
    assert chk.check(good[0]).ok  # monitoring starts at the first valid frame
    assert chk.check(good[1]).ok
    assert chk.check(good[1]).reason == "stale_counter"  # repeated
    assert chk.check(good[0]).reason == "stale_counter"  # replayed (goes back)
    assert chk.check(good[6]).reason == "stale_counter"  # jumps further than max_jump (5 > 3)
    assert chk.check(good[4]).ok  # 3 frames lost: still accepted
    corrupt = bytearray(good[5])
    corrupt[2] ^= 0x01  # one payload bit flipped: the CRC no longer matches
    assert chk.check(bytes(corrupt)).reason == "bad_crc"
    forged = bytearray(good[5])
    forged[0] = frame_crc(codec.data_ids["stop"], forged)  # a consistent frame, protected for another message
    assert chk.check(bytes(forged)).reason == "wrong_data_id"
    assert chk.check(good[5][:7]).reason == "bad_length"
    assert chk.check(good[5]).ok  # the rejected frames changed nothing
    assert chk.rejected == {"stale_counter": 3, "bad_crc": 1, "wrong_data_id": 1, "bad_length": 1}
    assert chk.accepted == 4


def test_the_counter_wraps_modulo_16():
    c = Codec()
    chk = c.checker("external_stop", max_jump=1)
    frames = _frames(c, "external_stop", 40, {"Stop": 0}, start=10)
    assert all(chk.check(f).ok for f in frames)
    with pytest.raises(ValueError):
        Checker(1, max_jump=16)


# -- the can: section -------------------------------------------------------------------------------
def _config(tmp_path: Path, can_text: str) -> Path:
    p = tmp_path / "cfg.yaml"
    p.write_text(DEFAULT_CONFIG.read_text() + "\n" + can_text)
    return p


def test_absent_or_null_can_section_means_no_side_channel(tmp_path):
    assert load_config().can is None
    assert load_config(_config(tmp_path, "can: null\n")).can is None


def test_can_section_parses_ids_and_periods(tmp_path):
    cfg = load_config(_config(tmp_path, "can:\n  interface: virtual\n  channel: cell\n  heartbeat_period_ms: 10\n"
                                        "  frames: {heartbeat: 0x300, external_stop: 0x10}\n"
                                        "  data_ids: {stop: 0xBEEF}\n  options: {receive_own_messages: false}\n"))
    can = cfg.can
    assert can.interface == "virtual" and can.channel == "cell" and can.heartbeat_period == pytest.approx(0.01)
    assert can.frames["heartbeat"] == 0x300 and can.frames["external_stop"] == 0x10 and can.frames["stop"] == 0x101
    assert can.data_ids["stop"] == 0xBEEF and can.consumer_timeout == pytest.approx(0.1)
    c = Codec.from_settings(can)
    assert c.encode("heartbeat", {"State": "idle", "Stage": 0, "Fault": 0})[0] == 0x300


@pytest.mark.parametrize("text,key", [
    ("can:\n  interface: warp\n  channel: x\n", "can.interface"),
    ("can:\n  interface: virtual\n", "can.channel"),
    ("can:\n  interface: virtual\n  channel: x\n  speed: 3\n", "can.speed"),
    ("can:\n  interface: virtual\n  channel: x\n  frames: {heartbeat: 0x20000000}\n", "can.frames.heartbeat"),
    ("can:\n  interface: virtual\n  channel: x\n  frames: {heartbeat: 0x101}\n", "can.frames"),
    ("can:\n  interface: virtual\n  channel: x\n  data_ids: {stop: 70000}\n", "can.data_ids.stop"),
    ("can:\n  interface: virtual\n  channel: x\n  data_ids: {stop: 0x5301}\n", "can.data_ids"),
    ("can:\n  interface: virtual\n  channel: x\n  heartbeat_period_ms: .nan\n", "can.heartbeat_period_ms"),
    ("can:\n  interface: virtual\n  channel: x\n  consumer_timeout_ms: 20\n", "can.consumer_timeout_ms"),
    ("can:\n  interface: virtual\n  channel: x\n  dbc: missing.dbc\n", "can.dbc"),
    ("can:\n  interface: virtual\n  channel: x\n  options: {fd: yes}\n", "can.options.fd"),
    ("can: 3\n", "can"),
])
def test_bad_can_sections_are_refused_naming_the_key(tmp_path, text, key):
    with pytest.raises(ConfigError) as err:
        load_config(_config(tmp_path, text))
    assert err.value.key == key, str(err.value)

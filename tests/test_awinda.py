"""EXPERIMENTAL Awinda support: configuration gate, station steps, snapshot integration (pure)."""

from __future__ import annotations

import math

import pytest

from mocapd.errors import ConfigError
from mocapd.io.xsens_serial import XsensPortConfig, XsensSerialDevice
from mocapd.protocols import xbus
from mocapd.protocols.awinda import AwindaConfig, SnapshotIntegrator, station_steps
from mocapd.protocols.mtdata2 import AwindaSnapshot, decode_mtdata2, encode_packet
from mocapd.protocols.xbus import MID
from mocapd.protocols.xsens_session import State, Streaming, XsensSession, output_settings


def test_experimental_gate_and_unknown_constants() -> None:
    with pytest.raises(ConfigError, match="experimental"):
        AwindaConfig().check()
    with pytest.raises(ConfigError, match="not publicly documented"):
        AwindaConfig(experimental=True).check()
    with pytest.raises(ConfigError, match=r"11\.\.25"):
        AwindaConfig(experimental=True, radio_channel=3, delta_q_scale=1e-9, delta_v_scale=1e-9).check()
    with pytest.raises(ConfigError, match="experimental"):
        XsensSerialDevice(XsensPortConfig("/dev/null"), lambda s: None, awinda=AwindaConfig())


def test_station_bring_up_sends_the_configured_requests() -> None:
    cfg = AwindaConfig(
        experimental=True, radio_channel=21, update_rate_hz=60, delta_q_scale=1.0, delta_v_scale=1.0
    )
    session = XsensSession(output_settings(60), steps=station_steps(cfg))
    session.start(0)
    replies = {
        MID.GOTO_CONFIG: xbus.encode(MID.GOTO_CONFIG_ACK),
        MID.REQ_DID: xbus.encode(MID.DEVICE_ID, bytes.fromhex("12300001")),
        0x04: xbus.encode(0x05),
        MID.ENABLE_MASTER: xbus.encode(MID.ENABLE_MASTER_ACK),
        MID.GOTO_MEASUREMENT: xbus.encode(MID.GOTO_MEASUREMENT_ACK),
    }
    sent = []
    for _ in range(6):
        out = session.data_to_send()
        if not out:
            break
        parser = xbus.XbusParser()
        parser.receive_data(out)
        (msg,) = parser.events_received()
        sent.append((msg.mid, msg.payload))
        session.receive_data(replies[msg.mid], 0)
    assert sent == [
        (MID.GOTO_CONFIG, b""),
        (MID.REQ_DID, b""),
        (0x04, b"\x00\x3c"),
        (MID.ENABLE_MASTER, b"\x00\x15"),
        (MID.GOTO_MEASUREMENT, b""),
    ]
    assert session.state is State.MEASURING
    (ev,) = session.events_received()
    assert isinstance(ev, Streaming) and ev.info.serial == "12300001"


def test_snapshot_integration_of_a_constant_turn() -> None:
    scale = 1e-9
    rate = 100.0
    half_angle_per_frame = 0.5 * math.radians(90.0) / rate  # 90°/s about z
    dq_z = round(math.sin(half_angle_per_frame) / scale)
    integ = SnapshotIntegrator(scale, 1e-6, rate)
    out = None
    for k in range(1, 101):
        snap = AwindaSnapshot(
            0x00B40001, k, (0, 0, dq_z), (0, 0, round(9.81 / rate / 1e-6)), (0, 0, 0), 0, 0, 0, 0, False
        )
        wire = decode_mtdata2(encode_packet(0xC810, snap)).items[0xC810].value
        assert wire == snap
        out = integ.add(snap)
    assert out is not None and out.sensor == "00B40001"
    angle = 2 * math.atan2(out.quat[3], out.quat[0])
    assert angle == pytest.approx(math.radians(90.0), abs=1e-6)
    assert out.acc[2] == pytest.approx(9.81, abs=1e-3)
    assert integ.add(snap) is None and integ.duplicates == 1  # retransmitted / repeated frame

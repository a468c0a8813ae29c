"""EXPERIMENTAL Awinda support: configuration gate, station steps, snapshot integration (pure)."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.rotations import quat_angle, quat_conjugate, quat_multiply
from mocapd.errors import ConfigError
from mocapd.io.xsens_serial import ImuSample, XsensPortConfig, XsensSerialDevice
from mocapd.protocols import xbus
from mocapd.protocols.awinda import AwindaConfig, SnapshotIntegrator, station_steps
from mocapd.protocols.mtdata2 import AwindaSnapshot, decode_mtdata2, encode_packet
from mocapd.protocols.xbus import MID
from mocapd.protocols.xsens_session import State, Streaming, XsensSession, output_settings
from mocapd.sim import xsens as xsens_sim


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
    cfg = AwindaConfig(experimental=True, radio_channel=21, update_rate_hz=60, delta_q_scale=1.0, delta_v_scale=1.0)
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


@pytest.mark.asyncio
async def test_station_path_end_to_end_on_a_pty(tmp_path: Path) -> None:
    """The experimental station path against a simulated station built on the same unverified assumptions."""
    children = [xsens_sim.synthetic_motion(device_id=0x00B40100 + k) for k in range(3)]
    station = xsens_sim.SimStation(children, delta_q_scale=1e-9, delta_v_scale=1e-6)
    sim = xsens_sim.XsensSimulator(tmp_path / "station", station).start()
    cfg = AwindaConfig(experimental=True, update_rate_hz=100, radio_channel=15, delta_q_scale=1e-9, delta_v_scale=1e-6)
    samples: list[ImuSample] = []
    dev = XsensSerialDevice(XsensPortConfig(str(sim.link)), samples.append, awinda=cfg)
    task = asyncio.create_task(dev.run())
    try:
        await _until(lambda: len({s.sensor for s in samples}) == 3 and len(samples) >= 90)
    finally:
        dev.stop()
        await task
        sim.stop()
    assert station.radio_channel == 15 and station.station_rate == 100
    assert dev.info is not None and dev.info.serial == "12300001"
    for motion in children:
        mine = [s for s in samples if s.sensor == f"{motion.device_id:08X}"]
        assert len(mine) >= 20
        # Integrated orientation relative to the first snapshot equals the motion's relative rotation.
        first, last = mine[0], mine[-1]
        assert first.packet_counter is not None and last.packet_counter is not None
        k0, k1 = first.packet_counter - 1, last.packet_counter - 1
        expected = quat_multiply(quat_conjugate(motion.quat[k0]), motion.quat[k1])
        got = quat_multiply(quat_conjugate(np.array(first.quat)), np.array(last.quat))
        assert quat_angle(got, expected) < 1e-4
        assert last.acc is not None and np.allclose(last.acc, motion.acc[k1], atol=1e-3)


async def _until(cond: Callable[[], bool], timeout: float = 10.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not cond():
        if loop.time() > end:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.01)

"""The sans-I/O bring-up session against the simulator's device logic, byte for byte (no ports, no clock)."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.rotations import quat_conjugate, quat_from_matrix, quat_multiply
from mocapd.errors import ConfigError
from mocapd.protocols import xbus
from mocapd.protocols.mtdata2 import CoordFrame, DataId, Precision
from mocapd.protocols.xbus import MID
from mocapd.protocols.xsens_session import (
    BringUpFailed,
    DeviceReportedError,
    DeviceReportedWarning,
    Sample,
    State,
    Streaming,
    XsensSession,
    output_settings,
)
from mocapd.sim import xsens as xsens_sim

MS = 1_000_000


def _pump(session: XsensSession, device: xsens_sim.SimDevice, now: int, rounds: int = 20) -> list[object]:
    events: list[object] = []
    for _ in range(rounds):
        out = session.data_to_send()
        if not out:
            break
        session.receive_data(device.receive(out, now), now)
        events += session.events_received()
    return events


def test_bring_up_and_stream_against_simulated_device() -> None:
    motion = xsens_sim.synthetic_motion(n=50)
    device = xsens_sim.SimDevice(motion)
    session = XsensSession(output_settings(120, precision=Precision.FP1632, frame=CoordFrame.NWU))
    session.start(0)
    events = _pump(session, device, 0)
    assert session.state is State.MEASURING
    (streaming,) = [e for e in events if isinstance(e, Streaming)]
    assert streaming.info.device_id == motion.device_id
    assert streaming.info.product_code == "MTw2-3A7G6" and streaming.info.firmware == "4.6.0"
    assert device.rate_hz == 120
    assert [s.data_id for s in device.settings][2] == DataId.QUATERNION | CoordFrame.NWU | Precision.FP1632
    # Stream three samples and decode them.
    now = 0
    chunks = b""
    for _ in range(3):
        due = device.due_ns(now)
        assert due is not None
        chunks += device.next_message(due)
    session.receive_data(chunks, now)
    samples = [e for e in session.events_received() if isinstance(e, Sample)]
    assert [s.data.packet_counter for s in samples] == [1, 2, 3]
    quat = samples[0].data.quaternion
    assert quat is not None and abs(sum(v * v for v in quat) - 1.0) < 1e-9
    assert samples[0].data.items[DataId.QUATERNION].frame is CoordFrame.NWU


def test_samples_before_config_ack_are_ignored_and_wakeup_is_acknowledged() -> None:
    session = XsensSession(output_settings(100))
    session.start(0)
    sent = session.data_to_send()
    assert sent == xbus.encode(MID.GOTO_CONFIG)
    stray = xbus.encode(MID.MTDATA2, b"")
    session.receive_data(stray + xbus.encode(MID.WAKE_UP), 0)
    assert session.data_to_send() == xbus.encode(MID.WAKE_UP_ACK)
    assert session.counters.ignored_messages == 1
    assert session.events_received() == []


def test_silent_device_is_retried_then_fails_with_the_step_name() -> None:
    session = XsensSession(output_settings(60), response_timeout_ns=100 * MS, attempts=3)
    session.start(0)
    assert session.data_to_send() == xbus.encode(MID.GOTO_CONFIG)
    session.handle_timeout(50 * MS)  # not yet due
    assert session.data_to_send() == b""
    session.handle_timeout(100 * MS)
    session.handle_timeout(200 * MS)
    assert session.data_to_send() == xbus.encode(MID.GOTO_CONFIG) * 2
    assert session.counters.retries == 2
    session.handle_timeout(300 * MS)
    (failed,) = session.events_received()
    assert isinstance(failed, BringUpFailed)
    assert "GoToConfig failed after 3 attempts" in failed.reason and "GOTO_CONFIG_ACK" in failed.reason
    assert session.state is State.FAILED and session.deadline_ns is None


def test_device_error_reply_is_reported_and_retried() -> None:
    session = XsensSession(output_settings(100), attempts=2)
    session.start(0)
    session.data_to_send()
    session.receive_data(xbus.encode(MID.GOTO_CONFIG_ACK), 0)
    session.data_to_send()
    session.receive_data(xbus.encode(MID.ERROR, b"\x04"), 1)
    (err,) = session.events_received()
    assert isinstance(err, DeviceReportedError) and err.report.code == 4
    session.handle_timeout(1)
    assert session.data_to_send() == xbus.encode(MID.REQ_DID)
    session.receive_data(xbus.encode(MID.ERROR, b"\x04"), 2)
    session.handle_timeout(2)
    failed = session.events_received()[-1]
    assert isinstance(failed, BringUpFailed)
    assert failed.reason == "ReqDID failed after 2 attempts: device error 0x04 (message sent is invalid)"


def test_warnings_are_reported_without_stopping_the_stream() -> None:
    session = XsensSession(output_settings(100))
    session.state = State.MEASURING
    session.receive_data(xbus.encode(MID.WARNING, (0x42).to_bytes(4, "big") + b"low battery"), 0)
    (ev,) = session.events_received()
    assert isinstance(ev, DeviceReportedWarning)
    assert ev.warning == xbus.XbusWarning(0x42, "low battery")
    assert session.counters.device_warnings == 1 and session.state is State.MEASURING
    assert xbus.decode_warning(b"\x01").code == -1


def test_rate_outside_60_to_120_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match=r"60\.\.120"):
        output_settings(200)


@pytest.mark.parametrize("frame", [CoordFrame.ENU, CoordFrame.NED])
def test_heading_fault_turns_the_reported_orientation_about_the_vertical(frame: CoordFrame) -> None:
    """A simulated heading error (offset + drift) turns what the device reports about ENU +z by exactly the
    fault's angle at each sample's time; the acceleration (sensor frame) is unchanged."""
    motion = xsens_sim.synthetic_motion(n=300)
    fault = xsens_sim.HeadingFault(offset_deg=30.0, drift_deg_per_min=600.0)  # 10°/s, to see it move
    reported = {}
    for name, heading in (("clean", None), ("faulty", fault)):
        device = xsens_sim.SimDevice(motion, heading=heading)
        session = XsensSession(output_settings(100, frame=frame))
        session.start(0)
        _pump(session, device, 0)
        chunks = b"".join(device.next_message(device.due_ns(0) or 0) for _ in range(150))
        session.receive_data(chunks, 0)
        reported[name] = [e.data for e in session.events_received() if isinstance(e, Sample)]
    assert len(reported["clean"]) == len(reported["faulty"]) == 150
    to_enu = quat_from_matrix(np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])) if frame is CoordFrame.NED else None
    for k in (0, 75, 149):
        clean, faulty = (np.array(reported[n][k].quaternion) for n in ("clean", "faulty"))
        if to_enu is not None:
            clean, faulty = quat_multiply(to_enu, clean), quat_multiply(to_enu, faulty)
        turn = quat_multiply(faulty, quat_conjugate(clean))  # about ENU +z by the fault's angle
        angle = 2.0 * np.arctan2(turn[3], turn[0])
        assert abs(turn[1]) < 1e-6 and abs(turn[2]) < 1e-6
        assert np.degrees(angle) == pytest.approx(np.degrees(fault.angle_rad(k / 100.0)), abs=1e-3)
        assert reported["faulty"][k].acceleration == reported["clean"][k].acceleration

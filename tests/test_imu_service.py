"""ImuInputs: serial devices and the bridge together, status, and calibrated bone orientations."""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import cast

import numpy as np
import pytest

from mocapd.core.imu_calibration import calibrate_tpose
from mocapd.core.rotations import matrix_from_quat, quat_angle, quat_from_matrix, quat_from_rotvec
from mocapd.pipeline.ringbuffer import LookupStatus
from mocapd.protocols.imu_bridge import BridgeRecord, encode_records
from mocapd.protocols.mtdata2 import CoordFrame
from mocapd.service.config.imu import BridgeConfig, ImuConfig
from mocapd.service.imu_inputs import ImuInputs
from mocapd.sim import xsens as xsens_sim


async def _until(cond: Callable[[], bool], timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.01)


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.asyncio
async def test_serial_and_bridge_inputs_feed_one_ingest(tmp_path: Path) -> None:
    q_still = quat_from_rotvec(np.array([0.2, -0.4, 1.0]))
    sims = [
        xsens_sim.XsensSimulator(
            tmp_path / f"imu{k}",
            xsens_sim.SimDevice(xsens_sim.still_motion(q_still, device_id=0x00B40200 + k)),
        ).start()
        for k in range(2)
    ]
    port = _free_udp_port()
    config = ImuConfig(
        ports=tuple(str(s.link) for s in sims),
        bridge=BridgeConfig(enabled=True, port=port),
    )
    inputs = ImuInputs(config)
    task = asyncio.create_task(inputs.run())
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    # The bridge sensor reports in NED; it must be buffered in ENU.
    ned_from_enu = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])
    q_ned = quat_from_matrix(ned_from_enu @ matrix_from_quat(q_still))
    try:
        await _until(lambda: all(d.streaming.is_set() for d in inputs.devices))
        for k in range(30):
            quat = (float(q_ned[0]), float(q_ned[1]), float(q_ned[2]), float(q_ned[3]))
            rec = BridgeRecord("00B40300", k / 60, quat, (0.0, 0.0, 9.81), CoordFrame.NED, k)
            sender.sendto(encode_records([rec]), ("127.0.0.1", port))
            await asyncio.sleep(1 / 60)
        await _until(
            lambda: len(inputs.ingest.streams) == 3 and all(len(s.buffer) >= 20 for s in inputs.ingest.streams.values())
        )
        status = inputs.status()
        devices = cast(list[dict[str, object]], status["devices"])
        assert [d["serial"] for d in devices] == ["00B40200", "00B40201"]
        assert cast(dict[str, int], status["bridge"])["records"] == 30
        # All three sensors hold the same still orientation; calibrate them as a 3-bone T-pose.
        recordings = {
            sid: (s.buffer.rows()[:, 0:4].copy(), s.buffer.rows()[:, 4:7].copy())
            for sid, s in inputs.ingest.streams.items()
        }
        bones = {"00B40200": "Hips", "00B40201": "Head", "00B40300": "LeftFoot"}
        calib = calibrate_tpose("p", recordings, bones, facing_heading_deg=10.0, window=10)
        ranges = [inputs.ingest.streams[sid].buffer.time_range() for sid in ("00B40200", "00B40201")]
        t_serial = min(r[1] for r in ranges if r is not None)
        result = {b.bone: b for b in inputs.bone_orientations(t_serial - 1_000_000, calib)}
        for bone in ("Hips", "Head"):
            assert result[bone].status is LookupStatus.OK
            assert quat_angle(result[bone].quat, np.array([1.0, 0, 0, 0])) < 1e-5  # type: ignore[arg-type]
        assert result["LeftFoot"].status in (LookupStatus.OK, LookupStatus.AFTER, LookupStatus.BEFORE)
        # The NED bridge input was re-expressed in ENU: same mounting as the serial sensors.
        assert quat_angle(calib.q_ib["00B40300"], calib.q_ib["00B40200"]) < 1e-5
    finally:
        sender.close()
        inputs.stop()
        await task
        for s in sims:
            s.stop()

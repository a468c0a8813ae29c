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


@pytest.mark.asyncio
async def test_new_sensor_ids_on_the_bridge_cannot_grow_the_daemon_or_evict_a_suit(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Issue 18 D4: datagrams each naming a new sensor id gave every id a buffer (~100 KiB) and a /status entry,
    without a cap. Built on the one assembly path (the synthetic rig's suit), the daemon holds at most
    ``MAX_OTHER_SENSORS`` unconfigured sensors, counts the evictions in /status, and keeps the suit's sensors."""
    from mocapd.pipeline.imu_ingest import MAX_OTHER_SENSORS
    from mocapd.service.assembly import assembled
    from mocapd.service.config import load_config
    from mocapd.service.demo.synthetic import synthetic_config

    cfg = load_config()
    bridge = cfg.imu.bridge.model_copy(update={"enabled": True, "port": 0})
    cfg = synthetic_config(cfg.model_copy(update={"imu": cfg.imu.model_copy(update={"bridge": bridge})}))
    with assembled(cfg) as demo:
        imu = demo.daemon.imu
        (suit,) = demo.daemon.rig.suits
        assert imu.bridge is not None
        port = await imu.bridge.start()
        sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:

            async def send(records: list[BridgeRecord]) -> None:
                before = imu.bridge.stats.datagrams if imu.bridge else 0
                for r in records:
                    sender.sendto(encode_records([r]), ("127.0.0.1", port))
                await _until(lambda: imu.bridge is not None and imu.bridge.stats.datagrams == before + len(records))

            def rec(sensor: str, k: int) -> BridgeRecord:
                return BridgeRecord(sensor, 1.0 + k / 100, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 9.81), CoordFrame.ENU, k)

            await send([rec(sid, k) for k in range(3) for sid in suit.sensors[:2]])
            for start in range(0, 700, 50):  # 700 ids, in bursts the socket's buffer holds
                await send([rec(f"F{k:07X}", 0) for k in range(start, start + 50)])
            st = imu.status()
        finally:
            sender.close()
            imu.bridge.close()
    sensors = cast(dict[str, dict[str, int]], st["sensors"])
    assert len(sensors) == 2 + MAX_OTHER_SENSORS
    assert st["sensors_evicted"] == 700 - MAX_OTHER_SENSORS
    assert all(sensors[sid]["buffered"] == 3 for sid in suit.sensors[:2])
    assert f"F{699:07X}" in sensors and f"F{0:07X}" not in sensors
    assert not [r for r in caplog.records if r.exc_info]

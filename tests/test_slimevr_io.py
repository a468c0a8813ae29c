"""The SlimeVR server socket on loopback, driven by a client no one here wrote: the PyPI package
``slimevr-tracker-emulator`` (0.0.2, MIT), plus hostile datagrams from a plain socket."""

from __future__ import annotations

import asyncio
import contextlib
import math
import socket
from collections.abc import AsyncIterator, Callable

import numpy as np
import pytest
from slimevr_tracker_emulator.async_tracker_emulator import SlimeVRTrackerEmulatorAsync
from slimevr_tracker_emulator.tracker_types import (
    ImuType,
    SensorAcceleration,
    SensorData,
    SensorPosition,
    SensorRotationQuat,
    SensorState,
)

from mocapd.errors import DeviceError
from mocapd.io.slimevr import SlimeVrListener
from mocapd.io.xsens_serial import ImuSample
from mocapd.protocols.mtdata2 import CoordFrame
from mocapd.service.config.schema import validate

# The emulator's handshake writes its firmware string with a NUL the length byte does not count, so a SlimeVR
# server (and mocapd, reading it the same way) sees its MAC 78:78:78:78:78:78 one byte early.
EMULATOR_MAC = "00:78:78:78:78:78"


def sensor(k: int) -> SensorData:
    return SensorData(k, SensorState.SENSOR_OK, ImuType.BNO080, SensorRotationQuat(0.0, 0.0, 0.0, 1.0),
                      SensorAcceleration(0.0, 0.0, 0.0), SensorPosition(0.0, 0.0, 0.0))  # fmt: skip


async def wait_for(cond: Callable[[], bool], timeout: float, what: str) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not cond():
        if loop.time() > end:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.02)


@contextlib.asynccontextmanager
async def emulator(port: int, n_sensors: int) -> AsyncIterator[SlimeVRTrackerEmulatorAsync]:
    emu = SlimeVRTrackerEmulatorAsync()
    for k in range(n_sensors):
        await emu.set_tracker(sensor(k))
    task = asyncio.create_task(emu.run(("127.0.0.1", port)))
    try:
        yield emu
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        if emu.sock is not None:
            emu.sock.close()


@pytest.mark.asyncio
async def test_emulated_tracker_connects_and_streams_every_sensor() -> None:
    got: list[ImuSample] = []
    listener = SlimeVrListener(got.append, port=0)
    port = await listener.start()
    runner = asyncio.create_task(listener.run())
    try:
        async with emulator(port, 3) as emu:
            await wait_for(lambda: len(listener.server.trackers) == 1, 5, "the handshake")
            # A quarter turn about +Z for sensor 2, as the emulator's x, y, z, w.
            s = math.sqrt(0.5)
            await emu.set_tracker_rotation(2, SensorRotationQuat(0.0, 0.0, s, s))
            await emu.set_tracker_acceleration(2, SensorAcceleration(0.5, 0.0, 0.0))
            want = f"{EMULATOR_MAC}/2"

            def turned() -> bool:
                return any(x.sensor == want and x.quat is not None and abs(x.quat[3] - s) < 1e-6 for x in got)

            await wait_for(turned, 10, "the turned orientation")
            await wait_for(lambda: listener.server.trackers[EMULATOR_MAC].rtt_ms is not None, 5, "a ping echo")
        st = listener.status()
        (tracker,) = st["trackers"]
        assert tracker["id"] == EMULATOR_MAC and tracker["protocol_version"] == 17 and tracker["firmware"] == "0.4.0"
        assert [x["id"] for x in tracker["sensors"]] == [f"{EMULATOR_MAC}/{k}" for k in range(3)]
        assert tracker["lost"] == 0 and tracker["reordered"] == 0
        assert st["bad_datagrams"] == 0 and st["unknown_source"] == 0
        assert {x.sensor for x in got} == {f"{EMULATOR_MAC}/{k}" for k in range(3)}
        assert all(x.frame is CoordFrame.ENU and x.device_ticks is None for x in got)
        assert any(x.sensor == want and x.quat == pytest.approx((s, 0.0, 0.0, s)) for x in got)
    finally:
        listener.close()
        await asyncio.wait_for(runner, 2)


@pytest.mark.asyncio
async def test_hostile_datagrams_are_counted_and_the_server_goes_on() -> None:
    got: list[ImuSample] = []
    listener = SlimeVrListener(got.append, port=0)
    port = await listener.start()
    runner = asyncio.create_task(listener.run())
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind(("127.0.0.1", 0))
        sock.sendto(b"\x00\x00\x00\x03" + bytes(8) + b"\x00\x00\x00\x02", ("127.0.0.1", port))  # a short handshake
        for junk in (b"", b"\x01", bytes(11), b"\xff" * 40, bytes.fromhex("00000011" + "00" * 8 + "0001") + bytes(17)):
            sock.sendto(junk, ("127.0.0.1", port))
        await wait_for(lambda: listener.server.counters.datagrams >= 6, 5, "the datagrams")
        st = listener.status()
        assert st["bad_datagrams"] == 5 and len(st["trackers"]) == 1
        # The reply went back to the sender.
        sock.settimeout(2)
        reply, _ = sock.recvfrom(100)
        assert reply.startswith(b"\x03Hey OVR =D 5")
    finally:
        sock.close()
        listener.close()
        await asyncio.wait_for(runner, 2)


@pytest.mark.asyncio
async def test_calibration_recording_hears_slimevr_sensors() -> None:
    from mocapd.service.cli.imu import record
    from mocapd.service.config.imu import ImuConfig

    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    ids = [f"{EMULATOR_MAC}/{k}" for k in range(2)]
    assignment = dict(zip(ids, ["Hips", "Head"], strict=True))
    config = validate(ImuConfig, {"slimevr": {"enabled": True, "port": port, "assignment": assignment}})
    async with emulator(port, 2):
        samples = await record(config, 1.0, 10.0)
    assert set(samples) == set(ids)
    # Still trackers go quiet; the server's holding keeps the recording dense enough for the still window.
    assert all(len(v) >= 20 for v in samples.values())


def test_calibrated_heading_resets_apply_to_buffered_samples() -> None:
    from mocapd.core.imu_calibration import ImuCalibration
    from mocapd.service.config.imu import ImuConfig
    from mocapd.service.imu_inputs import ImuInputs

    sid = f"{EMULATOR_MAC}/0"
    ident = (1.0, 0.0, 0.0, 0.0)
    calib = ImuCalibration("p", 0.0, "subject", np.array(ident), {sid: "Hips"}, {sid: np.array(ident)}, {sid: 0.0},
                           device_heading_deg={sid: 90.0})  # fmt: skip
    inputs = ImuInputs(ImuConfig())
    inputs.use_calibrations([calib])
    for k, other in enumerate((sid, "00B421E6")):
        inputs.on_sample(ImuSample(other, 1_000 + k, None, None, ident, (0.0, 0.0, 9.8), CoordFrame.ENU))
    s = math.sqrt(0.5)
    assert inputs.ingest.streams[sid].buffer.rows()[0, 0:4] == pytest.approx((s, 0.0, 0.0, s))  # Rz(90°)
    assert inputs.ingest.streams["00B421E6"].buffer.rows()[0, 0:4] == pytest.approx(ident)


def test_mount_yaw_option_covers_slimevr_sensors_only() -> None:
    from mocapd.errors import ConfigError
    from mocapd.service.cli.imu import _own_heading
    from mocapd.service.config.imu import ImuConfig

    a, b = f"{EMULATOR_MAC}/0", f"{EMULATOR_MAC}/1"
    config = ImuConfig(assignment={a: "Hips", b: "LeftFoot", "00B421E6": "Head"})
    assert _own_heading(config.sensors, [f"{b.lower()}=-90"]) == {a: 0.0, b: -90.0}
    for bad in ("00B421E6=90", f"{a}=left", "90"):
        with pytest.raises(ConfigError, match="--mount-yaw"):
            _own_heading(config.sensors, [bad])


@pytest.mark.asyncio
async def test_a_taken_port_is_a_named_opening_failure() -> None:
    first = SlimeVrListener(lambda s: None, port=0)
    port = await first.start()
    second = SlimeVrListener(lambda s: None, port=port)
    assert second.open_state().state == "opening"
    try:
        with pytest.raises(DeviceError, match=f"cannot bind udp 127.0.0.1:{port}"):
            await second.start()
        assert first.open_state().state == "open"
        state = second.open_state()
        assert state.state == "failed" and f"127.0.0.1:{port}" in state.error
    finally:
        first.close()

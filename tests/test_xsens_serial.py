"""mocapd's real serial path (pyserial + asyncio) against simulated devices on real pseudo-terminals."""

from __future__ import annotations

import asyncio
import os
import select
import tty
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.rotations import quat_angle
from mocapd.errors import DeviceError, DeviceTimeout
from mocapd.io.xsens_serial import ImuSample, XsensPortConfig, XsensSerialDevice
from mocapd.pipeline.imu_ingest import ImuIngest
from mocapd.pipeline.ringbuffer import LookupStatus
from mocapd.sim import xsens as xsens_sim

MTW = Path(__file__).parent / "data" / "opensense_mtw"


async def _until(cond: Callable[[], bool], timeout: float = 10.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not cond():
        if loop.time() > end:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.01)


@pytest.fixture
def sims(tmp_path: Path) -> Iterator[list[xsens_sim.XsensSimulator]]:
    motions = [xsens_sim.load_opensense(p) for p in sorted(MTW.glob("*.txt"))[:2]]
    motions.append(xsens_sim.synthetic_motion(device_id=0x00B40042))
    # 10 % of each fault: over the >= 90 samples the test waits for, missing one kind has probability < 1e-4
    # (samples sent before the port is opened are flushed by the open, so the seed alone does not decide).
    faults = [xsens_sim.Faults(), xsens_sim.Faults(), xsens_sim.Faults(0.1, 0.1, 0.1, seed=7)]
    started = [
        xsens_sim.XsensSimulator(tmp_path / f"imu{k}", xsens_sim.SimDevice(m, faults=f)).start()
        for k, (m, f) in enumerate(zip(motions, faults, strict=True))
    ]
    yield started
    for sim in started:
        sim.stop()


@pytest.mark.asyncio
async def test_three_devices_stream_into_ring_buffers(sims: list[xsens_sim.XsensSimulator]) -> None:
    ingest = ImuIngest()
    received: list[ImuSample] = []

    def on_sample(s: ImuSample) -> None:
        received.append(s)
        ingest.add(
            s.sensor,
            s.host_ns,
            device_ticks=s.device_ticks,
            packet_counter=s.packet_counter,
            quat=s.quat,
            acc=s.acc,
        )

    devices = [XsensSerialDevice(XsensPortConfig(str(sim.link), rate_hz=120), on_sample) for sim in sims]
    tasks = [asyncio.create_task(d.run()) for d in devices]
    try:
        await _until(lambda: all(d.stats.samples >= 90 for d in devices))
    finally:
        for d in devices:
            d.stop()
        await asyncio.gather(*tasks)

    for sim, dev in zip(sims, devices, strict=True):
        assert dev.info is not None and dev.info.device_id == sim.device.motion.device_id
        assert sim.device.rate_hz == 120
        assert dev.stats.connects == 1 and dev.stats.disconnects == 0
        stream = ingest.streams[dev.info.serial]
        assert len(stream.buffer) >= 80
        # Every sample carries the motion file's orientation/acceleration for its packet counter (float32).
        motion = sim.device.motion
        mine = [s for s in received if s.sensor == dev.info.serial]
        for s in mine:
            assert s.packet_counter is not None and s.quat is not None and s.acc is not None
            row = (s.packet_counter - 1) % len(motion.quat)
            assert quat_angle(np.array(s.quat), motion.quat[row]) < 1e-6
            assert np.allclose(s.acc, motion.acc[row], atol=1e-5)
        # The buffer interpolates between its samples at any time inside its range.
        t0, t1 = stream.buffer.time_range()  # type: ignore[misc]
        mid = stream.buffer.sample((t0 + t1) // 2)
        assert mid.status is LookupStatus.OK
        assert stream.buffer.sample(t1 + 1).status is LookupStatus.AFTER

    faulty_dev = devices[2]
    assert faulty_dev.session is not None
    counters = faulty_dev.session.parser.counters
    stats = sims[2].device.stats
    assert stats.bad_checksums > 0 and stats.dropped > 0 and stats.garbage > 0
    assert counters.checksum_errors >= 1 and counters.discarded_bytes > 0
    assert faulty_dev.info is not None
    assert ingest.streams[faulty_dev.info.serial].counter_gaps >= 1
    for dev in devices[:2]:
        assert dev.session is not None and dev.session.parser.counters.checksum_errors == 0


@pytest.mark.asyncio
async def test_unplug_and_replug_reconnects_on_the_same_path(tmp_path: Path) -> None:
    sim = xsens_sim.XsensSimulator(
        tmp_path / "imu", xsens_sim.SimDevice(xsens_sim.synthetic_motion(device_id=0x00B40007))
    ).start()
    samples: list[ImuSample] = []
    dev = XsensSerialDevice(
        XsensPortConfig(str(sim.link), rate_hz=60, reconnect_min_s=0.05, reconnect_max_s=0.2), samples.append
    )
    task = asyncio.create_task(dev.run())
    try:
        await _until(lambda: len(samples) >= 10)
        sim.unplug()
        await _until(lambda: dev.stats.disconnects == 1)
        await _until(lambda: dev.last_error is not None and "cannot open" in dev.last_error)
        assert not sim.link.exists()
        before = len(samples)
        sim.replug()
        await _until(lambda: dev.stats.connects == 2 and len(samples) >= before + 10)
        assert dev.streaming.is_set() and dev.last_error is None
        assert {s.sensor for s in samples} == {"00B40007"}
    finally:
        dev.stop()
        await task
        sim.stop()


@pytest.mark.asyncio
async def test_silent_port_fails_bring_up_with_a_clear_error(tmp_path: Path) -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    link = tmp_path / "silent"
    link.symlink_to(os.ttyname(slave))
    try:
        dev = XsensSerialDevice(XsensPortConfig(str(link), response_timeout_s=0.05, attempts=2), lambda s: None)
        with pytest.raises(DeviceTimeout, match="GoToConfig failed after 2 attempts"):
            await dev.run_once()
        assert dev.stats.bringup_failures == 1
        # Two GoToConfig requests reached the "device".
        got = b""
        while len(got) < 10 and select.select([master], [], [], 1.0)[0]:
            got += os.read(master, 100)
        assert got == bytes.fromhex("faff3000d1") * 2
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.asyncio
async def test_missing_port_is_a_device_error(tmp_path: Path) -> None:
    dev = XsensSerialDevice(XsensPortConfig(str(tmp_path / "nothing")), lambda s: None)
    with pytest.raises(DeviceError, match="cannot open serial port"):
        await dev.run_once()


@pytest.mark.asyncio
async def test_silent_stream_is_detected_as_a_stall_and_reopened(tmp_path: Path) -> None:
    sim = xsens_sim.XsensSimulator(tmp_path / "imu", xsens_sim.SimDevice(xsens_sim.synthetic_motion())).start()
    samples: list[ImuSample] = []
    dev = XsensSerialDevice(
        XsensPortConfig(str(sim.link), stall_timeout_s=0.3, reconnect_min_s=0.05, reconnect_max_s=0.1),
        samples.append,
    )
    task = asyncio.create_task(dev.run())
    try:
        await _until(lambda: len(samples) >= 5)
        sim.device.faults.dropout = 1.0  # the device still answers but stops sending samples
        await _until(lambda: dev.stats.stalls >= 1 and dev.stats.connects >= 2)
        assert any("no data for 0.3 s while streaming" in f for f in dev.stats.failures)
        sim.device.faults.dropout = 0.0
        before = len(samples)
        await _until(lambda: len(samples) >= before + 5)
    finally:
        dev.stop()
        await task
        sim.stop()


@pytest.mark.asyncio
async def test_stop_interrupts_the_back_off(tmp_path: Path) -> None:
    dev = XsensSerialDevice(
        XsensPortConfig(str(tmp_path / "absent"), reconnect_min_s=30.0, reconnect_max_s=30.0), lambda s: None
    )
    task = asyncio.create_task(dev.run())
    await _until(lambda: dev.last_error is not None)
    dev.stop()
    await asyncio.wait_for(task, timeout=5.0)  # far shorter than the 30 s back-off it was sleeping
    assert "cannot open serial port" in (dev.last_error or "")


@pytest.mark.asyncio
async def test_immediate_replug_on_reused_descriptors(tmp_path: Path) -> None:
    """Unplug and replug back to back: the new pty usually gets the old descriptor numbers."""
    sim = xsens_sim.XsensSimulator(tmp_path / "imu", xsens_sim.SimDevice(xsens_sim.synthetic_motion())).start()
    samples: list[ImuSample] = []
    dev = XsensSerialDevice(XsensPortConfig(str(sim.link), reconnect_min_s=0.05), samples.append)
    task = asyncio.create_task(dev.run())
    try:
        await _until(lambda: len(samples) >= 5)
        for cycle in range(1, 4):
            sim.unplug()
            sim.replug()
            await _until(lambda c=cycle: dev.stats.connects == c + 1 and dev.streaming.is_set())  # type: ignore[misc]
            before = len(samples)
            await _until(lambda b=before: len(samples) >= b + 5)  # type: ignore[misc]
        assert sim.generation == 4 and dev.stats.disconnects == 3
    finally:
        dev.stop()
        await task
        sim.stop()

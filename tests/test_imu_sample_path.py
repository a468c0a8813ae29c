"""The per-sample path of a serial Xsens device (bytes → session → device → inputs → ring buffer) gives the same
samples, times and buffer contents, bit for bit, as the plain numpy computation it replaced (issues 39, 45: the
path runs 1300 times a second for a suit, on the event loop).

The byte stream is a simulated MTw's (:class:`mocapd.sim.xsens.SimDevice`) replaying the real MTw orientations and
accelerations of ``tests/data/opensense_mtw``, several messages per read as the loop sees them when it is busy.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.rotations import quat_multiply, quat_multiply_floats
from mocapd.io.xsens_serial import ImuSample, XsensPortConfig, XsensSerialDevice
from mocapd.pipeline.imu_ingest import ImuIngest
from mocapd.protocols.mtdata2 import DataId, MtData2, decode_mtdata2
from mocapd.protocols.xbus import MID, XbusParser
from mocapd.protocols.xsens_session import Sample, State, Streaming, XsensSession, output_settings
from mocapd.service.config.imu import ImuConfig
from mocapd.service.imu_inputs import ImuInputs
from mocapd.sim import xsens as xsens_sim

DATA = Path(__file__).parent / "data"
MTW = DATA / "opensense_mtw"


def real_mtw_reads(path: Path, n: int = 600) -> tuple[Streaming, list[tuple[int, bytes]]]:
    """The Streaming event of a simulated MTw replaying a real recording, and ``n`` of its messages as
    (host time, bytes) reads of 1 to 4 messages each."""
    dev = xsens_sim.SimDevice(xsens_sim.load_opensense(path))
    session = XsensSession(output_settings(100))
    now = 1_000_000_000
    session.start(now)
    for _ in range(50):
        out = session.data_to_send()
        if out:
            session.receive_data(dev.receive(out, now), now)
        now += 1_000_000
        session.handle_timeout(now)
    assert session.state is State.MEASURING
    (streaming,) = [e for e in session.events_received() if isinstance(e, Streaming)]
    dev.due_ns(now)
    messages = [dev.next_message(now) for _ in range(n)]
    sizes = np.random.default_rng(7).integers(1, 5, size=n)
    reads: list[tuple[int, bytes]] = []
    k = 0
    for size in sizes:
        if k >= n:
            break
        now += 10_000_000 * int(size) + 37_000 * (k % 5)  # host stamps with jitter
        reads.append((now, b"".join(messages[k : k + int(size)])))
        k += int(size)
    return streaming, reads


def device_samples(streaming: Streaming, reads: list[tuple[int, bytes]]) -> list[ImuSample]:
    """What a streaming :class:`XsensSerialDevice` hands its callback for these reads."""
    got: list[ImuSample] = []
    device = XsensSerialDevice(XsensPortConfig("/dev/ttyMTW"), got.append)
    session = XsensSession(output_settings(100))
    session.state = State.MEASURING
    session._events.append(streaming)
    device._dispatch(session, [], reads[0][0])
    for now, data in reads:
        session.receive_data(data, now)
        device._dispatch(session, [], now)
    return got


def bits(x: object) -> bytes:
    return np.asarray(x, dtype=np.float64).tobytes()


def test_the_float_product_is_the_numpy_product_bit_for_bit() -> None:
    rng = np.random.default_rng(1)
    for path in sorted(MTW.glob("*.txt")):
        quats = xsens_sim.load_opensense(path).quat
        for q in quats[:: max(1, len(quats) // 500)]:
            angle = rng.uniform(-np.pi, np.pi)
            h = np.array([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)])
            g = rng.normal(size=4)
            for a in (h, g / np.linalg.norm(g)):
                b = tuple(float(v) for v in q)
                assert bits(quat_multiply_floats(tuple(float(v) for v in a), b)) == bits(quat_multiply(a, np.array(b)))


def test_headed_samples_are_buffered_as_the_numpy_product_gave_them() -> None:
    paths = sorted(MTW.glob("*.txt"))
    inputs = ImuInputs(ImuConfig())
    reference = ImuIngest(capacity=inputs.ingest.capacity)
    streams = [real_mtw_reads(p) for p in paths]
    sensors = [s.info.serial for s, _ in streams]
    turn, again = (np.array([np.cos(a), 0.0, 0.0, np.sin(a)]) for a in (0.35, -0.1))
    inputs.turn_headings({sensors[0]: turn})
    inputs.turn_headings({sensors[0]: again})  # a second turn composes with the first
    heading0 = quat_multiply(again, turn)
    for (streaming, reads), sensor in zip(streams, sensors, strict=True):
        samples = device_samples(streaming, reads)
        assert len(samples) == 600
        for s in samples:
            inputs.on_sample(s)
            quat = s.quat
            if sensor == sensors[0] and quat is not None:
                quat = tuple(float(v) for v in quat_multiply(heading0, np.array(quat)))  # the old code's
            reference.add(
                s.sensor, s.host_ns, device_ticks=s.device_ticks, packet_counter=s.packet_counter, quat=quat, acc=s.acc
            )
    for sensor in sensors:
        new, old = inputs.ingest.streams[sensor].buffer, reference.streams[sensor].buffer
        assert new.times().tobytes() == old.times().tobytes()
        assert new.rows().tobytes() == old.rows().tobytes()
    raw = np.array([s.quat for s in device_samples(*streams[0])])
    turned = inputs.ingest.streams[sensors[0]].buffer.rows()[:, 0:4]
    assert not np.allclose(turned, raw[-len(turned) :], atol=0.1)  # the heading was applied


def accessor_fields(d: MtData2) -> tuple[object, ...]:
    """What the device read of a message before :meth:`MtData2.imu_fields`: the properties, one by one."""
    quat_item = d.items.get(DataId.QUATERNION)
    return (
        d.packet_counter,
        d.sample_time_fine,
        d.quaternion,
        d.acceleration,
        quat_item.frame if quat_item is not None else None,
    )


def test_imu_fields_are_the_accessors_on_real_captures() -> None:
    payloads: list[bytes] = []
    for i in range(1, 6):  # real MTi captures: counter, time, acceleration, no quaternion, other outputs
        parser = XbusParser()
        parser.receive_data((DATA / "xbus_einride" / str(i) / "output.bin").read_bytes())
        payloads += [m.payload for m in parser.events_received() if m.mid == MID.MTDATA2]
    _, reads = real_mtw_reads(sorted(MTW.glob("*.txt"))[0], n=200)
    parser = XbusParser()
    parser.receive_data(b"".join(data for _, data in reads))
    payloads += [m.payload for m in parser.events_received() if m.mid == MID.MTDATA2]
    assert len(payloads) == 700
    for p in payloads:
        d = decode_mtdata2(p)
        fields = d.imu_fields()
        assert fields == accessor_fields(d)
        assert all(a is b or (a == b and type(a) is type(b)) for a, b in zip(fields, accessor_fields(d), strict=True))


def test_device_samples_are_those_the_accessors_built() -> None:
    streaming, reads = real_mtw_reads(sorted(MTW.glob("*.txt"))[1])
    samples = device_samples(streaming, reads)
    expected: list[ImuSample] = []
    session = XsensSession(output_settings(100))
    session.state = State.MEASURING
    for now, data in reads:
        session.receive_data(data, now)
        for ev in session.events_received():
            assert isinstance(ev, Sample)
            c, t, q, a, frame = accessor_fields(ev.data)
            expected.append(ImuSample(streaming.info.serial, now, t, c, q, a, frame))  # type: ignore[arg-type]
    assert samples == expected
    assert {s.sensor for s in samples} == {f"{streaming.info.device_id:08X}"}


def test_the_sensor_id_follows_the_device_brought_up() -> None:
    got: list[ImuSample] = []
    device = XsensSerialDevice(XsensPortConfig("/dev/ttyMTW"), got.append)
    streams = [real_mtw_reads(p, n=20) for p in sorted(MTW.glob("*.txt"))]
    session = XsensSession(output_settings(100))
    session.state = State.MEASURING
    for streaming, reads in streams:  # a different device on the same port after a reconnect
        session._events.append(streaming)
        for now, data in reads:
            session.receive_data(data, now)
            device._dispatch(session, [], now)
    assert [s.sensor for s in got] == [s.info.serial for s, r in streams for _ in range(20)]
    device.info = None
    session.receive_data(streams[0][1][0][1], 0)
    device._dispatch(session, [], 0)
    assert got[-1].sensor == "/dev/ttyMTW"


def reference_add(ingest: ImuIngest, s: ImuSample) -> int | None:
    """:meth:`ImuIngest.add` as it was: the newest time from ``time_range``, the row written field by field."""
    stream = ingest.stream(s.sensor)
    stream.last_host_ns = s.host_ns
    if s.quat is None or s.acc is None:
        stream.incomplete += 1
        return None
    if s.packet_counter is not None:
        if stream.last_counter is not None and s.packet_counter != (stream.last_counter + 1) & 0xFFFF:
            stream.counter_gaps += 1
        stream.last_counter = s.packet_counter
    t = s.host_ns
    device_s = np.nan
    if s.device_ticks is not None:
        stream.clock.update(s.device_ticks, s.host_ns)
        mapped = stream.clock.to_host_ns(s.device_ticks)
        t = mapped if mapped is not None else s.host_ns
        device_s = s.device_ticks / 10_000.0
    newest = stream.buffer.time_range()
    if newest is not None and t <= newest[1]:
        stream.clock_steps_back += 1
        t = newest[1] + 1
    values = {"quat": s.quat, "acc": s.acc, "device_time_s": [device_s]}
    values["packet_counter"] = [np.nan if s.packet_counter is None else s.packet_counter]
    return t if stream.buffer.push_fields(t, values) else None


def test_ingest_buffers_what_the_field_by_field_code_did() -> None:
    new, old = ImuIngest(capacity=256), ImuIngest(capacity=256)
    for path in sorted(MTW.glob("*.txt")):
        streaming, reads = real_mtw_reads(path)
        samples = device_samples(streaming, reads)
        # host stamps that step back and a device clock that resets: the clamped and re-fitted branches too
        samples[300:310] = [replace(s, host_ns=s.host_ns - 40_000_000) for s in samples[300:310]]
        samples[400:] = [replace(s, device_ticks=(s.device_ticks or 0) // 7) for s in samples[400:]]
        samples[450] = replace(samples[450], quat=None)
        samples[451] = replace(samples[451], packet_counter=None, device_ticks=None)
        for s in samples:
            assert new.add(
                s.sensor,
                s.host_ns,
                device_ticks=s.device_ticks,
                packet_counter=s.packet_counter,
                quat=s.quat,
                acc=s.acc,
            ) == reference_add(old, s)
    assert new.streams.keys() == old.streams.keys()
    for sensor, a in new.streams.items():
        b = old.streams[sensor]
        assert a.buffer.times().tobytes() == b.buffer.times().tobytes()
        assert a.buffer.rows().tobytes() == b.buffer.rows().tobytes()
        counts = ("incomplete", "counter_gaps", "clock_steps_back", "last_counter", "last_host_ns")
        assert [getattr(a, k) for k in counts] == [getattr(b, k) for k in counts]
        assert a.buffer.rejected_out_of_order == b.buffer.rejected_out_of_order
        assert a.clock_steps_back > 0 and a.incomplete == 1


def test_a_cleared_buffer_takes_any_time_and_then_only_later_ones() -> None:
    ingest = ImuIngest(capacity=8)
    buffer = ingest.stream("S").buffer
    row = np.arange(9.0)
    assert buffer.newest_ns() is None
    assert buffer.push(100, row) and buffer.push(200, row) and not buffer.push(200, row)
    assert buffer.newest_ns() == 200
    buffer.clear()
    assert buffer.newest_ns() is None
    assert buffer.push(50, row) and not buffer.push(40, row) and buffer.newest_ns() == 50
    for t in range(60, 200, 10):  # wraps the ring
        assert buffer.push(t, row)
    assert buffer.newest_ns() == buffer.time_range()[1] == 190  # type: ignore[index]
    with pytest.raises(ValueError):
        ingest.add("S", 0, device_ticks=None, packet_counter=None, quat=(1.0, 0.0, 0.0), acc=(0.0, 0.0, 9.8, 1.0))

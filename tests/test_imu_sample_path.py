"""The per-sample path of a serial Xsens device (bytes → session → device → inputs → ring buffer) gives the same
samples, times and buffer contents, bit for bit, as the plain numpy computation it replaced (issues 39, 45: the
path runs 1300 times a second for a suit, on the event loop).

The byte stream is a simulated MTw's (:class:`mocapd.sim.xsens.SimDevice`) replaying the real MTw orientations and
accelerations of ``tests/data/opensense_mtw``, several messages per read as the loop sees them when it is busy.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocapd.core.rotations import quat_multiply, quat_multiply_floats
from mocapd.io.xsens_serial import ImuSample, XsensPortConfig, XsensSerialDevice
from mocapd.pipeline.imu_ingest import ImuIngest
from mocapd.protocols.xsens_session import State, Streaming, XsensSession, output_settings
from mocapd.service.config.imu import ImuConfig
from mocapd.service.imu_inputs import ImuInputs
from mocapd.sim import xsens as xsens_sim

MTW = Path(__file__).parent / "data" / "opensense_mtw"


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

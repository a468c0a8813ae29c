"""IMU ingest: clock mapping into per-sensor ring buffers, counter gaps, incomplete samples."""

from __future__ import annotations

import itertools

from mocapd.pipeline.imu_ingest import ImuIngest
from mocapd.pipeline.ringbuffer import LookupStatus

MS = 1_000_000
Q = (1.0, 0.0, 0.0, 0.0)
A = (0.0, 0.0, 9.81)


def test_samples_are_buffered_at_their_mapped_device_time() -> None:
    ingest = ImuIngest(capacity=64)
    base = 10_000 * MS
    times = []
    for k in range(40):
        jitter = (k % 3) * MS  # arrival delays 0..2 ms; the device clock is exact
        t = ingest.add(
            "00B40001",
            base + k * 10 * MS + jitter,
            device_ticks=5000 + k * 100,
            packet_counter=k,
            quat=Q,
            acc=A,
        )
        assert t is not None
        times.append(t)
    steps = {b - a for a, b in itertools.pairwise(times[20:])}
    assert all(abs(s - 10 * MS) < 20_000 for s in steps)  # jitter removed: 10 ms apart within 20 µs
    stream = ingest.streams["00B40001"]
    assert len(stream.buffer) == 40 and stream.counter_gaps == 0
    r = stream.buffer.sample(times[-1] - 5 * MS)
    assert r.status is LookupStatus.OK
    assert stream.buffer.field(r.row, "device_time_s")[0] == (5000 + 38.5 * 100) / 10_000


def test_gaps_incomplete_and_no_device_time() -> None:
    ingest = ImuIngest()
    assert ingest.add("a", 1 * MS, device_ticks=None, packet_counter=1, quat=Q, acc=A) == 1 * MS
    ingest.add("a", 2 * MS, device_ticks=None, packet_counter=3, quat=Q, acc=A)
    assert ingest.add("a", 3 * MS, device_ticks=None, packet_counter=4, quat=None, acc=A) is None
    ingest.add("a", 4 * MS, device_ticks=None, packet_counter=0xFFFF, quat=Q, acc=A)
    ingest.add("a", 5 * MS, device_ticks=None, packet_counter=0, quat=Q, acc=A)  # wraps: no gap
    stream = ingest.streams["a"]
    assert stream.counter_gaps == 2 and stream.incomplete == 1
    # Host time not after the newest sample: kept, 1 ns after it, and counted.
    assert ingest.add("a", 5 * MS, device_ticks=None, packet_counter=1, quat=Q, acc=A) == 5 * MS + 1
    assert stream.clock_steps_back == 1


def test_unconfigured_sensors_are_a_bounded_table_that_evicts_the_longest_silent() -> None:
    """Issue 18 D4: every new sensor id got a buffer and a status entry, without a cap. Now at most
    ``max_other_sensors`` unconfigured sensors are held; a new one evicts the one silent longest (counted); the
    kept (configured) sensors are never evicted."""
    ingest = ImuIngest(capacity=16, max_other_sensors=4)
    ingest.keep(["SUIT0", "SUIT1"])
    ingest.add("SUIT0", 1 * MS, device_ticks=None, packet_counter=None, quat=Q, acc=A)
    for k in range(100):
        ingest.add(f"X{k}", (2 + k) * MS, device_ticks=None, packet_counter=None, quat=Q, acc=A)
        if k >= 50:  # X3 (evicted early on) comes back and keeps speaking
            ingest.add("X3", (2 + k) * MS + 1, device_ticks=None, packet_counter=None, quat=Q, acc=A)
    assert set(ingest.streams) == {"SUIT0", "X3", "X97", "X98", "X99"}
    assert ingest.evicted == 101 - 4  # 100 new ids and X3 again, 4 held
    ingest.add("SUIT1", 200 * MS, device_ticks=None, packet_counter=None, quat=Q, acc=A)  # kept: evicts nothing
    assert len(ingest.streams) == 6 and ingest.evicted == 97
    assert len(ingest.streams["SUIT0"].buffer) == 1
    ingest.keep(["X99"])  # a sensor that becomes configured leaves the table of others
    ingest.add("Y", 300 * MS, device_ticks=None, packet_counter=None, quat=Q, acc=A)  # 4 others again: no eviction
    ingest.add("Z", 301 * MS, device_ticks=None, packet_counter=None, quat=Q, acc=A)  # evicts X97, silent longest
    assert set(ingest.streams) == {"SUIT0", "SUIT1", "X99", "X3", "X98", "Y", "Z"} and ingest.evicted == 98

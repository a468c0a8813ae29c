"""Ring buffer: wrap-around, interpolation (linear, slerp, nearest), out-of-range reporting."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from mocapd.core.rotations import quat_angle, quat_from_rotvec, quat_slerp, random_quat
from mocapd.errors import InputError
from mocapd.pipeline.ringbuffer import IMU_FIELDS, FieldSpec, LookupStatus, RingBuffer

MS = 1_000_000


def _imu_buffer(capacity: int = 8) -> RingBuffer:
    return RingBuffer(capacity, IMU_FIELDS, max_gap_ns=50 * MS)


def test_empty_before_after() -> None:
    buf = _imu_buffer()
    assert buf.sample(0).status is LookupStatus.EMPTY
    assert buf.latest() is None and buf.time_range() is None
    for i in range(3):
        buf.push_fields(
            i * 10 * MS, {"quat": [1, 0, 0, 0], "acc": [i, 0, 0], "device_time_s": [i], "packet_counter": [i]}
        )
    assert buf.sample(-1).status is LookupStatus.BEFORE
    after = buf.sample(20 * MS + 1)
    assert after.status is LookupStatus.AFTER and np.isnan(after.row).all()
    assert (after.t_before, after.t_after) == (0, 20 * MS)


def test_linear_and_nearest_interpolation() -> None:
    buf = _imu_buffer()
    buf.push(0, [1, 0, 0, 0, 0.0, 2.0, -4.0, 0.0, 10])
    buf.push(10 * MS, [1, 0, 0, 0, 1.0, 4.0, 4.0, 0.01, 11])
    r = buf.sample(3 * MS)
    assert r.status is LookupStatus.OK
    assert np.allclose(buf.field(r.row, "acc"), [0.3, 2.6, -1.6])
    assert buf.field(r.row, "packet_counter")[0] == 10
    assert buf.field(buf.sample(7 * MS).row, "packet_counter")[0] == 11
    exact = buf.sample(10 * MS)
    assert exact.status is LookupStatus.OK and buf.field(exact.row, "acc")[0] == 1.0


def test_slerp_matches_core_slerp() -> None:
    rng = np.random.default_rng(0)
    q0, q1 = random_quat(rng, (2,))
    buf = _imu_buffer()
    buf.push(0, [*q0, 0, 0, 0, 0, 0])
    buf.push(8 * MS, [*q1, 0, 0, 0, 0, 0])
    got = buf.field(buf.sample(2 * MS).row, "quat")
    assert quat_angle(got, quat_slerp(q0, q1, 0.25)) < 1e-9


def test_slerp_takes_the_short_arc_across_sign_flip() -> None:
    q0 = quat_from_rotvec(np.array([0.0, 0.1, 0.0]))
    q1 = -quat_from_rotvec(np.array([0.0, 0.3, 0.0]))  # same rotation family, opposite sign
    buf = _imu_buffer()
    buf.push(0, [*q0, 0, 0, 0, 0, 0])
    buf.push(10 * MS, [*q1, 0, 0, 0, 0, 0])
    got = buf.field(buf.sample(5 * MS).row, "quat")
    assert quat_angle(got, quat_from_rotvec(np.array([0.0, 0.2, 0.0]))) < 1e-9


def test_wrap_around_keeps_newest_and_stays_contiguous() -> None:
    buf = RingBuffer(4, [FieldSpec("x", 1)])
    for i in range(11):
        assert buf.push(i * MS, [float(i)])
    assert len(buf) == 4 and buf.overwritten == 7
    assert list(buf.times()) == [7 * MS, 8 * MS, 9 * MS, 10 * MS]
    assert list(buf.rows()[:, 0]) == [7, 8, 9, 10]
    assert buf.sample(6 * MS).status is LookupStatus.BEFORE
    assert buf.sample(int(8.5 * MS)).row[0] == pytest.approx(8.5)
    latest = buf.latest()
    assert latest is not None and latest[0] == 10 * MS


def test_out_of_order_rejected_and_gap_reported() -> None:
    buf = RingBuffer(4, [FieldSpec("x", 1)], max_gap_ns=5 * MS)
    assert buf.push(10 * MS, [0.0])
    assert not buf.push(10 * MS, [1.0])
    assert not buf.push(9 * MS, [1.0])
    assert buf.rejected_out_of_order == 2
    buf.push(30 * MS, [1.0])
    gap = buf.sample(20 * MS)
    assert gap.status is LookupStatus.GAP and (gap.t_before, gap.t_after) == (10 * MS, 30 * MS)
    buf.clear()
    assert buf.sample(20 * MS).status is LookupStatus.EMPTY


def test_generic_widths_for_keypoint_streams() -> None:
    buf = RingBuffer(16, [FieldSpec("kp", 17 * 2), FieldSpec("conf", 17)])
    a, b = np.zeros(51), np.ones(51)
    buf.push(0, a)
    buf.push(2 * MS, b)
    r = buf.sample(MS)
    assert buf.field(r.row, "kp").shape == (34,) and np.allclose(r.row, 0.5)


def test_bad_layouts_raise() -> None:
    with pytest.raises(InputError, match="capacity"):
        RingBuffer(1, [FieldSpec("x", 1)])
    with pytest.raises(InputError, match="unique"):
        RingBuffer(4, [FieldSpec("x", 1), FieldSpec("x", 2)])
    with pytest.raises(InputError, match="width 4"):
        RingBuffer(4, [FieldSpec("q", 3, "slerp")])


def test_push_does_not_grow_memory() -> None:
    buf = RingBuffer(256, IMU_FIELDS)
    row = np.array([1.0, 0, 0, 0, 0, 0, 9.81, 0, 0])
    for i in range(512):  # wrap once so every slot has been written
        buf.push(i, row)
    tracemalloc.start()
    before, _ = tracemalloc.get_traced_memory()
    for i in range(512, 20_512):
        buf.push(i, row)
    after, _ = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert after - before < 4096  # fixed storage: 20 000 pushes leave nothing behind

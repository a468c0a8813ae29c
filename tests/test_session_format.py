"""Session stream framing on bytes: round trips, a golden record, CRC and length corruption, truncation at every
offset, delivery split at every offset, resynchronisation."""

from __future__ import annotations

import struct
import zlib
from dataclasses import replace

import numpy as np
import pytest

from mocapd.errors import InputError
from mocapd.protocols import session_format as sf


def _pose(frame: int, n_people: int = 2) -> sf.PoseRecord:
    rng = np.random.default_rng(frame)
    people = tuple(
        sf.PersonRecord(f"track:{k}" if k else "suit:suit0", None if k else "suit0", k, 4, 0 if k else 13, 7,
                        bool(k % 2 == 0), 0.8, rng.normal(size=66), rng.normal(size=(21, 3)))
        for k in range(n_people)
    )  # fmt: skip
    return sf.PoseRecord(frame, 10_000 + frame, 20_000 + frame, 1, people)


def _stream(n: int = 5) -> tuple[bytes, list[int]]:
    """A header and n pose records; returns the bytes and the end offset of each record."""
    data = sf.encode_record(sf.T_HEADER, sf.encode_header("poses"))
    ends = [len(data)]
    for i in range(1, n + 1):
        data += sf.encode_record(sf.T_POSE, sf.encode_pose(_pose(i)))
        ends.append(len(data))
    return data, ends


def test_golden_record_bytes() -> None:
    rec = sf.encode_record(sf.T_IMU, b"abc")
    head = b"MR\x01\x01\x03\x00\x00\x00"
    assert rec == head + b"abc" + struct.pack("<I", zlib.crc32(head + b"abc"))
    assert len(rec) == 3 + sf.OVERHEAD


def test_payload_round_trips() -> None:
    p = _pose(3)
    q = sf.decode_pose(sf.encode_pose(p))
    assert q.frame == 3 and q.t_solve_ns == p.t_solve_ns and q.tick_ns == p.tick_ns and q.missing_cameras == 1
    for a, b in zip(p.people, q.people, strict=True):
        assert (a.identity, a.suit, a.track, a.views, a.imus, a.iterations, a.converged) == (
            b.identity, b.suit, b.track, b.views, b.imus, b.iterations, b.converged)  # fmt: skip
        assert np.array_equal(a.theta, b.theta)  # float64: exact
        assert np.allclose(a.joints, b.joints, atol=1e-6)  # float32
        assert b.confidence == pytest.approx(0.8, abs=1e-7)
    imu = sf.ImuRecord("00B42001", 5, 6, None, 65535, (1.0, 0.0, 0.0, 0.0), (0.1, 9.8, -0.2))
    assert sf.decode_imu(sf.encode_imu(imu)) == imu
    imu2 = sf.ImuRecord("x", -1, 6, 123456789, None, (0.5, 0.5, 0.5, 0.5), (0.0, 0.0, 0.0))
    assert sf.decode_imu(sf.encode_imu(imu2)) == imu2
    kp = np.random.default_rng(0).uniform(0, 1000, (3, 17, 2))
    cf = np.full((3, 17), 0.9)
    k = sf.decode_keypoints(sf.encode_keypoints(2, 111, 222, kp, cf))
    assert (k.camera, k.capture_ns, k.arrival_ns) == (2, 111, 222)
    assert np.allclose(k.keypoints, kp, atol=1e-4) and np.allclose(k.confidences, cf)
    empty = sf.decode_keypoints(sf.encode_keypoints(0, 1, 2, np.zeros((0, 17, 2)), np.zeros((0, 17))))
    assert empty.keypoints.shape == (0, 17, 2)
    assert sf.decode_header(sf.encode_header("imu"))["stream"] == "imu"


def test_bad_payloads_and_arguments_are_errors() -> None:
    with pytest.raises(InputError):
        sf.decode_keypoints(sf.encode_keypoints(0, 1, 2, np.zeros((1, 17, 2)), np.zeros((1, 17)))[:-4])
    with pytest.raises(InputError):
        sf.decode_pose(sf.encode_pose(_pose(1)) + b"x")
    with pytest.raises(InputError):
        sf.decode_header(b"{not json")
    with pytest.raises(InputError):
        sf.decode_header(b'{"format": "other"}')
    with pytest.raises(InputError):
        sf.encode_record(9, b"")


def test_every_split_point_gives_the_same_records() -> None:
    data, _ = _stream(3)
    whole = sf.StreamDecoder()
    whole.receive_data(data)
    expected = whole.records_received()
    assert [r.rtype for r in expected] == [sf.T_HEADER, sf.T_POSE, sf.T_POSE, sf.T_POSE]
    for cut in range(len(data) + 1):
        d = sf.StreamDecoder()
        d.receive_data(data[:cut])
        got = d.records_received()
        d.receive_data(data[cut:])
        got += d.records_received()
        assert got == expected and d.pending == 0 and d.counters.corrupt == 0


def test_truncation_at_every_offset_keeps_every_whole_record_and_reports_the_tail() -> None:
    data, ends = _stream(3)
    for cut in range(len(data) + 1):
        d = sf.StreamDecoder()
        d.receive_data(data[:cut])
        tail = d.finish()
        whole = sum(1 for e in ends if e <= cut)
        assert len(d.records_received()) == whole, cut
        last_end = max([0] + [e for e in ends if e <= cut])
        assert tail == cut - last_end and d.counters.corrupt == 0


def test_a_corrupt_record_is_counted_and_skipped() -> None:
    data, ends = _stream(5)
    for pos in (ends[1] + 1, ends[2] + 3, ends[2] + 40, ends[3] - 2):  # sync, type, payload, CRC of a record
        bad = bytearray(data)
        bad[pos] ^= 0x5A
        d = sf.StreamDecoder()
        d.receive_data(bytes(bad))
        tail = d.finish()
        frames = [sf.decode_pose(r.payload).frame for r in d.records_received() if r.rtype == sf.T_POSE]
        lost = 2 if pos < ends[2] else 3
        assert frames == [f for f in range(1, 6) if f != lost], pos
        assert d.counters.corrupt >= 1 and tail == 0


def test_an_impossible_length_or_garbage_between_records_resynchronises() -> None:
    data, ends = _stream(3)
    bad = bytearray(data)
    bad[ends[1] + 4 : ends[1] + 8] = struct.pack("<I", sf.MAX_PAYLOAD + 1)
    d = sf.StreamDecoder()
    d.receive_data(bytes(bad))
    d.finish()
    assert [sf.decode_pose(r.payload).frame for r in d.records_received()[1:]] == [1, 3]
    # A plausible but wrong length (waits for bytes that never come): finish() finds the records after it.
    bad = bytearray(data)
    bad[ends[1] + 4 : ends[1] + 8] = struct.pack("<I", 10_000)
    d = sf.StreamDecoder()
    d.receive_data(bytes(bad))
    assert d.finish() == 0
    assert [sf.decode_pose(r.payload).frame for r in d.records_received()[1:]] == [1, 3]
    # Garbage (with a false sync word) between records, and an unknown but well-framed record type.
    junk = b"\x00MR\xff" * 5
    unknown = bytearray(sf.encode_record(sf.T_IMU, b"zz"))
    unknown[2] = 7
    unknown[-4:] = struct.pack("<I", zlib.crc32(bytes(unknown[:-4])))
    d = sf.StreamDecoder()
    d.receive_data(data[: ends[2]] + junk + bytes(unknown) + data[ends[2] :])
    d.finish()
    assert [sf.decode_pose(r.payload).frame for r in d.records_received()[1:]] == [1, 2, 3]
    assert d.counters.corrupt >= 1 and d.counters.skipped_bytes >= len(junk) - 1 and d.counters.unknown_types == 1


def test_pose_records_carry_each_persons_sized_skeleton() -> None:
    """θ is only meaningful on its skeleton: a body-sized person's offsets travel with their pose."""
    from dataclasses import replace

    from mocapd.core.skeleton import Skeleton

    tall = Skeleton.from_height(1.93)
    p = _pose(4)
    sized = replace(p, people=(replace(p.people[0], skeleton=tall), p.people[1]))
    q = sf.decode_pose(sf.encode_pose(sized))
    assert q.people[1].skeleton is None
    got = q.people[0].skeleton
    assert got is not None
    np.testing.assert_allclose(got.offsets, tall.offsets, atol=1e-6)  # float32 on disk
    assert abs(got.height - 1.93) < 1e-6 and abs(got.root_height - tall.root_height) < 1e-6
    assert len(sf.encode_pose(sized)) == len(sf.encode_pose(p)) + 8 + 63 * 4


def test_pose_records_carry_the_output_mode_and_each_poses_instant() -> None:
    p = _pose(4, n_people=3)
    people = (replace(p.people[0], t_pose_ns=p.t_solve_ns + 140_000_000), *p.people[1:])
    predicted = replace(p, people=people, output="predicted")
    q = sf.decode_pose(sf.encode_pose(predicted))
    assert q.output == "predicted"
    assert [x.t_pose_ns for x in q.people] == [p.t_solve_ns + 140_000_000, p.t_solve_ns, p.t_solve_ns]
    # A record written before the tail existed (no output byte, no instants) reads as delayed.
    old = sf.encode_pose(p)[: -(1 + 8 * 3)]
    r = sf.decode_pose(old)
    assert r.output == "delayed" and all(x.t_pose_ns is None for x in r.people)
    with pytest.raises(InputError, match="output"):
        sf.encode_pose(replace(p, output="early"))
    with pytest.raises(InputError, match="output mode"):
        sf.decode_pose(old + bytes([7]) + bytes(24))


def test_long_identities_are_cut_on_a_character_boundary() -> None:
    """Issue 45: an identity over 254 bytes was cut at byte 254, inside a UTF-8 character: the record failed to decode
    (173 of 242 records of a session). Now it is cut before the character and decodes to its first characters."""
    person = _pose(1, 1).people[0]
    for identity in ("é" * 200, "a" + "€" * 100, "🦴" * 70):
        rec = replace(_pose(1, 1), people=(replace(person, identity=identity, suit=identity),))
        back = sf.decode_pose(sf.encode_pose(rec)).people[0]
        assert back.identity is not None and identity.startswith(back.identity)
        assert 251 <= len(back.identity.encode()) <= 254 and back.suit == back.identity

"""The camera-host protocol (mocapd.protocols.remote) on bytes: round trips, each field's rule, garbage."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mocapd.core.sorting import Detections2D
from mocapd.protocols.remote import (
    CameraState,
    ClockMessage,
    Decoder,
    DetectionsMessage,
    StatusMessage,
    encode_clock,
    encode_detections,
    encode_status,
)


def _dets(n: int = 2, n_kp: int = 17) -> Detections2D:
    rng = np.random.default_rng(0)
    kp = rng.uniform(0, 500, (n, n_kp, 2)).astype(np.float32).astype(np.float64)
    cf = rng.uniform(0, 1, (n, n_kp)).astype(np.float32).astype(np.float64)
    return Detections2D(kp, cf)


def _fields(n: int = 2) -> list[object]:
    return msgpack.unpackb(encode_detections("hostA", "cam1", 2**64 - 1, 7, 123, 456, 640, 480, _dets(n)))  # type: ignore[no-any-return]


def test_detections_round_trip_bit_exact_in_float32() -> None:
    dets = _dets()
    data = encode_detections("hostA", "cam1", 99, 7, 10**18, 10**18 + 5, 640, 480, dets)
    assert data[:2] == b"\x9e\x01"  # array of 14, version 1
    assert data[2:6] == b"\xa3det"
    msg = Decoder().decode(data)
    assert isinstance(msg, DetectionsMessage)
    assert (msg.host, msg.camera, msg.run_id, msg.frame) == ("hostA", "cam1", 99, 7)
    assert (msg.capture_ns, msg.sent_ns, msg.width, msg.height) == (10**18, 10**18 + 5, 640, 480)
    np.testing.assert_array_equal(msg.detections.keypoints, dets.keypoints)
    np.testing.assert_array_equal(msg.detections.confidences, dets.confidences)
    np.testing.assert_allclose(msg.boxes[0, :2], dets.keypoints[0].min(axis=0), rtol=1e-6)


def test_no_people_is_a_valid_frame() -> None:
    msg = Decoder().decode(encode_detections("h", "c", 0, 0, 0, 0, 1, 1, Detections2D.empty(17)))
    assert (
        isinstance(msg, DetectionsMessage) and len(msg.detections) == 0 and msg.detections.keypoints.shape == (0, 17, 2)
    )


def test_status_and_clock_round_trip() -> None:
    d = Decoder()
    s = d.decode(encode_status("h-1", 5, 77, 12.5, [CameraState("c1", 10, True), CameraState("c2", 0, False)]))
    assert s == StatusMessage("h-1", 5, 77, 12.5, (CameraState("c1", 10, True), CameraState("c2", 0, False)))
    assert d.decode(encode_clock("h-1", 5, 2**63 - 1)) == ClockMessage("h-1", 5, 2**63 - 1)
    assert d.rejected == {}


F32_NAN = np.array([np.nan], "<f4").tobytes()
F32_INF = np.array([np.inf], "<f4").tobytes()


def _kp_with(value: float) -> bytes:
    kp = np.full((2, 17, 2), 10.0, "<f4")
    kp[1, 3, 0] = value
    return kp.tobytes()


# position in the det array -> (bad value, reason)
BAD_FIELDS: list[tuple[int, object, str]] = [
    (0, 2, "version"), (0, True, "version"), (1, "nope", "kind"),
    (2, "", "host"), (2, "a b", "host"), (2, "x" * 33, "host"), (2, 5, "host"),
    (3, "cam/1", "camera"), (3, b"cam1", "camera"),
    (4, -1, "run_id"), (4, 1.0, "run_id"),
    (5, -1, "frame"), (5, 2**63, "frame"), (5, True, "frame"),
    (6, -5, "capture_ns"), (6, 1.5, "capture_ns"), (6, None, "capture_ns"),
    (7, 2**63, "sent_ns"),
    (8, 0, "width"), (8, 65536, "width"), (9, 0, "height"),
    (10, 0, "n_kp"), (10, 257, "n_kp"), (10, 18, "keypoints"),
    (11, b"\x00" * 4, "boxes"), (11, "boxes", "boxes"),
    (12, b"\x00" * 7, "keypoints"), (12, [1.0], "keypoints"),
    (12, _kp_with(float("nan")), "keypoints_not_finite"), (12, _kp_with(float("inf")), "keypoints_not_finite"),
    (12, _kp_with(-641.0), "keypoints_range"), (12, _kp_with(1281.0), "keypoints_range"),
    (13, np.full((2, 17), 1.5, "<f4").tobytes(), "confidences_range"),
    (13, np.full((2, 17), -0.1, "<f4").tobytes(), "confidences_range"),
    (13, np.full((2, 17), np.nan, "<f4").tobytes(), "confidences_not_finite"),
    (13, b"", "confidences"),
    (11, np.array([[5, 5, 1, 9], [0, 0, 1, 1]], "<f4").tobytes(), "boxes_range"),
]  # fmt: skip


@pytest.mark.parametrize(("pos", "value", "reason"), BAD_FIELDS, ids=lambda v: repr(v)[:24])
def test_each_field_out_of_rule_is_counted_under_its_reason(pos: int, value: object, reason: str) -> None:
    fields = _fields()
    fields[pos] = value
    d = Decoder()
    assert d.decode(msgpack.packb(fields, use_bin_type=True)) is None
    assert d.rejected == {reason: 1}


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"", "not_msgpack"), (b"\xc1", "not_msgpack"), (b"\x92\x01", "not_msgpack"),
        (msgpack.packb({"v": 1}), "not_msgpack"), (msgpack.packb(1), "not_a_message"),
        (msgpack.packb([1]), "not_a_message"),
        (msgpack.packb([1, "det", "h"]), "length"), (msgpack.packb([1, "status"]), "length"),
        (msgpack.packb([1, "clock", "h", 1, -1]), "now_ns"),
        (msgpack.packb([1, "status", "h", 1, 1, float("nan"), []]), "uptime_s"),
        (msgpack.packb([1, "status", "h", 1, 1, 1.0, [["c", 1, 1]]]), "cameras"),
        (msgpack.packb(encode_detections("h", "c", 0, 0, 0, 0, 1, 1, Detections2D.empty(1))) + b"\x00", "not_msgpack"),
        (b"\x00" * (2**20 + 1), "too_large"),
    ],
)  # fmt: skip
def test_malformed_messages_are_counted(data: bytes, reason: str) -> None:
    d = Decoder()
    assert d.decode(data) is None
    assert d.rejected == {reason: 1}


def test_more_than_64_people_is_refused() -> None:
    d = Decoder()
    assert d.decode(encode_detections("h", "c", 0, 0, 0, 0, 640, 480, _dets(65))) is None
    assert d.rejected == {"people": 1}


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=512))
def test_garbage_bytes_never_raise(data: bytes) -> None:
    d = Decoder()
    out = d.decode(data)
    assert (out is None) == (sum(d.rejected.values()) == 1)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 400), st.integers(0, 255))
def test_a_corrupted_byte_never_raises_and_never_gives_non_finite_pixels(where: int, byte: int) -> None:
    data = bytearray(encode_detections("hostA", "cam1", 3, 7, 123, 456, 640, 480, _dets(1)))
    data[where % len(data)] = byte
    msg = Decoder().decode(bytes(data))
    if isinstance(msg, DetectionsMessage):
        assert np.isfinite(msg.detections.keypoints).all()
        assert ((msg.detections.confidences >= 0) & (msg.detections.confidences <= 1)).all()

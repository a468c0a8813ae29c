"""Camera hosts → solver host, protocol version 1: one camera-frame's detections, a host's status and its clock
(sans-I/O; carried over Zenoh by :mod:`mocapd.io.zenoh_link`, documented byte by byte in docs/scaling.md).

Every message is one msgpack **array** (positional: the smallest encoding, and a decoder that checks each
position's type cannot be fooled by a missing or extra key). Element 0 is the protocol version (positive
fixint ``0x01``), element 1 the message kind (a fixstr: ``"det"``, ``"status"``, ``"clock"``)::

    det     [1, "det", host, camera, run_id, frame, capture_ns, sent_ns, width, height, n_kp,
             boxes, keypoints, confidences]
    status  [1, "status", host, run_id, sent_ns, uptime_s, cameras]      cameras: [[name, frames, up], ...]
    clock   [1, "clock", host, run_id, now_ns]                           a clock query's reply

``host``/``camera``: str of 1-32 letters, digits, ``_ . -``; ``run_id``: uint64 drawn at random when the camera
host starts (a restarted host is a new run: its frame numbers start again); ``frame``: the camera's frame number in
this run (uint63, increasing); ``capture_ns``/``sent_ns``/``now_ns``: the host's monotonic clock (int63 ns);
``width``/``height``: the image size in pixels (1..65535); ``n_kp``: keypoints per person (1..256);
``boxes``/``keypoints``/``confidences``: msgpack bin of little-endian float32, ``n * 4`` (x0, y0, x1, y1),
``n * n_kp * 2`` (x, y) and ``n * n_kp`` values for ``n`` people (0..64). Pixels are finite and within
``[-width, 2 width] x [-height, 2 height]`` (a detector places a keypoint a little outside the image, never
that far); confidences are in [0, 1]; boxes have x0 <= x1, y0 <= y1; a frame is sent after it was captured
(``sent_ns >= capture_ns``, both on the host's clock).

A decoder never raises on bytes: what does not parse or breaks a rule is counted under a reason
(:attr:`Decoder.rejected`) and dropped.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
from numpy.typing import NDArray

from mocapd.core.sorting import Detections2D

VERSION = 1
MAX_MESSAGE_BYTES = 1 << 20
MAX_PEOPLE = 64
MAX_KEYPOINTS = 256
MAX_INT63 = 2**63 - 1
MAX_UINT64 = 2**64 - 1
MAX_CAMERAS = 64
_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,32}$")
_F32 = np.dtype("<f4")

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class DetectionsMessage:
    """One camera frame's detections as a camera host sent them (times on that host's clock)."""

    host: str
    camera: str
    run_id: int
    frame: int
    capture_ns: int
    sent_ns: int
    width: int
    height: int
    detections: Detections2D
    boxes: FloatArray
    """(n, 4) x0, y0, x1, y1 of each person's confident keypoints."""


@dataclass(frozen=True, slots=True)
class CameraState:
    name: str
    frames: int
    up: bool


@dataclass(frozen=True, slots=True)
class StatusMessage:
    host: str
    run_id: int
    sent_ns: int
    uptime_s: float
    cameras: tuple[CameraState, ...]


@dataclass(frozen=True, slots=True)
class ClockMessage:
    host: str
    run_id: int
    now_ns: int


Message = DetectionsMessage | StatusMessage | ClockMessage


def boxes_of(dets: Detections2D) -> FloatArray:
    """(n, 4) bounding boxes of each person's keypoints with confidence > 0 (all keypoints if none has)."""
    n = len(dets)
    out = np.zeros((n, 4))
    for p in range(n):
        seen = dets.confidences[p] > 0
        pts = dets.keypoints[p][seen] if seen.any() else dets.keypoints[p]
        out[p] = (*pts.min(axis=0), *pts.max(axis=0))
    return out


def encode_detections(
    host: str, camera: str, run_id: int, frame: int, capture_ns: int, sent_ns: int,
    width: int, height: int, dets: Detections2D,
) -> bytes:  # fmt: skip
    """The ``det`` message of one camera frame (see the module docstring)."""
    n_kp = int(dets.keypoints.shape[1])
    data: bytes = msgpack.packb(
        [VERSION, "det", host, camera, run_id, frame, capture_ns, sent_ns, width, height, n_kp,
         boxes_of(dets).astype(_F32).tobytes(), dets.keypoints.astype(_F32).tobytes(),
         dets.confidences.astype(_F32).tobytes()],
        use_bin_type=True,
    )  # fmt: skip
    return data


def encode_status(host: str, run_id: int, sent_ns: int, uptime_s: float, cameras: list[CameraState]) -> bytes:
    data: bytes = msgpack.packb(
        [VERSION, "status", host, run_id, sent_ns, float(uptime_s), [[c.name, c.frames, c.up] for c in cameras]],
        use_bin_type=True,
    )
    return data


def encode_clock(host: str, run_id: int, now_ns: int) -> bytes:
    data: bytes = msgpack.packb([VERSION, "clock", host, run_id, now_ns], use_bin_type=True)
    return data


class Rejected(Exception):  # noqa: N818 (internal control flow of the decoder, never escapes it)
    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def _int(v: Any, lo: int, hi: int, what: str) -> int:
    if type(v) is not int or not lo <= v <= hi:
        raise Rejected(what)
    return v


def _name(v: Any, what: str) -> str:
    if type(v) is not str or not _NAME.match(v):
        raise Rejected(what)
    return v


def _floats(v: Any, count: int, what: str) -> FloatArray:
    if type(v) is not bytes or len(v) != count * 4:
        raise Rejected(what)
    with np.errstate(invalid="ignore"):  # a signalling NaN in the bytes: refused just below, not warned about
        out = np.frombuffer(v, dtype=_F32).astype(np.float64)
    if not np.isfinite(out).all():
        raise Rejected(f"{what}_not_finite")
    return out


class Decoder:
    """Bytes → messages; everything else counted under a reason in :attr:`rejected` (never raises)."""

    def __init__(self) -> None:
        self.rejected: Counter[str] = Counter()
        self.decoded = 0

    def decode(self, data: bytes) -> Message | None:
        try:
            msg = self._decode(data)
        except Rejected as r:
            self.rejected[r.reason] += 1
            return None
        self.decoded += 1
        return msg

    def _decode(self, data: bytes) -> Message:
        if len(data) > MAX_MESSAGE_BYTES:
            raise Rejected("too_large")
        try:
            obj = msgpack.unpackb(
                data, raw=False, strict_map_key=True, use_list=True,
                max_bin_len=MAX_MESSAGE_BYTES, max_str_len=1024, max_array_len=4096, max_map_len=0,
                max_ext_len=0,
            )  # fmt: skip
        except (ValueError, TypeError, msgpack.exceptions.ExtraData, msgpack.exceptions.UnpackException,
                RecursionError):  # fmt: skip
            raise Rejected("not_msgpack") from None
        if type(obj) is not list or len(obj) < 2:
            raise Rejected("not_a_message")
        if obj[0] != VERSION or type(obj[0]) is not int:
            raise Rejected("version")
        kind = obj[1]
        if kind == "det":
            return self._detections(obj)
        if kind == "status":
            return self._status(obj)
        if kind == "clock":
            return self._clock(obj)
        raise Rejected("kind")

    @staticmethod
    def _detections(obj: list[Any]) -> DetectionsMessage:
        if len(obj) != 14:
            raise Rejected("length")
        host = _name(obj[2], "host")
        camera = _name(obj[3], "camera")
        run_id = _int(obj[4], 0, MAX_UINT64, "run_id")
        frame = _int(obj[5], 0, MAX_INT63, "frame")
        capture_ns = _int(obj[6], 0, MAX_INT63, "capture_ns")
        sent_ns = _int(obj[7], 0, MAX_INT63, "sent_ns")
        if sent_ns < capture_ns:
            raise Rejected("sent_before_capture")
        width = _int(obj[8], 1, 65535, "width")
        height = _int(obj[9], 1, 65535, "height")
        n_kp = _int(obj[10], 1, MAX_KEYPOINTS, "n_kp")
        if type(obj[12]) is not bytes or len(obj[12]) % (n_kp * 8):
            raise Rejected("keypoints")
        n = len(obj[12]) // (n_kp * 8)
        if n > MAX_PEOPLE:
            raise Rejected("people")
        boxes = _floats(obj[11], n * 4, "boxes").reshape(n, 4)
        kp = _floats(obj[12], n * n_kp * 2, "keypoints").reshape(n, n_kp, 2)
        cf = _floats(obj[13], n * n_kp, "confidences").reshape(n, n_kp)
        x, y = kp[..., 0], kp[..., 1]
        if ((x < -width) | (x > 2 * width) | (y < -height) | (y > 2 * height)).any():
            raise Rejected("keypoints_range")
        if ((cf < 0) | (cf > 1)).any():
            raise Rejected("confidences_range")
        if ((boxes[:, 0] > boxes[:, 2]) | (boxes[:, 1] > boxes[:, 3])).any():
            raise Rejected("boxes_range")
        return DetectionsMessage(host, camera, run_id, frame, capture_ns, sent_ns, width, height,
                                 Detections2D(kp, cf), boxes)  # fmt: skip

    @staticmethod
    def _status(obj: list[Any]) -> StatusMessage:
        if len(obj) != 7:
            raise Rejected("length")
        host = _name(obj[2], "host")
        run_id = _int(obj[3], 0, MAX_UINT64, "run_id")
        sent_ns = _int(obj[4], 0, MAX_INT63, "sent_ns")
        uptime = obj[5]
        if type(uptime) is not float or not math.isfinite(uptime) or not 0 <= uptime <= 1e10:
            raise Rejected("uptime_s")
        if type(obj[6]) is not list or len(obj[6]) > MAX_CAMERAS:
            raise Rejected("cameras")
        cams = []
        for c in obj[6]:
            if type(c) is not list or len(c) != 3 or type(c[2]) is not bool:
                raise Rejected("cameras")
            cams.append(CameraState(_name(c[0], "cameras"), _int(c[1], 0, MAX_INT63, "cameras"), c[2]))
        return StatusMessage(host, run_id, sent_ns, uptime, tuple(cams))

    @staticmethod
    def _clock(obj: list[Any]) -> ClockMessage:
        if len(obj) != 5:
            raise Rejected("length")
        return ClockMessage(_name(obj[2], "host"), _int(obj[3], 0, MAX_UINT64, "run_id"),
                            _int(obj[4], 0, MAX_INT63, "now_ns"))  # fmt: skip

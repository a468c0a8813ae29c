"""Session stream framing (version 1): length + type + CRC32 records, and the payloads of each record type.

A session stream file is a sequence of records; the first one is a :data:`T_HEADER` record. All integers are
little-endian. One record::

    offset  size  field
    0       2     sync        b"MR" (0x4D 0x52): where to look for the next record after a corrupt one
    2       1     type        T_HEADER=0, T_IMU=1, T_KEYPOINTS=2, T_POSE=3, T_FRAME=4, T_EVENT=5
    3       1     version     payload version of this type (1)
    4       4     length      n, payload bytes (uint32, at most MAX_PAYLOAD)
    8       n     payload     see below
    8+n     4     crc32       zlib.crc32 of bytes [0, 8+n) (sync, type, version, length and payload)

Payloads (struct formats; ``f4``/``f8`` arrays are little-endian float32/float64, C order):

- ``T_HEADER``: UTF-8 JSON object ``{"format": "mocapd-session-stream", "version": 1, "stream": name}``.
- ``T_IMU`` (one sample of one sensor, 86 + len(sensor) bytes): ``<qqqiH`` t_ns (buffer time: device time mapped
  to the host clock, as the solver used it), host_ns (host receive time), device_ticks (SampleTimeFine, 10 kHz;
  -1 = none), packet_counter (-1 = none), sensor id length m; then m bytes of UTF-8 sensor id; then ``<4f8 3f8``
  quaternion (w, x, y, z) of the sensor in ENU and specific force in the sensor frame (m/s², gravity included).
- ``T_KEYPOINTS`` (one detected camera frame): ``<qqHHH`` capture_ns (camera clock), arrival_ns (host clock when
  the detector delivered it), camera index, people n, keypoints k; then ``n·k·2`` float32 pixels (distorted, as
  detected) and ``n·k`` float32 confidences.
- ``T_POSE`` (one published frame): ``<qqqHH`` frame counter, t_solve_ns, tick_ns, missing cameras, people n;
  then per person: ``<B`` identity length + UTF-8 identity, ``<B`` suit length (255 = no suit) + UTF-8 suit,
  ``<iHHHBf`` track, views, imus, iterations, converged, confidence; then θ as 66 float64 (root translation +
  21 local rotation vectors) and the 21 global joint positions as 63 float32 (metres); then ``<B`` 1 if the
  person's own (body-sized) skeleton follows, 0 if θ is on the session's rig skeleton (manifest); if 1, ``<ff``
  root height and height (m) and the 21 bone offsets as 63 float32 (m) — θ means nothing without them.
  Then an optional tail (absent in records written before the daemon had a predicted output, which are read as
  delayed): ``<B`` output mode (0 delayed, 1 predicted) and per person ``<q`` the instant its pose is for
  (host ns: t_solve_ns, or the IMUs' newest instant for a predicted pose).
  Then, only in records where some person has fingers (issue 44; records without are exactly as before): ``<B``
  0x48 (``H``) and per person ``<B`` 0 (no fingers) or 1, followed for 1 by ``<B`` the hands present (bit 0 left,
  bit 1 right), ``<ff`` each hand's scale, the finger bones' rest offsets as 2 × 15 × 3 float32 (m), the fingertips
  in their distal bones as 2 × 5 × 3 float32 (m), and the local rotations of the 2 × 15 finger bones as unit
  quaternions (w, x, y, z), 120 float64 (:class:`mocapd.core.hand_skeleton.HandPose`; a hand not present holds
  its rest pose). A reader older than fingers refuses such a record (bytes left after its people).
- ``T_FRAME`` (one downscaled camera frame, optional ``frames`` stream): ``<qHHHI`` capture_ns (host clock, as
  the camera's detections), camera index, image width, image height, JPEG length m; then the m bytes of the
  baseline JPEG (the image as the camera panels show it, not the camera's full resolution).
- ``T_EVENT`` (something that happened to the rig while recording, ``events`` stream): a UTF-8 JSON object with
  at least ``t_ns`` (host clock, an integer) and ``kind`` (text). ``kind = "camera"``: a camera's calibration
  replaced while running (the bumped-camera watch applying a re-estimate): ``index`` (order of the manifest's
  cameras), ``camera`` (as the manifest's), ``source``, ``rotation_deg`` and the re-estimate's numbers; the camera
  is the one solved with from the first solve after ``t_ns``.

Decoding never raises on bad bytes: :class:`StreamDecoder` (sans-I/O: ``receive_data(bytes)``,
``records_received()``) counts a record whose CRC does not match, or whose length is impossible, as corrupt and
resynchronises on the next sync word; bytes left at the end that do not make a whole record are the *tail*
(:attr:`StreamDecoder.pending`), which a reader of a finished file reports as torn.
"""

from __future__ import annotations

import functools
import json
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import ParamSpec, TypeVar

import numpy as np
from numpy.typing import NDArray

from mocapd.core.hand_skeleton import N_FINGER_BONES, HandPose, HandSkeleton
from mocapd.core.skeleton import N_BONES, POSE_DIM, Skeleton
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

SYNC = b"MR"
T_HEADER, T_IMU, T_KEYPOINTS, T_POSE, T_FRAME, T_EVENT = 0, 1, 2, 3, 4, 5
RECORD_TYPES = (T_HEADER, T_IMU, T_KEYPOINTS, T_POSE, T_FRAME, T_EVENT)
PAYLOAD_VERSION = 1
FORMAT_VERSION = 1
MAX_PAYLOAD = 1 << 24
"""Largest payload a record may carry (16 MiB): a longer length field is corruption, not a record."""

_HEAD = struct.Struct("<2sBBI")
_CRC = struct.Struct("<I")
HEAD_SIZE = _HEAD.size  # 8
OVERHEAD = HEAD_SIZE + _CRC.size  # 12 bytes of framing per record

_IMU = struct.Struct("<qqqiH")
_IMU_VALUES = struct.Struct("<7d")
_KP = struct.Struct("<qqHHH")
_POSE = struct.Struct("<qqqHH")
_PERSON = struct.Struct("<iHHHBf")
_SIZES = struct.Struct("<ff")
_FRAME = struct.Struct("<qHHHI")
_NO_SUIT = 255
_HANDS_TAG = 0x48  # "H": the fingers section of a pose record
_HAND_FLOATS = 2 * N_FINGER_BONES * 3 + 2 * 5 * 3  # offsets and tips, float32
_HAND_QUATS = 2 * N_FINGER_BONES * 4  # rotations, float64
OUTPUT_MODES = ("delayed", "predicted")


_P = ParamSpec("_P")
_R = TypeVar("_R")


def _payload(kind: str) -> Callable[[Callable[_P, _R]], Callable[_P, _R]]:
    """A payload decoder that raises only InputError: a payload too short for its own counts, a name that is not
    UTF-8 or an array that does not fit (a record whose CRC is intact but whose bytes were not written by mocapd)
    says so in one line instead of escaping as ``struct.error``, ``UnicodeDecodeError`` or ``IndexError``."""

    def wrap(decode: Callable[_P, _R]) -> Callable[_P, _R]:
        @functools.wraps(decode)
        def checked(*args: _P.args, **kwargs: _P.kwargs) -> _R:
            try:
                return decode(*args, **kwargs)
            except InputError:
                raise
            except (struct.error, UnicodeDecodeError, ValueError, IndexError) as exc:
                raise InputError(f"{kind} record: malformed payload: {exc}") from None

        return checked

    return wrap


# ----------------------------------------------------------------------------------------------- framing
def encode_record(rtype: int, payload: bytes) -> bytes:
    """One framed record (sync, type, version, length, payload, CRC32)."""
    if rtype not in RECORD_TYPES:
        raise InputError(f"session record type {rtype} unknown; allowed: {RECORD_TYPES}")
    if len(payload) > MAX_PAYLOAD:
        raise InputError(f"session record payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    head = _HEAD.pack(SYNC, rtype, PAYLOAD_VERSION, len(payload))
    return head + payload + _CRC.pack(zlib.crc32(payload, zlib.crc32(head)))


@dataclass(frozen=True, slots=True)
class Record:
    """One decoded record: its type, payload and byte offset in the stream."""

    rtype: int
    payload: bytes
    offset: int


@dataclass
class DecodeCounters:
    records: int = 0
    corrupt: int = 0
    """Places where a record failed its CRC or had an impossible header (each followed by a resync)."""
    skipped_bytes: int = 0
    """Bytes passed over while resynchronising (not counting the final tail)."""
    unknown_types: int = 0
    by_type: dict[int, int] = field(default_factory=dict)


class StreamDecoder:
    """Sans-I/O decoder of a session stream: feed bytes, take the complete, CRC-checked records."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._offset = 0  # stream offset of _buf[0]
        self._out: list[Record] = []
        self.counters = DecodeCounters()

    def receive_data(self, data: bytes) -> None:
        """Append bytes and decode every complete record."""
        self._buf += data
        self._decode()

    def records_received(self) -> list[Record]:
        """The records decoded since the last call."""
        out, self._out = self._out, []
        return out

    @property
    def pending(self) -> int:
        """Bytes held that do not (yet) make a whole record: at the end of a file, the torn tail."""
        return len(self._buf)

    def _skip(self, n: int) -> None:
        del self._buf[:n]
        self._offset += n

    def _resync(self) -> None:
        """Drop bytes up to the next sync word after the current position (a corrupt record starts here)."""
        self.counters.corrupt += 1
        nxt = self._buf.find(SYNC, 1)
        n = nxt if nxt >= 0 else max(len(self._buf) - 1, 1)  # keep a last byte: it may start a sync word
        self.counters.skipped_bytes += n
        self._skip(n)

    def _decode(self) -> None:
        buf = self._buf
        while len(buf) >= HEAD_SIZE:
            if buf[0:2] != SYNC:
                self._resync()
                continue
            _, rtype, version, n = _HEAD.unpack_from(buf, 0)
            if n > MAX_PAYLOAD or rtype > 127 or version == 0:
                self._resync()
                continue
            end = HEAD_SIZE + n + _CRC.size
            if len(buf) < end:
                return  # wait for more bytes (or, at the end of a file, a torn tail)
            (crc,) = _CRC.unpack_from(buf, HEAD_SIZE + n)
            if zlib.crc32(memoryview(buf)[: HEAD_SIZE + n]) != crc:
                self._resync()
                continue
            if rtype not in RECORD_TYPES:
                self.counters.unknown_types += 1
            else:
                self._out.append(Record(rtype, bytes(buf[HEAD_SIZE : HEAD_SIZE + n]), self._offset))
                self.counters.records += 1
                self.counters.by_type[rtype] = self.counters.by_type.get(rtype, 0) + 1
            self._skip(end)

    def finish(self) -> int:
        """End of input: bytes held now can never complete the record they start. When a valid record follows
        them, they were a corrupt record (counted, skipped, and decoding goes on); what is left at the end is
        the torn tail of one partial record. Returns the tail's length in bytes."""
        while len(self._buf) > 0:
            nxt = self._buf.find(SYNC, 1)
            if nxt < 0:
                break
            probe = StreamDecoder()
            probe.receive_data(bytes(self._buf[nxt:]))
            if probe.counters.records == 0:
                break
            self._resync()
            self._decode()
        return len(self._buf)


# ----------------------------------------------------------------------------------------------- payloads
def encode_header(stream: str) -> bytes:
    return json.dumps({"format": "mocapd-session-stream", "version": FORMAT_VERSION, "stream": stream}).encode()


def decode_header(payload: bytes) -> dict[str, object]:
    """The stream header's JSON object; raises InputError when it is not one."""
    try:
        value = json.loads(payload.decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"session stream header is not JSON: {exc}") from exc
    if not isinstance(value, dict) or value.get("format") != "mocapd-session-stream":
        raise InputError(f"not a mocapd session stream header: {value!r}")
    return value


def encode_event(event: dict[str, object]) -> bytes:
    """A ``T_EVENT`` payload: the event as UTF-8 JSON (NaN and infinities refused: JSON has none)."""
    try:
        return json.dumps(event, allow_nan=False, separators=(",", ":")).encode()
    except (TypeError, ValueError) as exc:
        raise InputError(f"session event not JSON-able: {exc}") from None


def decode_event(payload: bytes) -> dict[str, object]:
    """A ``T_EVENT`` payload's JSON object; InputError when it is not one with an integer ``t_ns`` and a ``kind``."""
    try:
        value = json.loads(payload.decode())
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"event record is not JSON: {exc}") from None
    if not isinstance(value, dict):
        raise InputError("event record: not a JSON object")
    t, kind = value.get("t_ns"), value.get("kind")
    if isinstance(t, bool) or not isinstance(t, int) or not isinstance(kind, str):
        raise InputError("event record: no integer t_ns or no kind")
    return value


@dataclass(frozen=True, slots=True)
class ImuRecord:
    """One IMU sample as recorded (see the module docstring for the fields)."""

    sensor: str
    t_ns: int
    host_ns: int
    device_ticks: int | None
    packet_counter: int | None
    quat: tuple[float, float, float, float]
    acc: tuple[float, float, float]


def encode_imu(r: ImuRecord) -> bytes:
    sid = r.sensor.encode()
    head = _IMU.pack(
        r.t_ns, r.host_ns, -1 if r.device_ticks is None else r.device_ticks,
        -1 if r.packet_counter is None else r.packet_counter, len(sid),
    )  # fmt: skip
    return head + sid + _IMU_VALUES.pack(*r.quat, *r.acc)


@_payload("IMU")
def decode_imu(p: bytes) -> ImuRecord:
    t, host, ticks, counter, m = _IMU.unpack_from(p, 0)
    o = _IMU.size
    sid = p[o : o + m].decode()
    v = _IMU_VALUES.unpack_from(p, o + m)
    return ImuRecord(sid, t, host, None if ticks < 0 else ticks, None if counter < 0 else counter,
                     (v[0], v[1], v[2], v[3]), (v[4], v[5], v[6]))  # fmt: skip


@dataclass(frozen=True)
class KeypointRecord:
    """One detected camera frame.

    Attributes
    ----------
    keypoints : array, shape (n_people, n_kp, 2)
    confidences : array, shape (n_people, n_kp)
    """

    camera: int
    capture_ns: int
    arrival_ns: int
    keypoints: FloatArray
    confidences: FloatArray


def encode_keypoints(camera: int, capture_ns: int, arrival_ns: int, keypoints: FloatArray, conf: FloatArray) -> bytes:
    """A ``T_KEYPOINTS`` payload from a detector's output (keypoints (n, k, 2), confidences (n, k))."""
    n, k = conf.shape
    return (
        _KP.pack(capture_ns, arrival_ns, camera, n, k)
        + np.ascontiguousarray(keypoints, dtype="<f4").tobytes()
        + np.ascontiguousarray(conf, dtype="<f4").tobytes()
    )


@_payload("keypoint")
def decode_keypoints(p: bytes) -> KeypointRecord:
    capture, arrival, camera, n, k = _KP.unpack_from(p, 0)
    o = _KP.size
    if len(p) != o + 12 * n * k:
        raise InputError(f"keypoint record: {len(p)} bytes for {n} people x {k} keypoints")
    kp = np.frombuffer(p, "<f4", n * k * 2, o).reshape(n, k, 2).astype(np.float64)
    cf = np.frombuffer(p, "<f4", n * k, o + 8 * n * k).reshape(n, k).astype(np.float64)
    return KeypointRecord(camera, capture, arrival, kp, cf)


@dataclass(frozen=True)
class FrameRecord:
    """One recorded camera frame: ``jpeg`` of ``width`` x ``height`` pixels, captured at ``capture_ns``."""

    camera: int
    capture_ns: int
    width: int
    height: int
    jpeg: bytes


def encode_frame(r: FrameRecord) -> bytes:
    """A ``T_FRAME`` payload."""
    return _FRAME.pack(r.capture_ns, r.camera, r.width, r.height, len(r.jpeg)) + r.jpeg


@_payload("frame")
def decode_frame(p: bytes) -> FrameRecord:
    capture, camera, w, h, n = _FRAME.unpack_from(p, 0)
    if len(p) != _FRAME.size + n:
        raise InputError(f"frame record: {len(p)} bytes for a {n}-byte image")
    return FrameRecord(camera, capture, w, h, bytes(p[_FRAME.size :]))


@dataclass(frozen=True)
class PersonRecord:
    """One solved person of a recorded frame (theta (66,), joints (21, 3))."""

    identity: str
    suit: str | None
    track: int
    views: int
    imus: int
    iterations: int
    converged: bool
    confidence: float
    theta: FloatArray
    joints: FloatArray
    skeleton: Skeleton | None = None  # the person's own sized skeleton (None: the rig's, from the manifest)
    t_pose_ns: int | None = None  # the instant the pose is for (None: the frame's t_solve_ns)
    hands: HandPose | None = None  # the fingers (None: none solved)


@dataclass(frozen=True)
class PoseRecord:
    """One recorded output frame."""

    frame: int
    t_solve_ns: int
    tick_ns: int
    missing_cameras: int
    people: tuple[PersonRecord, ...]
    output: str = "delayed"  # the daemon's output mode: "delayed" or "predicted"


def _short(text: str | None) -> bytes:
    if text is None:
        return bytes([_NO_SUIT])
    # Cut on a character boundary: 254 bytes cut inside a UTF-8 character made the record undecodable (issue 45).
    b = text.encode()[:254].decode("utf-8", "ignore").encode()
    return bytes([len(b)]) + b


def encode_pose(r: PoseRecord) -> bytes:
    parts = [_POSE.pack(r.frame, r.t_solve_ns, r.tick_ns, r.missing_cameras, len(r.people))]
    for p in r.people:
        parts.append(_short(p.identity))
        parts.append(_short(p.suit))
        parts.append(
            _PERSON.pack(
                p.track,
                min(p.views, 65535),
                min(p.imus, 65535),
                min(p.iterations, 65535),
                int(p.converged),
                p.confidence,
            )
        )
        parts.append(np.ascontiguousarray(p.theta, dtype="<f8").tobytes())
        parts.append(np.ascontiguousarray(p.joints, dtype="<f4").tobytes())
        if p.skeleton is None:
            parts.append(b"\x00")
        else:
            parts.append(b"\x01" + _SIZES.pack(p.skeleton.root_height, p.skeleton.height))
            parts.append(np.ascontiguousarray(p.skeleton.offsets, dtype="<f4").tobytes())
    if r.output not in OUTPUT_MODES:
        raise InputError(f"pose record output {r.output!r}; allowed: {list(OUTPUT_MODES)}")
    parts.append(bytes([OUTPUT_MODES.index(r.output)]))
    parts.append(struct.pack(f"<{len(r.people)}q", *(r.t_solve_ns if p.t_pose_ns is None else p.t_pose_ns
                                                      for p in r.people)))  # fmt: skip
    if any(p.hands is not None for p in r.people):
        parts.append(bytes([_HANDS_TAG]))
        parts.extend(_encode_hands(p.hands) for p in r.people)
    return b"".join(parts)


def _encode_hands(h: HandPose | None) -> bytes:
    if h is None:
        return b"\x00"
    sk = h.skeleton
    present = int(bool(h.present[0])) | (int(bool(h.present[1])) << 1)
    return (
        bytes([1, present])
        + _SIZES.pack(*sk.scale)
        + np.concatenate([sk.offsets.ravel(), sk.tips.ravel()]).astype("<f4").tobytes()
        + np.ascontiguousarray(h.rotations, dtype="<f8").tobytes()
    )


def _decode_hands(p: bytes, o: int) -> tuple[HandPose | None, int]:
    if p[o] == 0:
        return None, o + 1
    if p[o] != 1:
        raise InputError(f"pose record: finger flag {p[o]} unknown")
    present = np.array([bool(p[o + 1] & 1), bool(p[o + 1] & 2)])
    scale = _SIZES.unpack_from(p, o + 2)
    o += 2 + _SIZES.size
    sizes = np.frombuffer(p, "<f4", _HAND_FLOATS, o).astype(np.float64)
    o += 4 * _HAND_FLOATS
    rotations = np.frombuffer(p, "<f8", _HAND_QUATS, o).reshape(2, N_FINGER_BONES, 4).astype(np.float64)
    o += 8 * _HAND_QUATS
    n_off = 2 * N_FINGER_BONES * 3
    skeleton = HandSkeleton(sizes[:n_off].reshape(2, N_FINGER_BONES, 3), sizes[n_off:].reshape(2, 5, 3),
                            np.array(scale, dtype=np.float64))  # fmt: skip
    return HandPose(rotations, present, skeleton), o


def _read_short(p: bytes, o: int) -> tuple[str | None, int]:
    m = p[o]
    if m == _NO_SUIT:
        return None, o + 1
    return p[o + 1 : o + 1 + m].decode(), o + 1 + m


@_payload("pose")
def decode_pose(p: bytes) -> PoseRecord:
    frame, t, tick, missing, n = _POSE.unpack_from(p, 0)
    o = _POSE.size
    people = []
    for _ in range(n):
        identity, o = _read_short(p, o)
        suit, o = _read_short(p, o)
        track, views, imus, iters, conv, conf = _PERSON.unpack_from(p, o)
        o += _PERSON.size
        theta = np.frombuffer(p, "<f8", POSE_DIM, o).astype(np.float64)
        o += 8 * POSE_DIM
        joints = np.frombuffer(p, "<f4", 3 * N_BONES, o).reshape(N_BONES, 3).astype(np.float64)
        o += 12 * N_BONES
        skeleton = None
        if p[o] == 1:
            root_height, height = _SIZES.unpack_from(p, o + 1)
            o += 1 + _SIZES.size
            offsets = np.frombuffer(p, "<f4", 3 * N_BONES, o).reshape(N_BONES, 3).astype(np.float64)
            o += 12 * N_BONES
            skeleton = Skeleton(offsets=offsets, root_height=float(root_height), height=float(height))
        else:
            o += 1
        people.append(PersonRecord(identity or "", suit, track, views, imus, iters, bool(conv), conf, theta, joints,
                                   skeleton))  # fmt: skip
    output = "delayed"
    if len(p) - o >= 1 + 8 * n:  # the tail: output mode and each pose's instant
        if p[o] >= len(OUTPUT_MODES):
            raise InputError(f"pose record: output mode {p[o]} unknown")
        output = OUTPUT_MODES[p[o]]
        times = struct.unpack_from(f"<{n}q", p, o + 1)
        people = [replace(person, t_pose_ns=tp) for person, tp in zip(people, times, strict=True)]
        o += 1 + 8 * n
        if o < len(p) and p[o] == _HANDS_TAG:  # the fingers section
            o += 1
            for k in range(n):
                hands, o = _decode_hands(p, o)
                people[k] = replace(people[k], hands=hands)
    if o != len(p):
        raise InputError(f"pose record: {len(p) - o} bytes left after {n} people")
    return PoseRecord(frame, t, tick, missing, tuple(people), output)

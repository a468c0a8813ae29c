"""The WebSocket pose stream, protocol version 1: messages, per-client options and encoding (sans-I/O).

This module only turns values into messages and messages into values; the server (:mod:`mocapd.io.ws_server`)
moves them. Every message is one WebSocket message holding one map (a msgpack map in a *binary* message, or a
JSON object in a *text* message) whose ``"type"`` key says what it is. Both encodings carry the same keys.

Encodings
---------
``msgpack`` (default): map keys are msgpack str; every float is a float32 (``0xca`` + 4 bytes big-endian);
integers use msgpack's smallest int/uint form (host time stamps are usually uint64, ``0xcf`` + 8 bytes); absent
optional values are nil (``0xc0``); lists are msgpack arrays. Keys are written in the order listed below, e.g. a
frame starts ``85`` (map of 5) ``a4 "type"`` ``a5 "frame"`` ``a5 "frame"`` ``cd 01 2c`` (frame 300)
``aa "t_solve_ns"`` ``cf`` + 8 bytes ...; read keys by name, not position. ``json``: UTF-8 JSON, floats
rounded to 6 decimals; integer time stamps are exact in JSON, but a JavaScript ``Number`` keeps them only to
2^53 ns (104 days of host uptime).

Coordinate conventions (:mod:`mocapd.protocols.conventions`, the only conversion): ``native`` (mocapd: right-
handed, +Y up, metres), ``unity`` (left-handed, +Y up, metres), ``unreal`` (left-handed, +Z up, centimetres),
``mvn`` (right-handed, +Z up, metres). Positions and rest offsets are converted ``p' = s·C p``, quaternions
``q' = (w, det C · C v)``, so forward kinematics in the target frame with the converted offsets and rotations
gives the converted global positions.

Server → client messages
------------------------
``hello`` (on connect, and again as the answer to every accepted ``subscribe``)::

    type            str     "hello"
    v               int     protocol version, 1
    server          str     "mocapd"
    convention      str     the convention of every position/rotation/offset this client now receives
    units           str     "m" or "cm"
    left_handed     bool
    encoding        str     "msgpack" or "json" (this message is already in it)
    encodings       [str]   encodings the server speaks
    conventions     [str]   conventions the server speaks
    stream_rate_hz  float   the solver's output rate
    output          str     "delayed": every pose is the solve at the fixed latency (t_solve_ns); "predicted":
                            the poses of suit wearers are carried forward to their IMUs' newest instant (each
                            subject's t_pose_ns), the others stay delayed
    decimation      int     this client gets frames whose counter is a multiple of this
    rate_hz         float   stream_rate_hz / decimation
    globals         bool    whether frames carry global joint positions
    subjects_filter [str] | nil   the subject ids this client asked for (nil: all)
    status          bool    whether status messages are sent
    max_message_bytes int   the largest client message accepted (larger ones close the connection, 1009)
    bones           [str]   the 21 bone names, index = bone (DESIGN.md order)
    parents         [int]   parent index per bone, -1 for the root
    skeletons       {str: {"bones": [str], "parents": [int], "offsets": [float × 63]}}
                            rest offsets per skeleton: joint position of bone i in its parent's frame in the
                            T-pose, x,y,z of bone 0..20 flattened (row 0 is zero), in this convention's units
    subjects        [{"id": str, "skeleton": str}]   the subjects of the latest frame
    cameras         [{"name": str, "width": int, "height": int}]   the rig's cameras whose views this server
                            can send (empty: none; a replay without recorded frames still has detections)
    camera_views    bool    whether this client receives camera messages
    camera_rate_hz  float   at most this many camera messages per second per camera for this client

``frame`` (one per output frame the client's options select)::

    type            str     "frame"
    frame           int     the daemon's frame counter (increases by one per solver tick, gaps = missed ticks)
    t_solve_ns      int     the solve time: host CLOCK_MONOTONIC nanoseconds the pose describes
    t_publish_ns    int     host CLOCK_MONOTONIC nanoseconds when the daemon published the frame; a client on
                            the same host may subtract it from its own monotonic clock to get delivery latency
    subjects        [subject]   the tracked subjects (only the requested ones), each:
        id          str     stable identity ("suit:<id>" for a suit wearer, "track:<n>" otherwise)
        skeleton    str     key into hello.skeletons
        suit        str | nil   the IMU suit bound to this subject
        root        [float × 3]   root (Hips) joint position, convention units
        rot         [float × 84]  local rotation of bone 0..20 as quaternions w,x,y,z (Hamilton, unit), each
                                  relative to the T-pose, in the convention's axes; bone 0's is global
        joints      [float × 63]  global joint positions x,y,z of bone 0..20 (only when globals is on)
        confidence  float   0..1, detector confidence of the keypoints used (reduced below two views)
        views       int     cameras that saw the subject this frame
        imus        int     IMUs that measured the subject this frame
        t_pose_ns   int     the instant this subject's pose describes (host CLOCK_MONOTONIC ns): t_solve_ns, or
                            later for a predicted pose (hello.output "predicted", suit wearers)

``status`` (at the configured status rate, when the client's ``status`` option is on)::

    type            str     "status"
    t_ns            int     host CLOCK_MONOTONIC nanoseconds of the report
    uptime_s        float
    output          map     configured_hz, achieved_hz, frames, missed_ticks, latency_s
    latency_ms      map     per stage ("detect", "sample", "sort", "solve", "publish", "end_to_end"):
                            {"p50": float|nil, "p95": float|nil, "p99": float|nil}
    cameras         [map]   name, kind, frames (received keypoint frames)
    imus            [map]   path, streaming (bool), samples, disconnects; a SlimeVR tracker: path "slimevr <MAC>",
                            streaming = connected, samples = its datagrams, disconnects nil
    tasks           {str: int}   supervised task -> failures so far
    governor        map     step (0: nothing shed), shed (what is left out now), reason (why); absent when the
                            daemon's governor is off
    stream          map     clients (connected now), sent (messages sent to this client), dropped (messages
                            dropped for this client because it read too slowly)

``camera`` (while the client's ``cameras`` option is on, at most ``camera_rate_hz`` per camera): what one
camera sees, for a camera panel. Pixel coordinates are in the camera's full resolution (``width`` x
``height``; origin at the top-left pixel corner, x right, y down), whatever the image's size::

    type            str     "camera"
    camera          int     index of the camera in hello.cameras
    name            str
    width, height   int     the camera's resolution
    t_capture_ns    int     host CLOCK_MONOTONIC ns of the frame (without an image: of the pose drawn)
    frame           int     counter of the pose frame drawn (the one solved nearest t_capture_ns; -1: none)
    t_solve_ns      int     its solve time
    image           bytes | str | nil   the frame, downscaled, as JPEG: msgpack bin, or base64 in JSON; nil when
                            the camera has no frames (a synthetic rig, a session recorded without frames)
    image_width, image_height  int   the JPEG's size (0 without an image)
    detections      [[float × 3K]]   per detected person, x, y, confidence of its K keypoints
    subjects        [{"id": str, "joints": [float|nil × 42]}]   every solved subject's 21 joints projected through
                            the camera's calibration (with its distortion), x, y per joint; nil behind the camera
    reprojection_px float | nil   mean distance between detected keypoints and the same keypoints of the
                            nearest solved subject, projected (nil: no detected person matched)
    detection_hz    float   detection sets received from this camera per second (last two seconds)

``error`` (the answer to a client message that could not be used; the connection stays open)::

    type            str     "error"
    code            str     "bad_encoding" | "bad_message" | "unknown_type" | "bad_field" | "too_large"
    message         str     what was wrong and what is allowed

Client → server messages
------------------------
A text message is read as JSON, a binary one as msgpack; at most ``max_message_bytes``. The only request is::

    type            str     "subscribe"
    subjects        [str] | nil   only these subject ids (at most 64 ids of at most 128 characters); nil: all
    rate_hz         float | nil   at most this rate: the server sends every n-th frame, n = round(stream/rate)
                                  (at least 1); nil: every frame; 0.01 to 1e6 Hz
    convention      str     "native" | "unity" | "unreal" | "mvn"
    encoding        str     "msgpack" | "json"
    globals         bool    add global joint positions to frames
    status          bool    receive status messages
    cameras         bool    receive camera messages (needs hello.cameras)
    camera_rate_hz  float | nil   camera messages per second per camera, 0.01 to 1e6, at most the server's
                                  rate (nil: it)

Every key but ``type`` is optional (absent keys keep their current value); unknown keys, wrong types or values
are answered with an ``error`` and change nothing. An accepted request is answered with a new ``hello``.

A client may also ask the daemon for a **heading reset** (docs/vr.md "Heading without cameras": the wearer stands
straight facing forward; every sensor of the suit is turned about the vertical so its bone faces forward)::

    type            str     "reset_heading"
    suit            str | nil   the suit to reset (nil or absent: every suit)

answered with ``heading_reset`` (``t_ns``, ``source``, ``suits``: per suit ``corrections_deg`` per sensor and
``no_recent_sample``, the sensors left alone), or with an ``error`` (code ``failed``: no such suit; ``rate_limited``:
more resets than ``[daemon] heading_reset_burst`` / ``heading_resets_per_s`` allow; ``unsupported``: a server without
a daemon, e.g. a replay).

Encoding cost: :class:`FrameEncoder` converts each subject once per convention and encodes each distinct
(encoding, convention, globals, subjects) once per frame, whatever the number of clients.
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol

import msgpack
import numpy as np
from numpy.typing import NDArray

from mocapd.core.hand_skeleton import HAND_BONE_NAMES, HandPose
from mocapd.core.rotations import quat_from_rotvec
from mocapd.core.skeleton import BONE_NAMES, N_BONES, PARENTS, POSE_DIM, Skeleton
from mocapd.protocols.conventions import Convention, convention
from mocapd.protocols.fingers import EXTENDED_PARENTS, hands_of, subject_fingers

FloatArray = NDArray[np.float64]
Message = bytes | str
"""One WebSocket message: ``bytes`` go out as a binary message (msgpack), ``str`` as a text message (JSON)."""

PROTOCOL_VERSION = 1
ENCODINGS = ("msgpack", "json")
STREAM_CONVENTIONS = ("native", "unity", "unreal", "mvn")
MAX_SUBJECTS_PER_REQUEST = 64
MAX_ID_CHARS = 128
MIN_RATE_HZ = 0.01
"""The lowest ``rate_hz`` / ``camera_rate_hz`` a client may ask for (one message per 100 s)."""
MAX_RATE_HZ = 1e6
"""The highest (anything above the server's own rate means every message; beyond this it is not a rate)."""
_SUBSCRIBE_KEYS = frozenset(
    {"type", "subjects", "rate_hz", "convention", "encoding", "globals", "status", "cameras", "camera_rate_hz"}
)
_RESET_KEYS = frozenset({"type", "suit"})
_JSON_DECIMALS = 6


class SubjectPose(Protocol):
    """What the stream needs of one solved subject (:class:`mocapd.pipeline.scheduler.PersonPose` has it)."""

    @property
    def identity(self) -> str: ...
    @property
    def suit(self) -> str | None: ...
    @property
    def theta(self) -> FloatArray: ...  # (66,) root translation + 21 local rotation vectors
    @property
    def joints(self) -> FloatArray: ...  # (21, 3) global joint positions, metres
    @property
    def confidence(self) -> float: ...
    @property
    def views(self) -> int: ...
    @property
    def imus(self) -> int: ...
    @property
    def skeleton(self) -> Skeleton | None: ...  # the subject's own sized skeleton (None: the stream's default)
    @property
    def t_pose_ns(self) -> int | None: ...  # the instant the pose describes (None: the frame's t_solve_ns)
    @property
    def hands(self) -> HandPose | None: ...  # the fingers (None: none solved)


class FramePoses(Protocol):
    """What the stream needs of one output frame (:class:`mocapd.pipeline.scheduler.PoseFrame` has it)."""

    @property
    def frame(self) -> int: ...
    @property
    def t_solve_ns(self) -> int: ...
    @property
    def people(self) -> Sequence[SubjectPose]: ...


@dataclass(frozen=True)
class StreamOptions:
    """What one client receives (its ``subscribe`` state)."""

    encoding: str = "msgpack"
    """"msgpack" (binary messages) or "json" (text messages)."""
    convention: str = "native"
    """Coordinate convention of positions, rotations and offsets (see :data:`STREAM_CONVENTIONS`)."""
    globals: bool = False
    """Whether frames carry global joint positions (63 more floats per subject)."""
    subjects: frozenset[str] | None = None
    """Only these subject ids (None: all)."""
    decimation: int = 1
    """Send frames whose counter is a multiple of this (1: every frame)."""
    status: bool = True
    """Whether status messages are sent."""
    cameras: bool = False
    """Whether camera messages are sent (camera panels)."""
    camera_rate_hz: float = 4.0
    """Camera messages per second per camera (at most the description's ``camera_rate_hz``)."""

    @property
    def encoding_key(self) -> tuple[str, str, bool, frozenset[str] | None]:
        """Clients with equal keys receive byte-identical frame messages."""
        return (self.encoding, self.convention, self.globals, self.subjects)


@dataclass(frozen=True)
class StreamDescription:
    """What the hello describes: the output rate and the skeleton of every subject.

    ``skeletons`` maps a skeleton key to a sized skeleton; ``skeleton_of(subject_id)`` names the key of a
    subject's skeleton (default: the first key, for a daemon with one skeleton for everyone).
    """

    rate_hz: float
    skeletons: Mapping[str, Skeleton]
    skeleton_of: Callable[[str], str] | None = None
    max_message_bytes: int = 4096
    cameras: tuple[tuple[str, int, int], ...] = ()
    """(name, width, height) of each camera whose views the server sends (empty: no camera messages)."""
    camera_rate_hz: float = 4.0
    """The most camera messages per second per camera a client may ask for."""
    output: str = "delayed"
    """The daemon's output mode, announced in the hello ("delayed" or "predicted")."""
    fingers: bool = False
    """Whether the hello names the finger bones (the server turns it on with the first frame that has fingers)."""

    def __post_init__(self) -> None:
        if not self.skeletons:
            raise ValueError("a stream needs at least one skeleton")
        if not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ValueError(f"stream rate must be > 0 Hz, got {self.rate_hz!r}")
        if self.output not in ("delayed", "predicted"):
            raise ValueError(f"output must be 'delayed' or 'predicted', got {self.output!r}")

    def skeleton_key(self, subject_id: str) -> str:
        if self.skeleton_of is None:
            return next(iter(self.skeletons))
        return self.skeleton_of(subject_id)


def encode(obj: Mapping[str, Any], encoding: str) -> Message:
    """One message map → msgpack ``bytes`` (floats as float32) or JSON ``str``."""
    if encoding == "msgpack":
        data: bytes = msgpack.packb(obj, use_single_float=True)
        return data
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


def decode(message: Message) -> Any:
    """A server message back to a map (for clients and tests): bytes are msgpack, str is JSON."""
    if isinstance(message, bytes):
        return msgpack.unpackb(message)
    return json.loads(message)


def _rows(a: FloatArray, encoding: str) -> list[list[float]]:
    """``(n, ...)`` → n flat lists of floats (rounded for JSON, where digits are bytes)."""
    if len(a) == 0:
        return []
    flat = np.asarray(a, dtype=np.float64).reshape(len(a), -1)
    if encoding == "json":
        flat = np.round(flat, _JSON_DECIMALS)
    out: list[list[float]] = flat.tolist()
    return out


def _floats(a: FloatArray, encoding: str) -> list[float]:
    return _rows(np.asarray(a, dtype=np.float64).reshape(1, -1), encoding)[0]


@dataclass(frozen=True)
class _Converted:
    """Every subject of a frame in one convention: root (n, 3), local quaternions (n, 84), joints (n, 63)."""

    root: FloatArray
    rot: FloatArray
    joints: FloatArray


class FrameEncoder:
    """One published frame, encoded lazily for each distinct client option set and cached.

    Parameters
    ----------
    frame : FramePoses
        The output frame (frame counter, solve time, people).
    t_publish_ns : int
        Host monotonic time of publication (nanoseconds), sent as ``t_publish_ns``.
    description : StreamDescription
        For the skeleton key of each subject.
    """

    def __init__(self, frame: FramePoses, t_publish_ns: int, description: StreamDescription) -> None:
        # Nothing is converted here: the publisher (the solver's tick) only pays for this object; the first
        # message() call, in some client's sender, does the numeric work.
        self.frame = frame
        self.t_publish_ns = int(t_publish_ns)
        self.description = description
        self.prepared = False
        self._people: list[SubjectPose] = []
        self._non_finite = 0
        self._root = self._quats = self._joints = np.zeros(0)
        self._converted: dict[str, _Converted] = {}
        self._lists: dict[tuple[str, str], tuple[list[list[float]], list[list[float]], list[list[float]]]] = {}
        self._messages: dict[tuple[str, str, bool, frozenset[str] | None], Message] = {}
        self._hand_poses: list[HandPose | None] = []
        self._hands: dict[tuple[str, str, bool], dict[int, dict[str, Any]]] = {}
        self.encodings = 0
        """How many messages were actually encoded (the rest came from the cache)."""

    def _prepare(self) -> None:
        if self.prepared:
            return
        self.prepared = True
        # A subject with a non-finite value is left out (JSON cannot carry NaN; no engine wants one) and counted.
        people = list(self.frame.people)
        n = len(people)
        theta = np.array([p.theta for p in people], dtype=np.float64).reshape(n, POSE_DIM)
        joints = np.array([p.joints for p in people], dtype=np.float64).reshape(n, N_BONES, 3)
        ok: NDArray[np.bool_] = np.ones(n, dtype=bool)
        if n:
            ok = np.asarray(np.isfinite(theta).all(axis=1) & np.isfinite(joints).all(axis=(1, 2)), dtype=bool)
        self._people = [p for p, good in zip(people, ok.tolist(), strict=True) if good]
        self._non_finite = n - len(self._people)
        # All subjects at once: one quaternion conversion per frame, one change of basis per convention.
        self._root = theta[ok, :3]
        self._quats = quat_from_rotvec(theta[ok, 3:].reshape(-1, N_BONES, 3))
        self._joints = joints[ok]
        self._hand_poses = hands_of(self._people)

    @property
    def people(self) -> list[SubjectPose]:
        """The subjects that are sent (finite values only)."""
        self._prepare()
        return self._people

    @property
    def non_finite(self) -> int:
        """Subjects left out because a value was NaN or infinite."""
        self._prepare()
        return self._non_finite

    def message(self, options: StreamOptions) -> Message:
        """The frame message for a client with these options (encoded at most once per option set)."""
        key = options.encoding_key
        cached = self._messages.get(key)
        if cached is not None:
            return cached
        self._prepare()
        enc = options.encoding
        roots, rots, joints = self._values(options.convention, enc)
        hands = self._hands_values(options.convention, enc, options.globals)
        subjects = []
        for k, person in enumerate(self.people):
            if options.subjects is not None and person.identity not in options.subjects:
                continue
            s: dict[str, Any] = {
                "id": person.identity,
                "skeleton": self.description.skeleton_key(person.identity),
                "suit": person.suit,
                "root": roots[k],
                "rot": rots[k],
            }
            if options.globals:
                s["joints"] = joints[k]
            conf = float(person.confidence)
            s["confidence"] = round(conf, 4) if math.isfinite(conf) else 0.0
            s["views"] = int(person.views)
            s["imus"] = int(person.imus)
            s["t_pose_ns"] = int(self.frame.t_solve_ns if person.t_pose_ns is None else person.t_pose_ns)
            if k in hands:  # only subjects with fingers carry the key: a stream without fingers is as before
                s["hands"] = hands[k]
            subjects.append(s)
        msg = encode(
            {"type": "frame", "frame": int(self.frame.frame), "t_solve_ns": int(self.frame.t_solve_ns),
             "t_publish_ns": self.t_publish_ns, "subjects": subjects},
            enc,
        )  # fmt: skip
        self._messages[key] = msg
        self.encodings += 1
        return msg

    def _values(self, conv_name: str, encoding: str) -> tuple[list[list[float]], ...]:
        """Per subject: root, rotations and joints as float lists in a convention (converted once each)."""
        lists = self._lists.get((conv_name, encoding))
        if lists is None:
            cv = self._converted.get(conv_name)
            if cv is None:
                c = convention(conv_name)
                cv = self._converted[conv_name] = _Converted(
                    c.positions(self._root), c.quaternions(self._quats), c.positions(self._joints)
                )
            lists = self._lists[(conv_name, encoding)] = (
                _rows(cv.root, encoding),
                _rows(cv.rot, encoding),
                _rows(cv.joints, encoding),
            )
        return lists

    def _hands_values(self, conv_name: str, encoding: str, globals_: bool) -> dict[int, dict[str, Any]]:
        """Per subject with fingers (index into :attr:`people`): its ``hands`` map in a convention."""
        key = (conv_name, encoding, globals_)
        cached = self._hands.get(key)
        if cached is not None:
            return cached
        idx = [k for k, h in enumerate(self._hand_poses) if h is not None]
        poses = [h for h in self._hand_poses if h is not None]
        out: dict[int, dict[str, Any]] = {}
        if idx:
            c = convention(conv_name)
            rot = _rows(c.quaternions(np.stack([h.rotations for h in poses])), encoding)
            offsets = _rows(c.positions(np.stack([h.skeleton.offsets for h in poses])), encoding)
            tips = _rows(c.positions(np.stack([h.skeleton.tips for h in poses])), encoding)
            joints = tip_joints = None
            if globals_:
                people = [self._people[k] for k in idx]
                skeletons = [p.skeleton if p.skeleton is not None
                             else self.description.skeletons[self.description.skeleton_key(p.identity)]
                             for p in people]  # fmt: skip
                fs = subject_fingers(np.stack([p.theta for p in people]), skeletons, poses)
                joints, tip_joints = _rows(c.positions(fs.positions), encoding), _rows(c.positions(fs.tips), encoding)
            for i, (k, h) in enumerate(zip(idx, poses, strict=True)):
                m: dict[str, Any] = {"present": [bool(v) for v in h.present], "rot": rot[i], "offsets": offsets[i],
                                     "tip_offsets": tips[i]}  # fmt: skip
                if joints is not None and tip_joints is not None:
                    m["joints"], m["tip_joints"] = joints[i], tip_joints[i]
                out[k] = m
        self._hands[key] = out
        return out


def skeleton_map(skeleton: Skeleton, conv: Convention, encoding: str) -> dict[str, Any]:
    """The hello's description of one skeleton in a convention: bones, parents, offsets (63 floats)."""
    return {
        "bones": list(BONE_NAMES),
        "parents": list(skeleton.parents),
        "offsets": _floats(conv.positions(skeleton.offsets), encoding),
    }


def decimation_for(stream_rate_hz: float, rate_hz: float | None) -> int:
    """Every n-th frame so that the client gets at most about ``rate_hz`` (None: every frame)."""
    if rate_hz is None or rate_hz >= stream_rate_hz:
        return 1
    return max(1, round(stream_rate_hz / rate_hz))


def health_subset(health: Mapping[str, Any]) -> dict[str, Any]:
    """The part of the daemon's /status document a status message carries (missing parts are left out)."""
    out: dict[str, Any] = {}
    if "uptime_s" in health:
        out["uptime_s"] = health["uptime_s"]
    if isinstance(health.get("output"), Mapping):
        out["output"] = dict(health["output"])
    lat = health.get("latency_ms")
    if isinstance(lat, Mapping):
        out["latency_ms"] = {
            stage: {k: v.get(k) for k in ("p50", "p95", "p99")} for stage, v in lat.items() if isinstance(v, Mapping)
        }
    cams = health.get("cameras")
    if isinstance(cams, list):
        out["cameras"] = [{k: c.get(k) for k in ("name", "kind", "frames")} for c in cams if isinstance(c, Mapping)]
    imu = health.get("imu")
    devices = imu.get("devices") if isinstance(imu, Mapping) else None
    if isinstance(devices, list):
        out["imus"] = [
            {k: d.get(k) for k in ("path", "streaming", "samples", "disconnects")}
            for d in devices
            if isinstance(d, Mapping)
        ]
    slimevr = imu.get("slimevr") if isinstance(imu, Mapping) else None
    trackers = slimevr.get("trackers") if isinstance(slimevr, Mapping) else None
    if isinstance(trackers, list):  # SlimeVR trackers are IMUs too (the viewer listed "none" while they streamed)
        out.setdefault("imus", []).extend(
            {"path": f"slimevr {t.get('id')}", "streaming": bool(t.get("connected")), "samples": t.get("packets"),
             "disconnects": None}
            for t in trackers
            if isinstance(t, Mapping)
        )  # fmt: skip
    tasks = health.get("tasks")
    if isinstance(tasks, Mapping):
        out["tasks"] = {k: v.get("failures", 0) for k, v in tasks.items() if isinstance(v, Mapping)}
    governor = health.get("governor")
    if isinstance(governor, Mapping):
        out["governor"] = {k: governor.get(k) for k in ("step", "shed", "reason")}
    return out


class CameraPanel(Protocol):
    """What a camera message needs (:class:`mocapd.pipeline.camera_views.CameraView` has it)."""

    @property
    def camera(self) -> int: ...
    @property
    def name(self) -> str: ...
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def capture_ns(self) -> int: ...
    @property
    def frame(self) -> int: ...
    @property
    def t_solve_ns(self) -> int: ...
    @property
    def detections(self) -> FloatArray: ...  # (n_people, n_kp, 3)
    @property
    def subjects(self) -> Sequence[Any]: ...  # each with .id (str) and .joints (21, 2)
    @property
    def reprojection_px(self) -> float | None: ...
    @property
    def detection_hz(self) -> float: ...


def _maybe(values: FloatArray, encoding: str) -> list[float | None]:
    """Floats with NaN as nil (JSON has no NaN), rounded to 2 decimals for JSON (hundredths of a pixel)."""
    flat = np.asarray(values, dtype=np.float64).reshape(-1)
    if encoding == "json":
        flat = np.round(flat, 2)
    return [None if not math.isfinite(v) else v for v in flat.tolist()]


def camera_message(panel: CameraPanel, jpeg: bytes | None, image_size: tuple[int, int], encoding: str) -> Message:
    """The ``camera`` message of one panel (see the module doc); ``image_size`` is the JPEG's (width, height)."""
    image: bytes | str | None = jpeg
    if jpeg is not None and encoding == "json":
        image = base64.b64encode(jpeg).decode("ascii")
    rep = panel.reprojection_px
    return encode(
        {
            "type": "camera", "camera": int(panel.camera), "name": panel.name,
            "width": int(panel.width), "height": int(panel.height), "t_capture_ns": int(panel.capture_ns),
            "frame": int(panel.frame), "t_solve_ns": int(panel.t_solve_ns),
            "image": image, "image_width": int(image_size[0]) if jpeg is not None else 0,
            "image_height": int(image_size[1]) if jpeg is not None else 0,
            "detections": [_maybe(d, encoding) for d in panel.detections],
            "subjects": [{"id": s.id, "joints": _maybe(s.joints, encoding)} for s in panel.subjects],
            "reprojection_px": None if rep is None or not math.isfinite(rep) else round(float(rep), 2),
            "detection_hz": round(float(panel.detection_hz), 2),
        },
        encoding,
    )  # fmt: skip


class RequestError(ValueError):
    """A client message that cannot be used; ``code`` goes into the error reply."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class ClientSession:
    """One client's side of the protocol: its options, its requests in, its hello/error/status messages out.

    Feed every message the client sent to :meth:`receive_message`; send what :meth:`messages_to_send` returns
    before any further frame. Frames come from :class:`FrameEncoder` with :attr:`options`, for the frames
    :meth:`wants` accepts.
    """

    def __init__(self, description: StreamDescription, defaults: StreamOptions | None = None) -> None:
        self.description = description
        self.options = defaults if defaults is not None else StreamOptions()
        self.requests = 0
        self.errors = 0
        self._outbox: list[Message] = []
        self._commands: list[tuple[str, dict[str, Any]]] = []
        self.latest_subjects: tuple[str, ...] = ()

    # -------------------------------------------------------------------------------------------- output
    def messages_to_send(self) -> list[Message]:
        """Replies produced since the last call (in order)."""
        out, self._outbox = self._outbox, []
        return out

    def hello(self) -> Message:
        """The hello for the current options (also queued by accepted subscribe requests)."""
        o = self.options
        conv = convention(o.convention)
        rate = self.description.rate_hz
        return encode(
            {
                "type": "hello", "v": PROTOCOL_VERSION, "server": "mocapd",
                "convention": o.convention, "units": "cm" if conv.scale == 100.0 else "m",
                "left_handed": conv.left_handed, "encoding": o.encoding,
                "encodings": list(ENCODINGS), "conventions": list(STREAM_CONVENTIONS),
                "stream_rate_hz": rate, "output": self.description.output, "decimation": o.decimation,
                "rate_hz": rate / o.decimation,
                "globals": o.globals,
                "subjects_filter": None if o.subjects is None else sorted(o.subjects),
                "status": o.status, "max_message_bytes": self.description.max_message_bytes,
                "bones": list(BONE_NAMES), "parents": list(PARENTS),
                "skeletons": {k: skeleton_map(s, conv, o.encoding) for k, s in self.description.skeletons.items()},
                "subjects": [
                    {"id": s, "skeleton": self.description.skeleton_key(s)} for s in self.latest_subjects
                ],
                "cameras": [{"name": n, "width": w, "height": h} for n, w, h in self.description.cameras],
                "camera_views": o.cameras, "camera_rate_hz": o.camera_rate_hz,
                **({"finger_bones": list(HAND_BONE_NAMES), "finger_parents": list(EXTENDED_PARENTS[N_BONES:])}
                   if self.description.fingers else {}),
            },
            o.encoding,
        )  # fmt: skip

    def status(self, health: Mapping[str, Any], t_ns: int, stream: Mapping[str, int]) -> Message:
        """A status message: the health subset of the daemon's status plus this client's stream counters."""
        return encode({"type": "status", "t_ns": int(t_ns), **health_subset(health), "stream": dict(stream)},
                      self.options.encoding)  # fmt: skip

    def wants(self, frame_number: int) -> bool:
        """Whether this client's decimation selects the frame with this counter."""
        return frame_number % self.options.decimation == 0

    def error(self, code: str, message: str) -> Message:
        return encode({"type": "error", "code": code, "message": message}, self.options.encoding)

    def commands_received(self) -> list[tuple[str, dict[str, Any]]]:
        """Requests for the daemon (``("reset_heading", {"suit": ...})``) since the last call, for the server to carry
        out and answer with :meth:`reply` or :meth:`error`."""
        out, self._commands = self._commands, []
        return out

    def reply(self, kind: str, payload: Mapping[str, Any]) -> Message:
        """The answer to a request the daemon carried out: ``{"type": kind, **payload}``."""
        return encode({"type": kind, **payload}, self.options.encoding)

    # -------------------------------------------------------------------------------------------- input
    def receive_message(self, data: Message) -> RequestError | None:
        """Handle one client message: apply a valid subscribe (queue a hello) or queue an error reply; returns
        the error (for the server's counters) or None."""
        self.requests += 1
        try:
            request = self._parse(data)
            if request["type"] == "reset_heading":
                self._commands.append(("reset_heading", {"suit": request.get("suit")}))
                return None
            self.options = self._apply(request)
        except RequestError as exc:
            self.errors += 1
            self._outbox.append(self.error(exc.code, str(exc)))
            return exc
        self._outbox.append(self.hello())
        return None

    def _parse(self, data: Message) -> dict[str, Any]:
        limit = self.description.max_message_bytes
        size = len(data) if isinstance(data, bytes) else len(data.encode("utf-8", "surrogatepass"))
        if size > limit:
            raise RequestError("too_large", f"message of {size} bytes; at most {limit} bytes")
        try:
            obj = msgpack.unpackb(data, strict_map_key=True) if isinstance(data, bytes) else json.loads(data)
        except (ValueError, RecursionError) as exc:  # msgpack's and json's errors are ValueErrors
            what = "msgpack (binary message)" if isinstance(data, bytes) else "JSON (text message)"
            raise RequestError("bad_encoding", f"not valid {what}: {exc}") from None
        if not isinstance(obj, dict):
            raise RequestError("bad_message", f"a request must be a map, got {type(obj).__name__}")
        kind = obj.get("type")
        keys = {"subscribe": _SUBSCRIBE_KEYS, "reset_heading": _RESET_KEYS}.get(kind) if isinstance(kind, str) else None
        if keys is None:
            raise RequestError("unknown_type", f"unknown request type {kind!r}; requests: 'subscribe', 'reset_heading'")
        unknown = set(obj) - keys
        if unknown:
            raise RequestError("bad_field", f"unknown key(s) {sorted(map(str, unknown))}; allowed: {sorted(keys)}")
        suit = obj.get("suit")
        named = isinstance(suit, str) and 0 < len(suit) <= MAX_ID_CHARS
        if kind == "reset_heading" and suit is not None and not named:
            raise RequestError("bad_field", f"suit = {suit!r}; allowed: a suit's name (1 to {MAX_ID_CHARS} characters)")
        return obj

    def _apply(self, r: Mapping[str, Any]) -> StreamOptions:
        o = self.options
        updates: dict[str, Any] = {}
        if "encoding" in r:
            if r["encoding"] not in ENCODINGS:
                raise RequestError("bad_field", f"encoding = {r['encoding']!r}; allowed: {list(ENCODINGS)}")
            updates["encoding"] = r["encoding"]
        if "convention" in r:
            if r["convention"] not in STREAM_CONVENTIONS:
                raise RequestError(
                    "bad_field", f"convention = {r['convention']!r}; allowed: {list(STREAM_CONVENTIONS)}"
                )
            updates["convention"] = r["convention"]
        for key in ("globals", "status"):
            if key in r:
                if not isinstance(r[key], bool):
                    raise RequestError("bad_field", f"{key} = {r[key]!r}; allowed: true or false")
                updates[key] = r[key]
        if "subjects" in r:
            updates["subjects"] = _subjects(r["subjects"])
        if "cameras" in r:
            if not isinstance(r["cameras"], bool):
                raise RequestError("bad_field", f"cameras = {r['cameras']!r}; allowed: true or false")
            if r["cameras"] and not self.description.cameras:
                raise RequestError("bad_field", "cameras: this server has no camera views")
            updates["cameras"] = r["cameras"]
        if "camera_rate_hz" in r:
            top = self.description.camera_rate_hz
            rate = _rate("camera_rate_hz", r["camera_rate_hz"], top, f"nil for {top}")
            updates["camera_rate_hz"] = top if rate is None else rate
        if "rate_hz" in r:
            stream = self.description.rate_hz
            rate = _rate("rate_hz", r["rate_hz"], stream, "nil for every frame")
            updates["decimation"] = decimation_for(stream, rate)
        return replace(o, **updates)


def _shown(value: object) -> str:
    """A client's value for an error message, cut short (a reply must not echo kilobytes back)."""
    if isinstance(value, int) and abs(value) >= 10**30:
        return f"an integer of {len(str(abs(value)))} digits"
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _rate(key: str, value: object, top: float, nil: str) -> float | None:
    """A client's rate (Hz) checked for type, finiteness and range, at most ``top`` (None stays None).

    The bounds matter downstream: a rate of 1e-20 Hz would make a decimation of 6e21 frames, which msgpack
    cannot encode, and an integer of 400 digits cannot even become a float.
    """
    if value is None:
        return None
    # Compared as given: an int as an int (10**400 has no float), NaN and ±inf fall outside the bounds.
    if isinstance(value, bool) or not isinstance(value, int | float) or not MIN_RATE_HZ <= value <= MAX_RATE_HZ:
        raise RequestError("bad_field", f"{key} = {_shown(value)}; allowed: a number from {MIN_RATE_HZ} to "
                                        f"{MAX_RATE_HZ:g} Hz, or {nil}")  # fmt: skip
    return float(min(value, top))


def _subjects(value: object) -> frozenset[str] | None:
    if value is None:
        return None
    if not isinstance(value, list) or len(value) > MAX_SUBJECTS_PER_REQUEST:
        raise RequestError(
            "bad_field", f"subjects must be a list of at most {MAX_SUBJECTS_PER_REQUEST} ids, or nil for all"
        )
    for s in value:
        if not isinstance(s, str) or not 0 < len(s) <= MAX_ID_CHARS:
            raise RequestError("bad_field", f"subject id {s!r}: allowed: a string of 1..{MAX_ID_CHARS} characters")
    return frozenset(value)

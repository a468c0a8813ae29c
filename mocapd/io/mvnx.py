"""Xsens MVN ``.mvnx`` exports (XML, versions 3–4) → segment and sensor arrays, and a SourceMotion.

MVN's world is Z up, X forward (at reset), Y left; mocapd's is Y up with the person's left +X, so a vector
``(x, y, z)`` of MVN is ``(y, z, x)`` here (a cyclic permutation, still right-handed). Quaternions are (w, x, y,
z) in both. Frames of type ``identity``, ``tpose`` and ``tpose-isb`` are calibration poses and are returned
apart from the ``normal`` frames of the recording.

The file is a door (issue 34): it must be a regular file of at most :data:`MAX_FILE_BYTES`
(:mod:`mocapd.io.input_files`) and is parsed as a stream (expat feeding a target that keeps only the numbers it
needs: a frame's text is dropped once its arrays are read, so memory follows the recording's arrays, not the XML
tree, ~10 times their size). Counts and values are checked: at most :data:`MAX_SEGMENTS` segments and
:data:`MAX_SENSORS` sensors, no element's text beyond :data:`MAX_TEXT_CHARS`, at most :data:`MAX_FRAMES` frames,
a frame rate in [:data:`MIN_FPS`, :data:`MAX_FPS`] that agrees with the frames' times within 10 %, times in ms
finite, at least 0 and increasing, every number finite; anything else is one ``InputError`` naming the file.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.imu import STANDARD_GRAVITY
from mocapd.core.motion import SourceMotion
from mocapd.core.rotations import matrix_from_quat, quat_from_matrix, quat_normalize
from mocapd.errors import InputError
from mocapd.io.input_files import GiB, open_input
from mocapd.io.malformed import malformed_file

FloatArray = NDArray[np.float64]

MAX_FILE_BYTES = 8 * GiB
"""Largest MVNX file read (~12 KB of XML a frame at 60 Hz: about three hours)."""
MAX_SEGMENTS = 64
MAX_SENSORS = 64
MAX_JOINTS = 128
MAX_POINTS = 4096
"""Segment points read (MVN's 23 segments have 127)."""
MAX_FRAMES = 5_000_000
MAX_TEXT_CHARS = 1 << 20
"""Longest text of one element (a frame's 23 segment orientations are ~1.5 KB)."""
MIN_FPS = 1.0
MAX_FPS = 1_000.0
"""Frame rates accepted (MVN records at 60 to 240 Hz)."""
MAX_TIME_MS = 1e10
"""Latest frame time accepted (ms from the start: about 115 days)."""
_CHUNK = 1 << 20
_FRAME_FIELDS = ("orientation", "position", "sensorOrientation", "sensorFreeAcceleration")
MVN_FACING_HEADING_DEG = 90.0
"""The facing of an MVNX take's wearer in its sensors' world: MVN's +X is where they faced at MVN's calibration
(reset), and a session holds the sensors' orientations in MVN's global frame read as Xsens's ENU, whose +X is east
(``calibrate imu --facing-heading``: degrees clockwise from north)."""

_PERM = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
"""MVN (Z up, X forward, Y left) → mocapd (Y up, X left, Z forward)."""


@dataclass(frozen=True)
class MvnxRecording:
    """The parts of an MVNX file mocapd uses (mocapd's axes).

    Attributes
    ----------
    segments : tuple of str (n_seg)
    segment_parents : tuple of int (n_seg)
        From the file's joint list (-1 for the root segment).
    sensors : tuple of str (n_sen)
        Segment label each sensor is strapped to.
    fps : float
    time_ms : array, shape (n_frames,)
    segment_orientation : array, shape (n_frames, n_seg, 4)
        Global segment orientations (w, x, y, z).
    segment_position : array, shape (n_frames, n_seg, 3)
        Segment origins (m).
    sensor_orientation : array, shape (n_frames, n_sen, 4)
        Sensor orientations in the world (MVN's calibrated ``sensorOrientation``), or zeros when absent.
    sensor_free_acceleration : array, shape (n_frames, n_sen, 3)
        Sensor accelerations in the world with gravity removed (m/s²), or zeros when absent.
    tpose_orientation : array, shape (n_seg, 4) or None
        Segment orientations of the ``tpose`` calibration frame if present.
    segment_points : dict of str to dict of str to array, shape (3,)
        Each segment's named points (joints ``j…``, anatomical landmarks ``p…``) in the segment's frame, as MVN
        calibrated them for the wearer (``<points><point><pos_b>``; MVN's axes: Z up, X forward, Y left).
    joints : tuple of (str, str)
        The file's joint list: (``parent/point``, ``child/point``), the point where the child segment hangs.
    """

    segments: tuple[str, ...]
    segment_parents: tuple[int, ...]
    sensors: tuple[str, ...]
    fps: float
    time_ms: FloatArray
    segment_orientation: FloatArray
    segment_position: FloatArray
    sensor_orientation: FloatArray
    sensor_free_acceleration: FloatArray
    tpose_orientation: FloatArray | None
    segment_points: dict[str, dict[str, FloatArray]] = field(default_factory=dict)
    joints: tuple[tuple[str, str], ...] = ()

    def body(self) -> MvnBody | None:
        """The wearer's body as MVN calibrated it (:func:`mvn_body`), or None where the file has no segment
        points."""
        return mvn_body(self.segment_points, self.joints)

    def sensor_readings(self) -> tuple[FloatArray, FloatArray]:
        """Each sensor's orientation and specific force as the device frames have them (MVN's Z-up global frame,
        the sensor's own axes), for sessions and calibration: the inverse of the axis change applied on reading.

        Returns
        -------
        quat : array, shape (n_frames, n_sen, 4)
            Sensor → MVN global frame (w, x, y, z).
        specific_force : array, shape (n_frames, n_sen, 3)
            In the sensor frame, gravity included (m/s²): ``R_iᵀ (a_free + g ẑ)``.
        """
        q = self.sensor_orientation.copy()
        q[..., 1:] = q[..., 1:] @ _PERM  # the vector part back to MVN axes (_PERM is orthogonal)
        free = self.sensor_free_acceleration @ _PERM
        R = matrix_from_quat(quat_normalize(q))
        f = np.einsum("...ji,...j->...i", R, free + np.array([0.0, 0.0, STANDARD_GRAVITY]))
        return quat_normalize(q), np.asarray(f)

    def to_motion(self, name: str = "mvnx") -> SourceMotion:
        """The segments as a joint tree (each segment's origin a joint) for retargeting."""
        G = matrix_from_quat(self.segment_orientation)
        x = self.segment_position
        _f, n = x.shape[:2]
        tr = np.empty_like(x)
        rot = np.empty_like(self.segment_orientation)
        for j, p in enumerate(self.segment_parents):
            if p < 0:
                tr[:, j] = x[:, j]
                rot[:, j] = self.segment_orientation[:, j]
            else:
                Gp_t = np.swapaxes(G[:, p], -1, -2)
                tr[:, j] = np.einsum("fij,fj->fi", Gp_t, x[:, j] - x[:, p])
                rot[:, j] = quat_from_matrix(Gp_t @ G[:, j])
        return SourceMotion(name, self.segments, self.segment_parents, tr, rot, np.zeros((n, 3)), self.fps)


def _floats(text: str | None, what: str) -> FloatArray:
    if text is None:
        raise InputError(f"MVNX: frame without <{what}>")
    return np.array(text.split(), dtype=np.float64)


def _vec(a: FloatArray) -> FloatArray:
    return np.asarray(a.reshape(-1, 3) @ _PERM.T)


def _quat(a: FloatArray) -> FloatArray:
    q = a.reshape(-1, 4)
    out = np.empty_like(q)
    out[:, 0] = q[:, 0]
    out[:, 1:] = q[:, 1:] @ _PERM.T
    return quat_normalize(out)


def read_mvnx(path: str | Path) -> MvnxRecording:
    """Read an MVNX file (see module doc)."""
    p = Path(path)
    target = _Target(p.name)
    parser = ET.XMLParser(target=target)
    with open_input(p, "MVNX file", max_bytes=MAX_FILE_BYTES) as fh, malformed_file(f"MVNX {p.name}"):
        try:
            while chunk := fh.read(_CHUNK):
                parser.feed(chunk)
            parser.close()
        except ET.ParseError as exc:
            raise InputError(f"cannot read MVNX file {p}: {exc}") from None
        except OSError as exc:
            raise InputError(f"cannot read MVNX file {p}: {exc.strerror or exc}") from None
        rec = target.recording()
    arrays = [rec.time_ms, rec.segment_orientation, rec.segment_position, rec.sensor_orientation,
              rec.sensor_free_acceleration]  # fmt: skip
    if rec.tpose_orientation is not None:  # the calibration pose: a nan there would reach the retarget silently
        arrays.append(rec.tpose_orientation)
    if not (np.isfinite(rec.fps) and rec.fps > 0) or not all(np.isfinite(a).all() for a in arrays):
        raise InputError(f"MVNX {p.name}: non-finite values (frame rate {rec.fps!r}, or a frame's numbers)")
    _check_times(rec, p.name)
    return rec


def _check_times(rec: MvnxRecording, name: str) -> None:
    """Frame rate and times plausible: MVN's rate, and ms times that start at >= 0 and increase at about it."""
    if not MIN_FPS <= rec.fps <= MAX_FPS:
        raise InputError(f"MVNX {name}: frameRate {rec.fps:.6g}; allowed: {MIN_FPS:g} to {MAX_FPS:g} Hz")
    t = rec.time_ms
    if t.size and not (t[0] >= 0 and t[-1] <= MAX_TIME_MS):
        raise InputError(f"MVNX {name}: frame times from {t[0]:.6g} to {t[-1]:.6g} ms; allowed: 0 to "
                         f"{MAX_TIME_MS:.0e} ms")  # fmt: skip
    if np.any(np.diff(t) <= 0):
        k = int(np.argmax(np.diff(t) <= 0))
        raise InputError(f"MVNX {name}: frame times do not increase ({t[k]:.6g} ms, then {t[k + 1]:.6g} ms)")
    if t.size > 2:
        step_fps = 1000.0 / float(np.median(np.diff(t)))
        if abs(rec.fps / step_fps - 1.0) > 0.1:
            raise InputError(f"MVNX {name}: frameRate {rec.fps:g} Hz disagrees with the frames' times "
                             f"({step_fps:.4g} Hz)")  # fmt: skip


@dataclass
class _Target:
    """An expat target that keeps what :class:`MvnxRecording` needs (see the module docstring)."""

    name: str
    ns: str | None = None
    path: list[str] = field(default_factory=list)
    fps_text: str | None = None
    subjects: int = 0
    segs: list[str] = field(default_factory=list)
    sensors: list[str] = field(default_factory=list)
    joints: list[tuple[str | None, str | None]] = field(default_factory=list)
    frame: dict[str, Any] | None = None
    text: list[str] | None = None
    text_chars: int = 0
    times: list[float] = field(default_factory=list)
    ori: list[FloatArray] = field(default_factory=list)
    pos: list[FloatArray] = field(default_factory=list)
    s_ori: list[FloatArray] = field(default_factory=list)
    s_acc: list[FloatArray] = field(default_factory=list)
    tpose: FloatArray | None = None
    points: dict[str, dict[str, FloatArray]] = field(default_factory=dict)
    n_points: int = 0
    point: str | None = None

    def start(self, tag: str, attrib: dict[str, str]) -> None:
        if self.ns is None:
            self.ns = tag.split("}", maxsplit=1)[0] + "}" if tag.startswith("{") else ""
        local = tag.removeprefix(self.ns) if self.ns else tag
        self.path.append(local)
        if "subject" not in self.path:
            return
        if local == "subject" and self.subjects == 0:
            self.subjects = 1
            self.fps_text = attrib.get("frameRate", "60")
        elif self.subjects != 1 or len(self.path) < 2:
            return
        elif local == "segment":
            self._count(self.segs, MAX_SEGMENTS, "segments").append(attrib.get("label", ""))
        elif local == "point" and self.path[-2] == "points" and "segment" in self.path and self.segs:
            if self.n_points >= MAX_POINTS:
                raise InputError(f"MVNX {self.name}: more than {MAX_POINTS} segment points")
            self.point, self.n_points = attrib.get("label", ""), self.n_points + 1
        elif local == "pos_b" and self.path[-2] == "point" and self.point is not None:
            self.text, self.text_chars = [], 0
        elif local == "sensor":
            self._count(self.sensors, MAX_SENSORS, "sensors").append(attrib.get("label", ""))
        elif local == "joint":
            self._count(self.joints, MAX_JOINTS, "joints").append((None, None))
        elif (local in ("connector1", "connector2") and self.path[-2] == "joint") or (
            local in _FRAME_FIELDS and self.path[-2] == "frame" and self.frame is not None
        ):
            self.text, self.text_chars = [], 0
        elif local == "frame":
            if len(self.times) >= MAX_FRAMES:
                raise InputError(f"MVNX {self.name}: more than {MAX_FRAMES} frames")
            self.frame = {"type": attrib.get("type", "normal"), "time": attrib.get("time", "0")}

    def _count(self, items: list[Any], limit: int, what: str) -> list[Any]:
        if len(items) >= limit:
            raise InputError(f"MVNX {self.name}: more than {limit} {what}")
        return items

    def data(self, text: str) -> None:
        if self.text is not None:
            self.text_chars += len(text)
            if self.text_chars > MAX_TEXT_CHARS:
                raise InputError(f"MVNX {self.name}: <{self.path[-1]}> holds more than {MAX_TEXT_CHARS} characters")
            self.text.append(text)

    def end(self, tag: str) -> None:
        local = self.path.pop() if self.path else ""
        text = "".join(self.text) if self.text is not None else None
        self.text = None
        if local == "pos_b" and text is not None and self.point is not None:
            xyz = _floats(text, "pos_b")
            if xyz.shape != (3,):
                raise InputError(f"MVNX {self.name}: segment {self.segs[-1]!r} point {self.point!r}: pos_b holds "
                                 f"{xyz.size} numbers, not 3")  # fmt: skip
            self.points.setdefault(self.segs[-1], {})[self.point] = xyz
        elif local == "point":
            self.point = None
        elif local in ("connector1", "connector2") and text is not None and self.joints:
            c1, c2 = self.joints[-1]
            self.joints[-1] = (text, c2) if local == "connector1" else (c1, text)
        elif local in _FRAME_FIELDS and self.frame is not None and text is not None:
            self.frame[local] = text
        elif local == "frame" and self.frame is not None:
            self._frame(self.frame)
            self.frame = None
        elif local == "subject" and self.subjects == 1:
            self.subjects = 2  # a second <subject> is not read (as before: the first one)

    def close(self) -> None:
        return None

    def _frame(self, fr: dict[str, Any]) -> None:
        kind = fr["type"]
        if kind == "tpose":
            self.tpose = _quat(_floats(fr.get("orientation"), "orientation"))
        if kind != "normal":
            return
        n = len(self.sensors)
        self.times.append(float(fr["time"]))
        self.ori.append(_quat(_floats(fr.get("orientation"), "orientation")))
        self.pos.append(_vec(_floats(fr.get("position"), "position")))
        so, sa = fr.get("sensorOrientation"), fr.get("sensorFreeAcceleration")
        self.s_ori.append(_quat(_floats(so, "sensorOrientation")) if so is not None else np.zeros((n, 4)))
        self.s_acc.append(_vec(_floats(sa, "sensorFreeAcceleration")) if sa is not None else np.zeros((n, 3)))

    def recording(self) -> MvnxRecording:
        name = self.name
        if self.subjects == 0:
            raise InputError(f"MVNX {name}: no <subject>")
        fps = float(self.fps_text or "60")
        if not math.isfinite(fps):
            raise InputError(f"MVNX {name}: non-finite values (frame rate {fps!r}, or a frame's numbers)")
        segs = self.segs
        index = {s: i for i, s in enumerate(segs)}
        parents = [-1] * len(segs)
        for c1, c2 in self.joints:
            if c1 is None or c2 is None:
                continue
            a, b = c1.split("/")[0], c2.split("/")[0]
            if a in index and b in index:
                parents[index[b]] = index[a]
        order = _topological(parents)
        if not self.times:
            raise InputError(f"MVNX {name}: no normal frames")
        perm = np.array(order)
        inv = {old: new for new, old in enumerate(order)}
        return MvnxRecording(
            segments=tuple(segs[i] for i in order),
            segment_parents=tuple(-1 if parents[i] < 0 else inv[parents[i]] for i in order),
            sensors=tuple(self.sensors),
            fps=fps,
            time_ms=np.array(self.times),
            segment_orientation=np.stack(self.ori)[:, perm],
            segment_position=np.stack(self.pos)[:, perm],
            sensor_orientation=np.stack(self.s_ori),
            sensor_free_acceleration=np.stack(self.s_acc),
            tpose_orientation=None if self.tpose is None else self.tpose[perm],
            segment_points=self.points,
            joints=tuple((c1, c2) for c1, c2 in self.joints if c1 is not None and c2 is not None),
        )


def _topological(parents: list[int]) -> list[int]:
    roots = [i for i, p in enumerate(parents) if p < 0]
    if len(roots) != 1:
        raise InputError(f"MVNX: segment hierarchy must have one root, found {len(roots)}")
    order, frontier = [], roots
    while frontier:
        order.extend(frontier)
        frontier = [c for c, p in enumerate(parents) if p in frontier]
    return order


@dataclass(frozen=True)
class MvnBody:
    """The wearer's height and segment lengths (m; :data:`mocapd.core.body_dims.SEGMENTS`) from an MVNX file's
    segment points: what MVN Studio's body dimensions and calibration made of the person."""

    height: float
    segments: dict[str, float]


_SOLE = ("HeelFoot", "FirstMetatarsal", "FifthMetatarsal", "PivotFoot")
"""The foot's points on the floor when standing (``pRightHeelFoot`` ...)."""


def mvn_body(points: dict[str, dict[str, FloatArray]], joints: tuple[tuple[str, str], ...]) -> MvnBody | None:
    """The wearer's body from MVN's segment points (each in its segment's frame) and joint list.

    MVN's segment frames are all aligned with the world in its neutral pose, so a point's place in that pose is the
    sum of the joint offsets down the tree: the height is the top of the head above the soles' points, the
    lengths are joint to joint (both sides averaged), the torso the hip joints' midpoint to the neck's base
    (``jT1C7``). None where the file lacks any of the points needed (an older MVNX without ``<points>``).
    """
    origin: dict[str, FloatArray] = {}
    parent_of = {c2.split("/")[0]: (c1.split("/", 1), c2.split("/", 1)) for c1, c2 in joints if "/" in c1 + c2}
    if not points or not parent_of:
        return None

    def at(seg: str, depth: int = 0) -> FloatArray:
        """A segment's origin in the neutral pose (m, relative to the root segment's)."""
        if seg in origin:
            return origin[seg]
        if seg not in parent_of or depth > MAX_SEGMENTS:
            origin[seg] = np.zeros(3)  # the root
            return origin[seg]
        (ps, pp), (cs, cp) = parent_of[seg]
        origin[seg] = at(ps, depth + 1) + points[ps][pp] - points[cs][cp]
        return origin[seg]

    def point(seg: str, label: str) -> FloatArray:
        return at(seg) + points[seg][label]

    def mean_len(seg: str, label: str) -> float:
        return float(np.mean([np.linalg.norm(points[f"{s}{seg}"][f"j{s}{label}"]) for s in ("Right", "Left")]))

    try:
        sole = np.median([point(f"{s}Foot", f"p{s}{p}")[2] for s in ("Right", "Left") for p in _SOLE])
        hips = 0.5 * (point("Pelvis", "jRightHip") + point("Pelvis", "jLeftHip"))
        ankle = 0.5 * (point("RightFoot", "jRightAnkle") + point("LeftFoot", "jLeftAnkle"))
        segments = {
            "hip_width": float(np.linalg.norm(point("Pelvis", "jRightHip") - point("Pelvis", "jLeftHip"))),
            "thigh": mean_len("UpperLeg", "Knee"),
            "shank": mean_len("LowerLeg", "Ankle"),
            "foot": mean_len("Foot", "BallFoot"),
            "ankle_height": float(ankle[2] - sole),
            "torso": float(np.linalg.norm(point("T8", "jT1C7") - hips)),
            "shoulder_width": float(np.linalg.norm(at("RightUpperArm") - at("LeftUpperArm"))),
            "upper_arm": mean_len("UpperArm", "Elbow"),
            "forearm": mean_len("ForeArm", "Wrist"),
        }
        height = float(point("Head", "pTopOfHead")[2] - sole)
    except KeyError:
        return None
    return MvnBody(round(height, 4), {k: round(v, 4) for k, v in segments.items()})

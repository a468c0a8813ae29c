"""Xsens MVN ``.mvnx`` exports (XML, versions 3–4) → segment and sensor arrays, and a SourceMotion.

MVN's world is Z up, X forward (at reset), Y left; mocapd's is Y up with the person's left +X, so a vector
``(x, y, z)`` of MVN is ``(y, z, x)`` here (a cyclic permutation, still right-handed). Quaternions are (w, x, y,
z) in both. Frames of type ``identity``, ``tpose`` and ``tpose-isb`` are calibration poses and are returned
apart from the ``normal`` frames of the recording.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mocapd.core.imu import STANDARD_GRAVITY
from mocapd.core.motion import SourceMotion
from mocapd.core.rotations import matrix_from_quat, quat_from_matrix, quat_normalize
from mocapd.errors import InputError
from mocapd.io.malformed import malformed_file

FloatArray = NDArray[np.float64]

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


def _floats(el: ET.Element | None, what: str) -> FloatArray:
    if el is None or el.text is None:
        raise InputError(f"MVNX: frame without <{what}>")
    return np.array(el.text.split(), dtype=np.float64)


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
    try:
        root = ET.parse(p).getroot()
    except (OSError, ET.ParseError) as exc:
        raise InputError(f"cannot read MVNX file {p}: {exc}") from exc
    ns = root.tag.split("}")[0] + "}" if root.tag.startswith("{") else ""
    subject = root.find(f"{ns}subject")
    if subject is None:
        raise InputError(f"MVNX {p.name}: no <subject>")
    with malformed_file(f"MVNX {p.name}"):
        rec = _recording(subject, ns, p.name)
    arrays = [rec.time_ms, rec.segment_orientation, rec.segment_position, rec.sensor_orientation,
              rec.sensor_free_acceleration]  # fmt: skip
    if rec.tpose_orientation is not None:  # the calibration pose: a nan there would reach the retarget silently
        arrays.append(rec.tpose_orientation)
    if not (np.isfinite(rec.fps) and rec.fps > 0) or not all(np.isfinite(a).all() for a in arrays):
        raise InputError(f"MVNX {p.name}: non-finite values (frame rate {rec.fps!r}, or a frame's numbers)")
    return rec


def _recording(subject: ET.Element, ns: str, name: str) -> MvnxRecording:
    fps = float(subject.get("frameRate", "60"))
    segs = [s.get("label", "") for s in subject.iter(f"{ns}segment")]
    sensors = [s.get("label", "") for s in subject.iter(f"{ns}sensor")]
    index = {s: i for i, s in enumerate(segs)}
    parents = [-1] * len(segs)
    for joint in subject.iter(f"{ns}joint"):
        c1, c2 = joint.find(f"{ns}connector1"), joint.find(f"{ns}connector2")
        if c1 is None or c2 is None or c1.text is None or c2.text is None:
            continue
        a, b = c1.text.split("/")[0], c2.text.split("/")[0]
        if a in index and b in index:
            parents[index[b]] = index[a]
    order = _topological(parents)
    times, ori, pos, s_ori, s_acc = [], [], [], [], []
    tpose: FloatArray | None = None
    for fr in subject.iter(f"{ns}frame"):
        kind = fr.get("type", "normal")
        if kind == "tpose":
            tpose = _quat(_floats(fr.find(f"{ns}orientation"), "orientation"))
        if kind != "normal":
            continue
        times.append(float(fr.get("time", "0")))
        ori.append(_quat(_floats(fr.find(f"{ns}orientation"), "orientation")))
        pos.append(_vec(_floats(fr.find(f"{ns}position"), "position")))
        so, sa = fr.find(f"{ns}sensorOrientation"), fr.find(f"{ns}sensorFreeAcceleration")
        s_ori.append(_quat(_floats(so, "sensorOrientation")) if so is not None else np.zeros((len(sensors), 4)))
        s_acc.append(_vec(_floats(sa, "sensorFreeAcceleration")) if sa is not None else np.zeros((len(sensors), 3)))
    if not times:
        raise InputError(f"MVNX {name}: no normal frames")
    perm = np.array(order)
    inv = {old: new for new, old in enumerate(order)}
    return MvnxRecording(
        segments=tuple(segs[i] for i in order),
        segment_parents=tuple(-1 if parents[i] < 0 else inv[parents[i]] for i in order),
        sensors=tuple(sensors),
        fps=fps,
        time_ms=np.array(times),
        segment_orientation=np.stack(ori)[:, perm],
        segment_position=np.stack(pos)[:, perm],
        sensor_orientation=np.stack(s_ori),
        sensor_free_acceleration=np.stack(s_acc),
        tpose_orientation=None if tpose is None else tpose[perm],
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

"""Export recorded subjects as BVH (:mod:`mocapd.protocols.bvh_writer`), CSV and glTF 2.0 binary
(:mod:`mocapd.protocols.gltf_writer`: every subject, one animation each), on a uniform 60 Hz grid.

The subject's recorded frames (their solve times need not be uniform: missed ticks, another output rate) are
resampled to ``rate`` Hz from its first to its last frame: root translation linearly, every bone's local rotation
by slerp, between the two recorded frames around each output time. A subject with fingers (issue 44) keeps them:
their local rotations are resampled by slerp too (a frame without fingers: the rest pose) and BVH, glTF and FBX
carry the 30 finger bones (:mod:`mocapd.protocols.fingers`); the CSV has the body's columns only.

CSV columns (one row per output frame, header row first; lengths in metres, quaternions (w, x, y, z))::

    frame, time_s, t_solve_ns, subject, root_x, root_y, root_z,
    <Bone>_qw, <Bone>_qx, <Bone>_qy, <Bone>_qz    for the 21 bones in skeleton order (local rotations)
    <Bone>_x, <Bone>_y, <Bone>_z                  for the 21 bones in skeleton order (global joint positions)
    source_s                                      (last, so that the columns before it keep their places)

Every file is written atomically (:mod:`mocapd.io.output_files`: a temporary file renamed into place when
complete); the export command checks the paths before it starts.

``time_s`` is seconds since the first exported frame, ``t_solve_ns`` the host-clock instant it stands for (the
solve time; in a session recorded with predicted output, the instants the suit wearer's poses were carried to),
``source_s`` seconds since the session began (a recorded session: its start; an imported take: its recording's
first sample, so a file's sample row ``k`` at update rate ``r`` is the row with ``source_s = k / r`` when no
sample was dropped). A bone's joint position is where the bone starts: the joint that joins it to its parent
(``Hips`` is the root, ``LeftLowerLeg`` the left knee). World frame: right-handed, +Y up, metres, floor at y = 0,
+Z where the subject faced at calibration (or magnetic north).
"""

from __future__ import annotations

import csv
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mocapd.core.hand_skeleton import N_FINGER_BONES, HandSkeleton
from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import quat_from_rotvec, quat_slerp, rotvec_from_quat
from mocapd.core.skeleton import BONE_NAMES, N_BONES, Skeleton
from mocapd.errors import InputError
from mocapd.io.output_files import atomic_file, write_bytes_atomic, write_text_atomic
from mocapd.protocols.bvh_writer import bvh_text
from mocapd.protocols.gltf_writer import GltfSubject, glb_bytes
from mocapd.protocols.session_format import PoseRecord

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class SubjectTrack:
    """One subject's poses over time: solve times (n,) ns and θ (n, 66); with fingers also their local rotations
    ``hands`` (n, 2, 15, 4) (w, x, y, z; a frame or a hand without fingers holds the rest pose: straight fingers)
    on ``hand_skeleton``."""

    subject: str
    t_ns: IntArray
    thetas: FloatArray
    skeleton: Skeleton | None = None  # the subject's own sized skeleton, as last recorded (None: the rig's)
    hands: FloatArray | None = None  # (n, 2, 15, 4): None when the subject never had fingers
    hand_skeleton: HandSkeleton | None = None  # the hands' sizes, as last recorded


def subjects(poses: list[PoseRecord]) -> Counter[str]:
    """Frames per identity."""
    return Counter(p.identity for f in poses for p in f.people)


FLEETING_S = 0.5
"""A subject seen for less than this (s) is a fleeting track (a person taken for a new one for a few frames before
their suit or track took them over): glTF and FBX leave it out unless it is named (:func:`lasting_subjects`)."""


def lasting_subjects(poses: list[PoseRecord]) -> tuple[list[str], dict[str, str]]:
    """The identities seen for at least :data:`FLEETING_S`, and the others with what they were (frames, seconds).

    Each subject of a glTF or FBX holds its first pose before its first frame and its last after its last: a
    subject of two frames stood frozen through the whole take beside the person it was. When every subject is
    fleeting (a very short session), all are kept."""
    first: dict[str, int] = {}
    last: dict[str, int] = {}
    frames: Counter[str] = Counter()
    for f in poses:
        for p in f.people:
            t = f.t_solve_ns if p.t_pose_ns is None else p.t_pose_ns
            first[p.identity] = min(first.get(p.identity, t), t)
            last[p.identity] = max(last.get(p.identity, t), t)
            frames[p.identity] += 1
    fleeting = {who: f"{frames[who]} frame(s), {(last[who] - first[who]) / 1e9:.2f} s" for who in sorted(frames)
                if last[who] - first[who] < FLEETING_S * 1e9}  # fmt: skip
    kept = sorted(who for who in frames if who not in fleeting)
    return (kept, fleeting) if kept else (sorted(frames), {})


def subject_track(poses: list[PoseRecord], subject: str | None = None) -> SubjectTrack:
    """The frames of ``subject`` (default: the identity seen in most frames)."""
    counts = subjects(poses)
    if not counts:
        raise InputError("the session has no solved person to export")
    if subject is None:
        subject = counts.most_common(1)[0][0]
    elif subject not in counts:
        raise InputError(f"no subject {subject!r} in the session; recorded: {sorted(counts)}")
    t, th = [], []
    skeleton = None
    rest = np.zeros((2, N_FINGER_BONES, 4))
    rest[..., 0] = 1.0
    fingers: list[FloatArray] = []
    hand_skeleton = None
    for f in poses:
        for p in f.people:
            if p.identity == subject:
                t.append(f.t_solve_ns if p.t_pose_ns is None else p.t_pose_ns)  # a predicted pose: its own instant
                th.append(p.theta)
                skeleton = p.skeleton if p.skeleton is not None else skeleton
                fingers.append(rest if p.hands is None else p.hands.rotations)
                hand_skeleton = p.hands.skeleton if p.hands is not None else hand_skeleton
    order = np.argsort(np.array(t), kind="stable")
    hands = np.array(fingers)[order] if hand_skeleton is not None else None
    return SubjectTrack(subject, np.array(t, dtype=np.int64)[order], np.array(th)[order], skeleton, hands,
                        hand_skeleton)  # fmt: skip


def resample(track: SubjectTrack, rate_hz: float = 60.0, origin_ns: int | None = None) -> SubjectTrack:
    """The track on a uniform grid of ``rate_hz`` from its first frame (root: linear; rotations: slerp).

    ``origin_ns``: the grid runs through this instant instead (its first point the first at or after the track's
    first frame), so subjects exported together share one frame grid (FBX keys whole frames).
    """
    t = track.t_ns
    period = round(1e9 / rate_hz)  # the daemon's tick period (integer ns), so a 60 Hz session keeps its times
    start = int(t[0]) if origin_ns is None else origin_ns + -(-(int(t[0]) - origin_ns) // period) * period
    if t.size == 1 or start > t[-1]:
        return track
    # A take whose instants are k / rate rounded one by one (an imported 60 Hz recording: mocapd.core.motion.time_grid)
    # ends up to half a nanosecond per period before the integer period's grid: its last frame is the grid's last
    # point all the same (3006 samples, 3006 rows; a 1 µs shortfall used to drop it).
    slack = (int(t[-1]) - start) // (2 * period) + 1
    grid = start + np.arange((int(t[-1]) - start + slack) // period + 1, dtype=np.int64) * period
    k = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, t.size - 2)
    alpha = np.clip((grid - t[k]) / np.maximum(t[k + 1] - t[k], 1), 0.0, 1.0)
    th = track.thetas
    out = np.empty((grid.size, th.shape[1]))
    out[:, 0:3] = th[k, 0:3] + alpha[:, None] * (th[k + 1, 0:3] - th[k, 0:3])
    q0 = quat_from_rotvec(th[k, 3:].reshape(-1, N_BONES, 3))
    q1 = quat_from_rotvec(th[k + 1, 3:].reshape(-1, N_BONES, 3))
    q = quat_slerp(q0, q1, np.repeat(alpha[:, None], N_BONES, axis=1))
    out[:, 3:] = rotvec_from_quat(q).reshape(grid.size, -1)
    hands = None
    if track.hands is not None:  # the fingers by slerp too
        w = np.repeat(alpha, 2 * N_FINGER_BONES).reshape(grid.size, 2, N_FINGER_BONES)
        hands = quat_slerp(track.hands[k], track.hands[k + 1], w)
    return SubjectTrack(track.subject, grid, out, track.skeleton, hands, track.hand_skeleton)


def write_bvh(path: str | Path, skeleton: Skeleton, track: SubjectTrack, rate_hz: float = 60.0) -> int:
    """Write ``track`` (already on a ``rate_hz`` grid) as BVH; returns the frame count."""
    write_text_atomic(path, bvh_text(skeleton.offsets, track.thetas, rate_hz, hands=track.hands,
                                     hand_skeleton=track.hand_skeleton))  # fmt: skip
    return int(track.thetas.shape[0])


def write_gltf(path: str | Path, tracks: list[tuple[SubjectTrack, Skeleton]], generator: str = "mocapd") -> int:
    """Write resampled tracks, each with its skeleton, as one ``.glb``; returns the number of animations.

    Times are seconds from the earliest first frame of all tracks, so the subjects' animations stay in sync.
    """
    if not tracks:
        raise InputError("no subject to export")
    t0 = min(int(t.t_ns[0]) for t, _ in tracks)
    subjects = [GltfSubject(t.subject, sk.offsets, sk.root_height, (t.t_ns - t0) / 1e9, t.thetas, t.hands,
                            t.hand_skeleton) for t, sk in tracks]  # fmt: skip
    write_bytes_atomic(path, glb_bytes(subjects, generator))
    return len(subjects)


def csv_header() -> list[str]:
    cols = ["frame", "time_s", "t_solve_ns", "subject", "root_x", "root_y", "root_z"]
    cols += [f"{b}_{c}" for b in BONE_NAMES for c in ("qw", "qx", "qy", "qz")]
    cols += [f"{b}_{c}" for b in BONE_NAMES for c in ("x", "y", "z")]
    return [*cols, "source_s"]


def spreadsheet_safe(text: str) -> str:
    """A text cell a spreadsheet shows as text: one starting with ``= + - @``, a tab or a carriage return is
    prefixed with ``'`` (OWASP's advice on CSV injection): a subject named ``=HYPERLINK(...)`` went into the CSV
    verbatim and became a formula where the file was opened (issue 45)."""
    return f"'{text}" if text[:1] in ("=", "+", "-", "@", "\t", "\r") else text


def write_csv(path: str | Path, skeleton: Skeleton, track: SubjectTrack, origin_ns: int | None = None) -> int:
    """Write ``track`` as CSV (columns in the module docstring); returns the row count. ``source_s`` counts from
    ``origin_ns``, the session's start (an imported take: its recording's first sample; default: the first row)."""
    origin = int(track.t_ns[0]) if origin_ns is None else origin_ns
    n = int(track.thetas.shape[0])
    q = quat_from_rotvec(track.thetas[:, 3:].reshape(n, N_BONES, 3)).reshape(n, -1)
    x = Kinematics(skeleton).forward(track.thetas).positions.reshape(n, -1)
    subject = spreadsheet_safe(track.subject)  # the only text cell: numbers are written by mocapd
    with atomic_file(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(csv_header())
        for i in range(n):
            w.writerow(
                [i, f"{(track.t_ns[i] - track.t_ns[0]) / 1e9:.6f}", int(track.t_ns[i]), subject]
                + [f"{v:.6f}" for v in track.thetas[i, 0:3]]
                + [f"{v:.7f}" for v in q[i]]
                + [f"{v:.6f}" for v in x[i]]
                + [f"{(track.t_ns[i] - origin) / 1e9:.6f}"]
            )
    return n

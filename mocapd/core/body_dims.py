"""A person's skeleton from what a user can measure with a tape: a height, and any of a few segment lengths.

Without cameras nothing measures the wearer of a suit, and the default proportions scaled from a height can be
centimetres off per segment (a thigh 4 cm short shortens every stride). So the user may give segment lengths;
every segment not given keeps the default proportions scaled to the height (:meth:`Skeleton.from_height`).

Segments (metres; left and right alike):

========================= ============================================================ ============================
name                      the landmarks, as a tape measures them                       bones set (offset in the
                                                                                       parent)
========================= ============================================================ ============================
hip_width                 left hip joint centre to right hip joint centre              Left/RightUpperLeg (x)
thigh                     hip joint centre to knee joint centre (the knee's joint      Left/RightLowerLeg
                          line, at the side of the knee)
shank                     knee joint centre to ankle joint centre (the tip of the      Left/RightFoot
                          outer ankle bone)
foot                      ankle joint centre to the ball of the foot (the big toe's    Left/RightToes
                          joint), straight
ankle_height              floor to the ankle joint centre, standing                    (root height)
torso                     the midpoint between the two hip joint centres to the base   Spine, Spine1, Spine2,
                          of the neck (the bony bump at the back of the neck's base,   Spine3, Neck (scaled
                          C7), straight                                                together)
shoulder_width            left shoulder joint centre to right shoulder joint centre    Left/RightUpperArm (x)
upper_arm                 shoulder joint centre to elbow joint centre                  Left/RightLowerArm
forearm                   elbow joint centre to wrist joint centre                     Left/RightHand
========================= ============================================================ ============================

Each is the straight distance between two joints of the 21-bone skeleton in the T-pose (left side for the paired
ones). The torso's lower end is the midpoint of the hip joints, which sits below the ``Hips`` joint (the root, the
pelvis' centre, about 5 cm higher): its length is measured from there, as a tape does, not from the root.

The hips joint (the root) stands at ``ankle_height`` plus the legs' vertical offsets (hip, thigh, shank) above the
floor at rest. Pure: no I/O.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mocapd.core.skeleton import BONE_INDEX, REFERENCE_HEIGHT, Skeleton
from mocapd.errors import InputError

DEFAULT_ANKLE_HEIGHT = 0.07
"""Ankle above the floor at rest for a 1.75 m person (m), as :data:`mocapd.core.skeleton.DEFAULT_ROOT_HEIGHT`."""

_PAIRS = {
    "thigh": ("LeftLowerLeg", "RightLowerLeg"),
    "shank": ("LeftFoot", "RightFoot"),
    "foot": ("LeftToes", "RightToes"),
    "upper_arm": ("LeftLowerArm", "RightLowerArm"),
    "forearm": ("LeftHand", "RightHand"),
}
_WIDTHS = {"hip_width": ("LeftUpperLeg", "RightUpperLeg"), "shoulder_width": ("LeftUpperArm", "RightUpperArm")}
_TORSO = ("Spine", "Spine1", "Spine2", "Spine3", "Neck")

SEGMENTS: dict[str, str] = {
    "hip_width": "left hip joint centre to right hip joint centre",
    "thigh": "hip joint centre to knee joint centre (the knee's joint line, at its side)",
    "shank": "knee joint centre to ankle joint centre (the tip of the outer ankle bone)",
    "foot": "ankle joint centre to the ball of the foot (the big toe's joint), straight",
    "ankle_height": "floor to the ankle joint centre, standing",
    "torso": "the midpoint between the two hip joint centres to the base of the neck (the bony bump at the back of "
    "the neck's base, C7), straight",
    "shoulder_width": "left shoulder joint centre to right shoulder joint centre",
    "upper_arm": "shoulder joint centre to elbow joint centre",
    "forearm": "elbow joint centre to wrist joint centre",
}
"""Segment name -> what it measures (the order help texts list them in)."""

LIMITS = (0.02, 1.5)
"""Allowed range of a segment length (m)."""


@dataclass(frozen=True)
class BodySpec:
    """What sizes a person's skeleton: a height and the segment lengths given (the rest scale with the height)."""

    height: float = REFERENCE_HEIGHT
    segments: Mapping[str, float] | None = None
    source: str | None = None
    """Where height and segments came from when not typed in (``"mvnx"``: an MVN export's calibrated body)."""

    def skeleton(self) -> Skeleton:
        return skeleton_from_segments(self.height, self.segments or {})

    def describe(self) -> dict[str, object]:
        """JSON-able record of how the skeleton was made (a session's manifest keeps it)."""
        given = dict(sorted((self.segments or {}).items()))
        return {
            "source": self.source or ("segments" if given else "height"),
            "height_m": self.height,
            "segments_m": given,
            "lengths_m": {k: round(v, 4) for k, v in segment_lengths(self.skeleton()).items()},
        }


def segment_lengths(skeleton: Skeleton) -> dict[str, float]:
    """Every segment of :data:`SEGMENTS` as ``skeleton`` has it (m; left side for the paired ones)."""
    off = skeleton.offsets
    out: dict[str, float] = {}
    for name in SEGMENTS:
        if name in _PAIRS:
            out[name] = float(np.linalg.norm(off[BONE_INDEX[_PAIRS[name][0]]]))
        elif name in _WIDTHS:
            left, right = (off[BONE_INDEX[b], 0] for b in _WIDTHS[name])
            out[name] = float(left - right)
        elif name == "torso":
            out[name] = float(np.linalg.norm(_torso(off) - _hip_centre(off)))
        else:  # ankle_height
            out[name] = float(skeleton.root_height - _leg_drop(off))
    return out


def default_lengths(height: float = REFERENCE_HEIGHT) -> dict[str, float]:
    """The segments of the default proportions at ``height`` (what is used for every segment not given)."""
    return segment_lengths(Skeleton.from_height(height))


def _leg_drop(off: np.ndarray) -> float:
    """How far below the hips joint the ankle is at rest (m, positive), from the left leg's offsets."""
    return -float(sum(off[BONE_INDEX[b], 1] for b in ("LeftUpperLeg", "LeftLowerLeg", "LeftFoot")))


def _torso(off: np.ndarray) -> np.ndarray:
    """The base of the neck (the Neck joint) from the Hips joint, rest pose (m), shape (3,)."""
    return np.asarray(sum(off[BONE_INDEX[b]] for b in _TORSO), dtype=np.float64)


def _hip_centre(off: np.ndarray) -> np.ndarray:
    """The midpoint of the hip joints from the Hips joint, rest pose (m), shape (3,): below it."""
    return np.asarray((off[BONE_INDEX["LeftUpperLeg"]] + off[BONE_INDEX["RightUpperLeg"]]) / 2.0, dtype=np.float64)


def _torso_scale(torso: np.ndarray, hips: np.ndarray, length: float) -> float:
    """The scale ``s`` of the torso's bones with ``|s · torso - hips| = length`` (the larger root; the hip centre
    stays where the legs put it)."""
    a, b, c = float(torso @ torso), float(torso @ hips), float(hips @ hips) - length**2
    return (b + float(np.sqrt(max(b * b - a * c, 0.0)))) / a


def skeleton_from_segments(height: float, segments: Mapping[str, float]) -> Skeleton:
    """The default proportions at ``height`` with the given segments set to their lengths (m).

    Raises
    ------
    InputError
        An unknown segment name, or a length outside :data:`LIMITS`, or a height outside [0.5, 2.6] m.
    """
    base = Skeleton.from_height(height)
    off = base.offsets.copy()
    for name, length in segments.items():
        if name not in SEGMENTS:
            raise InputError(f"unknown body segment {name!r}; segments: {', '.join(SEGMENTS)}")
        if not (np.isfinite(length) and LIMITS[0] <= length <= LIMITS[1]):
            raise InputError(f"body segment {name} = {length!r} m; allowed: {LIMITS[0]:g}..{LIMITS[1]:g} m")
        if name in _PAIRS:
            for bone in _PAIRS[name]:
                i = BONE_INDEX[bone]
                off[i] *= length / float(np.linalg.norm(off[i]))
        elif name in _WIDTHS:
            left, right = (BONE_INDEX[b] for b in _WIDTHS[name])
            off[left, 0], off[right, 0] = 0.5 * length, -0.5 * length
        elif name == "torso":
            off[[BONE_INDEX[b] for b in _TORSO]] *= _torso_scale(_torso(off), _hip_centre(off), length)
    ankle = segments.get("ankle_height", DEFAULT_ANKLE_HEIGHT * height / REFERENCE_HEIGHT)
    return Skeleton(offsets=off, root_height=_leg_drop(off) + float(ankle), height=height)

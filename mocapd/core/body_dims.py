"""A person's skeleton from what a user can measure with a tape: a height, and any of a few segment lengths.

Without cameras nothing measures the wearer of a suit, and the default proportions scaled from a height can be
centimetres off per segment (a thigh 4 cm short shortens every stride). So the user may give segment lengths;
every segment not given keeps the default proportions scaled to the height (:meth:`Skeleton.from_height`).

Segments (metres, each the distance between two joints of the 21-bone skeleton in the T-pose; left and right
alike):

============== ================================================ ===================================
name           what                                             bones set (offset in the parent)
============== ================================================ ===================================
hip_width      between the two hip joints                       Left/RightUpperLeg (x)
thigh          hip joint to knee                                Left/RightLowerLeg
shank          knee to ankle                                    Left/RightFoot
foot           ankle to the ball of the foot (toe joint)        Left/RightToes
ankle_height   ankle above the floor, standing                  (root height)
torso          hip joint centre (pelvis) to the base of the     Spine, Spine1, Spine2, Spine3, Neck
               neck, along the spine                            (scaled together)
shoulder_width between the two shoulder joints                  Left/RightUpperArm (x)
upper_arm      shoulder to elbow                                Left/RightLowerArm
forearm        elbow to wrist                                   Left/RightHand
============== ================================================ ===================================

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
    "hip_width": "between the two hip joints",
    "thigh": "hip joint to knee",
    "shank": "knee to ankle",
    "foot": "ankle to the ball of the foot (toe joint)",
    "ankle_height": "ankle above the floor, standing",
    "torso": "pelvis (hip joint centre) to the base of the neck",
    "shoulder_width": "between the two shoulder joints",
    "upper_arm": "shoulder to elbow",
    "forearm": "elbow to wrist",
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
            out[name] = float(np.linalg.norm(sum(off[BONE_INDEX[b]] for b in _TORSO)))
        else:  # ankle_height
            out[name] = float(skeleton.root_height - _leg_drop(off))
    return out


def default_lengths(height: float = REFERENCE_HEIGHT) -> dict[str, float]:
    """The segments of the default proportions at ``height`` (what is used for every segment not given)."""
    return segment_lengths(Skeleton.from_height(height))


def _leg_drop(off: np.ndarray) -> float:
    """How far below the hips joint the ankle is at rest (m, positive), from the left leg's offsets."""
    return -float(sum(off[BONE_INDEX[b], 1] for b in ("LeftUpperLeg", "LeftLowerLeg", "LeftFoot")))


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
            idx = [BONE_INDEX[b] for b in _TORSO]
            off[idx] *= length / float(np.linalg.norm(off[idx].sum(axis=0)))
    ankle = segments.get("ankle_height", DEFAULT_ANKLE_HEIGHT * height / REFERENCE_HEIGHT)
    return Skeleton(offsets=off, root_height=_leg_drop(off) + float(ankle), height=height)

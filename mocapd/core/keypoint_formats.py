"""Named keypoint sets of 2D pose detectors and their default track targets on the 21-bone skeleton.

A track target is a point rigidly attached to a bone: ``(bone, offset t_pb)``, the offset in metres in the
bone's frame (seed 000 §3.1). Bone frames coincide with the world axes in the rest pose (T-pose facing +Z,
+Y up, right-handed, so +X is the subject's left), with the origin at the bone's proximal joint. A keypoint
at a joint centre therefore sits at the origin of the child bone (elbow → LowerArm), and face keypoints sit
at offsets from the Head bone's origin (the top of the neck).

The offsets below are anthropometric defaults for a 1.75 m adult; :mod:`mocapd.core.offset_calibration`
estimates better ones per detector (seed 003 §3.3.2) and writes them to an offsets file.

Formats: ``coco17`` (Ultralytics YOLO-pose, MMPose, RTMPose), ``body25`` (OpenPose) and ``halpe26``
(AlphaPose, RTMPose-Halpe). Keypoint names are the formats' own, lower-case snake case.
"""

from __future__ import annotations

from dataclasses import dataclass

from mocapd.errors import ConfigError

# DESIGN.md's skeleton, in order. The lead's mocapd.core.skeleton is the authority; this copy only
# validates bone names here without importing a module written in parallel.
BONE_NAMES: tuple[str, ...] = (
    "Hips", "Spine", "Spine1", "Spine2", "Spine3", "Neck", "Head",
    "LeftUpperArm", "LeftLowerArm", "LeftHand", "RightUpperArm", "RightLowerArm", "RightHand",
    "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "LeftToes", "RightUpperLeg", "RightLowerLeg", "RightFoot", "RightToes",
)  # fmt: skip

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class TrackTarget:
    """A point on a bone: the bone's name and the offset (metres, bone frame) from its origin."""

    bone: str
    offset: Vec3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class KeypointFormat:
    """A detector's keypoint list and where each keypoint lives on the skeleton.

    Attributes
    ----------
    name : str
        Format name used in config (``coco17``, ``body25``, ``halpe26``).
    keypoints : tuple of str
        Keypoint names in the detector's output order.
    targets : dict
        Keypoint name → TrackTarget, for every keypoint the solver should use.
    edges : tuple of (int, int)
        Keypoint index pairs to draw as a stick figure.
    """

    name: str
    keypoints: tuple[str, ...]
    targets: dict[str, TrackTarget]
    edges: tuple[tuple[int, int], ...]

    def __post_init__(self) -> None:
        for kp, tt in self.targets.items():
            if kp not in self.keypoints:
                raise ConfigError(f"{self.name}: track target for unknown keypoint {kp!r}")
            if tt.bone not in BONE_NAMES:
                raise ConfigError(f"{self.name}: keypoint {kp!r} on unknown bone {tt.bone!r}")

    @property
    def n_keypoints(self) -> int:
        return len(self.keypoints)

    def index(self, name: str) -> int:
        """Position of keypoint ``name`` in the detector output."""
        try:
            return self.keypoints.index(name)
        except ValueError:
            raise ConfigError(f"{self.name} has no keypoint {name!r}; it has {list(self.keypoints)}") from None

    def with_offsets(self, offsets: dict[str, TrackTarget]) -> KeypointFormat:
        """A copy whose targets are replaced by ``offsets`` where given (e.g. from a calibration file)."""
        merged = dict(self.targets)
        merged.update(offsets)
        return KeypointFormat(self.name, self.keypoints, merged, self.edges)


def _mirror(name: str, tt: TrackTarget) -> tuple[str, TrackTarget]:
    """The right-side twin of a left-side target: name and bone Left→Right, x negated."""
    x, y, z = tt.offset
    return name.replace("left", "right"), TrackTarget(tt.bone.replace("Left", "Right"), (-x, y, z))


def _both_sides(left: dict[str, TrackTarget]) -> dict[str, TrackTarget]:
    out = dict(left)
    for name, tt in left.items():
        rname, rtt = _mirror(name, tt)
        out[rname] = rtt
    return out


# Left-side targets shared by the formats; right sides are mirrored (x → -x).
_LEFT_LIMBS: dict[str, TrackTarget] = {
    "left_shoulder": TrackTarget("LeftUpperArm"),
    "left_elbow": TrackTarget("LeftLowerArm"),
    "left_wrist": TrackTarget("LeftHand"),
    "left_hip": TrackTarget("LeftUpperLeg"),
    "left_knee": TrackTarget("LeftLowerLeg"),
    "left_ankle": TrackTarget("LeftFoot"),
}
_LEFT_FACE: dict[str, TrackTarget] = {
    "left_eye": TrackTarget("Head", (0.032, 0.085, 0.085)),
    "left_ear": TrackTarget("Head", (0.075, 0.06, 0.0)),
}
_LEFT_FOOT: dict[str, TrackTarget] = {
    # Toes bone origin = ball of the foot; big toe tip is forward and medial (-x on the left foot).
    "left_big_toe": TrackTarget("LeftToes", (-0.02, -0.01, 0.05)),
    "left_small_toe": TrackTarget("LeftToes", (0.03, -0.01, 0.02)),
    # Foot bone origin = ankle centre, about 7 cm above the floor; the heel is behind and below it.
    "left_heel": TrackTarget("LeftFoot", (0.0, -0.07, -0.05)),
}
_NOSE = TrackTarget("Head", (0.0, 0.05, 0.10))

_COCO17_NAMES = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip",
    "left_knee", "right_knee", "left_ankle", "right_ankle",
)  # fmt: skip
_COCO17_EDGES = (
    (0, 1), (0, 2), (1, 3), (2, 4), (5, 6), (5, 7), (7, 9), (6, 8), (8, 10), (5, 11), (6, 12),
    (11, 12), (11, 13), (13, 15), (12, 14), (14, 16),
)  # fmt: skip

COCO17 = KeypointFormat(
    name="coco17",
    keypoints=_COCO17_NAMES,
    targets={"nose": _NOSE, **_both_sides(_LEFT_FACE), **_both_sides(_LEFT_LIMBS)},
    edges=_COCO17_EDGES,
)

_BODY25_NAMES = (
    "nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder", "left_elbow",
    "left_wrist", "mid_hip", "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle",
    "right_eye", "left_eye", "right_ear", "left_ear", "left_big_toe", "left_small_toe", "left_heel",
    "right_big_toe", "right_small_toe", "right_heel",
)  # fmt: skip

BODY25 = KeypointFormat(
    name="body25",
    keypoints=_BODY25_NAMES,
    targets={
        "nose": _NOSE,
        "neck": TrackTarget("Neck"),
        "mid_hip": TrackTarget("Hips"),
        **_both_sides(_LEFT_FACE),
        **_both_sides(_LEFT_LIMBS),
        **_both_sides(_LEFT_FOOT),
    },
    edges=(
        (0, 1),
        (1, 2),
        (2, 3),
        (3, 4),
        (1, 5),
        (5, 6),
        (6, 7),
        (1, 8),
        (8, 9),
        (9, 10),
        (10, 11),
        (8, 12),
        (12, 13),
        (13, 14),
        (0, 15),
        (15, 17),
        (0, 16),
        (16, 18),
        (14, 19),
        (19, 20),
        (14, 21),
        (11, 22),
        (22, 23),
        (11, 24),
    ),
)

_HALPE26_NAMES = (
    *_COCO17_NAMES, "head", "neck", "hip", "left_big_toe", "right_big_toe", "left_small_toe",
    "right_small_toe", "left_heel", "right_heel",
)  # fmt: skip

HALPE26 = KeypointFormat(
    name="halpe26",
    keypoints=_HALPE26_NAMES,
    targets={
        **COCO17.targets,
        "head": TrackTarget("Head", (0.0, 0.20, 0.02)),
        "neck": TrackTarget("Neck"),
        "hip": TrackTarget("Hips"),
        **_both_sides(_LEFT_FOOT),
    },
    edges=(
        *_COCO17_EDGES,
        (17, 18),
        (18, 19),
        (19, 11),
        (19, 12),
        (15, 20),
        (15, 22),
        (15, 24),
        (16, 21),
        (16, 23),
        (16, 25),
    ),
)

FORMATS: dict[str, KeypointFormat] = {f.name: f for f in (COCO17, BODY25, HALPE26)}


def keypoint_format(name: str) -> KeypointFormat:
    """The format called ``name`` (``coco17``, ``body25``, ``halpe26``)."""
    try:
        return FORMATS[name]
    except KeyError:
        raise ConfigError(f"unknown keypoint format {name!r}; known: {sorted(FORMATS)}") from None

"""Keypoint sets of 2D detectors and their track targets ``(bone, offset t_pb)`` (seed 003 §3.1, §3.3.2).

A 2D detector outputs a named keypoint set; each keypoint is tied to a skeleton bone and an offset in that
bone's frame. Joint keypoints sit on a bone's joint (zero offset by default); surface keypoints (nose, eyes,
ears) have non-zero offsets. Calibrated offsets (seed 003 §3.3.2) replace the defaults.

Bone frames coincide with the world axes in the rest pose (T-pose facing +Z, +Y up, right-handed, so +X is
the subject's left), with the origin at the bone's proximal joint: a keypoint at a joint centre sits at the
origin of the child bone (elbow → LowerArm), and face keypoints at offsets from the Head bone's origin (the
top of the neck). Default offsets are anthropometric for a 1.75 m adult.

Two views of the same data live here:

* :class:`KeypointFormat` (``coco17``, ``body25``, ``halpe26``, ``blazepose33``): a detector's keypoint names in
  output order, a :class:`TrackTarget` per keypoint and the stick-figure edges; chosen by name in config, written to
  and read from offsets files (:mod:`mocapd.core.offset_calibration`);
* :class:`TrackTargets`: the solver's arrays (bone indices, offsets), from
  :meth:`KeypointFormat.track_targets` or :func:`coco17_targets`.

``COCO17`` (name, bone, offset) is the one table of COCO-17 defaults; the formats take their COCO-17
keypoints from it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.skeleton import BONE_INDEX, N_BONES, REFERENCE_HEIGHT, Skeleton
from mocapd.errors import ConfigError, InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class TrackTargets:
    """A set of positional track targets.

    Attributes
    ----------
    names : tuple of str, length n
    bones : int array, shape (n,)
        Bone index of each target.
    offsets : array, shape (n, 3)
        Offset of each target in its bone's frame (metres).
    """

    names: tuple[str, ...]
    bones: IntArray
    offsets: FloatArray

    def __post_init__(self) -> None:
        bones = np.asarray(self.bones, dtype=np.intp)
        offsets = np.asarray(self.offsets, dtype=np.float64)
        n = len(self.names)
        if bones.shape != (n,) or offsets.shape != (n, 3):
            raise InputError(
                f"track targets: {n} names need bones ({n},) and offsets ({n}, 3); "
                f"got {bones.shape} and {offsets.shape}"
            )
        if not np.all(np.isfinite(offsets)):
            raise InputError("track target offsets contain non-finite values")
        outside = bones[(bones < 0) | (bones >= N_BONES)]
        if outside.size:
            raise InputError(f"track target bones must be bone indices in [0, {N_BONES}), got {outside[0]}")
        object.__setattr__(self, "bones", bones)
        object.__setattr__(self, "offsets", offsets)

    def __len__(self) -> int:
        return len(self.names)

    def with_offsets(self, offsets: FloatArray) -> TrackTargets:
        """The same targets with new (e.g. calibrated) offsets, shape (n, 3)."""
        return TrackTargets(self.names, self.bones, np.asarray(offsets, dtype=np.float64))


# COCO-17 keypoint order with the bone each keypoint lives on and its default offset (1.75 m person).
COCO17: tuple[tuple[str, str, tuple[float, float, float]], ...] = (
    ("nose", "Head", (0.0, 0.06, 0.10)),
    ("left_eye", "Head", (0.035, 0.09, 0.08)),
    ("right_eye", "Head", (-0.035, 0.09, 0.08)),
    ("left_ear", "Head", (0.075, 0.07, 0.0)),
    ("right_ear", "Head", (-0.075, 0.07, 0.0)),
    ("left_shoulder", "LeftUpperArm", (0.0, 0.0, 0.0)),
    ("right_shoulder", "RightUpperArm", (0.0, 0.0, 0.0)),
    ("left_elbow", "LeftLowerArm", (0.0, 0.0, 0.0)),
    ("right_elbow", "RightLowerArm", (0.0, 0.0, 0.0)),
    ("left_wrist", "LeftHand", (0.0, 0.0, 0.0)),
    ("right_wrist", "RightHand", (0.0, 0.0, 0.0)),
    ("left_hip", "LeftUpperLeg", (0.0, 0.0, 0.0)),
    ("right_hip", "RightUpperLeg", (0.0, 0.0, 0.0)),
    ("left_knee", "LeftLowerLeg", (0.0, 0.0, 0.0)),
    ("right_knee", "RightLowerLeg", (0.0, 0.0, 0.0)),
    ("left_ankle", "LeftFoot", (0.0, 0.0, 0.0)),
    ("right_ankle", "RightFoot", (0.0, 0.0, 0.0)),
)


def coco17_targets(skeleton: Skeleton | None = None) -> TrackTargets:
    """COCO-17 track targets with default offsets scaled to the skeleton's height."""
    s = (skeleton.height if skeleton is not None else REFERENCE_HEIGHT) / REFERENCE_HEIGHT
    return TrackTargets(
        names=tuple(n for n, _, _ in COCO17),
        bones=np.array([BONE_INDEX[b] for _, b, _ in COCO17], dtype=np.intp),
        offsets=np.array([o for _, _, o in COCO17]) * s,
    )


FLOOR_TARGET_BONES: tuple[str, ...] = ("LeftFoot", "LeftToes", "RightFoot", "RightToes")
"""Joints the floor-penetration term applies to (seed 003 §3.2.5: feet and toes)."""


def floor_targets() -> TrackTargets:
    """The floor term's targets: the joints of both feet and toes (zero offsets)."""
    return TrackTargets(
        names=FLOOR_TARGET_BONES,
        bones=np.array([BONE_INDEX[b] for b in FLOOR_TARGET_BONES], dtype=np.intp),
        offsets=np.zeros((len(FLOOR_TARGET_BONES), 3)),
    )


# ------------------------------------------------------------------------------------ detector formats

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
    targets: Mapping[str, TrackTarget]
    edges: tuple[tuple[int, int], ...]

    def __post_init__(self) -> None:
        for kp, tt in self.targets.items():
            if kp not in self.keypoints:
                raise ConfigError(f"{self.name}: track target for unknown keypoint {kp!r}")
            if tt.bone not in BONE_INDEX:
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

    def with_offsets(self, offsets: Mapping[str, TrackTarget]) -> KeypointFormat:
        """A copy whose targets are replaced by ``offsets`` where given (e.g. from a calibration file)."""
        merged = dict(self.targets)
        merged.update(offsets)
        return KeypointFormat(self.name, self.keypoints, merged, self.edges)

    def track_targets(self, skeleton: Skeleton | None = None) -> TrackTargets:
        """The solver's arrays for the keypoints that have a target, in output order; offsets scaled to the
        skeleton's height (as :func:`coco17_targets`)."""
        s = (skeleton.height if skeleton is not None else REFERENCE_HEIGHT) / REFERENCE_HEIGHT
        names = tuple(k for k in self.keypoints if k in self.targets)
        return TrackTargets(
            names=names,
            bones=np.array([BONE_INDEX[self.targets[k].bone] for k in names], dtype=np.intp),
            offsets=np.array([self.targets[k].offset for k in names], dtype=np.float64).reshape(-1, 3) * s,
        )


def _both_sides(left: dict[str, TrackTarget]) -> dict[str, TrackTarget]:
    """Left-side targets and their right-side twins (name and bone Left→Right, x negated)."""
    out = dict(left)
    for name, tt in left.items():
        x, y, z = tt.offset
        out[name.replace("left", "right")] = TrackTarget(tt.bone.replace("Left", "Right"), (-x, y, z))
    return out


_COCO17_TARGETS: dict[str, TrackTarget] = {name: TrackTarget(bone, off) for name, bone, off in COCO17}
_LEFT_FOOT: dict[str, TrackTarget] = {
    # Toes bone origin = ball of the foot; big toe tip is forward and medial (-x on the left foot).
    "left_big_toe": TrackTarget("LeftToes", (-0.02, -0.01, 0.05)),
    "left_small_toe": TrackTarget("LeftToes", (0.03, -0.01, 0.02)),
    # Foot bone origin = ankle centre, about 7 cm above the floor; the heel is behind and below it.
    "left_heel": TrackTarget("LeftFoot", (0.0, -0.07, -0.05)),
}
_COCO17_EDGES = (
    (0, 1), (0, 2), (1, 3), (2, 4), (5, 6), (5, 7), (7, 9), (6, 8), (8, 10), (5, 11), (6, 12),
    (11, 12), (11, 13), (13, 15), (12, 14), (14, 16),
)  # fmt: skip

COCO17_FORMAT = KeypointFormat(
    name="coco17",
    keypoints=tuple(_COCO17_TARGETS),
    targets=_COCO17_TARGETS,
    edges=_COCO17_EDGES,
)
"""COCO-17 (Ultralytics YOLO-pose, MMPose, RTMPose)."""

BODY25_FORMAT = KeypointFormat(
    name="body25",
    keypoints=(
        "nose",
        "neck",
        "right_shoulder",
        "right_elbow",
        "right_wrist",
        "left_shoulder",
        "left_elbow",
        "left_wrist",
        "mid_hip",
        "right_hip",
        "right_knee",
        "right_ankle",
        "left_hip",
        "left_knee",
        "left_ankle",
        "right_eye",
        "left_eye",
        "right_ear",
        "left_ear",
        "left_big_toe",
        "left_small_toe",
        "left_heel",
        "right_big_toe",
        "right_small_toe",
        "right_heel",
    ),
    targets={
        **_COCO17_TARGETS,
        "neck": TrackTarget("Neck"),
        "mid_hip": TrackTarget("Hips"),
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
"""OpenPose BODY_25."""

HALPE26_FORMAT = KeypointFormat(
    name="halpe26",
    keypoints=(
        *_COCO17_TARGETS,
        "head",
        "neck",
        "hip",
        "left_big_toe",
        "right_big_toe",
        "left_small_toe",
        "right_small_toe",
        "left_heel",
        "right_heel",
    ),
    targets={
        **_COCO17_TARGETS,
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
"""AlphaPose / RTMPose Halpe-26."""

_LEFT_BLAZEPOSE: dict[str, TrackTarget] = {
    # Face points beside COCO-17's eyes and ears (Head bone, origin at the top of the neck).
    "left_eye_inner": TrackTarget("Head", (0.02, 0.09, 0.085)),
    "left_eye_outer": TrackTarget("Head", (0.05, 0.09, 0.075)),
    "left_mouth": TrackTarget("Head", (0.025, 0.01, 0.095)),
    # Hand bone origin = wrist, the hand along +x (T-pose, palm down, thumb forward +z). BlazePose's pinky and index
    # points are their first knuckles, the thumb point its second joint.
    "left_pinky": TrackTarget("LeftHand", (0.08, 0.0, -0.03)),
    "left_index": TrackTarget("LeftHand", (0.09, 0.0, 0.025)),
    "left_thumb": TrackTarget("LeftHand", (0.05, -0.01, 0.05)),
    "left_heel": _LEFT_FOOT["left_heel"],
    # The tip of the second toe: forward of the Toes bone's origin (ball of the foot), near the floor.
    "left_foot_index": TrackTarget("LeftToes", (-0.01, -0.02, 0.05)),
}

_BLAZEPOSE33_EDGES = (
    (0, 1), (1, 2), (2, 3), (3, 7), (0, 4), (4, 5), (5, 6), (6, 8), (9, 10),
    (11, 12), (11, 13), (13, 15), (15, 17), (15, 19), (15, 21), (17, 19),
    (12, 14), (14, 16), (16, 18), (16, 20), (16, 22), (18, 20),
    (11, 23), (12, 24), (23, 24), (23, 25), (24, 26), (25, 27), (26, 28),
    (27, 29), (28, 30), (29, 31), (30, 32), (27, 31), (28, 32),
)  # fmt: skip
BLAZEPOSE33_FORMAT = KeypointFormat(
    name="blazepose33",
    # MediaPipe's landmark order; its "mouth_left"/"mouth_right" are named left_mouth/right_mouth here so that every
    # left/right pair reads left_*/right_* (mocapd.core.lr_flips.lr_pairs).
    keypoints=(
        "nose",
        "left_eye_inner",
        "left_eye",
        "left_eye_outer",
        "right_eye_inner",
        "right_eye",
        "right_eye_outer",
        "left_ear",
        "right_ear",
        "left_mouth",
        "right_mouth",
        "left_shoulder",
        "right_shoulder",
        "left_elbow",
        "right_elbow",
        "left_wrist",
        "right_wrist",
        "left_pinky",
        "right_pinky",
        "left_index",
        "right_index",
        "left_thumb",
        "right_thumb",
        "left_hip",
        "right_hip",
        "left_knee",
        "right_knee",
        "left_ankle",
        "right_ankle",
        "left_heel",
        "right_heel",
        "left_foot_index",
        "right_foot_index",
    ),
    targets={**_COCO17_TARGETS, **_both_sides(_LEFT_BLAZEPOSE)},
    edges=_BLAZEPOSE33_EDGES,
)
"""MediaPipe BlazePose (GHUM 3D) 33 landmarks: COCO-17's points plus heels, foot index, pinky, index, thumb and
more face points."""

FORMATS: Mapping[str, KeypointFormat] = {
    f.name: f for f in (COCO17_FORMAT, BODY25_FORMAT, HALPE26_FORMAT, BLAZEPOSE33_FORMAT)
}

# ------------------------------------------------------------------------------------------------ hands

HAND21: tuple[str, ...] = (
    "wrist",
    "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
    "index_finger_mcp", "index_finger_pip", "index_finger_dip", "index_finger_tip",
    "middle_finger_mcp", "middle_finger_pip", "middle_finger_dip", "middle_finger_tip",
    "ring_finger_mcp", "ring_finger_pip", "ring_finger_dip", "ring_finger_tip",
    "pinky_mcp", "pinky_pip", "pinky_dip", "pinky_tip",
)  # fmt: skip
"""The hand landmark model's 21 points of one hand, in its output order, named as MediaPipe's ``HandLandmark``
(lower case): the wrist, then per finger from the palm out (thumb: carpometacarpal, metacarpophalangeal,
interphalangeal joints and tip; the others: MCP, PIP, DIP joints and tip)."""

FINGERS: Mapping[str, tuple[str, ...]] = {
    finger: tuple(n for n in HAND21 if n.startswith(finger)) for finger in ("thumb", "index", "middle", "ring", "pinky")
}
"""Each finger's four points of :data:`HAND21`, from the palm out."""

HAND21_EDGES: tuple[tuple[int, int], ...] = (
    (0, 1), (1, 2), (2, 3), (3, 4), (0, 5), (5, 6), (6, 7), (7, 8), (5, 9), (9, 10), (10, 11), (11, 12),
    (9, 13), (13, 14), (14, 15), (15, 16), (13, 17), (0, 17), (17, 18), (18, 19), (19, 20),
)  # fmt: skip
"""MediaPipe's ``HAND_CONNECTIONS`` (the palm and each finger's chain) as index pairs of :data:`HAND21`."""

HAND_SIDES = ("left", "right")


def hand_keypoint_names(side: str) -> tuple[str, ...]:
    """The 21 keypoint names of the ``side`` ("left" or "right") hand of a person: ``left_hand_wrist``,
    ``left_hand_thumb_cmc``, ... ``left_hand_pinky_tip``. The side is the *body's* (the hand at the end of the
    person's left arm), never the hand model's own handedness guess."""
    if side not in HAND_SIDES:
        raise ConfigError(f"hand side must be one of {list(HAND_SIDES)}, got {side!r}")
    return tuple(f"{side}_hand_{n}" for n in HAND21)


HANDS42: tuple[str, ...] = (*hand_keypoint_names("left"), *hand_keypoint_names("right"))
"""A person's two hands: the left hand's 21 points (:func:`hand_keypoint_names`), then the right hand's."""

_LEFT_HAND_TARGETS: dict[str, TrackTarget] = {}
"""Track targets of the left hand's points (the right hand's are their twins). None yet: the finger bones (issue 44)
give them; until then the hand points ride along with the body's keypoints and the solver skips them."""


def with_hands(body: KeypointFormat) -> KeypointFormat:
    """``body``'s keypoints followed by :data:`HANDS42` (the format ``<body>_hands``): what the detector delivers
    with ``[detector] hands`` on. The body's columns, targets and edges are unchanged, so a consumer that takes the
    body's columns sees exactly what it sees with hands off."""
    n = body.n_keypoints
    hand_edges = tuple((n + side * 21 + a, n + side * 21 + b) for side in (0, 1) for a, b in HAND21_EDGES)
    # Each hand model's wrist drawn to the body's wrist of the same side.
    wrists = tuple(
        (body.index(f"{s}_wrist"), n + i * 21) for i, s in enumerate(HAND_SIDES) if f"{s}_wrist" in body.keypoints
    )
    return KeypointFormat(
        name=f"{body.name}_hands",
        keypoints=(*body.keypoints, *HANDS42),
        targets={**body.targets, **_both_sides(_LEFT_HAND_TARGETS)},
        edges=(*body.edges, *hand_edges, *wrists),
    )


COCO17_HANDS_FORMAT = with_hands(COCO17_FORMAT)
"""COCO-17 (YOLO's keypoints; hand crops from the forearm) and both hands: 17 + 42 keypoints."""
BLAZEPOSE33_HANDS_FORMAT = with_hands(BLAZEPOSE33_FORMAT)
"""BlazePose's 33 landmarks (hand crops from wrist, pinky and index) and both hands: 33 + 42 keypoints."""

HAND_FORMATS: Mapping[str, KeypointFormat] = {f.name: f for f in (COCO17_HANDS_FORMAT, BLAZEPOSE33_HANDS_FORMAT)}
"""The formats ``[detector] hands`` delivers, by name (never a detector model's own format: not in
:data:`FORMATS`)."""


def keypoint_format(name: str) -> KeypointFormat:
    """The format called ``name`` (``coco17``, ``body25``, ``halpe26``, ``blazepose33``, ``coco17_hands``,
    ``blazepose33_hands``)."""
    try:
        return FORMATS[name] if name in FORMATS else HAND_FORMATS[name]
    except KeyError:
        raise ConfigError(f"unknown keypoint format {name!r}; known: {sorted([*FORMATS, *HAND_FORMATS])}") from None

"""MVN real-time network streaming, pose datagrams of type 02 ("MXTP02": segment positions + quaternions).

This is what Xsens MVN Analyze/Animate's Network Streamer sends, and what its consumers read: the Xsens MVN live
plugins for Unity and Unreal, MotionBuilder, Warudo's "Xsens MVN" input, and many home-made receivers. Source
followed: Xsens document MV0305P "MVN real-time network streaming Protocol Specification", revision N (September
2018), sections 2.4 (header), 2.5.3 (type 02), 2.5.8/2.5.11 (quaternions, byte order) and 3.1 (segment table).

Datagram (all multi-byte fields big-endian, "network byte order")::

    offset size type      field
    0      6    ASCII     ID string "MXTP02" (not NUL-terminated; "MXTP" + message type "02")
    6      4    uint32    sample counter: one per sent sample (we send the output frame number, so gaps mean
                          frames that were not sent; the spec allows skipping)
    10     1    uint8     datagram counter: bits 0-6 = index of this datagram within the sample (0, 1, ...),
                          bit 7 set on the last datagram of the sample (a sample in one datagram: 0x80)
    11     1    uint8     number of items (segments) in THIS datagram
    12     4    uint32    time code: milliseconds since the stream started (the first frame sent), mod 2**32, of
                          the instant this character's pose is for (later than the frame's solve time for a
                          predicted pose: mocapd's ``[daemon] output = "predicted"``)
    16     1    uint8     character id (0 for the first character; see the subject mapping below)
    17     1    uint8     number of body segments of the character: 23
    18     1    uint8     number of props: 0
    19     1    uint8     number of finger-tracking segments: 0, or 40 for a character with fingers (below)
    20     2    -         reserved, zero
    22     2    uint16    payload size: bytes after the 24-byte header in THIS datagram (= 32 × items)
    24     32×n          items, per segment:
                 +0  int32    segment id (1 .. 23: the spec's 0-based segment index + 1)
                 +4  float32  x  ┐ position of the segment origin, metres, MVN global frame:
                 +8  float32  y  │ right-handed, +Z up, +X forward, +Y left
                 +12 float32  z  ┘ (mocapd.protocols.conventions.MVN)
                 +16 float32  q0 (w) ┐ segment orientation (segment frame → global), unit quaternion
                 +20 float32  q1 (x) │ in the same frame; identity = the segment in the T-pose, as in the
                 +24 float32  q2 (y) │ spec's scale information (type 13: "perfect/ideal T-pose, where all
                 +28 float32  q3 (z) ┘ segment orientations are set to identity")

Units: section 2.5.6 of revision N says "cm", but the MVN user manual ("position units are in meters"), MVNX
files and the receivers we checked read metres; we send metres.

Splitting: a full character is 24 + 23 × 32 = 760 bytes, one datagram (with fingers 24 + 63 × 32 = 2040: two at
the default limit). When ``max_datagram_bytes`` is smaller, the
items of one character are split over datagrams with counters 0, 1, ..., 0x80 | last; every datagram repeats the
header (same sample counter, time code and character id; its own item count and payload size). Each character is
sent as its own datagram set (spec 2.4.1.6: "each character will send its own full packet").

Segments, in order (id: MVN segment ← mocapd bone, DESIGN.md's 21-bone skeleton)::

     1 Pelvis ← Hips          9 RightUpperArm ← RightUpperArm   16 RightUpperLeg ← RightUpperLeg
     2 L5     ← Spine        10 RightForeArm  ← RightLowerArm   17 RightLowerLeg ← RightLowerLeg
     3 L3     ← Spine1       11 RightHand     ← RightHand       18 RightFoot     ← RightFoot
     4 T12    ← Spine2       12 LeftShoulder  ← (rule below)    19 RightToe      ← RightToes
     5 T8     ← Spine3       13 LeftUpperArm  ← LeftUpperArm    20 LeftUpperLeg  ← LeftUpperLeg
     6 Neck   ← Neck         14 LeftForeArm   ← LeftLowerArm    21 LeftLowerLeg  ← LeftLowerLeg
     7 Head   ← Head         15 LeftHand      ← LeftHand        22 LeftFoot      ← LeftFoot
     8 RightShoulder ← (rule below)                             23 LeftToe       ← LeftToes

A segment's position is its joint (the bone's origin) and its orientation is the bone's global rotation, both
from forward kinematics of θ, converted with :data:`mocapd.protocols.conventions.MVN`. Shoulder rule: mocapd has
no clavicles (the upper arms hang from Spine3), so each shoulder segment is rigid with the chest: orientation =
Spine3's, origin = the point of Spine3's frame on the mid-line at the height and depth of that side's upper-arm
joint, i.e. ``x_Spine3 + Q_Spine3 · (0, o_y, o_z)`` with ``o`` the upper arm's rest offset. The segment then spans
from the sternum to the shoulder joint, as MVN's does, and never moves relative to the chest.

Fingers (issue 44; spec revision N, sections 2.4.1.9, 2.5.1 and 3.1 table 2): a character whose subject has fingers
(:class:`mocapd.core.hand_skeleton.HandPose`) sends 40 finger-tracking segments after its 23 body segments (no
props), left hand then right, header byte 19 = 40. Per hand, in the spec's order, with ids 24 .. 43 (left) and
44 .. 63 (right) (index + 1; the left carpus's index is 23 + props, the right's 43 + props)::

    Carpus ← Hand (the body's hand bone: its rotation, at the wrist)
    FirstMC, FirstPP, FirstDP ← ThumbProximal, ThumbIntermediate, ThumbDistal (mocapd's thumb starts at its CMC)
    SecondMC, ThirdMC, FourthMC, FifthMC ← Hand: mocapd has no metacarpal bones of the four fingers; rigid with the
        hand, at the point :data:`CMC_FRACTION` of the way from the wrist to that finger's knuckle (the CMC joints)
    Second/Third/Fourth/Fifth PP, MP, DP ← Index/Middle/Ring/Little Proximal, Intermediate, Distal

each at its joint with its global rotation (identity at rest: the flat hand, as the body's T-pose). A hand that was
not solved this frame is sent with its rest pose (straight fingers, rigid with the hand), since the count is per
character. A character without fingers is sent exactly as above, with 0.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.hand_skeleton import HandPose
from mocapd.core.kinematics import Kinematics
from mocapd.core.per_skeleton import PerSkeleton
from mocapd.core.rotations import quat_from_matrix
from mocapd.core.skeleton import BONE_INDEX, POSE_DIM, Skeleton
from mocapd.errors import InputError
from mocapd.protocols.conventions import MVN
from mocapd.protocols.fingers import HAND_OF_SIDE, finger_kinematics

FloatArray = NDArray[np.float64]

ID_STRING = b"MXTP02"
HEADER = struct.Struct(">6sIBBIBBBB2xH")
"""The 24-byte datagram header (see the module docstring)."""
HEADER_SIZE = HEADER.size
ITEM_SIZE = 32
ITEM_DTYPE = np.dtype([("id", ">i4"), ("position", ">f4", (3,)), ("quaternion", ">f4", (4,))])
"""One segment item: int32 id, float32 x, y, z, float32 q0..q3 (w, x, y, z), big-endian."""
LAST_DATAGRAM = 0x80
MAX_DATAGRAMS = 0x80  # the datagram index has 7 bits
DEFAULT_PORT = 9763
DEFAULT_MAX_DATAGRAM = 1472  # a 1500-byte Ethernet MTU minus the IPv4 (20) and UDP (8) headers

SEGMENTS: tuple[str, ...] = (
    "Pelvis", "L5", "L3", "T12", "T8", "Neck", "Head",
    "RightShoulder", "RightUpperArm", "RightForeArm", "RightHand",
    "LeftShoulder", "LeftUpperArm", "LeftForeArm", "LeftHand",
    "RightUpperLeg", "RightLowerLeg", "RightFoot", "RightToe",
    "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "LeftToe",
)  # fmt: skip
"""MVN body segments in spec order; the segment id is the index + 1."""
N_SEGMENTS = len(SEGMENTS)
SEGMENT_IDS = np.arange(1, N_SEGMENTS + 1, dtype=np.int32)

SEGMENT_BONES: tuple[str, ...] = (
    "Hips", "Spine", "Spine1", "Spine2", "Spine3", "Neck", "Head",
    "Spine3", "RightUpperArm", "RightLowerArm", "RightHand",
    "Spine3", "LeftUpperArm", "LeftLowerArm", "LeftHand",
    "RightUpperLeg", "RightLowerLeg", "RightFoot", "RightToes",
    "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "LeftToes",
)  # fmt: skip
"""The mocapd bone whose global rotation (and, except for the shoulders, joint) each segment takes."""
_SOURCE = np.array([BONE_INDEX[b] for b in SEGMENT_BONES], dtype=np.intp)

FINGER_SEGMENTS: tuple[str, ...] = (
    "Carpus", "FirstMC", "FirstPP", "FirstDP",
    *(f"{n}{s}" for n in ("Second", "Third", "Fourth", "Fifth") for s in ("MC", "PP", "MP", "DP")),
)  # fmt: skip
"""The 20 finger-tracking segments of one hand in spec order (prefixed ``Left``/``Right`` in MVN's names)."""
N_FINGER_SEGMENTS = 2 * len(FINGER_SEGMENTS)  # 40: both hands, the only count besides 0
FINGER_SEGMENT_IDS = np.arange(N_SEGMENTS + 1, N_SEGMENTS + N_FINGER_SEGMENTS + 1, dtype=np.int32)
CMC_FRACTION = 0.3
"""Where the four fingers' metacarpal segments start, as a fraction of the wrist-to-knuckle offset (the CMC joints
lie about a third of the way along the palm)."""
# Per segment of a hand: the finger bone (0..14) giving its pose, or -1 for the hand's own rotation; and for the
# -1 ones the finger whose proximal offset places it (-1: at the wrist).
_FINGER_SOURCE = (-1, 0, 1, 2, *(b for f in range(1, 5) for b in (-1, 3 * f, 3 * f + 1, 3 * f + 2)))
_MC_OF = (-1, -1, -1, -1, *(k for f in range(1, 5) for k in (3 * f, -1, -1, -1)))
_SHOULDERS = ((SEGMENTS.index("RightShoulder"), "RightUpperArm"), (SEGMENTS.index("LeftShoulder"), "LeftUpperArm"))


@dataclass(frozen=True)
class MvnHeader:
    """The decoded fields of a datagram header (used by :func:`parse_header` and in tests)."""

    sample_counter: int
    datagram_index: int
    last: bool
    items: int
    time_code_ms: int
    character_id: int
    body_segments: int
    props: int
    finger_segments: int
    payload_size: int


def parse_header(data: bytes) -> MvnHeader:
    """Decode the 24-byte header of an ``MXTP02`` datagram (``InputError`` on a short or foreign datagram)."""
    if len(data) < HEADER_SIZE:
        raise InputError(f"MVN datagram shorter than its {HEADER_SIZE}-byte header: {len(data)} bytes")
    ident, sample, counter, items, tc, char, body, props, fingers, payload = HEADER.unpack_from(data)
    if ident != ID_STRING:
        raise InputError(f"not an MXTP02 datagram: ID string {ident!r}")
    return MvnHeader(sample, counter & 0x7F, bool(counter & LAST_DATAGRAM), items, tc, char, body, props, fingers,
                     payload)  # fmt: skip


class MvnSegments:
    """Global segment positions and orientations (MVN frame) from pose vectors of one sized skeleton."""

    def __init__(self, skeleton: Skeleton) -> None:
        self.kinematics = Kinematics(skeleton)
        spine3 = BONE_INDEX["Spine3"]
        self._spine3 = spine3
        offsets = skeleton.offsets
        self._clavicles = [(seg, np.array([0.0, offsets[BONE_INDEX[arm], 1], offsets[BONE_INDEX[arm], 2]]))
                           for seg, arm in _SHOULDERS]  # fmt: skip

    def compute(self, thetas: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Segment poses for a batch of subjects.

        Parameters
        ----------
        thetas : array, shape (n, 66)
            Pose vectors (mocapd world, metres).

        Returns
        -------
        positions : array, shape (n, 23, 3)
            Segment origins in the MVN frame (metres).
        quaternions : array, shape (n, 23, 4)
            Segment orientations (w, x, y, z) in the MVN frame.
        """
        thetas = np.asarray(thetas, dtype=np.float64)
        if thetas.ndim != 2 or thetas.shape[1] != POSE_DIM:
            raise InputError(f"thetas must have shape (n, {POSE_DIM}), got {thetas.shape}")
        fk = self.kinematics.forward(thetas)
        rot = fk.rotations[:, _SOURCE]
        pos = fk.positions[:, _SOURCE].copy()
        q3 = fk.rotations[:, self._spine3]
        x3 = fk.positions[:, self._spine3]
        for seg, c in self._clavicles:
            pos[:, seg] = x3 + q3 @ c
        return MVN.positions(pos), MVN.quaternions(quat_from_matrix(rot))

    def compute_fingers(self, theta: FloatArray, hands: HandPose) -> tuple[FloatArray, FloatArray]:
        """The 40 finger-tracking segments of one subject: positions (40, 3) and quaternions (40, 4), MVN frame."""
        fk = self.kinematics.forward(np.asarray(theta, dtype=np.float64).reshape(1, POSE_DIM))
        side = list(HAND_OF_SIDE)
        G_hand, x_hand = fk.rotations[:, side], fk.positions[:, side]  # (1, 2, 3, 3), (1, 2, 3)
        fs = finger_kinematics(G_hand, x_hand, hands.rotations[None], [hands.skeleton])
        rot = np.empty((2, len(FINGER_SEGMENTS), 3, 3))
        pos = np.empty((2, len(FINGER_SEGMENTS), 3))
        for h in range(2):
            for k, (bone, mc) in enumerate(zip(_FINGER_SOURCE, _MC_OF, strict=True)):
                if bone >= 0:
                    rot[h, k], pos[h, k] = fs.rotations[0, h, bone], fs.positions[0, h, bone]
                else:
                    local = CMC_FRACTION * hands.skeleton.offsets[h, mc] if mc >= 0 else np.zeros(3)
                    rot[h, k], pos[h, k] = G_hand[0, h], x_hand[0, h] + G_hand[0, h] @ local
        return MVN.positions(pos.reshape(-1, 3)), MVN.quaternions(quat_from_matrix(rot.reshape(-1, 3, 3)))


class MvnEncoder:
    """Encodes output frames into ``MXTP02`` datagrams (pure: values in, bytes out).

    Parameters
    ----------
    skeleton : Skeleton
        The sized skeleton the pose vectors refer to.
    max_datagram_bytes : int
        Largest datagram to produce (header included); a character that does not fit is split.
    """

    def __init__(self, skeleton: Skeleton, *, max_datagram_bytes: int = DEFAULT_MAX_DATAGRAM) -> None:
        per = (max_datagram_bytes - HEADER_SIZE) // ITEM_SIZE
        if per < 1:
            raise InputError(f"max_datagram_bytes = {max_datagram_bytes} cannot hold the header and one segment "
                             f"({HEADER_SIZE + ITEM_SIZE} bytes)")  # fmt: skip
        if -(-N_SEGMENTS // per) > MAX_DATAGRAMS:
            raise InputError(f"max_datagram_bytes = {max_datagram_bytes} would need more than {MAX_DATAGRAMS} "
                             "datagrams per character")  # fmt: skip
        self.segments = MvnSegments(skeleton)
        self._sized = PerSkeleton(self.segments, MvnSegments)  # per-person skeletons (body sizing)
        self.items_per_datagram = per
        self._t0_ns: int | None = None

    def time_code_ms(self, t_ns: int) -> int:
        """Milliseconds since the first frame encoded (the stream's start), modulo 2**32."""
        if self._t0_ns is None:
            self._t0_ns = t_ns
        return ((t_ns - self._t0_ns) // 1_000_000) & 0xFFFFFFFF

    def encode(
        self,
        sample_counter: int,
        t_ns: int,
        characters: Sequence[tuple[int, FloatArray]],
        skeletons: Sequence[Skeleton | None] | None = None,
        times_ns: Sequence[int] | None = None,
        hands: Sequence[HandPose | None] | None = None,
    ) -> list[bytes]:
        """Datagrams for one output frame.

        Parameters
        ----------
        sample_counter : int
            Sent as is, modulo 2**32 (mocapd sends its output frame number).
        t_ns : int
            Solve time of the frame (host monotonic ns); the time code counts from the first call.
        characters : sequence of (character id, θ (66,))
            The subjects to send, each with its character id (0 .. 255).
        skeletons : sequence of Skeleton or None, optional
            Each character's own sized skeleton (None, or no sequence: the encoder's).
        times_ns : sequence of int, optional
            The instant each character's pose is for (host ns; default: ``t_ns`` for all), sent as its time code.
        hands : sequence of HandPose or None, optional
            Each character's fingers (None: no finger-tracking segments, as without).

        Returns
        -------
        list of bytes
            One datagram set per character, in the given order.
        """
        tc = self.time_code_ms(t_ns)
        if not characters:
            return []
        ids = [c for c, _ in characters]
        if any(not 0 <= c <= 255 for c in ids):
            raise InputError(f"MVN character ids must be within 0..255, got {ids}")
        thetas = np.stack([np.asarray(t, dtype=np.float64) for _, t in characters])
        if skeletons is None or all(sk is None for sk in skeletons):
            pos, quat = self.segments.compute(thetas)
        else:
            parts = [self._sized.get(sk).compute(th[None]) for sk, th in zip(skeletons, thetas, strict=True)]
            pos, quat = np.concatenate([a for a, _ in parts]), np.concatenate([b for _, b in parts])
        items = np.empty((len(characters), N_SEGMENTS), dtype=ITEM_DTYPE)
        items["id"] = SEGMENT_IDS
        items["position"] = pos
        items["quaternion"] = quat
        sample = sample_counter & 0xFFFFFFFF
        per = self.items_per_datagram
        out: list[bytes] = []
        codes = [tc] * len(ids) if times_ns is None else [self.time_code_ms(t) for t in times_ns]
        if len(codes) != len(ids):
            raise InputError(f"MVN: {len(codes)} time stamps for {len(ids)} characters")
        for k, char in enumerate(ids):
            these = items[k]
            fingers = 0
            h = None if hands is None else hands[k]
            if h is not None:  # the 40 finger-tracking segments follow the body's (spec 2.5.1)
                sk = None if skeletons is None else skeletons[k]
                fpos, fquat = self._sized.get(sk).compute_fingers(thetas[k], h)
                # Assigned into a big-endian array of its own: np.concatenate would promote to native byte order.
                both = np.empty(N_SEGMENTS + N_FINGER_SEGMENTS, dtype=ITEM_DTYPE)
                both[:N_SEGMENTS] = these
                extra = both[N_SEGMENTS:]
                extra["id"], extra["position"], extra["quaternion"] = FINGER_SEGMENT_IDS, fpos, fquat
                these, fingers = both, N_FINGER_SEGMENTS
            for index, start in enumerate(range(0, len(these), per)):
                chunk = these[start : start + per]
                last = LAST_DATAGRAM if start + per >= len(these) else 0
                head = HEADER.pack(ID_STRING, sample, index | last, len(chunk), codes[k], char, N_SEGMENTS, 0, fingers,
                                   len(chunk) * ITEM_SIZE)  # fmt: skip
                out.append(head + chunk.tobytes())
        return out

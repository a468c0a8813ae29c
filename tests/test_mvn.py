"""MVN network streaming (MXTP02): decoded by a reader written here from the Xsens specification (MV0305P rev. N,
sections 2.4.1, 2.5.3, 3.1), not with the encoder's code; poses round-trip to the solved frame's FK."""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
import pytest

from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import matrix_from_quat, random_rotvec
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.errors import InputError
from mocapd.protocols.mvn import MvnEncoder, parse_header

# Spec section 3.1, in order; the id on the wire is the index + 1.
SPEC_SEGMENTS = [
    "Pelvis", "L5", "L3", "T12", "T8", "Neck", "Head", "RightShoulder", "RightUpperArm", "RightForeArm",
    "RightHand", "LeftShoulder", "LeftUpperArm", "LeftForeArm", "LeftHand", "RightUpperLeg", "RightLowerLeg",
    "RightFoot", "RightToe", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "LeftToe",
]  # fmt: skip
# Our bone for each segment (DESIGN.md); the shoulders follow the chest (Spine3).
OURS = {
    "Pelvis": "Hips", "L5": "Spine", "L3": "Spine1", "T12": "Spine2", "T8": "Spine3", "Neck": "Neck", "Head": "Head",
    "RightUpperArm": "RightUpperArm", "RightForeArm": "RightLowerArm", "RightHand": "RightHand",
    "LeftUpperArm": "LeftUpperArm", "LeftForeArm": "LeftLowerArm", "LeftHand": "LeftHand",
    "RightUpperLeg": "RightUpperLeg", "RightLowerLeg": "RightLowerLeg", "RightFoot": "RightFoot",
    "RightToe": "RightToes", "LeftUpperLeg": "LeftUpperLeg", "LeftLowerLeg": "LeftLowerLeg", "LeftFoot": "LeftFoot",
    "LeftToe": "LeftToes",
}  # fmt: skip
# MVN global frame (Z up, X forward, Y left) from mocapd's (Y up, Z forward, X = subject's left): rows.
TO_MVN = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@dataclass
class Datagram:
    ident: bytes
    sample: int
    counter: int
    items: int
    time_code: int
    character: int
    body: int
    props: int
    fingers: int
    reserved: bytes
    payload_size: int
    segments: list[tuple[int, tuple[float, float, float], tuple[float, float, float, float]]]


def read_datagram(data: bytes) -> Datagram:
    """Byte offsets straight from the specification's header table (section 2.4.1)."""
    assert len(data) >= 24
    n_items = data[11]
    payload_size = int.from_bytes(data[22:24], "big")
    assert len(data) == 24 + payload_size, "payload size must be the datagram length minus the header"
    segments = []
    for k in range(n_items):
        off = 24 + 32 * k
        seg_id = int.from_bytes(data[off : off + 4], "big", signed=True)
        x, y, z, q0, q1, q2, q3 = struct.unpack("!7f", data[off + 4 : off + 32])
        segments.append((seg_id, (x, y, z), (q0, q1, q2, q3)))
    return Datagram(
        ident=data[0:6], sample=int.from_bytes(data[6:10], "big"), counter=data[10], items=n_items,
        time_code=int.from_bytes(data[12:16], "big"), character=data[16], body=data[17], props=data[18],
        fingers=data[19], reserved=data[20:22], payload_size=payload_size, segments=segments,
    )  # fmt: skip


def from_mvn(positions: np.ndarray, quats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MVN positions (n, 3) and (w, x, y, z) quaternions (n, 4) back to mocapd world positions and matrices."""
    R_mvn = matrix_from_quat(quats)
    return positions @ TO_MVN, TO_MVN.T @ R_mvn @ TO_MVN


def random_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    theta = np.zeros((n, 66))
    theta[:, :3] = rng.normal(size=(n, 3)) + np.array([0.0, 1.0, 0.0])
    theta[:, 3:] = random_rotvec(rng, (n, 21), max_angle=1.2).reshape(n, 63)
    return theta


SKELETON = Skeleton.from_height(1.82)


def test_header_fields_and_layout() -> None:
    enc = MvnEncoder(SKELETON)
    theta = random_poses(2, 0)
    t0 = 5_000_000_000
    first = enc.encode(41, t0, [(0, theta[0]), (7, theta[1])])
    later = enc.encode(43, t0 + 1_500_400_000, [(0, theta[0])])
    assert [len(d) for d in first] == [760, 760]  # 24 + 23 × 32: one datagram per character
    a, b = read_datagram(first[0]), read_datagram(first[1])
    for d in (a, b):
        assert d.ident == b"MXTP02" and d.sample == 41 and d.counter == 0x80  # last (and only) datagram
        assert d.items == 23 and d.body == 23 and d.props == 0 and d.fingers == 0 and d.reserved == b"\x00\x00"
        assert d.payload_size == 736 and d.time_code == 0
        assert [s[0] for s in d.segments] == list(range(1, 24))
    assert (a.character, b.character) == (0, 7)
    c = read_datagram(later[0])
    assert c.sample == 43 and c.time_code == 1500  # ms since the first frame of the stream
    assert first[0][:6] == b"MXTP02" and first[0][24:28] == b"\x00\x00\x00\x01"  # Pelvis id, big-endian int32
    h = parse_header(first[1])
    assert (h.sample_counter, h.last, h.datagram_index, h.character_id, h.payload_size) == (41, True, 0, 7, 736)


def test_rest_pose_is_identity_in_a_z_up_frame() -> None:
    theta = np.zeros(66)
    theta[:3] = [0.3, SKELETON.root_height, -0.2]  # x = subject's left, y = up, z = forward
    d = read_datagram(MvnEncoder(SKELETON).encode(0, 0, [(0, theta)])[0])
    for _, _, q in d.segments:
        np.testing.assert_allclose(q, [1.0, 0.0, 0.0, 0.0], atol=1e-7)  # the T-pose: every segment identity
    pelvis = d.segments[0][1]
    np.testing.assert_allclose(pelvis, [-0.2, 0.3, SKELETON.root_height], atol=1e-6)  # X fwd, Y left, Z up
    head = d.segments[SPEC_SEGMENTS.index("Head")][1]
    assert head[2] > pelvis[2] + 0.5
    left_hand = d.segments[SPEC_SEGMENTS.index("LeftHand")][1]
    assert left_hand[1] > pelvis[1] + 0.5  # the left arm points along +Y in MVN


def test_poses_round_trip_to_forward_kinematics() -> None:
    theta = random_poses(3, 1)
    datagrams = MvnEncoder(SKELETON).encode(9, 0, [(k, theta[k]) for k in range(3)])
    fk = Kinematics(SKELETON).forward(theta)
    for k, data in enumerate(datagrams):
        d = read_datagram(data)
        assert d.character == k
        pos = np.array([s[1] for s in d.segments])
        quat = np.array([s[2] for s in d.segments])
        np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-6)
        x, R = from_mvn(pos, quat)
        for i, name in enumerate(SPEC_SEGMENTS):
            if name in OURS:
                b = BONE_INDEX[OURS[name]]
                np.testing.assert_allclose(x[i], fk.positions[k, b], atol=2e-6, err_msg=name)
                np.testing.assert_allclose(R[i], fk.rotations[k, b], atol=2e-6, err_msg=name)
        # Shoulder rule: rigid with the chest, on the mid-line at the upper arm's height and depth.
        s3 = BONE_INDEX["Spine3"]
        for seg, arm in (("RightShoulder", "RightUpperArm"), ("LeftShoulder", "LeftUpperArm")):
            i = SPEC_SEGMENTS.index(seg)
            o = SKELETON.offsets[BONE_INDEX[arm]]
            want = fk.positions[k, s3] + fk.rotations[k, s3] @ np.array([0.0, o[1], o[2]])
            np.testing.assert_allclose(x[i], want, atol=2e-6)
            np.testing.assert_allclose(R[i], fk.rotations[k, s3], atol=2e-6)


def test_splitting_into_several_datagrams() -> None:
    theta = random_poses(2, 2)
    whole = MvnEncoder(SKELETON).encode(5, 0, [(0, theta[0]), (1, theta[1])])
    split = MvnEncoder(SKELETON, max_datagram_bytes=24 + 32 * 10).encode(5, 0, [(0, theta[0]), (1, theta[1])])
    assert len(split) == 6  # 10 + 10 + 3 items per character
    decoded = [read_datagram(d) for d in split]
    assert [d.counter for d in decoded] == [0x00, 0x01, 0x82] * 2  # spec example: 0, 1, 0x82
    assert [d.items for d in decoded] == [10, 10, 3] * 2
    assert [d.character for d in decoded] == [0, 0, 0, 1, 1, 1]
    assert all(d.sample == 5 and d.body == 23 and len(raw) <= 344 for d, raw in zip(decoded, split, strict=True))
    for c in range(2):
        payload = b"".join(raw[24:] for raw in split[3 * c : 3 * c + 3])
        assert payload == whole[c][24:]


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(InputError, match="cannot hold"):
        MvnEncoder(SKELETON, max_datagram_bytes=40)
    with pytest.raises(InputError, match=r"0\.\.255"):
        MvnEncoder(SKELETON).encode(0, 0, [(256, np.zeros(66))])
    with pytest.raises(InputError, match="shape"):
        MvnEncoder(SKELETON).encode(0, 0, [(0, np.zeros(65))])
    with pytest.raises(InputError, match="MXTP02"):
        parse_header(b"MXTP01" + bytes(18))
    with pytest.raises(InputError, match="shorter"):
        parse_header(b"MXTP02")
    assert MvnEncoder(SKELETON).encode(0, 0, []) == []


def test_per_character_skeletons_match_an_encoder_built_on_each() -> None:
    """Body sizing gives each person their own skeleton: a mixed frame encodes every character exactly as an
    encoder built on that character's skeleton would."""
    from mocapd.core.skeleton import Skeleton
    from mocapd.protocols.mvn import MvnEncoder

    small, tall = Skeleton.from_height(1.55), Skeleton.from_height(1.95)
    rng = np.random.default_rng(7)
    thetas = [np.concatenate([[0.0, 1.0, 0.0], rng.normal(scale=0.2, size=63)]) for _ in range(2)]
    mixed = MvnEncoder(small).encode(5, 1_000, [(0, thetas[0]), (1, thetas[1])], [None, tall])
    alone_small = MvnEncoder(small).encode(5, 1_000, [(0, thetas[0])])
    alone_tall = MvnEncoder(tall).encode(5, 1_000, [(1, thetas[1])])
    assert mixed == alone_small + alone_tall
    assert alone_tall != MvnEncoder(small).encode(5, 1_000, [(1, thetas[1])])


def test_each_character_carries_the_instant_of_its_pose() -> None:
    """A predicted pose is for a later instant than the frame's solve time: its time code says so."""
    enc = MvnEncoder(SKELETON)
    theta = random_poses(2, 1)
    t0 = 5_000_000_000
    enc.encode(1, t0, [(0, theta[0])])
    out = enc.encode(2, t0 + 16_000_000, [(0, theta[0]), (1, theta[1])], times_ns=[t0 + 150_000_000, t0 + 16_000_000])
    assert [read_datagram(d).time_code for d in out] == [150, 16]
    with pytest.raises(InputError, match="time stamps"):
        enc.encode(3, t0, [(0, theta[0])], times_ns=[t0, t0])

"""Rokoko Studio Live JSON v3 on bytes, decoded by a reader written here from the plugins' documented data model (the
field names of the Unity plugin's JsonLiveSerializerV3.cs, LZ4 frames, Unity's frame, world rotations times the
Studio T-pose table) and not from their parsing code: every joint back to mocapd's forward kinematics."""

from __future__ import annotations

import json
import socket
from collections.abc import Iterator
from typing import Any

import lz4.frame
import numpy as np
import pytest

from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import matrix_from_quat, random_rotvec, rotvec_from_matrix
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.errors import InputError
from mocapd.io.udp_stream import ACTOR_COLOURS, RokokoUdpSink
from mocapd.pipeline.scheduler import PersonPose, PoseFrame
from mocapd.protocols.conventions import UNITY
from mocapd.protocols.rokoko import RokokoActor, RokokoEncoder

SKELETON = Skeleton.from_height(1.75)
LZ4_MAGIC = bytes.fromhex("04224d18")  # the LZ4 frame format's magic number 0x184D2204, little-endian

# The Studio T-pose as the Unity plugin prints it (Actor.cs, SmartsuitTPose: x, y, z, w, three decimals), by Rokoko
# joint name; fingers per (side, finger) and the thumb's first phalanx apart.
_L, _R = (-0.5, -0.5, 0.5, -0.5), (0.5, -0.5, 0.5, 0.5)
STUDIO_TPOSE = {
    "hip": (0, 0, 0, 1), "spine": (0, 0, 1, 0), "chest": (0, 0, 1, 0), "neck": (0, 0, 1, 0), "head": (0, 0, 1, 0),
    "leftShoulder": (0, 0, 0.707, -0.707), "rightShoulder": (0, 0, 0.707, 0.707),
    "leftUpperArm": _L, "leftLowerArm": _L, "leftHand": _L, "rightUpperArm": _R, "rightLowerArm": _R, "rightHand": _R,
    "leftUpLeg": (0, 0.707, 0, 0.707), "leftLeg": (0, 0.707, 0, 0.707), "leftFoot": (0, 0.707, -0.707, 0),
    "leftToe": (0, 0.707, -0.707, 0), "leftToeEnd": (0, 0.707, -0.707, 0),
    "rightUpLeg": (0, -0.707, 0, 0.707), "rightLeg": (0, -0.707, 0, 0.707), "rightFoot": (0, -0.707, 0.707, 0),
    "rightToe": (0, -0.707, 0.707, 0), "rightToeEnd": (0, -0.707, 0.707, 0),
}  # fmt: skip
_THUMBS = {"left": ((-0.561, -0.701, 0.430, -0.092), (-0.653, -0.653, 0.271, -0.271)),
           "right": ((0.561, -0.701, 0.430, 0.092), (0.653, -0.653, 0.271, 0.271))}  # fmt: skip
for side, flat in (("left", _L), ("right", _R)):
    thumb0, thumb = _THUMBS[side]
    for k, ph in enumerate(("Proximal", "Medial", "Distal", "Tip")):
        STUDIO_TPOSE[f"{side}Thumb{ph}"] = thumb0 if k == 0 else thumb
        for finger in ("Index", "Middle", "Ring", "Little"):
            STUDIO_TPOSE[f"{side}{finger}{ph}"] = flat
# Rokoko joint -> the mocapd bone whose world rotation it carries and whose joint it sits at (None: elsewhere).
SOURCE = {
    "hip": "Hips", "spine": "Spine", "chest": "Spine3", "neck": "Neck", "head": "Head",  # spine: swung (check_actor)
    "leftUpperArm": "LeftUpperArm", "leftLowerArm": "LeftLowerArm", "leftHand": "LeftHand",
    "rightUpperArm": "RightUpperArm", "rightLowerArm": "RightLowerArm", "rightHand": "RightHand",
    "leftUpLeg": "LeftUpperLeg", "leftLeg": "LeftLowerLeg", "leftFoot": "LeftFoot", "leftToe": "LeftToes",
    "rightUpLeg": "RightUpperLeg", "rightLeg": "RightLowerLeg", "rightFoot": "RightFoot", "rightToe": "RightToes",
}  # fmt: skip


def decode(datagram: bytes) -> dict[str, Any]:
    """One datagram: an LZ4 frame (by its magic number) holding UTF-8 JSON, or the JSON itself."""
    text = lz4.frame.decompress(datagram) if datagram[:4] == LZ4_MAGIC else datagram
    doc: dict[str, Any] = json.loads(text.decode("utf-8"))
    return doc


def quat(d: dict[str, float]) -> np.ndarray:
    """A JSON rotation {x, y, z, w} as (w, x, y, z)."""
    return np.array([d["w"], d["x"], d["y"], d["z"]], dtype=np.float64)


def native(joint: dict[str, Any], name: str) -> tuple[np.ndarray, np.ndarray]:
    """A joint's position and bone rotation in mocapd's frame: p = Cᵀ p_unity; the Studio T-pose removed from the
    world rotation (R_unity = G · T), then G = Cᵀ G_unity C."""
    p = np.array([joint["position"][k] for k in "xyz"]) @ UNITY.basis
    x, y, z, w = STUDIO_TPOSE[name]
    T = matrix_from_quat(np.array([w, x, y, z], dtype=np.float64) / np.linalg.norm([w, x, y, z]))
    G = matrix_from_quat(quat(joint["rotation"])) @ T.T
    return p, UNITY.basis.T @ G @ UNITY.basis


def moving(seed: int, x: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    theta = np.zeros(66)
    theta[:3] = [x, 0.93, -0.7]
    theta[3:] = random_rotvec(rng, (21,), max_angle=1.0).ravel()
    return theta


def check_actor(actor: dict[str, Any], skeleton: Skeleton, theta: np.ndarray, tol: float = 2e-6) -> None:
    """Every body joint of a decoded actor against forward kinematics of θ (1e-3 on rotations: the plugin's
    three-decimal table, 3e-3 on the thumbs)."""
    fk = Kinematics(skeleton).forward(theta)
    body = actor["body"]
    assert set(body) == set(STUDIO_TPOSE) and len(body) == 63
    off = skeleton.offsets
    for name, joint in body.items():
        p, G = native(joint, name)
        bone = SOURCE.get(name)
        if bone is None:  # shoulders (the chest's), toe ends (the toes'), fingers (the hand's)
            side = "Left" if name.startswith("left") else "Right"
            bone = "Spine3" if "Shoulder" in name else f"{side}Toes" if "ToeEnd" in name else f"{side}Hand"
            b = BONE_INDEX[bone]
            if "Shoulder" in name:
                o = off[BONE_INDEX[f"{side}UpperArm"]]
                local = np.array([0.0, o[1], o[2]])  # the mid-line at the upper arm's height and depth
            else:
                local = 0.5 * off[b]  # the leaf's end site
            want = fk.positions[b] + fk.rotations[b] @ local
        else:
            b = BONE_INDEX[bone]
            want = fk.positions[b]
        np.testing.assert_allclose(p, want, atol=tol, err_msg=name)
        if name == "spine":  # Spine's rotation swung to point the lower spine at mocapd's chest (Spine3's joint)
            lower = off[BONE_INDEX["Spine1"]] + off[BONE_INDEX["Spine2"]] + off[BONE_INDEX["Spine3"]]
            chest = fk.positions[BONE_INDEX["Spine3"]] - fk.positions[b]
            np.testing.assert_allclose(G @ lower / np.linalg.norm(lower), chest / np.linalg.norm(chest), atol=1e-3)
            turn = rotvec_from_matrix(G @ fk.rotations[b].T)  # the swing: about an axis across the lower spine
            assert abs(turn @ fk.rotations[b] @ lower) < 1e-3 * np.linalg.norm(lower)
            continue
        np.testing.assert_allclose(G, fk.rotations[b], atol=3e-3 if "Thumb" in name else 1e-3, err_msg=name)


def test_tpose_sends_studios_tpose_and_the_documented_header() -> None:
    enc = RokokoEncoder(SKELETON, fps=60.0, compression="none")
    d = enc.encode(7, 5_000_000_000, [RokokoActor("suit:suit0", SKELETON.rest_pose(), (255, 59, 48))])
    assert d.actors == 1 and d.data[:1] == b"{" and d.json_bytes == len(d.data)
    assert d.data.startswith(
        b'{"version":3,"fps":60,"frame":7,"scene":{"timestamp":0.000000,"actors":[{"name":"suit:suit0",'
        b'"color":[255,59,48],"meta":{"hasGloves":false,"hasLeftGlove":false,"hasRightGlove":false,"hasBody":true,'
        b'"hasFace":false},"dimensions":{"totalHeight":1.750000,"hipHeight":0.'
    )
    assert d.data.endswith(b'}}}],"props":[]}}')
    doc = decode(d.data)
    assert list(doc) == ["version", "fps", "frame", "scene"] and doc["frame"] == 7
    (actor,) = doc["scene"]["actors"]
    assert actor["dimensions"]["hipHeight"] == pytest.approx(SKELETON.root_height, abs=1e-6)
    hip = actor["body"]["hip"]["position"]
    assert (hip["x"], hip["y"], hip["z"]) == (0.0, pytest.approx(SKELETON.root_height, abs=1e-6), 0.0)
    for name, joint in actor["body"].items():  # the plugins' T-pose, up to the quaternion's sign
        x, y, z, w = STUDIO_TPOSE[name]
        want = np.array([w, x, y, z]) / np.linalg.norm([w, x, y, z])
        got = quat(joint["rotation"])
        assert min(np.abs(got - want).max(), np.abs(got + want).max()) < 1e-3, (name, got, want)
    # The left arm is on the subject's left: -x in Unity's frame (the subject faces +z).
    assert actor["body"]["leftHand"]["position"]["x"] < -0.5 < 0.5 < actor["body"]["rightHand"]["position"]["x"]
    check_actor(actor, SKELETON, SKELETON.rest_pose())


def test_moving_actors_decode_to_forward_kinematics_on_their_own_skeletons() -> None:
    small = Skeleton.from_height(1.52)
    enc = RokokoEncoder(SKELETON, fps=30.0)
    t0 = 1_000_000_000
    for k in range(3):
        a, b = moving(k, -0.6), moving(10 + k, 0.9)
        actors = [RokokoActor("Alice", a), RokokoActor("track:4", b, skeleton=small)]
        d = enc.encode(100 + k, t0 + k * 33_333_333, actors)
        assert d.data[:4] == LZ4_MAGIC and d.data[4] & 0x08  # an LZ4 frame that stores its content size
        assert len(d.data) < d.json_bytes / 3
        doc = decode(d.data)
        assert doc["fps"] == 30 and doc["frame"] == 100 + k
        assert doc["scene"]["timestamp"] == pytest.approx(k * 0.033333333, abs=2e-6)
        alice, four = doc["scene"]["actors"]
        assert (alice["name"], four["name"]) == ("Alice", "track:4")
        assert four["dimensions"]["totalHeight"] == pytest.approx(1.52)
        check_actor(alice, SKELETON, a)
        check_actor(four, small, b)


def test_actors_that_do_not_fit_are_left_out() -> None:
    poses = [RokokoActor(f"p{i}", moving(i, i - 1.0)) for i in range(3)]
    full = RokokoEncoder(SKELETON, fps=60.0, compression="none").encode(1, 0, poses)
    one = RokokoEncoder(SKELETON, fps=60.0, compression="none").encode(1, 0, poses[:1])
    enc = RokokoEncoder(SKELETON, fps=60.0, compression="none", max_datagram_bytes=len(full.data) - 1)
    d = enc.encode(1, 0, poses)
    assert d.actors == 2 and [a["name"] for a in decode(d.data)["scene"]["actors"]] == ["p0", "p1"]
    tiny = RokokoEncoder(SKELETON, fps=60.0, compression="none", max_datagram_bytes=len(one.data) - 1)
    assert tiny.encode(2, 0, poses).actors == 0
    with pytest.raises(InputError, match="finite"):
        enc.encode(3, 0, [RokokoActor("bad", np.full(66, np.nan))])
    with pytest.raises(InputError, match="compression"):
        RokokoEncoder(SKELETON, fps=60.0, compression="zstd")


@pytest.fixture
def receiver() -> Iterator[socket.socket]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    yield sock
    sock.close()


def person(identity: str, theta: np.ndarray) -> PersonPose:
    return PersonPose(identity, 0, None, theta, Kinematics(SKELETON).forward(theta).positions, 0.9, 3, 0, 5, True)


@pytest.mark.asyncio
async def test_sink_sends_one_scene_per_due_frame_with_named_coloured_actors(receiver: socket.socket) -> None:
    port = receiver.getsockname()[1]
    sink = RokokoUdpSink(SKELETON, [("127.0.0.1", port)], fps=60.0, rate_divisor=2,
                         actor_names={"suit:suit0": "Alice"}, subjects=["suit:suit0", "track:2"])  # fmt: skip
    await sink.start()
    try:
        a, b, c = moving(1, 0.0), moving(2, 1.0), moving(3, -1.0)
        for n in range(1, 6):
            people = [person("track:2", b), person("track:9", c), person("suit:suit0", a)]
            sink.publish(PoseFrame(n, n * 16_666_667, n * 16_666_667, people if n != 3 else people[:1], 0))
        docs = [decode(receiver.recv(65536)) for _ in range(3)]  # frames 1, 3 (track:2 alone), 5
    finally:
        await sink.aclose()
    assert [d["frame"] for d in docs] == [1, 3, 5] and all(d["fps"] == 30 for d in docs)
    assert [d["scene"]["timestamp"] for d in docs] == pytest.approx([0.0, 0.0333333, 0.0666667], abs=1e-6)
    assert all(d["scene"]["props"] == [] for d in docs)
    # Actors in the order of the subjects list (track:9 is not in it), named by actor_names, coloured by slot.
    alice, two = docs[2]["scene"]["actors"]
    assert (alice["name"], two["name"]) == ("Alice", "track:2")
    assert (alice["color"], two["color"]) == ([*ACTOR_COLOURS[0]], [*ACTOR_COLOURS[1]])
    assert alice["meta"]["hasBody"] and two["meta"]["hasBody"]
    check_actor(alice, SKELETON, a)
    # Frame 3 lost Alice: she stays first, at her last pose, without a body update; the list keeps its order.
    lost, kept = docs[1]["scene"]["actors"]
    assert (lost["name"], lost["meta"]["hasBody"], kept["meta"]["hasBody"]) == ("Alice", False, True)
    check_actor(lost, SKELETON, a)
    st = sink.status()
    assert st["frames_seen"] == 5 and st["frames_sent"] == 3 and st["datagrams_sent"] == 3
    assert st["compression"] == "lz4" and st["oversize_actors"] == 0 and st["slots"] == {"suit:suit0": 0, "track:2": 1}


@pytest.mark.asyncio
async def test_a_lost_subject_leaves_the_scene_once_its_slot_is_released(receiver: socket.socket) -> None:
    sink = RokokoUdpSink(SKELETON, [("127.0.0.1", receiver.getsockname()[1])], fps=60.0, release_after_frames=2)
    await sink.start()
    try:
        who = [["track:1", "track:2"], ["track:2"], ["track:2"], ["track:2", "track:3"]]
        for n, ids in enumerate(who, start=1):
            sink.publish(PoseFrame(n, n, n, [person(i, moving(n, 0.0)) for i in ids], 0))
        docs = [decode(receiver.recv(65536)) for _ in who]
    finally:
        await sink.aclose()
    scenes = [[(a["name"], a["meta"]["hasBody"]) for a in d["scene"]["actors"]] for d in docs]
    assert scenes == [
        [("track:1", True), ("track:2", True)],
        [("track:1", False), ("track:2", True)],
        [("track:2", True)],  # released after 2 frames away
        [("track:3", True), ("track:2", True)],  # the new subject takes the freed slot 0
    ]

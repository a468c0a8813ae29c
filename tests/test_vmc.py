"""VMC protocol over a real UDP socket on 127.0.0.1, decoded by python-osc; bone names as Unity's HumanBodyBones,
local transforms in Unity's left-handed frame chained back to the solved frame's forward kinematics."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import pytest
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage

from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import matrix_from_quat, random_rotvec
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.errors import InputError
from mocapd.io.udp_stream import VmcUdpSink
from mocapd.pipeline.scheduler import PersonPose, PoseFrame
from mocapd.protocols.conventions import UNITY
from mocapd.protocols.vmc import VmcEncoder

SKELETON = Skeleton.from_height(1.68)
# UnityEngine.HumanBodyBones names we expect, with their parents in a Unity humanoid.
UNITY_PARENT = {
    "Hips": None, "Spine": "Hips", "Chest": "Spine", "UpperChest": "Chest", "Neck": "UpperChest", "Head": "Neck",
    "LeftShoulder": "UpperChest", "LeftUpperArm": "LeftShoulder", "LeftLowerArm": "LeftUpperArm",
    "LeftHand": "LeftLowerArm", "RightShoulder": "UpperChest", "RightUpperArm": "RightShoulder",
    "RightLowerArm": "RightUpperArm", "RightHand": "RightLowerArm", "LeftUpperLeg": "Hips",
    "LeftLowerLeg": "LeftUpperLeg", "LeftFoot": "LeftLowerLeg", "LeftToes": "LeftFoot", "RightUpperLeg": "Hips",
    "RightLowerLeg": "RightUpperLeg", "RightFoot": "RightLowerLeg", "RightToes": "RightFoot",
}  # fmt: skip


def person(identity: str, theta: np.ndarray, views: int = 3) -> PersonPose:
    joints = Kinematics(SKELETON).forward(theta).positions
    return PersonPose(identity, 0, None, theta, joints, 0.9, views, 0, 5, True)


def frame(n: int, t_ns: int, people: list[PersonPose]) -> PoseFrame:
    return PoseFrame(n, t_ns, t_ns, people, 0)


def random_pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    theta = np.zeros(66)
    theta[:3] = [0.4, 0.95, -1.1]
    theta[3:] = random_rotvec(rng, (21,), max_angle=1.0).ravel()
    return theta


@pytest.fixture
def receiver() -> Iterator[socket.socket]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    yield sock
    sock.close()


def drain(sock: socket.socket, n: int) -> list[bytes]:
    return [sock.recv(65536) for _ in range(n)]


def messages(datagrams: list[bytes]) -> list[OscMessage]:
    out: list[OscMessage] = []
    for d in datagrams:
        assert OscBundle.dgram_is_bundle(d)
        out.extend(m for m in OscBundle(d) if isinstance(m, OscMessage))
    return out


def globals_from_locals(bones: dict[str, list[float]]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Chain Unity local transforms (p, q as x, y, z, w) into world transforms, then back to mocapd axes."""
    world: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, parent in UNITY_PARENT.items():  # parents come first in this table
        p = np.array(bones[name][0:3])
        x, y, z, w = bones[name][3:7]
        R = matrix_from_quat(np.array([w, x, y, z]))
        if parent is None:
            world[name] = (p, R)
        else:
            pp, pR = world[parent]
            world[name] = (pp + pR @ p, pR @ R)
    # Unity's frame is a mirror of ours (x = -X): the conversion is its own inverse.
    return {n: (UNITY.positions(p), UNITY.matrices(R)) for n, (p, R) in world.items()}


@pytest.mark.asyncio
async def test_vmc_bundles_over_udp_decode_and_round_trip(receiver: socket.socket) -> None:
    port = receiver.getsockname()[1]
    sink = VmcUdpSink(SKELETON, [("127.0.0.1", port)])
    await sink.start()
    theta = random_pose(0)
    t0 = 10_000_000_000
    sink.publish(frame(100, t0, [person("suit:a", theta)]))
    sink.publish(frame(101, t0 + 250_000_000, [person("suit:a", theta)]))
    await sink.aclose()
    first, second = drain(receiver, 2), drain(receiver, 2)  # a frame is two bundles at the 1472-byte default
    assert all(len(d) <= 1472 for d in first + second)
    msgs = messages(first)
    addrs = [m.address for m in msgs]
    assert addrs[0] == "/VMC/Ext/Root/Pos" and addrs[-2:] == ["/VMC/Ext/OK", "/VMC/Ext/T"]
    assert addrs[1:-2] == ["/VMC/Ext/Bone/Pos"] * 22
    assert msgs[0].params == ["root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    assert msgs[-2].params == [1, 3, 0, 1]  # loaded, calibrated, normal mode, tracked
    assert msgs[-1].params == [0.0]
    assert messages(second)[-1].params == [pytest.approx(0.25)]
    bones = {m.params[0]: m.params[1:] for m in msgs[1:-2]}
    assert set(bones) == set(UNITY_PARENT)
    assert all(len(v) == 7 and all(isinstance(f, float) for f in v) for v in bones.values())

    fk = Kinematics(SKELETON).forward(theta)
    world = globals_from_locals(bones)
    same = [b for b in UNITY_PARENT if b in BONE_INDEX]  # bones with the same name in both skeletons
    assert len(same) == 18
    for name in same:
        x, R = world[name]
        np.testing.assert_allclose(x, fk.positions[BONE_INDEX[name]], atol=3e-6, err_msg=name)
        np.testing.assert_allclose(R, fk.rotations[BONE_INDEX[name]], atol=3e-6, err_msg=name)
    # Spine1 -> Chest; Spine2 and Spine3 -> UpperChest (at Spine2's joint, with Spine3's rotation).
    np.testing.assert_allclose(world["Chest"][0], fk.positions[BONE_INDEX["Spine1"]], atol=3e-6)
    np.testing.assert_allclose(world["Chest"][1], fk.rotations[BONE_INDEX["Spine1"]], atol=3e-6)
    np.testing.assert_allclose(world["UpperChest"][0], fk.positions[BONE_INDEX["Spine2"]], atol=3e-6)
    np.testing.assert_allclose(world["UpperChest"][1], fk.rotations[BONE_INDEX["Spine3"]], atol=3e-6)
    s3 = BONE_INDEX["Spine3"]
    for side in ("Left", "Right"):  # the shoulder rule: rigid with the chest, mid-line at the upper arm's height
        o = SKELETON.offsets[BONE_INDEX[f"{side}UpperArm"]]
        want = fk.positions[s3] + fk.rotations[s3] @ np.array([0.0, o[1], o[2]])
        np.testing.assert_allclose(world[f"{side}Shoulder"][0], want, atol=3e-6)
        np.testing.assert_allclose(world[f"{side}Shoulder"][1], fk.rotations[s3], atol=3e-6)
    st = sink.status()
    assert st["datagrams_sent"] == 4 and st["frames_sent"] == 2 and st["datagrams_dropped"] == 0


def test_rest_pose_in_unity_frame() -> None:
    theta = np.zeros(66)
    theta[:3] = [0.2, SKELETON.root_height, 0.5]
    msgs = messages(VmcEncoder(SKELETON, max_datagram_bytes=65507).encode(0, theta))
    bones = {m.params[0]: m.params[1:] for m in msgs if m.address == "/VMC/Ext/Bone/Pos"}
    for v in bones.values():
        np.testing.assert_allclose(v[3:], [0.0, 0.0, 0.0, 1.0], atol=1e-7)  # T-pose: identity local rotations
    np.testing.assert_allclose(bones["Hips"][:3], [-0.2, SKELETON.root_height, 0.5], atol=1e-6)  # x mirrored
    assert bones["LeftLowerArm"][0] < 0 < bones["RightLowerArm"][0]  # Unity +X is the subject's right
    assert bones["LeftUpperArm"][1] == 0.0  # the shoulder rule puts the arm's height in the shoulder bone


def test_one_avatar_per_destination_in_order_of_appearance() -> None:
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
            s.settimeout(2.0)
        dests = [("127.0.0.1", s.getsockname()[1]) for s in socks]
        sink = VmcUdpSink(SKELETON, dests, max_datagram_bytes=4096, release_after_frames=2)
        sink.sender.open()
        a, b, c = random_pose(1), random_pose(2), random_pose(3)
        sink.publish(frame(0, 0, [person("track:1", a), person("suit:s", b, views=0)]))
        sink.publish(frame(1, 10, [person("track:9", c), person("suit:s", b)]))  # no free avatar for track:9
        got = [messages(drain(s, 1)) for s in socks]
        hips0 = next(m for m in got[0] if m.address == "/VMC/Ext/Bone/Pos" and m.params[0] == "Hips")
        hips1 = next(m for m in got[1] if m.address == "/VMC/Ext/Bone/Pos" and m.params[0] == "Hips")
        np.testing.assert_allclose(hips0.params[1:4], UNITY.positions(a[:3]), atol=1e-6)
        np.testing.assert_allclose(hips1.params[1:4], UNITY.positions(b[:3]), atol=1e-6)
        assert next(m for m in got[1] if m.address == "/VMC/Ext/OK").params[3] == 0  # no views, no IMUs
        assert messages(drain(socks[1], 1))[-2].params[3] == 1
        assert sink.slots.unassigned == 1
        sink.publish(frame(2, 20, [person("track:9", c), person("suit:s", b)]))  # track:1 gone 2 frames: freed
        drain(socks[1], 1)
        hips = next(m for m in messages(drain(socks[0], 1)) if m.params and m.params[0] == "Hips")
        np.testing.assert_allclose(hips.params[1:4], UNITY.positions(c[:3]), atol=1e-6)
    finally:
        for s in socks:
            s.close()


def test_bone_message_bytes_as_documented() -> None:
    theta = np.zeros(66)
    raw = b"".join(VmcEncoder(SKELETON).encode(0, theta))
    prefix = bytes.fromhex(
        "2F 56 4D 43 2F 45 78 74 2F 42 6F 6E 65 2F 50 6F 73 00 00 00"  # "/VMC/Ext/Bone/Pos" + 3 NUL
        "2C 73 66 66 66 66 66 66 66 00 00 00"  # ",sfffffff" + 3 NUL
        "4C 65 66 74 55 70 70 65 72 41 72 6D 00 00 00 00"  # "LeftUpperArm" + 4 NUL
    )
    at = raw.index(prefix)
    assert raw[at - 4 : at] == (76).to_bytes(4, "big")  # the bundle element's size field
    values = np.frombuffer(raw[at + 48 : at + 76], dtype=">f4")
    o = SKELETON.offsets[BONE_INDEX["LeftUpperArm"]]
    np.testing.assert_allclose(values, [-o[0], 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], atol=1e-7)  # x mirrored, then xyzw


def test_per_subject_skeletons_match_an_encoder_built_on_each() -> None:
    from mocapd.core.skeleton import Skeleton
    from mocapd.protocols.vmc import VmcEncoder

    small, tall = Skeleton.from_height(1.55), Skeleton.from_height(1.95)
    rng = np.random.default_rng(8)
    thetas = np.stack([np.concatenate([[0.0, 1.0, 0.0], rng.normal(scale=0.2, size=63)]) for _ in range(2)])
    mixed = VmcEncoder(small).encode_many(1_000, thetas, [True, True], [tall, None])
    assert mixed[0] == VmcEncoder(tall).encode_many(1_000, thetas[:1], [True])[0]
    assert mixed[1] == VmcEncoder(small).encode_many(1_000, thetas[1:], [True])[0]
    assert mixed[0] != VmcEncoder(small).encode_many(1_000, thetas[:1], [True])[0]


def test_each_avatar_gets_the_instant_of_its_pose(receiver: socket.socket) -> None:
    """Through the real sink: a predicted subject's /VMC/Ext/T is its own pose instant, not the frame's solve
    time (which the delayed subject keeps)."""
    dest = ("127.0.0.1", receiver.getsockname()[1])
    sink = VmcUdpSink(SKELETON, [dest, dest], max_datagram_bytes=4096)
    sink.sender.open()
    t0 = 2_000_000_000
    sink.publish(frame(0, t0, []))  # the stream's clock starts here
    ahead = replace(person("suit:s", random_pose(1)), t_pose_ns=t0 + 500_000_000)
    sink.publish(replace(frame(1, t0 + 250_000_000, [ahead, person("track:2", random_pose(2))]), output="predicted"))
    times = sorted(m.params[0] for m in messages(drain(receiver, 2)) if m.address == "/VMC/Ext/T")
    assert times == pytest.approx([0.25, 0.5])
    with pytest.raises(InputError, match="time stamps"):
        VmcEncoder(SKELETON).encode_many(t0, np.stack([random_pose(1)]), [True], times_ns=[t0, t0])

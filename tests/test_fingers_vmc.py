"""Fingers on VMC (issue 44) over a real UDP socket on 127.0.0.1, decoded by python-osc: a subject whose hands are
closing into a fist sends the 15 finger bones of each hand present under Unity's HumanBodyBones names, after the 22
body bones and before OK and T; chaining the received local transforms (body, then fingers) in Unity's frame gives
the fingers' forward kinematics; a hand not solved sends no finger bones, a subject without fingers none."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import numpy as np
import pytest

from mocapd.core.hand_skeleton import FINGER_BONES, FINGER_PARENTS, HAND_BONE_NAMES, HandSkeleton
from mocapd.core.rotations import matrix_from_quat
from mocapd.core.skeleton import Skeleton
from mocapd.io.udp_stream import VmcUdpSink
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.protocols.conventions import UNITY
from mocapd.protocols.fingers import subject_fingers
from tests.finger_support import fist, person_with_fingers
from tests.test_vmc import UNITY_PARENT, drain, messages, random_pose

SKELETON = Skeleton.from_height(1.68)
HANDS = HandSkeleton.from_body(SKELETON)


@pytest.fixture
def receiver() -> Iterator[socket.socket]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    yield sock
    sock.close()


def chain(bones: dict[str, list[float]]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """World transforms (mocapd axes) of every received bone: Unity's parents, then each finger's."""
    parents: dict[str, str | None] = dict(UNITY_PARENT)
    for side in ("Left", "Right"):
        for b, up in zip(FINGER_BONES, FINGER_PARENTS, strict=True):
            parents[side + b] = side + ("Hand" if up < 0 else FINGER_BONES[up])
    world: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, parent in parents.items():
        if name not in bones:
            continue
        p = np.array(bones[name][0:3])
        x, y, z, w = bones[name][3:7]
        R = matrix_from_quat(np.array([w, x, y, z]))
        if parent is None:
            world[name] = (p, R)
        else:
            pp, pR = world[parent]
            world[name] = (pp + pR @ p, pR @ R)
    return {n: (UNITY.positions(p), UNITY.matrices(R)) for n, (p, R) in world.items()}


@pytest.mark.asyncio
async def test_finger_bones_over_udp_chain_to_the_fingers_forward_kinematics(receiver: socket.socket) -> None:
    sink = VmcUdpSink(SKELETON, [("127.0.0.1", receiver.getsockname()[1])], max_datagram_bytes=65507)
    await sink.start()
    theta = random_pose(4)
    hands = [fist(0.0, HANDS), fist(0.6, HANDS), fist(1.0, HANDS, present=(False, True)), None]
    t0 = 10_000_000_000
    for k, h in enumerate(hands):
        sink.publish(PoseFrame(k, t0 + k * 16_666_667, 0, [person_with_fingers("suit:a", theta, SKELETON, h)], 0))
    await sink.aclose()
    received = [messages(drain(receiver, 1)) for _ in hands]  # one bundle each at this limit
    for h, msgs in zip(hands, received, strict=True):
        addrs = [m.address for m in msgs]
        assert addrs[0] == "/VMC/Ext/Root/Pos" and addrs[-2:] == ["/VMC/Ext/OK", "/VMC/Ext/T"]
        names = [m.params[0] for m in msgs[1:-2]]
        assert names[:22] == list(UNITY_PARENT)
        present = [] if h is None else [s for s, on in zip(("Left", "Right"), h.present, strict=True) if on]
        assert names[22:] == [n for n in HAND_BONE_NAMES if any(n.startswith(s) for s in present)]
        if h is None:
            continue
        bones = {m.params[0]: m.params[1:] for m in msgs[1:-2]}
        world = chain(bones)
        fs = subject_fingers(theta[None], [SKELETON], [h])
        for s, side in enumerate(("Left", "Right")):
            if not h.present[s]:
                continue
            for b, bone in enumerate(FINGER_BONES):
                x, R = world[side + bone]
                np.testing.assert_allclose(x, fs.positions[0, s, b], atol=5e-6, err_msg=side + bone)
                np.testing.assert_allclose(R, fs.rotations[0, s, b], atol=5e-6, err_msg=side + bone)
    # The fist closes: the received index fingertip bone ends nearer the palm at 0.6 than flat.
    flat, bent = (
        chain({m.params[0]: m.params[1:] for m in received[0][1:-2]}),
        chain({m.params[0]: m.params[1:] for m in received[1][1:-2]}),
    )
    wrist = flat["LeftHand"][0]
    assert (
        np.linalg.norm(bent["LeftIndexDistal"][0] - wrist) < np.linalg.norm(flat["LeftIndexDistal"][0] - wrist) - 0.01
    )

"""Fingers on Rokoko Studio Live JSON v3 (issue 44), through the real sink over UDP on 127.0.0.1, LZ4-decoded: the
finger joints of each hand solved (Proximal/Medial/Distal at the finger bones' joints with their world rotations in
Studio's convention, Tip at the fingertip) decode, with the plugins' T-pose table removed, to the fingers' forward
kinematics; ``hasLeftGlove``/``hasRightGlove``/``hasGloves`` say which hands; a hand without fingers is sent
straight at the hand's end site, as before."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import numpy as np
import pytest

from mocapd.core.hand_skeleton import FINGER_BONES, FINGERS, HandSkeleton
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.io.udp_stream import RokokoUdpSink
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.protocols.fingers import subject_fingers
from tests.finger_support import fist, person_with_fingers
from tests.test_rokoko import check_actor, decode, moving, native

SKELETON = Skeleton.from_height(1.75)
HANDS = HandSkeleton.from_body(SKELETON)


@pytest.fixture
def receiver() -> Iterator[socket.socket]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    yield sock
    sock.close()


@pytest.mark.asyncio
async def test_finger_joints_decode_to_the_fingers_forward_kinematics(receiver: socket.socket) -> None:
    sink = RokokoUdpSink(SKELETON, [("127.0.0.1", receiver.getsockname()[1])], fps=60.0)
    await sink.start()
    a, b = moving(7, -0.5), moving(8, 0.8)
    hands = fist(0.8, HANDS, present=(True, False))
    try:
        people = [person_with_fingers("suit:a", a, SKELETON, hands), person_with_fingers("track:2", b, SKELETON, None)]
        sink.publish(PoseFrame(1, 16_666_667, 0, people, 0))
        doc = decode(receiver.recv(65536))
    finally:
        await sink.aclose()
    with_fingers, without = doc["scene"]["actors"]
    assert with_fingers["meta"] == {"hasGloves": True, "hasLeftGlove": True, "hasRightGlove": False, "hasBody": True,
                                    "hasFace": False}  # fmt: skip
    assert without["meta"]["hasGloves"] is False and without["meta"]["hasLeftGlove"] is False
    check_actor(without, SKELETON, b)  # no fingers: exactly as before (straight, at the hand's end site)
    fs = subject_fingers(a[None], [SKELETON], [hands])
    body = with_fingers["body"]
    for b_idx, bone in enumerate(FINGER_BONES):
        name = "left" + bone.replace("Intermediate", "Medial")
        p, G = native(body[name], name)
        np.testing.assert_allclose(p, fs.positions[0, 0, b_idx], atol=2e-6, err_msg=name)
        np.testing.assert_allclose(G, fs.rotations[0, 0, b_idx], atol=3e-3 if "Thumb" in name else 1e-3, err_msg=name)
    for f, finger in enumerate(FINGERS):
        name = f"left{finger}Tip"
        p, G = native(body[name], name)
        np.testing.assert_allclose(p, fs.tips[0, 0, f], atol=2e-6, err_msg=name)
        np.testing.assert_allclose(G, fs.rotations[0, 0, 3 * f + 2], atol=3e-3 if f == 0 else 1e-3, err_msg=name)
    # The right hand has no fingers this frame: its finger joints ride straight at the hand's end site.
    fk = Kinematics(SKELETON).forward(a)
    hand = BONE_INDEX["RightHand"]
    end = fk.positions[hand] + fk.rotations[hand] @ (0.5 * SKELETON.offsets[hand])
    for finger in FINGERS:
        p, G = native(body[f"right{finger}Distal"], f"right{finger}Distal")
        np.testing.assert_allclose(p, end, atol=2e-6)
        np.testing.assert_allclose(G, fk.rotations[hand], atol=3e-3)
    # A fist: the left index fingertip is much nearer the wrist than along a flat hand.
    wrist = native(body["leftHand"], "leftHand")[0]
    assert np.linalg.norm(native(body["leftIndexTip"], "leftIndexTip")[0] - wrist) < 0.12

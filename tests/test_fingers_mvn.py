"""Fingers on the MVN network stream (issue 44), through the real sink over UDP on 127.0.0.1, read with the
specification's byte offsets (tests/test_mvn.py): a character with fingers says 40 finger-tracking segments in its
header and sends them after its 23 body segments, split over two datagrams at the default 1472 bytes, with ids 24 to
63 in the order of the spec's table 2 (left hand, then right); each decodes to the fingers' forward kinematics (the
thumb's three bones, the four fingers' phalanges; carpus and the four metacarpals rigid with the hand); a hand not
solved is straight; a character without fingers is as before (0, 23 segments, one datagram)."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import numpy as np
import pytest

from mocapd.core.hand_skeleton import HandSkeleton
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.io.udp_stream import MvnUdpSink
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.protocols.fingers import subject_fingers
from tests.finger_support import fist, person_with_fingers
from tests.test_mvn import from_mvn, random_poses, read_datagram

SKELETON = Skeleton.from_height(1.82)
HANDS = HandSkeleton.from_body(SKELETON)
# Spec table 2 (revision N), one hand, in order; our finger bone (index in the hand) for each, None: the hand.
TABLE2 = [("Carpus", None), ("FirstMC", 0), ("FirstPP", 1), ("FirstDP", 2)] + [
    (f"{n}{s}", None if s == "MC" else 3 * f + ("PP", "MP", "DP").index(s))
    for f, n in enumerate(("Second", "Third", "Fourth", "Fifth"), start=1)
    for s in ("MC", "PP", "MP", "DP")
]


@pytest.fixture
def receiver() -> Iterator[socket.socket]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    yield sock
    sock.close()


@pytest.mark.asyncio
async def test_finger_segments_over_udp_decode_to_the_fingers(receiver: socket.socket) -> None:
    sink = MvnUdpSink(SKELETON, [("127.0.0.1", receiver.getsockname()[1])], character_ids={"suit:a": 0, "track:b": 1})
    await sink.start()
    a, b = random_poses(2, seed=9)
    hands = fist(0.9, HANDS, present=(True, False))
    try:
        people = [person_with_fingers("suit:a", a, SKELETON, hands), person_with_fingers("track:b", b, SKELETON, None)]
        sink.publish(PoseFrame(77, 1_000_000_000, 0, people, 0))
        grams = [read_datagram(receiver.recv(65536)) for _ in range(3)]
    finally:
        await sink.aclose()
    first, second, other = grams
    assert [(g.character, g.counter, g.body, g.props, g.fingers, g.items) for g in grams] == [
        (0, 0x00, 23, 0, 40, 45), (0, 0x81, 23, 0, 40, 18), (1, 0x80, 23, 0, 0, 23)]  # fmt: skip
    assert all(g.sample == 77 for g in grams) and first.time_code == second.time_code
    assert [s[0] for s in other.segments] == list(range(1, 24))
    segments = first.segments + second.segments
    assert [s[0] for s in segments] == list(range(1, 64))
    fk = Kinematics(SKELETON).forward(a)
    fs = subject_fingers(a[None], [SKELETON], [hands])
    for h, side in enumerate(("Left", "Right")):
        hand = BONE_INDEX[f"{side}Hand"]
        for k, (name, bone) in enumerate(TABLE2):
            seg_id, p, q = segments[23 + 20 * h + k]
            assert seg_id == 24 + 20 * h + k, name
            x, R = from_mvn(np.array([p]), np.array([q]))
            if bone is None:  # carpus at the wrist; a metacarpal 0.3 of the way to its knuckle; both with the hand
                mc = 0.3 * HANDS.offsets[h, 3 * (k // 4)] if name.endswith("MC") else np.zeros(3)
                want_x, want_R = fk.positions[hand] + fk.rotations[hand] @ mc, fk.rotations[hand]
            else:
                want_x, want_R = fs.positions[0, h, bone], fs.rotations[0, h, bone]
            np.testing.assert_allclose(x[0], want_x, atol=5e-6, err_msg=side + name)
            np.testing.assert_allclose(R[0], want_R, atol=5e-6, err_msg=side + name)
    # The right hand was not solved: straight, rigid with the hand; the left one a fist.
    right_dp = from_mvn(np.array([segments[23 + 20 + 7][1]]), np.array([segments[23 + 20 + 7][2]]))[1][0]
    np.testing.assert_allclose(right_dp, fk.rotations[BONE_INDEX["RightHand"]], atol=5e-6)
    left_dp = from_mvn(np.array([segments[23 + 7][1]]), np.array([segments[23 + 7][2]]))[1][0]
    bend = np.degrees(np.arccos((np.trace(fk.rotations[BONE_INDEX["LeftHand"]].T @ left_dp) - 1) / 2))
    total = 0.9 * (80 + 100 + 70)  # the index finger's three flexions about one axis: 225°, a 135° turn
    assert bend == pytest.approx(360 - total, abs=0.01)

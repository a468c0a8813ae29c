"""Fingers on the WebSocket stream (issue 44), on bytes and over a real socket: a frame whose subjects have fingers
carries each one's ``hands`` (local finger rotations, rest offsets, and with ``globals`` the finger joints and
tips); forward kinematics over the message's body and finger bones, in every convention and both encodings, gives
the fingers' joints the server sent and the native ones converted; the server announces the finger bones in a fresh
hello before the first frame with fingers, and a stream without fingers never names them."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import numpy as np
import pytest
from websockets.asyncio.client import connect

from mocapd.core.hand_skeleton import HAND_BONE_NAMES, HandSkeleton
from mocapd.core.rotations import quat_multiply, quat_rotate
from mocapd.core.skeleton import BONE_NAMES, N_BONES, PARENTS, Skeleton
from mocapd.io.ws_server import ServerSettings, WebSocketStreamServer
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.protocols.conventions import convention
from mocapd.protocols.fingers import subject_fingers
from mocapd.protocols.ws_stream import (
    STREAM_CONVENTIONS,
    ClientSession,
    FrameEncoder,
    StreamDescription,
    StreamOptions,
    decode,
)
from tests.finger_support import fist, person_with_fingers
from tests.ws_support import random_frame

SKEL = Skeleton.from_height(1.75)
TALL = Skeleton.from_height(1.92)


def frame_with_fingers(closure: float, number: int = 7) -> PoseFrame:
    """Three subjects: both hands closing (own tall skeleton, bigger hands), only the right hand, no fingers."""
    base = random_frame(np.random.default_rng(5), number, ["suit:suit0", "track:1", "track:2"], SKEL)
    a, b, c = base.people
    people = [
        person_with_fingers(a.identity, a.theta, TALL, fist(closure, HandSkeleton.from_body(TALL)), own=True),
        person_with_fingers(b.identity, b.theta, SKEL, fist(closure, present=(False, True)), track=1),
        c,
    ]
    return PoseFrame(number, base.t_solve_ns, 0, people, 0)


def extended_fk(root: list[float], rot: list[float], offsets: list[float], parents: list[int]) -> np.ndarray:
    """Joint positions of every bone from root, local quaternions and offsets in the message's own frame."""
    q = np.asarray(rot, dtype=np.float64).reshape(-1, 4)
    off = np.asarray(offsets, dtype=np.float64).reshape(-1, 3)
    glob, pos = np.empty_like(q), np.empty((len(parents), 3))
    for b, p in enumerate(parents):
        if p < 0:
            glob[b], pos[b] = q[b], root
        else:
            glob[b] = quat_multiply(glob[p], q[b])
            pos[b] = pos[p] + quat_rotate(glob[p], off[b])
    return np.concatenate([pos, glob], axis=1)


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
@pytest.mark.parametrize("conv", STREAM_CONVENTIONS)
def test_finger_joints_from_the_message_match_in_every_convention(conv: str, encoding: str) -> None:
    frame = frame_with_fingers(0.7)
    desc = StreamDescription(60.0, {"default": SKEL, "tall": TALL},
                             lambda i: "tall" if i == "suit:suit0" else "default", fingers=True)  # fmt: skip
    session = ClientSession(desc)
    session.receive_message(json.dumps({"type": "subscribe", "convention": conv, "encoding": encoding,
                                        "globals": True}))  # fmt: skip
    hello = decode(session.messages_to_send()[-1])
    assert hello["finger_bones"] == list(HAND_BONE_NAMES)
    parents = [*hello["parents"], *hello["finger_parents"]]
    assert [(BONE_NAMES + HAND_BONE_NAMES)[p] for p in hello["finger_parents"][::3]] == ["LeftHand"] * 5 + [
        "RightHand"
    ] * 5
    msg = decode(FrameEncoder(frame, 0, desc).message(session.options))
    by_id = {s["id"]: s for s in msg["subjects"]}
    assert "hands" not in by_id["track:2"]  # a subject without fingers is sent as before
    c = convention(conv)
    tol = 1e-4 * c.scale if encoding == "msgpack" else 3e-5 * c.scale  # float32 / 6 decimals
    for person in frame.people[:2]:
        s = by_id[person.identity]
        assert person.hands is not None
        h = s["hands"]
        assert h["present"] == [bool(v) for v in person.hands.present]
        offsets = hello["skeletons"][s["skeleton"]]["offsets"] + h["offsets"]
        both = extended_fk(s["root"], s["rot"] + h["rot"], offsets, parents)
        sk = person.skeleton or SKEL
        native = subject_fingers(person.theta[None], [sk], [person.hands])
        expected = c.positions(native.positions[0].reshape(-1, 3))
        np.testing.assert_allclose(both[N_BONES:, :3], expected, atol=tol)
        np.testing.assert_allclose(np.reshape(h["joints"], (-1, 3)), expected, atol=tol)
        np.testing.assert_allclose(np.reshape(h["tip_joints"], (-1, 3)), c.positions(native.tips[0].reshape(-1, 3)),
                                   atol=tol)  # fmt: skip
        # The fingers really are bent: the middle fingertip is nearer the wrist than the flat hand's.
        wrist = both[[9, 12], :3]
        reach = np.linalg.norm(np.reshape(h["tip_joints"], (2, 5, 3))[:, 2] - wrist, axis=1)
        flat = np.linalg.norm(c.positions(person.hands.skeleton.offsets[:, 6:9].sum(axis=1)
                                          + person.hands.skeleton.tips[:, 2]), axis=1)  # fmt: skip
        present = person.hands.present
        assert np.all(reach[present] < 0.8 * flat[present]) and np.allclose(reach[~present], flat[~present], rtol=1e-4)


def test_hands_without_globals_carry_no_joints() -> None:
    desc = StreamDescription(60.0, {"default": SKEL}, fingers=True)
    m = decode(FrameEncoder(frame_with_fingers(1.0), 0, desc).message(StreamOptions()))
    assert set(m["subjects"][1]["hands"]) == {"present", "rot", "offsets", "tip_offsets"}
    assert len(m["subjects"][1]["hands"]["rot"]) == 120 and len(m["subjects"][1]["hands"]["offsets"]) == 90


@pytest.mark.asyncio
async def test_the_server_announces_fingers_before_the_first_frame_with_them() -> None:
    srv = WebSocketStreamServer(ServerSettings(port=0, status_hz=0), StreamDescription(60.0, {"default": SKEL}))
    await srv.start()
    try:
        async with connect(f"ws://127.0.0.1:{srv.port}/") as ws:
            messages: list[dict[str, Any]] = [decode(await ws.recv())]
            assert messages[0]["type"] == "hello" and "finger_bones" not in messages[0]
            srv.publish(random_frame(np.random.default_rng(1), 1, ["track:1"], SKEL))
            srv.publish(frame_with_fingers(0.5, number=2))
            async with asyncio.timeout(5):
                while not (messages[-1]["type"] == "frame" and messages[-1]["frame"] == 2):
                    messages.append(decode(await ws.recv()))
    finally:
        await srv.aclose()
    kinds = [(m["type"], m.get("frame"), "finger_bones" in m) for m in messages]
    assert kinds == [("hello", None, False), ("frame", 1, False), ("hello", None, True), ("frame", 2, False)]
    assert "hands" not in messages[1]["subjects"][0]
    assert [("hands" in s) for s in messages[3]["subjects"]] == [True, True, False]
    assert messages[2]["finger_parents"][:3] == [9, 21, 22] and len(messages[2]["finger_parents"]) == 30
    assert messages[2]["parents"] == list(PARENTS)

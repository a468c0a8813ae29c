"""Fingers in the session format (issue 44): pose records carry each person's hands (present flags, sized hand
skeleton, local finger rotations) through encode/decode, a recorded session on disk, the resolved stream ``mocapd
resolve`` writes, and a replay's published frames; a record without fingers has no fingers section (the golden
digests of tests/test_fingerless_outputs_unchanged.py), and a cut or unknown fingers section is an InputError."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.hand_skeleton import HandPose, HandSkeleton
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import Skeleton
from mocapd.core.synthetic import moving_sequence
from mocapd.errors import InputError
from mocapd.io.session import RESOLVED, SessionWriter, open_session
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.protocols import session_format as sf
from mocapd.service.outputs.recorder import pose_record
from mocapd.service.session.replay import pose_frame
from mocapd.service.session.solve import write_resolved
from tests.finger_support import closing, fist, person_with_fingers

SKEL = Skeleton.from_height(1.75)
HANDS = HandSkeleton.reference((1.07, 0.93))


def take(n: int = 12) -> list[sf.PoseRecord]:
    """A fist closing on ``suit:suit0`` (its right hand lost in the middle third), ``track:1`` without fingers."""
    thetas = moving_sequence(SKEL, n, seed=3)
    out = []
    for i, c in enumerate(closing(n)):
        right = not (n // 3 <= i < 2 * n // 3)
        a = person_with_fingers("suit:suit0", thetas[i], SKEL, fist(float(c), HANDS, (True, right)))
        b = person_with_fingers("track:1", thetas[n - 1 - i], SKEL, None, track=1)
        frame = PoseFrame(i, 1_000_000_000 + i * 16_666_667, 0, [a, b], 0)
        out.append(pose_record(frame))
    return out


def same_hands(a: HandPose | None, b: HandPose | None) -> None:
    assert (a is None) == (b is None)
    if a is None or b is None:
        return
    np.testing.assert_array_equal(a.present, b.present)
    np.testing.assert_array_equal(a.rotations, b.rotations)  # float64: exact
    np.testing.assert_allclose(a.skeleton.offsets, b.skeleton.offsets, atol=1e-7)  # float32
    np.testing.assert_allclose(a.skeleton.tips, b.skeleton.tips, atol=1e-7)
    np.testing.assert_allclose(a.skeleton.scale, b.skeleton.scale, rtol=1e-7)


def test_pose_records_carry_fingers_and_records_without_have_no_section() -> None:
    frames = take()
    for f in frames:
        g = sf.decode_pose(sf.encode_pose(f))
        for p, q in zip(f.people, g.people, strict=True):
            same_hands(p.hands, q.hands)
            assert q.t_pose_ns == f.t_solve_ns
    plain = replace(frames[0], people=tuple(replace(p, hands=None) for p in frames[0].people))
    with_fingers, without = sf.encode_pose(frames[0]), sf.encode_pose(plain)
    assert with_fingers.startswith(without) and with_fingers[len(without)] == 0x48  # "H", after the old record
    assert len(with_fingers) - len(without) == 1 + (2 + 8 + 4 * 120 + 8 * 120) + 1  # one person with, one without


def test_a_cut_or_unknown_fingers_section_is_an_input_error() -> None:
    data = sf.encode_pose(take()[5])
    for cut in (1, 100, 1000):
        with pytest.raises(InputError, match="pose record"):
            sf.decode_pose(data[:-cut])
    tag = len(data) - (1 + (2 + 8 + 4 * 120 + 8 * 120) + 1)
    bad = bytearray(data)
    bad[tag + 1] = 7
    with pytest.raises(InputError, match="finger flag 7"):
        sf.decode_pose(bytes(bad))


def test_a_recorded_and_a_resolved_session_read_back_their_fingers_and_replay_them(tmp_path: Path) -> None:
    frames = take()
    w = SessionWriter(tmp_path / "s", {"format": "mocapd-session", "version": 1}, flush_interval_s=0.1)
    w.open()
    for f in frames:
        w.put("poses", sf.T_POSE, sf.encode_pose, f)
    w.close()
    session = open_session(tmp_path / "s")
    write_resolved(session, frames)
    for stream in ("poses", RESOLVED):
        read = open_session(tmp_path / "s").poses(stream)
        assert len(read) == len(frames)
        for f, g in zip(frames, read, strict=True):
            for p, q in zip(f.people, g.people, strict=True):
                same_hands(p.hands, q.hands)
    # A replay publishes what was recorded: the frame's people carry their fingers again.
    replayed = pose_frame(open_session(tmp_path / "s").poses()[4])
    assert replayed.people[0].hands is not None and replayed.people[1].hands is None
    assert list(replayed.people[0].hands.present) == [True, False]
    joints = Kinematics(SKEL).forward(replayed.people[0].theta).positions
    np.testing.assert_allclose(replayed.people[0].joints, joints, atol=1e-5)

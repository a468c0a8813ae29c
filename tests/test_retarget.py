"""Retargeting onto the 21-bone skeleton: every shared mocap file stays within a few cm of its source joints."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapd.core.kinematics import Kinematics
from mocapd.core.motion import SourceMotion
from mocapd.core.retarget import retarget
from mocapd.core.rotations import quat_from_matrix
from mocapd.core.skeleton import BONE_NAMES, PARENTS, Skeleton
from mocapd.core.synthetic import moving_sequence
from mocapd.eval.data import default_data_root, load_clip

MOCAP = default_data_root() / "mocap"
FILES = sorted(MOCAP.rglob("*.bvh")) + sorted(MOCAP.rglob("*.amc"))


def test_every_file_is_found() -> None:
    assert len(FILES) >= 50, f"expected the shared mocap files under {MOCAP}"


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_retargeted_joints_stay_near_source(path: Path) -> None:
    clip = load_clip(path)
    assert clip.fps == 60.0
    err = clip.joint_error()
    assert np.all(np.isfinite(clip.theta))
    assert float(err.mean()) < 0.02, f"mean {1e3 * err.mean():.1f} mm"
    assert float(np.percentile(err, 99)) < 0.05, f"p99 {1e3 * np.percentile(err, 99):.1f} mm"
    assert float(err.max()) < 0.10, f"max {1e3 * err.max():.1f} mm"
    # Plausible human: 1.4–2.0 m, feet on the floor, T-pose rest facing +Z with the left arm along +X.
    sk = clip.skeleton
    assert 1.4 < sk.height < 2.0
    rest = Kinematics(sk).forward(sk.rest_pose()).positions
    left_hand = rest[BONE_NAMES.index("LeftHand")] - rest[BONE_NAMES.index("LeftUpperArm")]
    assert left_hand[0] > 0.4 and abs(left_hand[1]) < 0.1
    toes = rest[BONE_NAMES.index("LeftToes")] - rest[BONE_NAMES.index("LeftFoot")]
    assert toes[2] > 0.05
    assert np.percentile(clip.positions[:, [15, 16, 19, 20], 1].min(axis=1), 1) == pytest.approx(0.05, abs=0.02)


def test_round_trip_of_our_own_skeleton() -> None:
    """A clip recorded on our skeleton (as a SourceMotion with our names) retargets to itself."""
    sk = Skeleton.from_height(1.8)
    theta = moving_sequence(sk, 120, seed=3)
    fk = Kinematics(sk).forward(theta)
    names = [
        n.replace("UpperArm", "Arm").replace("LowerArm", "ForeArm").replace("UpperLeg", "UpLeg") for n in BONE_NAMES
    ]
    names = [n.replace("LowerLeg", "Leg").replace("Toes", "ToeBase").replace("Neck", "LowerNeck") for n in names]
    tr = np.broadcast_to(sk.offsets, (120, 21, 3)).copy()
    tr[:, 0] = theta[:, :3]
    local = quat_from_matrix(fk.local)
    m = SourceMotion("own", tuple(names), PARENTS, tr, local, np.zeros((21, 3)), 60.0)
    r = retarget(m)
    assert float(r.joint_error().max()) < 1e-6
    # The same shape: bone lengths equal ours.
    np.testing.assert_allclose(
        np.linalg.norm(r.skeleton.offsets, axis=1), np.linalg.norm(sk.offsets, axis=1), atol=1e-6
    )

"""The synthetic rig's recorded motion: shipped clips load, resample smoothly and place people apart."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.kinematics import Kinematics
from mocapd.core.motion import resample_poses
from mocapd.core.rotations import quat_angle, quat_from_rotvec, rotvec_from_quat
from mocapd.errors import ConfigError, InputError
from mocapd.sim.world import TRUTH_FPS, SyntheticWorld, load_demo_motion


def test_resample_poses_keeps_the_samples_and_interpolates_rotations() -> None:
    rng = np.random.default_rng(0)
    theta = np.zeros((7, 66))
    theta[:, :3] = np.cumsum(rng.normal(scale=0.01, size=(7, 3)), axis=0)
    # A root turning through 170° about Y: the rotation vectors stay continuous, the interpolation takes the
    # short way between samples.
    theta[:, 4] = np.linspace(0.0, np.radians(170.0), 7)
    theta[:, 6:] = rng.normal(scale=0.2, size=(7, 60))
    out = resample_poses(theta, 60.0, 240.0)
    assert out.shape == (25, 66)
    np.testing.assert_allclose(out[::4], theta, atol=1e-9)  # every 4th sample is an input sample
    q = quat_from_rotvec(out[:, 3:6])
    steps = quat_angle(q[1:], q[:-1])
    assert steps.max() < np.radians(170.0 / 6 / 4) * 1.2  # evenly spread, no flip to the long way round
    # Within a segment the interpolated rotation lies between its ends.
    mid = quat_from_rotvec(out[2, 3:6])
    a, b = quat_from_rotvec(theta[0, 3:6]), quat_from_rotvec(theta[1, 3:6])
    assert quat_angle(mid, a) < quat_angle(a, b) and quat_angle(mid, b) < quat_angle(a, b)
    assert np.isfinite(rotvec_from_quat(q)).all()


def test_resample_poses_rejects_bad_input() -> None:
    with pytest.raises(InputError, match="shape"):
        resample_poses(np.zeros((1, 66)), 60.0, 240.0)
    with pytest.raises(InputError, match="positive"):
        resample_poses(np.zeros((3, 66)), 0.0, 240.0)


def test_shipped_recorded_motion_loads() -> None:
    clips, skeleton = load_demo_motion()
    assert len(clips) == 4
    kin = Kinematics(skeleton)
    for clip in clips:
        assert clip.shape[0] >= 10 * TRUTH_FPS and np.isfinite(clip).all()
        pos = kin.forward(clip[:: int(TRUTH_FPS) // 4]).positions
        assert pos[..., 1].min() > 0.0  # on or above the floor
        assert np.ptp(clip[:, [0, 2]], axis=0).max() < 0.6  # in place: people do not wander into each other
        # Real motion moves: hands travel well over a metre in a clip.
        assert np.linalg.norm(np.diff(pos[:, 9], axis=0), axis=1).sum() > 1.0


def test_recorded_world_keeps_people_apart_and_in_view() -> None:
    world = SyntheticWorld(n_cams=4, n_people=4, n_suits=0, motion="recorded")
    rng = np.random.default_rng(1)
    for t in np.linspace(0.0, 2.0 * world.loop_s, 9):
        roots = np.array([world.joints_at(p, float(t))[0] for p in range(4)])
        d = np.linalg.norm(roots[:, None, [0, 2]] - roots[None, :, [0, 2]], axis=-1)
        assert d[np.triu_indices(4, 1)].min() > 0.8
        for cam in range(4):
            assert world.detections(cam, float(t), rng).keypoints.shape[0] >= 3  # nearly everyone in every view


def test_unknown_motion_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="procedural"):
        SyntheticWorld(motion="dance")

"""The sensor simulator's noise models do what docs/accuracy.md says."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.imu import IMU_SET_13, default_mounts
from mocapd.core.keypoints import coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.retarget import Retargeted
from mocapd.core.rotations import matrix_from_quat, quat_angle, quat_from_matrix
from mocapd.eval.data import default_data_root, load_clip
from mocapd.eval.harness import windows
from mocapd.eval.simulate import (
    DetectionNoise,
    ImuNoise,
    outdoor_arc,
    simulate_detections,
    simulate_imus,
    totalcapture_ring,
)


@pytest.fixture(scope="module")
def clip() -> Retargeted:
    return windows(load_clip(default_data_root() / "mocap/cmu/131_03.bvh"))[0]


def test_rigs() -> None:
    ring = totalcapture_ring()
    assert len(ring) == 8 and len(totalcapture_ring(3)) == 3
    for c in ring:
        assert c.center[1] == pytest.approx(2.5)
        assert np.hypot(c.center[0], c.center[2]) == pytest.approx(4.5)
    arc = outdoor_arc()
    ang = [np.degrees(np.arctan2(c.center[0], c.center[2])) for c in arc]
    assert max(ang) - min(ang) == pytest.approx(120.0)


def test_clean_detections_are_projections(clip: Retargeted) -> None:
    cams = totalcapture_ring()
    t = coco17_targets(clip.skeleton)
    uv, conf = simulate_detections(clip, cams, t, DetectionNoise.clean(), np.random.default_rng(0))
    fk = Kinematics(clip.skeleton).forward(clip.theta)
    pts = Kinematics.targets(fk, t.bones, t.offsets)
    exact = np.stack([c.project(pts) for c in cams], axis=1)
    ok = conf > 0
    err = np.linalg.norm(uv - exact, axis=-1)[ok]
    assert ok.mean() > 0.95
    assert np.sqrt(np.mean(err**2)) == pytest.approx(np.sqrt(2.0), rel=0.1)  # σ = 1 px per axis


def test_realistic_detection_rates(clip: Retargeted) -> None:
    cams = totalcapture_ring()
    t = coco17_targets(clip.skeleton)
    noise = DetectionNoise.realistic()
    uv, conf = simulate_detections(clip, cams, t, noise, np.random.default_rng(1))
    no_occ = DetectionNoise(occlusion=False, missed=0.0)
    _, conf_vis = simulate_detections(clip, cams, t, no_occ, np.random.default_rng(1))
    visible = conf_vis > 0
    missed = 1.0 - (conf > 0).sum() / visible.sum()
    assert 0.06 < missed < 0.4  # 5 % random misses plus self-occlusion
    assert np.all(np.isnan(uv[conf == 0]))
    assert np.all((conf >= 0) & (conf <= 1))
    # Confidence falls as the error grows.
    fk = Kinematics(clip.skeleton).forward(clip.theta)
    exact = np.stack([c.project(Kinematics.targets(fk, t.bones, t.offsets)) for c in cams], axis=1)
    err = np.linalg.norm(uv - exact, axis=-1)
    ok = conf > 0
    big = err[ok] > np.percentile(err[ok], 97)
    assert conf[ok][big].mean() < 0.5 * conf[ok][~big].mean()


def test_imu_model(clip: Retargeted) -> None:
    mounts = default_mounts(IMU_SET_13, clip.skeleton)
    fk = Kinematics(clip.skeleton).forward(clip.theta)
    bones = [m.bone_index for m in mounts]
    truth = quat_from_matrix(fk.rotations[:, bones])
    q, acc = simulate_imus(clip, mounts, ImuNoise.clean(), np.random.default_rng(0))
    assert np.max(quat_angle(q, truth)) < 1e-6
    sites = Kinematics.targets(fk, np.array(bones), np.array([m.t_ib for m in mounts]))
    fd = (sites[2:] - 2 * sites[1:-1] + sites[:-2]) * clip.fps**2
    np.testing.assert_allclose(acc[2:], fd, atol=1e-6)
    assert np.all(np.isnan(acc[:2]))
    q2, acc2 = simulate_imus(clip, mounts, ImuNoise(), np.random.default_rng(0))
    ang = np.degrees(quat_angle(q2, truth))
    # 5° RMS calibration error + 1° RMS noise (+ a negligible heading walk over seconds).
    assert 2.0 < np.sqrt(np.mean(ang**2)) < 9.0
    # Acceleration noise 0.2 m/s² per axis plus ~1° of gravity leakage (9.8 sin 1° ≈ 0.17).
    d = acc2[2:] - fd
    assert 0.15 < np.sqrt(np.mean(d**2)) < 0.4
    assert matrix_from_quat(q2).shape == (clip.n_frames, 13, 3, 3)

"""Heading correction from the cameras: per-frame observations, the robust windowed estimator, and the scheduler
correcting simulated per-sensor heading errors (offset + drift) with four cameras, frozen without them."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.heading import (
    HeadingEstimator,
    HeadingOptions,
    bone_vectors,
    observe_headings,
    wrap,
    yaw_quat,
)
from mocapd.core.imu import IMU_SET_13
from mocapd.core.keypoints import coco17_targets, keypoint_format
from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import (
    quat_conjugate,
    quat_from_matrix,
    quat_multiply,
    quat_normalize,
    random_rotvec,
)
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.errors import InputError
from tests.imu_lockstep import SuitLockstep, suit_lockstep

MS = 1_000_000
S_NS = 1_000_000_000


# --------------------------------------------------------------------------------------------- observations
def _posed(seed: int, keypoints: str = "coco17") -> tuple[Skeleton, object, np.ndarray, np.ndarray]:
    """A skeleton in a random pose: its targets, true bone orientations of IMU_SET_13 (13, 4) and keypoints."""
    skeleton = Skeleton.from_height(1.75)
    targets = keypoint_format(keypoints).track_targets(skeleton)
    rng = np.random.default_rng(seed)
    theta = skeleton.rest_pose()
    theta[3:] = random_rotvec(rng, (21,), max_angle=0.7).reshape(-1)
    for toes in ("LeftToes", "RightToes"):  # toe keypoints count as rigid with the foot: exact with flat toes
        theta[3 + 3 * BONE_INDEX[toes] : 6 + 3 * BONE_INDEX[toes]] = 0.0
    kin = Kinematics(skeleton)
    fk = kin.forward(theta)
    q_true = quat_from_matrix(fk.rotations[[BONE_INDEX[b] for b in IMU_SET_13]])
    return skeleton, targets, q_true, kin.targets(fk, targets.bones, targets.offsets)


@pytest.mark.parametrize("keypoints", ["coco17", "halpe26"])
def test_observe_headings_recovers_each_bones_yaw(keypoints: str) -> None:
    skeleton, targets, q_true, points = _posed(3, keypoints)
    vectors = bone_vectors(skeleton, targets, IMU_SET_13)  # type: ignore[arg-type]
    error = np.radians(np.linspace(-60.0, 60.0, 13))
    raw = quat_multiply(yaw_quat(-error), q_true)  # each sensor believes its bone is turned by -error
    ok = np.ones(len(points), dtype=bool)
    yaw, evidence = observe_headings(raw, vectors, points, ok)
    feet = [IMU_SET_13.index("LeftFoot"), IMU_SET_13.index("RightFoot")]
    seen = np.array([v.observable for v in vectors])
    if keypoints == "coco17":  # the ankle is the only foot keypoint: a foot's heading cannot be seen
        assert not seen[feet].any() and seen.sum() == 11
        assert np.all(np.isnan(yaw[feet])) and np.all(evidence[feet] == 0.0)
    else:
        assert seen.all()
    np.testing.assert_allclose(wrap(yaw[seen] - error[seen]), 0.0, atol=1e-9)
    assert np.all(evidence[seen] > 0.0)
    # Keypoints that were not triangulated are left out; a bone with none left is not observed.
    ok[[targets.names.index("left_shoulder"), targets.names.index("left_elbow")]] = False  # type: ignore[attr-defined]
    yaw2, _ = observe_headings(raw, vectors, points, ok)
    assert np.isnan(yaw2[IMU_SET_13.index("LeftUpperArm")])
    np.testing.assert_allclose(wrap(yaw2[0] - error[0]), 0.0, atol=1e-9)


def test_a_vertical_limb_gives_no_evidence() -> None:
    skeleton = Skeleton.from_height(1.75)
    targets = coco17_targets(skeleton)
    kin = Kinematics(skeleton)
    fk = kin.forward(skeleton.rest_pose())  # T-pose: legs vertical, arms horizontal
    points = kin.targets(fk, targets.bones, targets.offsets)
    bones = ("LeftLowerLeg", "LeftUpperArm")
    vectors = bone_vectors(skeleton, targets, bones)
    q = quat_from_matrix(fk.rotations[[BONE_INDEX[b] for b in bones]])
    _, evidence = observe_headings(q, vectors, points, np.ones(len(points), dtype=bool))
    assert evidence[0] < 1e-12 < HeadingOptions().min_evidence_m2 < evidence[1]


# --------------------------------------------------------------------------------------------- estimator
def test_estimator_rejects_outliers_and_follows_at_a_bounded_rate() -> None:
    opts = HeadingOptions(window_s=4.0, min_samples=12, max_rate_deg_s=60.0)
    est = HeadingEstimator(opts)
    rng = np.random.default_rng(1)
    truth = {"A": np.radians(30.0), "B": np.radians(179.0)}  # B sits on the wrap-around
    applied = []
    for k in range(120):  # 6 s at 20 Hz
        t = k * 50 * MS
        yaw = np.array([truth[s] + rng.normal(0.0, np.radians(1.0)) for s in ("A", "B")])
        outlier = rng.random(2) < 0.25  # a quarter of the frames are mismatched keypoints
        yaw[outlier] = rng.uniform(-np.pi, np.pi, outlier.sum())
        est.observe(t, ["A", "B"], wrap(yaw), np.full(2, 0.05))
        applied.append(est.offsets(["A", "B"]))
    steps = np.abs(wrap(np.diff(np.array(applied), axis=0)))
    assert steps.max() <= np.radians(60.0) * 0.05 + 1e-12  # never faster than 60°/s
    final = est.offsets(["A", "B"])
    assert abs(np.degrees(wrap(final[0] - truth["A"]))) < 1.0
    assert abs(np.degrees(wrap(final[1] - truth["B"]))) < 1.0  # not averaged towards 0 across ±180°
    st = est.status()
    assert st["A"]["state"] == "estimating" and st["A"]["rejected"] > 5 and st["A"]["samples"] <= 81


def test_estimator_needs_evidence_and_freezes() -> None:
    est = HeadingEstimator(HeadingOptions(min_samples=3, max_rate_deg_s=1000.0))
    weak = HeadingOptions().min_evidence_m2 / 2
    for k in range(10):
        est.observe(k * 50 * MS, ["A"], np.array([0.5]), np.array([weak]))
    assert est.offsets(["A", "unknown"]).tolist() == [0.0, 0.0] and est.status()["A"]["state"] == "gathering"
    for k in range(10, 20):
        est.observe(k * 50 * MS, ["A"], np.array([0.5]), np.array([0.05]))
    assert est.offsets(["A"])[0] == pytest.approx(0.5)
    est.freeze(["A"])
    assert est.status()["A"]["state"] == "frozen" and est.offsets(["A"])[0] == pytest.approx(0.5)
    # Back in view after a long gap with a different heading: the rate limit counts from the new observation.
    est.observe(100 * S_NS, ["A"], np.array([1.0]), np.array([0.05]))
    assert est.offsets(["A"])[0] == pytest.approx(0.5)
    off = HeadingEstimator(HeadingOptions(enabled=False))
    off.observe(0, ["A"], np.array([0.5]), np.array([1.0]))
    assert off.offsets(["A"]).tolist() == [0.0] and off.status() == {}


BAD_OPTIONS = [{"window_s": 0.0}, {"min_samples": 0}, {"min_views": 1}, {"max_rate_deg_s": float("nan")},
               {"outlier_floor_deg": -1.0}]  # fmt: skip


@pytest.mark.parametrize("kwargs", BAD_OPTIONS)
def test_bad_options_are_rejected(kwargs: dict[str, float]) -> None:
    with pytest.raises(InputError):
        HeadingOptions(**kwargs)  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------- in the rig
def _residual_deg(ls: SuitLockstep, t_ns: int, corrected: bool = True) -> np.ndarray:
    """Per suit sensor: the heading error left (degrees) at ``t_ns`` — the rotation about world up between the
    true bone orientation and the (corrected) calibrated one made from what the simulated device reported."""
    sched, suit = ls.scheduler, ls.scheduler.suits["suit0"]
    fk = ls.world.kin.forward(ls.world.theta_at(0, t_ns / 1e9))
    q_true = quat_from_matrix(fk.rotations[[m.bone_index for m in suit.mounts]])
    q_i = np.array([ls.ingest.streams[s].buffer.sample(t_ns).row[0:4] for s in suit.sensors])
    q_ib = np.array([suit.calibration.q_ib[s] for s in suit.sensors])
    raw = quat_multiply(quat_multiply(suit.calibration.q_ig[None], quat_normalize(q_i)), quat_conjugate(q_ib))
    if corrected:
        raw = quat_multiply(yaw_quat(sched.heading.offsets(suit.sensors)), raw)
    r = quat_multiply(q_true, quat_conjugate(raw))  # a pure rotation about +Y
    return np.asarray(np.degrees(wrap(2.0 * np.arctan2(r[:, 2], r[:, 0]))))


def test_heading_errors_corrected_within_10_s_with_four_cameras_and_frozen_without() -> None:
    """±45° per-sensor heading errors drifting 10°/min: within 3° after 10 s of four cameras for every sensor
    the cameras can observe with COCO-17 (the feet, which they cannot, are left alone); then the cameras lose the
    person: every offset is frozen, and no heading is made worse than the uncorrected one."""
    ls = suit_lockstep(rate_hz=30)
    suit = ls.scheduler.suits["suit0"]
    ls.faults = ls.world.heading_faults(ls.world.suits[0], 45.0, 10.0, seed=1)
    assert max(abs(f.offset_deg) for f in ls.faults.values()) == 45.0
    worst, last = [], 0
    for _ in range(300):  # 10 s at 30 Hz
        last = ls.tick().t_solve_ns
        worst.append(np.abs(_residual_deg(ls, last)))
    status = ls.scheduler.heading_status()["suit0"]
    seen = np.array([status[s]["observable"] for s in suit.sensors])
    assert seen.sum() == 11 and {m.bone for m, v in zip(suit.mounts, seen, strict=True) if not v} == {
        "LeftFoot", "RightFoot"}  # fmt: skip
    final = worst[-1]
    assert final[seen].max() <= 3.0, final
    outside = [k for k, w in enumerate(worst) if w[seen].max() > 3.0]
    raw = np.abs(_residual_deg(ls, last, corrected=False))
    print(f"heading: all 11 observable sensors within 3° from t = {(outside[-1] + 1) / 30:.1f} s on; after 10 s "
          f"the largest error is {final[seen].max():.2f}° (uncorrected: up to {raw.max():.0f}°)")  # fmt: skip
    np.testing.assert_array_equal(ls.scheduler.heading.offsets(suit.sensors)[~seen], 0.0)
    # Only one camera from now on: no triangulation, so nothing is estimated; offsets stay as they were.
    ls.live_cameras = {0}
    ls.run(1.0)
    frozen = ls.scheduler.heading.offsets(suit.sensors)
    for frame in ls.run(3.0):
        np.testing.assert_array_equal(ls.scheduler.heading.offsets(suit.sensors), frozen)
        fixed = np.abs(_residual_deg(ls, frame.t_solve_ns))
        raw = np.abs(_residual_deg(ls, frame.t_solve_ns, corrected=False))
        assert np.all(fixed <= raw + 1e-6)
    assert all(s["state"] == "frozen" for s in ls.scheduler.heading_status()["suit0"].values() if s["observable"])


def test_one_camera_never_changes_a_heading() -> None:
    ls = suit_lockstep(rate_hz=30)
    ls.faults = ls.world.heading_faults(ls.world.suits[0], 45.0, 10.0, seed=2)
    ls.live_cameras = {0}
    frames = ls.run(3.0)
    suit = ls.scheduler.suits["suit0"]
    np.testing.assert_array_equal(ls.scheduler.heading.offsets(suit.sensors), 0.0)
    np.testing.assert_array_equal(_residual_deg(ls, frames[-1].t_solve_ns),
                                  _residual_deg(ls, frames[-1].t_solve_ns, corrected=False))  # fmt: skip


def test_every_sensor_corrected_with_foot_keypoints() -> None:
    """With Halpe-26 (heel and toes) the feet are observable too: all 13 sensors within 3° after 10 s."""
    ls = suit_lockstep(rate_hz=30, keypoints="halpe26")
    ls.faults = ls.world.heading_faults(ls.world.suits[0], 45.0, 10.0, seed=1)
    frames = ls.run(10.0)
    final = np.abs(_residual_deg(ls, frames[-1].t_solve_ns))
    assert final.max() <= 3.0, final
    assert all(s["observable"] for s in ls.scheduler.heading_status()["suit0"].values())

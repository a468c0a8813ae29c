"""The resolve smoother and the export resampling on known signals (the whole resolve runs in
test_session_e2e.py against the synthetic truth)."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import quat_angle, quat_from_rotvec, quat_multiply, rotvec_from_quat
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.core.synthetic import moving_sequence
from mocapd.errors import InputError
from mocapd.io.session_export import SubjectTrack, resample, subject_track
from mocapd.protocols.session_format import PersonRecord, PoseRecord
from mocapd.service.session.solve import ResolveOptions, recorded_instants, rts_smooth, smooth_thetas


def test_rts_smoother_removes_most_of_the_noise_of_a_smooth_signal() -> None:
    rng = np.random.default_rng(0)
    t = np.arange(600) / 60.0
    truth = np.stack([np.sin(1.3 * t), 0.2 * t, np.cos(0.7 * t) ** 2], axis=1)
    z = truth + rng.normal(scale=0.01, size=truth.shape)
    sm = rts_smooth(t, z, np.full(3, 0.01), np.full(3, 5.0))
    assert np.sqrt(np.mean((sm - truth) ** 2)) < 0.5 * np.sqrt(np.mean((z - truth) ** 2))
    assert np.array_equal(rts_smooth(t[:2], z[:2], np.full(3, 0.01), np.full(3, 5.0)), z[:2])


def test_smoothing_poses_keeps_a_clean_motion_and_splits_at_gaps() -> None:
    sk = Skeleton.from_height()
    th = moving_sequence(sk, 240, fps=60.0, seed=2)
    t = (np.arange(240) * 1e9 / 60).astype(np.int64)
    t[120:] += 2_000_000_000  # a 2 s gap: two segments
    sm = smooth_thetas(t, th, ResolveOptions())
    n = th.shape[0]
    err = quat_angle(quat_from_rotvec(sm[:, 3:].reshape(n, 21, 3)), quat_from_rotvec(th[:, 3:].reshape(n, 21, 3)))
    assert np.degrees(err).max() < 1.0 and np.abs(sm[:, :3] - th[:, :3]).max() < 0.003


def test_smoothing_keeps_the_pose_when_the_solve_turns_an_upper_arm_about_itself() -> None:
    """Keypoints fix an upper arm's direction, not its twist: the solve may turn it 150° about its own axis between
    two frames while the forearm's local rotation undoes it (the same pose, every joint where it was). Smoothing the
    local rotations blended the two solutions into a forearm where neither was (``resolve`` below live on the
    waving forearms of ``mocapd eval keypoints``: here the hand 10.8 mm off instead of 5.4 mm); the world rotations
    are smoothed as if the solve had not jumped."""
    sk = Skeleton.from_height()
    kin = Kinematics(sk)
    upper, lower = BONE_INDEX["RightUpperArm"], BONE_INDEX["RightLowerArm"]
    axis = sk.offsets[lower] / np.linalg.norm(sk.offsets[lower])  # the upper arm's own axis (rest pose)
    n = 50
    wave = np.outer(1.2 + 0.8 * np.sin(2 * np.pi * 1.5 * np.arange(n) / 25), [0.0, 0.0, 1.0])  # a waving forearm
    steady = np.zeros((n, 66))
    steady[:, 1] = sk.root_height
    steady[:, 3 + 3 * lower : 6 + 3 * lower] = wave
    jumped = steady.copy()
    twist = np.radians(150.0) * axis
    jumped[25:, 3 + 3 * upper : 6 + 3 * upper] = twist
    undo = quat_multiply(quat_from_rotvec(-twist)[None], quat_from_rotvec(wave[25:]))
    jumped[25:, 3 + 3 * lower : 6 + 3 * lower] = rotvec_from_quat(undo)
    truth = kin.forward(steady).positions
    assert np.abs(kin.forward(jumped).positions - truth).max() < 1e-9  # the same poses
    t = (np.arange(n) * 1e9 / 25).astype(np.int64)
    err_steady = np.abs(kin.forward(smooth_thetas(t, steady, ResolveOptions())).positions - truth).max()
    err_jumped = np.abs(kin.forward(smooth_thetas(t, jumped, ResolveOptions())).positions - truth).max()
    assert err_steady < 0.01 and abs(err_jumped - err_steady) < 1e-3, (err_steady, err_jumped)


def test_a_short_segment_is_left_as_solved() -> None:
    """Shorter than ``min_segment_s`` (a track's first frames, the solve converging from its warm start): no
    velocity to learn, nothing smoothed."""
    rng = np.random.default_rng(1)
    th = rng.normal(scale=0.5, size=(6, 66))
    t = (np.arange(6) * 1e9 / 25).astype(np.int64)
    assert np.array_equal(smooth_thetas(t, th, ResolveOptions()), th)
    assert not np.array_equal(smooth_thetas(t, th, ResolveOptions(min_segment_s=0.1)), th)


def _poses(subject: str, times: list[int], thetas: np.ndarray) -> list[PoseRecord]:
    return [
        PoseRecord(i, t, t, 0, (PersonRecord(subject, None, 1, 4, 0, 3, True, 0.9, thetas[i], np.zeros((21, 3))),))
        for i, t in enumerate(times)
    ]


def test_resampling_fills_missed_ticks_on_a_uniform_grid() -> None:
    sk = Skeleton.from_height()
    th = moving_sequence(sk, 61, fps=60.0, seed=4)
    period = round(1e9 / 60)
    keep = [i for i in range(61) if i % 7 != 3]  # missed ticks
    track = subject_track(_poses("track:1", [i * period for i in keep], th[keep]), None)
    out = resample(track, 60.0)
    assert out.subject == "track:1" and out.thetas.shape == (61, 66)
    assert np.all(np.diff(out.t_ns) == period)
    assert np.allclose(out.thetas[keep], th[keep], atol=1e-9)  # recorded frames unchanged
    q = quat_angle(
        quat_from_rotvec(out.thetas[:, 3:].reshape(61, 21, 3)), quat_from_rotvec(th[:, 3:].reshape(61, 21, 3))
    )
    assert np.degrees(q).max() < 2.0  # interpolated ones close to the motion
    one = SubjectTrack("x", np.array([5]), th[:1])
    assert resample(one) is one
    with pytest.raises(InputError):
        subject_track(_poses("track:1", [0], th[:1]), "track:9")
    with pytest.raises(InputError):
        subject_track([], None)


def test_resolve_follows_the_recorded_instants_and_fills_the_missed_ticks() -> None:
    period = round(1e9 / 60)
    # A live "auto" latency coming down by 0.3 ms a tick: the instants drift off any grid from the first one.
    live = np.array([i * period - 300_000 * i for i in range(40) if i not in (10, 11, 12, 25)], dtype=np.int64)
    t = recorded_instants(live[::-1], period)
    assert set(live.tolist()) <= set(t.tolist()) and np.all(np.diff(t) > 0)
    assert np.diff(t).max() <= 1.5 * period and t.size == 40  # the four missed ticks filled, nothing else
    assert recorded_instants(live[:1], period).tolist() == live[:1].tolist()

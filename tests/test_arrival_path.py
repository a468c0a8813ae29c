"""A keypoint set's path onto the event loop (issue 39): the scheduler files it with its undistorted copy, the
detection delay in the histogram. Made cheaper, with the same results as the old code (kept here as the oracle)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mocapd.core.camera import Camera
from mocapd.core.people import PeopleTracker
from mocapd.core.sorting import Detections2D, DetectionSorter
from mocapd.core.suit_binding import SuitBinder
from mocapd.core.tracking import SubjectTracker, TrackingOptions
from mocapd.errors import InputError
from mocapd.pipeline.latency import BUCKETS_MS, LatencyStats
from mocapd.pipeline.scheduler import FixedLatencyScheduler
from mocapd.sim.world import SyntheticWorld

MS = 1_000_000


def _distorting_scheduler() -> tuple[FixedLatencyScheduler, SyntheticWorld]:
    """The synthetic ring of cameras with real lens distortion (the world's cameras have none)."""
    world = SyntheticWorld(4, 2, 0, seed=3)
    cameras = [
        dataclasses.replace(c, dist=np.array([-0.21, 0.08, 0.0012, -0.0007, -0.012]) * (1 + 0.1 * i))
        for i, c in enumerate(world.cameras)
    ]
    tracker = PeopleTracker(SubjectTracker(DetectionSorter(cameras), TrackingOptions()),
                            SuitBinder(world.skeleton, names=world.targets.names))  # fmt: skip
    return FixedLatencyScheduler(cameras, world.skeleton, world.targets, tracker), world


def old_undistort(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """``FixedLatencyScheduler._undistort`` before issue 39, verbatim."""
    und = camera.undistort_points(np.nan_to_num(uv))
    return np.where(np.isfinite(uv), und, np.nan)


def test_a_filed_set_carries_the_old_undistorted_copy_bit_for_bit() -> None:
    sched, world = _distorting_scheduler()
    rng = np.random.default_rng(0)
    t = 10**12
    for k in range(60):
        for c in range(4):
            dets = world.detections(c, k / 30, rng)
            if k % 3 == 1 and len(dets):  # some sets with unseen keypoints as NaN (one coordinate or both)
                kp = dets.keypoints.copy()
                kp[0, 3] = np.nan
                kp[0, 5, 1] = np.nan
                kp[-1, 7, 0] = np.inf
                dets = Detections2D(kp, dets.confidences)
            t += 8 * MS
            assert sched.add_detections(c, t, dets, t + 30 * MS)
            filed = sched.timelines[c].frames()[1][-1]
            if not len(dets):
                assert filed is dets
                continue
            assert filed.keypoints is dets.keypoints and filed.confidences is dets.confidences
            assert filed.undistorted is not None
            expected = old_undistort(sched.cameras[c], dets.keypoints)
            assert filed.undistorted.tobytes() == expected.tobytes()
            assert filed == dataclasses.replace(dets, undistorted=filed.undistorted)


def test_with_undistorted_checks_the_shape() -> None:
    dets = Detections2D(np.zeros((2, 17, 2)), np.ones((2, 17)))
    with pytest.raises(InputError, match="undistorted"):
        dets.with_undistorted(np.zeros((1, 17, 2)))
    und = np.ones((2, 17, 2))
    out = dets.with_undistorted(und)
    assert out.undistorted is und and out.keypoints is dets.keypoints and dets.undistorted is None


def test_the_histogram_buckets_as_searchsorted_did() -> None:
    """``LatencyStats.add`` bisects a list of the bounds; the old code searched a float array ("left" side)."""
    bounds = np.array([b * 1e6 for b in BUCKETS_MS])
    values = [-5, 0, 1, 10**15, *(int(b) + d for b in bounds for d in (-1, 0, 1)), *range(0, 3 * 10**9, 7_777_777)]
    s = LatencyStats(window=16)
    expected = np.zeros(len(BUCKETS_MS) + 1, dtype=np.int64)
    for v in values:
        s.add(v)
        expected[int(np.searchsorted(bounds, v, side="left"))] += 1
    assert np.array_equal(s.bucket_counts, expected)

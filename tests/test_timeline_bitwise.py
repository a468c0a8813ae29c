"""A timeline's people between two frames, blended for every matched pair at once (issue 39), are the floats the
pair-by-pair loop gave (kept here verbatim as the oracle)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core.sorting import Detections2D
from mocapd.pipeline.keypoint_timeline import DetectionTimeline, SampleStatus, interpolate_people, match_people

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
MS = 1_000_000


def _blend(pa: FloatArray, pb: FloatArray, both: BoolArray, in_a: BoolArray, alpha: float) -> FloatArray:
    """``keypoint_timeline._blend`` before issue 39, verbatim."""
    out: FloatArray = np.where(both[:, None], pa + alpha * (pb - pa), np.where(in_a[:, None], pa, pb))
    return out


def old_interpolate_people(
    a: Detections2D, b: Detections2D, alpha: float, match_px: float, *, pairs: list[tuple[int, int]] | None = None
) -> Detections2D:
    """``interpolate_people`` before issue 39, verbatim."""
    near = a if alpha <= 0.5 else b
    if pairs is None:
        pairs = match_people(a, b, match_px)
    with_und = a.undistorted is not None and b.undistorted is not None
    kps: list[FloatArray] = []
    cfs: list[FloatArray] = []
    unds: list[FloatArray] = []
    for i, j in pairs:
        ca, cb = a.confidences[i], b.confidences[j]
        both = (ca > 0) & (cb > 0)
        kps.append(_blend(a.keypoints[i], b.keypoints[j], both, ca > 0, alpha))
        cfs.append(np.where(both, ca + alpha * (cb - ca), np.where(ca > 0, ca * (1.0 - alpha), cb * alpha)))
        if with_und:
            assert a.undistorted is not None and b.undistorted is not None
            unds.append(_blend(a.undistorted[i], b.undistorted[j], both, ca > 0, alpha))
    matched_near = {i for i, _ in pairs} if near is a else {j for _, j in pairs}
    for p in range(near.keypoints.shape[0]):
        if p not in matched_near:
            kps.append(near.keypoints[p])
            cfs.append(near.confidences[p])
            if with_und:
                assert near.undistorted is not None
                unds.append(near.undistorted[p])
    n_kp = a.keypoints.shape[1]
    if not kps:
        return Detections2D.empty(n_kp)
    return Detections2D(np.stack(kps), np.stack(cfs), np.stack(unds) if with_und else None)


def _same(new: Detections2D, old: Detections2D) -> None:
    for x, y in ((new.keypoints, old.keypoints), (new.confidences, old.confidences)):
        assert x.shape == y.shape and x.dtype == y.dtype and x.tobytes() == y.tobytes()
    assert (new.undistorted is None) == (old.undistorted is None)
    if new.undistorted is not None and old.undistorted is not None:
        assert new.undistorted.shape == old.undistorted.shape
        assert new.undistorted.tobytes() == old.undistorted.tobytes()


def _frame(rng: np.random.Generator, base: FloatArray, undistorted: bool) -> Detections2D:
    n = int(rng.integers(0, 5))
    n_kp = base.shape[1]
    kp = base[rng.integers(0, len(base), n)] + rng.normal(0.0, rng.choice([3.0, 60.0]), (n, n_kp, 2))
    cf = np.where(rng.random((n, n_kp)) < 0.8, rng.uniform(0.05, 1.0, (n, n_kp)), 0.0)
    und = kp * 0.97 + 4.0 if undistorted else None
    return Detections2D(kp, cf, und)


def test_blended_people_are_the_old_floats() -> None:
    rng = np.random.default_rng(11)
    for n_kp in (17, 133):
        base = rng.uniform(0.0, 1500.0, (3, n_kp, 2))
        for _ in range(300):
            und = bool(rng.random() < 0.7)
            a, b = _frame(rng, base, und), _frame(rng, base, und and rng.random() < 0.9)
            pairs = match_people(a, b, 80.0)
            for alpha in (0.0, 0.25, 0.5, 0.5000001, 0.9, 1.0, float(rng.random())):
                _same(interpolate_people(a, b, alpha, 80.0, pairs=pairs), old_interpolate_people(a, b, alpha, 80.0))
                _same(interpolate_people(a, b, alpha, 20.0), old_interpolate_people(a, b, alpha, 20.0))


def test_a_timeline_samples_the_old_people() -> None:
    """Through the timeline, as the tick samples it: 60 Hz look-ups between 30 Hz frames of two people."""
    rng = np.random.default_rng(2)
    base = rng.uniform(0.0, 1500.0, (2, 17, 2))
    tl = DetectionTimeline(17)
    frames = []
    for k in range(40):
        walk = base + k * np.array([3.0, -2.0])
        kp = walk + rng.normal(0.0, 1.0, walk.shape)
        cf = np.where(rng.random((2, 17)) < 0.9, 0.8, 0.0)
        d = Detections2D(kp[::-1] if k % 2 else kp, cf, kp + 1.0)
        frames.append((k * 33 * MS, d))
        tl.push(k * 33 * MS, d)
    for t in range(0, 39 * 33 * MS, 16 * MS + 666_667):
        s = tl.sample(t)
        k = t // (33 * MS)
        if s.status is SampleStatus.INTERPOLATED:
            (t0, a), (t1, b) = frames[k], frames[k + 1]
            _same(s.detections, old_interpolate_people(a, b, (t - t0) / (t1 - t0), 80.0))
        else:
            assert s.status is SampleStatus.EXACT and s.detections is frames[k][1]
    late = tl.sample(45 * 33 * MS)  # past the newest frame by more than max_age: nobody
    assert late.status is SampleStatus.STALE and len(late.detections) == 0

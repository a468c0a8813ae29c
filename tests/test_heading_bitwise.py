"""The heading observation of every sensor at once (the daemon's event loop observes a suit's 13 sensors 20 times a
second): the same yaw and evidence floats, to the bit, as one bone at a time did. The old code is kept here,
verbatim, as the reference."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pytest

from mocapd.core.heading import BoneVectors, bone_vectors, observe_headings, yaw_quat
from mocapd.core.imu import IMU_SET_13
from mocapd.core.rotations import quat_multiply, quat_rotate
from tests.test_heading import _posed


def _old_observe_headings(
    q_gb: np.ndarray, vectors: Sequence[BoneVectors], points: np.ndarray, ok: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    n = len(vectors)
    yaw = np.full(n, np.nan)
    evidence = np.zeros(n)
    for k, bv in enumerate(vectors):
        use = ok[bv.first] & ok[bv.second]
        if not use.any() or not np.all(np.isfinite(q_gb[k])):
            continue
        a = quat_rotate(q_gb[k][None], bv.vectors[use])
        o = points[bv.second[use]] - points[bv.first[use]]
        c = float(np.sum(a[:, 0] * o[:, 0] + a[:, 2] * o[:, 2]))
        s = float(np.sum(a[:, 2] * o[:, 0] - a[:, 0] * o[:, 2]))
        evidence[k] = np.hypot(c, s)
        yaw[k] = np.arctan2(s, c)
    return yaw, evidence


@pytest.mark.parametrize("keypoints", ["coco17", "halpe26"])
def test_every_sensor_at_once_gives_what_one_bone_at_a_time_gave(keypoints: str) -> None:
    """Posed bodies with noisy keypoints, keypoints not triangulated, sensors missing (NaN orientations), subsets
    and orders of the sensors as the scheduler passes them (the measured ones)."""
    rng = np.random.default_rng(0)
    compared = 0
    for seed in range(40):
        skeleton, targets, q_true, points = _posed(seed, keypoints)
        vectors = bone_vectors(skeleton, targets, IMU_SET_13)  # type: ignore[arg-type]
        for _ in range(10):
            raw = quat_multiply(yaw_quat(rng.uniform(-np.pi, np.pi, 13)), q_true)
            raw[rng.random(13) < 0.1] = np.nan
            noisy = points + rng.normal(0.0, 0.02, points.shape)
            ok = rng.random(len(points)) > 0.15
            idx = np.flatnonzero(rng.random(13) > 0.2)
            got = observe_headings(raw[idx], [vectors[i] for i in idx], noisy, ok)
            want = _old_observe_headings(raw[idx], [vectors[i] for i in idx], noisy, ok)
            assert got[0].tobytes() == want[0].tobytes() and got[1].tobytes() == want[1].tobytes()
            compared += int(np.isfinite(want[0]).sum())
    assert compared > 2000


def test_many_pairs_on_one_bone_sum_as_before() -> None:
    """Bones with 1 to 40 pairs (np.sum's pairwise blocks start at 8): the same sums."""
    rng = np.random.default_rng(1)
    for _ in range(300):
        n = int(rng.integers(1, 6))
        n_kp = 60
        vectors = []
        for k in range(n):
            m = int(rng.integers(0, 41))
            vectors.append(
                BoneVectors(f"b{k}", rng.integers(0, n_kp, m), rng.integers(0, n_kp, m), rng.normal(size=(m, 3)))
            )
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        points = rng.normal(size=(n_kp, 3))
        ok = rng.random(n_kp) > 0.1
        got, want = observe_headings(q, vectors, points, ok), _old_observe_headings(q, vectors, points, ok)
        assert got[0].tobytes() == want[0].tobytes() and got[1].tobytes() == want[1].tobytes()

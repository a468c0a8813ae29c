"""Metrics of ``mocapd eval video`` beside the held-out-view error (:mod:`mocapd.eval.heldout`): jitter, bone-length
stability, people (identity switches, frames, bystanders) and left/right flips accepted. Pure numpy/scipy.

All take a system's per-identity 3D keypoints (n_frames, n_kp, 3), NaN where the identity was not solved, and the
cameras' detections. How a system's people are tied to the detections of a camera is the held-out metric's
matching (projection, Hungarian, gate), so no system's own association is trusted by the metrics.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from mocapd.core.camera import Camera
from mocapd.core.lr_flips import COCO17_LR_PAIRS, FlipOptions, choose_swaps, undistorted
from mocapd.core.sorting import Detections2D
from mocapd.eval.heldout import COCO17_COMPARED, held_out_errors
from mocapd.pipeline.keypoint_timeline import person_distances

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

COCO17_BONES: dict[str, tuple[int, int]] = {
    "left_upper_arm": (5, 7),
    "right_upper_arm": (6, 8),
    "left_forearm": (7, 9),
    "right_forearm": (8, 10),
    "left_thigh": (11, 13),
    "right_thigh": (12, 14),
    "left_shank": (13, 15),
    "right_shank": (14, 16),
    "shoulder_width": (5, 6),
    "hip_width": (11, 12),
}
"""Segments between COCO-17 keypoints whose length a rigid body keeps."""


def accelerations(points: FloatArray, fps: float, keypoints: Sequence[int] = COCO17_COMPARED) -> FloatArray:
    """Acceleration magnitudes (m/s²) of each keypoint by central second differences, over every three consecutive
    frames where it is known; shape (n, ) flattened over frames and keypoints."""
    p = np.asarray(points, dtype=np.float64)[:, list(keypoints)]
    if p.shape[0] < 3:
        return np.zeros(0)
    a = (p[2:] - 2.0 * p[1:-1] + p[:-2]) * fps * fps
    m = np.linalg.norm(a, axis=-1)
    out: FloatArray = m[np.isfinite(m)]
    return out


def jitter(people: Sequence[FloatArray], fps: float, keypoints: Sequence[int] = COCO17_COMPARED) -> dict[str, float]:
    """Median and 90th percentile of the joint acceleration magnitude (m/s²) over all people, frames, keypoints."""
    acc = [accelerations(p, fps, keypoints) for p in people]
    v = np.concatenate(acc) if acc else np.zeros(0)
    if v.size == 0:
        return {"median": float("nan"), "p90": float("nan"), "n": 0}
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "n": int(v.size)}


def bone_lengths(points: FloatArray, bones: dict[str, tuple[int, int]] = COCO17_BONES) -> dict[str, FloatArray]:
    """Per bone: its length (m) in every frame where both ends are known."""
    p = np.asarray(points, dtype=np.float64)
    out = {}
    for name, (a, b) in bones.items():
        d = np.linalg.norm(p[:, a] - p[:, b], axis=-1)
        out[name] = d[np.isfinite(d)]
    return out


def bone_cv(people: Sequence[FloatArray], bones: dict[str, tuple[int, int]] = COCO17_BONES) -> dict[str, float]:
    """Coefficient of variation (std / mean) of each bone's length over the take, per person, then the median over
    people; ``median`` is the median over bones (NaN where a bone was never seen)."""
    per: dict[str, list[float]] = {b: [] for b in bones}
    for p in people:
        for name, v in bone_lengths(p, bones).items():
            if v.size >= 3 and v.mean() > 0:
                per[name].append(float(v.std() / v.mean()))
    out = {name: float(np.median(v)) if v else float("nan") for name, v in per.items()}
    finite = [v for v in out.values() if np.isfinite(v)]
    out["median"] = float(np.median(finite)) if finite else float("nan")
    return out


def track_2d(detections: Sequence[Detections2D], max_step: float = 0.5, min_confidence: float = 0.3) -> list[IntArray]:
    """People followed frame to frame in one camera (the reference the identity metric compares against).

    Consecutive frames' people are paired by an optimal assignment on their mean keypoint distance, accepted below
    ``max_step`` × the person's size (at video rates a person moves a few percent of their size per frame); an
    unpaired person starts a new track. Returns per frame the track id of each detection.
    """
    ids: list[IntArray] = []
    next_id = 0
    prev: Detections2D | None = None
    for det in detections:
        cur = np.full(len(det), -1, dtype=np.int64)
        if prev is not None and len(prev) and len(det):
            d = person_distances(prev, det, min_confidence)
            size = np.array([_size(det, i, min_confidence) for i in range(len(det))])
            ok = np.isfinite(d) & (d < max_step * np.maximum(size, 1.0)[None, :])
            rows, cols = linear_sum_assignment(np.where(ok, d, 1e12))
            for i, j in zip(rows, cols, strict=True):
                if ok[i, j]:
                    cur[j] = ids[-1][i]
        for j in np.flatnonzero(cur < 0):
            cur[j] = next_id
            next_id += 1
        ids.append(cur)
        prev = det
    return ids


def _size(det: Detections2D, i: int, min_confidence: float) -> float:
    ok = det.confidences[i] >= min_confidence
    if np.count_nonzero(ok) < 2:
        return 0.0
    return float(np.ptp(det.keypoints[i][ok], axis=0).max())


def matched_detections(
    cameras: Sequence[Camera], detections: Sequence[Sequence[Detections2D]], people: Sequence[FloatArray]
) -> IntArray:
    """Which detection of each camera each person projects onto, per frame: (n_frames, n_people, n_cams), -1 none
    (the held-out metric's matching, on the cameras the people were solved with)."""
    n_frames = len(detections)
    out = np.full((n_frames, len(people), len(cameras)), -1, dtype=np.int64)
    if not people:
        return out
    pts = np.stack(people, axis=1)
    for c, cam in enumerate(cameras):
        out[:, :, c] = held_out_errors(cam, [row[c] for row in detections], pts).matched
    return out


def identity_switches(matched: IntArray, tracks: Sequence[Sequence[IntArray]]) -> list[int]:
    """Per person: the frames at which it jumped to another person.

    ``matched`` (n_frames, n_people, n_cams) from :func:`matched_detections`, ``tracks[c][f]`` the 2D track ids of
    camera ``c`` (:func:`track_2d`). In a camera, a person switches when the 2D track it projects onto changes while
    the previous track is still there (a track that ended and another that began is the same person re-found, not a
    switch); a frame counts as an identity switch when more than half of the cameras that saw the person in both
    frames switched.
    """
    n_frames, n_people, n_cams = matched.shape
    out = [0] * n_people
    for p in range(n_people):
        for f in range(1, n_frames):
            both = switched = 0
            for c in range(n_cams):
                a, b = matched[f - 1, p, c], matched[f, p, c]
                if a < 0 or b < 0:
                    continue
                both += 1
                ta, tb = tracks[c][f - 1][a], tracks[c][f][b]
                if ta != tb and ta in set(tracks[c][f].tolist()):
                    switched += 1
            if both and switched * 2 > both:
                out[p] += 1
    return out


def accepted_flips(
    cameras: Sequence[Camera],
    detections: Sequence[Sequence[Detections2D]],
    people: Sequence[FloatArray],
    matched: IntArray,
    pairs: tuple[tuple[int, int], ...] = COCO17_LR_PAIRS,
    min_confidence: float = 0.5,
) -> tuple[IntArray, IntArray]:
    """Left/right flips per camera: found, and accepted into the solution.

    A camera's detection of a person is flipped for a keypoint pair when the views that see the person agree on it
    better with that camera's two labels exchanged (:func:`mocapd.core.lr_flips.choose_swaps` on the detections the
    person projects onto, the labelling that swaps fewer views taken as right). The flip is accepted when the
    person's solution, projected into that camera, sits nearer the detected (flipped) labels than the exchanged
    ones. Returns (found, accepted), each of shape (n_cams,), summed over frames, people and pairs.
    """
    n_cams = len(cameras)
    found = np.zeros(n_cams, dtype=np.int64)
    accepted = np.zeros(n_cams, dtype=np.int64)
    opts = FlipOptions(min_confidence=min_confidence)
    for p, pts in enumerate(people):
        for f in range(len(detections)):
            m = matched[f, p]
            if np.count_nonzero(m >= 0) < 3:
                continue  # two views cannot say which of them is flipped
            n_kp = pts.shape[1]
            kp = np.zeros((n_cams, n_kp, 2))
            cf = np.zeros((n_cams, n_kp))
            for c in np.flatnonzero(m >= 0).tolist():
                kp[c] = detections[f][c].keypoints[m[c]]
                cf[c] = detections[f][c].confidences[m[c]]
            P, und = undistorted(list(cameras), kp)
            dec = choose_swaps(P, und, cf, pairs, None, opts)
            for c, q in np.argwhere(dec.swaps).tolist():
                left, right = pairs[q]
                if min(cf[c, left], cf[c, right]) < min_confidence:
                    continue  # one label only: nothing to say on which side the solution took
                found[c] += 1
                uv = cameras[c].project(pts[f][[left, right]])
                if not np.all(np.isfinite(uv)):
                    continue
                straight = np.linalg.norm(uv - kp[c, [left, right]], axis=-1).sum()
                crossed = np.linalg.norm(uv - kp[c, [right, left]], axis=-1).sum()
                if straight < crossed:
                    accepted[c] += 1
    return found, accepted

"""Held-out-view error: how far a 3D reconstruction made *without* a camera lands from that camera's own detections.

For real footage there is no ground truth, but there is a view no system has seen: solve or triangulate with every
camera but ``k``, project the result into ``k`` and compare it with ``k``'s confident detections. The detector's
own error in ``k`` is in the number too (it is the floor every system shares), so the metric ranks systems on the
same detections rather than measuring absolute accuracy.

Pure functions (numpy, scipy): the detections of the held-out camera per frame, its calibration and the 3D
keypoints each system gave per frame and person. Which detection of camera ``k`` is which of the system's people
is decided here, the same way for every system: per frame, an optimal assignment (Hungarian) on the median pixel
distance over the keypoints confident in the detection and projected from the person, accepted when that median is
below ``max_match`` × the detection's height (a person projected further away is not compared at all, and the
result says how many were: :attr:`HeldOutErrors.compared`).

Used by ``mocapd eval video`` (docs/accuracy-video.md); written to judge keypoint tracking between detections and
learned fusion too, which give 3D keypoints per frame the same way.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from mocapd.core.camera import Camera
from mocapd.core.sorting import Detections2D
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

COCO17_GROUPS: dict[str, tuple[int, ...]] = {
    "head": (0,),
    "shoulders": (5, 6),
    "elbows": (7, 8),
    "wrists": (9, 10),
    "hips": (11, 12),
    "knees": (13, 14),
    "ankles": (15, 16),
}
"""Joint groups of COCO-17 (the keypoints every evaluated system estimates: nose, shoulders, elbows, wrists, hips,
knees, ankles; eyes and ears are left out because Pose2Sim's COCO-17 model does not triangulate them)."""

COCO17_COMPARED: tuple[int, ...] = tuple(i for g in COCO17_GROUPS.values() for i in g)


@dataclass(frozen=True)
class HeldOutErrors:
    """Per frame and person: the pixel error of each keypoint in the held-out view.

    Attributes
    ----------
    errors : array, shape (n_frames, n_people, n_kp)
        Distance (px) between the projection and the detection; NaN where not compared (person not matched,
        keypoint not confident, not estimated or behind the camera).
    matched : int array, shape (n_frames, n_people)
        Index of the held-out camera's detection each person was matched to, -1 for none.
    """

    errors: FloatArray
    matched: IntArray

    @property
    def compared(self) -> int:
        """Keypoints compared."""
        return int(np.count_nonzero(np.isfinite(self.errors)))


def _height(det: Detections2D, i: int, min_confidence: float) -> float:
    ok = det.confidences[i] >= min_confidence
    if np.count_nonzero(ok) < 2:
        return 0.0
    y = det.keypoints[i][ok, 1]
    x = det.keypoints[i][ok, 0]
    return float(max(np.ptp(y), np.ptp(x)))


def held_out_errors(
    camera: Camera,
    detections: Sequence[Detections2D],
    points: FloatArray,
    min_confidence: float = 0.5,
    max_match: float = 0.5,
    min_keypoints: int = 3,
) -> HeldOutErrors:
    """The held-out-view errors of one system in one camera.

    Parameters
    ----------
    camera : Camera
        The held-out camera (which the system did not use).
    detections : sequence of n_frames Detections2D
        That camera's detections per frame.
    points : array, shape (n_frames, n_people, n_kp, 3)
        The system's 3D keypoints (world), in the detector's keypoint order; NaN where it has none.
    min_confidence : float
        Only detected keypoints of at least this confidence are compared (and define a detection's height).
    max_match : float
        A person is matched to a detection only when the median distance is below this × the detection's height.
    min_keypoints : int
        Keypoints a person and a detection must share to be matched.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 4 or pts.shape[-1] != 3 or pts.shape[0] != len(detections):
        raise InputError(f"points must be (n_frames={len(detections)}, n_people, n_kp, 3), got {pts.shape}")
    n_frames, n_people, n_kp, _ = pts.shape
    errors = np.full((n_frames, n_people, n_kp), np.nan)
    matched = np.full((n_frames, n_people), -1, dtype=np.int64)
    for f, det in enumerate(detections):
        if len(det) == 0 or n_people == 0:
            continue
        if det.keypoints.shape[1] != n_kp:
            raise InputError(f"frame {f}: detections have {det.keypoints.shape[1]} keypoints, points {n_kp}")
        uv = camera.project(pts[f].reshape(-1, 3)).reshape(n_people, n_kp, 2)  # NaN behind the camera / missing
        d = np.linalg.norm(uv[:, None] - det.keypoints[None], axis=-1)  # (people, detections, kp)
        conf = det.confidences[None] >= min_confidence
        usable = conf & np.isfinite(d)
        count = usable.sum(axis=-1)
        with warnings.catch_warnings():  # people sharing no keypoint with a detection: all-NaN rows, inf below
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.where(count >= min_keypoints, np.nanmedian(np.where(usable, d, np.nan), axis=-1), np.inf)
        heights = np.array([_height(det, i, min_confidence) for i in range(len(det))])
        gate = med < max_match * heights[None, :]
        if not np.any(gate):
            continue
        rows, cols = linear_sum_assignment(np.where(gate, med, 1e12))
        for p, i in zip(rows, cols, strict=True):
            if gate[p, i]:
                matched[f, p] = i
                errors[f, p] = np.where(usable[p, i], d[p, i], np.nan)
    return HeldOutErrors(errors, matched)


def summarize(
    errors: FloatArray, groups: Mapping[str, Sequence[int]] = COCO17_GROUPS, keypoints: Sequence[int] | None = None
) -> dict[str, dict[str, float]]:
    """Median and 90th percentile (px) and count of held-out errors per joint group and over ``keypoints`` (the
    groups' keypoints by default) as ``"all"``; errors of shape (..., n_kp), NaN ignored."""
    e = np.asarray(errors, dtype=np.float64)
    sel = [i for g in groups.values() for i in g] if keypoints is None else list(keypoints)
    out: dict[str, dict[str, float]] = {}
    for name, idx in [("all", sel), *groups.items()]:
        v = e[..., list(idx)]
        v = v[np.isfinite(v)]
        out[name] = (
            {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "n": int(v.size)}
            if v.size
            else {"median": float("nan"), "p90": float("nan"), "n": 0}
        )
    return out


@dataclass(frozen=True)
class Difference:
    """A quantile of one system's held-out errors minus the same quantile of another's, with its uncertainty."""

    value: float
    """``quantile(other) - quantile(base)`` (px) over the keypoints both were compared on."""
    low: float
    """Lower end of the 95 % interval (px): frames resampled with replacement."""
    high: float
    """Upper end (px)."""
    n: int
    """Keypoints compared."""

    @property
    def worse(self) -> bool:
        """``other`` is worse than ``base`` beyond the frames' own scatter (the whole interval above zero)."""
        return self.low > 0.0


def quantile_difference(
    base: FloatArray, other: FloatArray, q: float = 50.0, n_boot: int = 1000, seed: int = 0
) -> Difference:
    """How much ``other``'s ``q``-th percentile held-out error differs from ``base``'s, and whether it is more than
    the take's frames let one tell apart.

    Both are compared on the keypoints both were compared on. The interval resamples whole *frames* (with
    replacement, the same frames for both systems), not keypoints: the keypoints of one frame share its pose, its
    detections and its solve, so they are not independent, and a keypoint bootstrap would call a difference made by
    a few frames certain. On the Pose2Sim demos (100 frames) a median moves by ±1-1.5 px between resamples, so a
    0.3 px difference of two medians says nothing by itself (docs/accuracy-video.md).

    Parameters
    ----------
    base, other : array, shape (n_frames, ...)
        Held-out errors (px), NaN where not compared; the first axis is the frame.
    q : float
        Percentile (50: the median, 90: the p90).
    n_boot : int
        Resamples.
    seed : int

    Returns
    -------
    Difference
    """
    a = np.asarray(base, dtype=np.float64)
    b = np.asarray(other, dtype=np.float64)
    if a.shape != b.shape or a.ndim < 1:
        raise InputError(f"quantile_difference: shapes {a.shape} and {b.shape} differ (or no frame axis)")
    both = np.isfinite(a) & np.isfinite(b)
    n = int(np.count_nonzero(both))
    if n == 0:
        nan = float("nan")
        return Difference(nan, nan, nan, 0)
    a2, b2, m2 = a.reshape(a.shape[0], -1), b.reshape(b.shape[0], -1), both.reshape(both.shape[0], -1)

    def diff(frames: IntArray) -> float:
        m = m2[frames]
        if not m.any():
            return float("nan")
        return float(np.percentile(b2[frames][m], q) - np.percentile(a2[frames][m], q))

    frames = np.flatnonzero(m2.any(axis=1))
    rng = np.random.default_rng(seed)
    boot = np.array([diff(rng.choice(frames, frames.size)) for _ in range(n_boot)])
    low, high = np.nanpercentile(boot, [2.5, 97.5])
    return Difference(diff(frames), float(low), float(high), n)


@dataclass(frozen=True)
class CameraOffsets:
    """The part of held-out errors that is one constant image shift per camera, and what is left without it.

    A calibration's error (a camera turned or its principal point off by a fraction of a degree), or a camera whose
    exposures lag the others' while the subject moves steadily, moves *every* keypoint the other views predict in
    that camera by about the same pixels; a keypoint model's own cross-view disagreement does not (its bias turns
    with the view of the body part). Splitting the two tells a footage floor from a model's error.

    Attributes
    ----------
    mean : array, shape (n_cameras, 2)
        Per held-out camera, the mean signed error (detected - predicted, px); NaN for a camera with none.
    median : array, shape (n_cameras,)
        Per camera, the median error (px).
    median_less_mean : array, shape (n_cameras,)
        Per camera, the median of ``|error - mean|`` (px): the error were that camera's constant shift removed.
    """

    mean: FloatArray
    median: FloatArray
    median_less_mean: FloatArray

    def less_mean(self, signed: FloatArray, cameras: IntArray) -> FloatArray:
        """``|signed - mean[camera]|`` per error (px): ``signed`` (n, ..., 2), ``cameras`` (n,); NaN kept."""
        s = np.asarray(signed, dtype=np.float64)
        shift = self.mean[np.asarray(cameras)].reshape((len(s),) + (1,) * (s.ndim - 2) + (2,))
        return np.asarray(np.linalg.norm(s - shift, axis=-1), dtype=np.float64)


def camera_offsets(signed: FloatArray, cameras: IntArray, n_cameras: int) -> CameraOffsets:
    """Each held-out camera's constant shift of the held-out errors (:class:`CameraOffsets`).

    Parameters
    ----------
    signed : array, shape (n, ..., 2)
        Signed held-out errors (detected - predicted, px), any number of keypoints per row; NaN where not compared.
    cameras : int array, shape (n,)
        The held-out camera of each row, in ``0 .. n_cameras - 1``.
    n_cameras : int
    """
    s = np.asarray(signed, dtype=np.float64)
    cams = np.asarray(cameras, dtype=np.int64)
    if s.ndim < 2 or s.shape[-1] != 2 or cams.shape != (len(s),):
        raise InputError(f"signed errors must be (n, ..., 2) with one camera per row, got {s.shape}, {cams.shape}")
    if len(cams) and not (cams.min() >= 0 and cams.max() < n_cameras):
        raise InputError(f"camera indices must be in 0..{n_cameras - 1}")
    mean = np.full((n_cameras, 2), np.nan)
    median = np.full(n_cameras, np.nan)
    less = np.full(n_cameras, np.nan)
    for k in range(n_cameras):
        v = s[cams == k].reshape(-1, 2)
        v = v[np.isfinite(v).all(axis=1)]
        if len(v):
            mean[k] = v.mean(axis=0)
            median[k] = np.median(np.linalg.norm(v, axis=1))
            less[k] = np.median(np.linalg.norm(v - mean[k], axis=1))
    return CameraOffsets(mean, median, less)

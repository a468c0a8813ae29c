"""Each IMU's heading offset, estimated from the cameras: the rotation about world up between a sensor's calibrated
bone orientation and the orientation the cameras observe (pure: time is an argument).

A magnetometer-aided IMU knows "up" from gravity well, but its heading (yaw about the vertical) from the magnetic
field, which iron in floors, furniture and the body's own equipment bends by tens of degrees, and which a
magnetometer-free IMU (SlimeVR) only integrates, so it drifts. Cameras see where limbs point. For every bone that
carries a sensor, the keypoints *rigidly attached to it* (see :func:`bone_vectors`) give vectors whose
coordinates in the bone's frame are known; the sensor's calibrated orientation ``R_gb`` predicts them in the world
(``a = R_gb v``); the triangulated keypoints observe them (``o``). The heading offset is the rotation ``ψ`` about
+Y that best maps the predicted vectors onto the observed ones (Wahba's problem restricted to one axis, closed
form)::

    maximise Σ o · R_y(ψ) a  =  cos ψ · c + sin ψ · s + const,
    c = Σ a_x o_x + a_z o_z,   s = Σ a_z o_x - a_x o_z      →   ψ = atan2(s, c)

``hypot(c, s)`` (m²: the summed products of the vectors' horizontal lengths) is the frame's evidence: a vertical
limb says nothing about heading (rotating it about the vertical does not move it), a horizontal one says the most.
Frames with too little evidence are not used.

:class:`HeadingEstimator` keeps, per sensor id, a window of such per-frame offsets, takes their weighted median,
rejects the samples far from it (mismatched or mis-triangulated keypoints) and averages the rest; the offset it
applies follows that estimate at a bounded rate (a correction of 45° is not a 45° jump of the avatar). With no
observations (fewer than two cameras see the person) nothing changes: the offset is frozen. The estimate is of the
*total* offset of each sensor's raw calibrated orientation, never of a residual, so applying it cannot feed back.

It is transport-agnostic: sensors are ids, observations are numbers. Whoever turns buffered sensor orientations
into bone orientations (the scheduler for suits: Xsens, the IMU bridge, SlimeVR trackers) applies
``R_y(offset) · R_gb`` and feeds the raw ``R_gb`` back with the person's triangulated keypoints.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.keypoints import TrackTargets
from mocapd.core.rotations import quat_from_rotvec, quat_rotate
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

CHILD_TOLERANCE_M = 0.06
"""A keypoint on a child bone counts as rigid with the parent when it sits at most this far from the child's joint
(a joint keypoint: the knee on the shank is the thigh's far end; a toe keypoint a few cm past the toe joint)."""


@dataclass(frozen=True)
class HeadingOptions:
    """How heading offsets are estimated and applied (validated on construction)."""

    enabled: bool = True
    """Estimate and apply heading offsets (False: raw calibrated orientations, nothing estimated)."""
    window_s: float = 4.0
    """Per-frame offsets kept per sensor (seconds). The estimate lags a drifting heading by about half of it."""
    min_samples: int = 12
    """Frames with enough evidence a sensor needs in the window before its estimate is used."""
    min_evidence_m2: float = 0.004
    """A frame's evidence (Σ of products of horizontal vector lengths, m²) below this is not used: 0.004 m² is one
    vector with a 6.3 cm horizontal component, e.g. a 30 cm limb 12° off vertical."""
    outlier_mads: float = 3.0
    """Samples further than this many (scaled) median absolute deviations from the median are rejected ..."""
    outlier_floor_deg: float = 3.0
    """... but never closer than this (a window of nearly equal samples has a MAD of almost nothing)."""
    max_rate_deg_s: float = 20.0
    """The applied offset moves towards the estimate at most this fast."""
    min_views: int = 2
    """Cameras that must see the person for an observation (a triangulation needs two)."""

    def __post_init__(self) -> None:
        positive = {"window_s": self.window_s, "min_evidence_m2": self.min_evidence_m2,
                    "outlier_mads": self.outlier_mads, "max_rate_deg_s": self.max_rate_deg_s}  # fmt: skip
        for name, value in positive.items():
            if not np.isfinite(value) or value <= 0:
                raise InputError(f"heading option {name} must be a finite number > 0, got {value!r}")
        if not np.isfinite(self.outlier_floor_deg) or self.outlier_floor_deg < 0:
            raise InputError(f"heading option outlier_floor_deg must be >= 0, got {self.outlier_floor_deg!r}")
        if self.min_samples < 1 or self.min_views < 2:
            raise InputError(
                f"heading options: min_samples >= 1 and min_views >= 2 needed, got {self.min_samples}, {self.min_views}"
            )


# ------------------------------------------------------------------------------------------- observations
@dataclass(frozen=True)
class BoneVectors:
    """The keypoint pairs rigidly attached to one bone and their difference in the bone's frame.

    Attributes
    ----------
    bone : str
    first, second : int arrays, shape (m,)
        Keypoint indices of each pair; the vector is ``keypoint[second] - keypoint[first]``.
    vectors : array, shape (m, 3)
        That vector in the bone's frame (metres).
    """

    bone: str
    first: IntArray
    second: IntArray
    vectors: FloatArray

    @property
    def observable(self) -> bool:
        """Whether the cameras can see this bone's heading at all (it has a keypoint pair)."""
        return len(self.first) > 0


def rigid_keypoints(
    skeleton: Skeleton, targets: TrackTargets, bone: str, child_tolerance_m: float = CHILD_TOLERANCE_M
) -> tuple[IntArray, FloatArray]:
    """Keypoints that move rigidly with ``bone`` and their positions in its frame.

    A keypoint on the bone sits at its offset; a keypoint on a child bone within ``child_tolerance_m`` of the
    child's joint sits (approximately) at the child's rest offset plus its own offset.

    Returns
    -------
    indices : int array, shape (k,)
    positions : array, shape (k, 3)
        Bone-frame positions (metres).
    """
    b = BONE_INDEX[bone]
    idx, pos = [], []
    for k, (kb, off) in enumerate(zip(targets.bones, targets.offsets, strict=True)):
        if kb == b:
            idx.append(k)
            pos.append(off)
        elif skeleton.parents[kb] == b and np.linalg.norm(off) <= child_tolerance_m:
            idx.append(k)
            pos.append(skeleton.offsets[kb] + off)
    return np.array(idx, dtype=np.intp), np.array(pos, dtype=np.float64).reshape(-1, 3)


def bone_vectors(skeleton: Skeleton, targets: TrackTargets, bones: Sequence[str]) -> tuple[BoneVectors, ...]:
    """Per bone, every pair of its rigid keypoints (:func:`rigid_keypoints`) and their bone-frame difference.

    With COCO-17 the feet have none (the ankle is the only foot keypoint): their heading cannot be observed and is
    left alone; Halpe-26 and Body25 add heel and toes.
    """
    out = []
    for bone in bones:
        idx, pos = rigid_keypoints(skeleton, targets, bone)
        i, j = np.triu_indices(len(idx), k=1)
        out.append(BoneVectors(bone, idx[i], idx[j], pos[j] - pos[i]))
    return tuple(out)


def observe_headings(
    q_gb: FloatArray, vectors: Sequence[BoneVectors], points: FloatArray, ok: NDArray[np.bool_]
) -> tuple[FloatArray, FloatArray]:
    """Per sensor bone, this frame's heading offset and its evidence.

    Parameters
    ----------
    q_gb : array, shape (n, 4)
        The sensors' calibrated (uncorrected) bone orientations, world ← bone, (w, x, y, z).
    vectors : sequence of n BoneVectors
        The rigid keypoint pairs of the same bones, in the same order.
    points : array, shape (n_kp, 3)
        Triangulated keypoints (world, metres).
    ok : bool array, shape (n_kp,)
        Which of them were triangulated.

    Returns
    -------
    yaw : array, shape (n,)
        Rotation about +Y (radians, in (-π, π]) taking the predicted vectors onto the observed ones: the
        correction to apply as ``R_y(yaw) · R_gb``. NaN where no pair was observed.
    evidence : array, shape (n,)
        ``hypot(c, s)`` (m²); 0 where nothing was observed.
    """
    n = len(vectors)
    if q_gb.shape != (n, 4):
        raise InputError(f"q_gb must have shape ({n}, 4) for {n} bones, got {q_gb.shape}")
    yaw = np.full(n, np.nan)
    evidence = np.zeros(n)
    if n == 0:
        return yaw, evidence
    # Every bone's pairs at once (the daemon observes 13 sensors 20 times a second on its event loop): each pair's
    # products as one bone at a time gave them, then each bone's two sums by np.sum over its own contiguous run of
    # them, as over the bone's own array before (np.add.reduceat adds in another order: not the same floats).
    lengths = np.array([len(bv.first) for bv in vectors], dtype=np.intp)
    owner = np.repeat(np.arange(n), lengths)
    first = np.concatenate([bv.first for bv in vectors]).astype(np.intp, copy=False)
    second = np.concatenate([bv.second for bv in vectors]).astype(np.intp, copy=False)
    vec = np.concatenate([np.reshape(bv.vectors, (-1, 3)) for bv in vectors])
    use = ok[first] & ok[second] & np.all(np.isfinite(q_gb), axis=1)[owner]
    counts = np.bincount(owner[use], minlength=n)
    seen = counts > 0
    if not seen.any():
        return yaw, evidence
    a = quat_rotate(q_gb[owner[use]], vec[use])
    o = points[second[use]] - points[first[use]]
    pc = a[:, 0] * o[:, 0] + a[:, 2] * o[:, 2]
    ps = a[:, 2] * o[:, 0] - a[:, 0] * o[:, 2]
    ends = np.cumsum(counts)[seen].tolist()
    starts = (np.cumsum(counts) - counts)[seen].tolist()
    c = np.array([np.sum(pc[i:j]) for i, j in zip(starts, ends, strict=True)])
    s = np.array([np.sum(ps[i:j]) for i, j in zip(starts, ends, strict=True)])
    evidence[seen] = np.hypot(c, s)
    yaw[seen] = np.arctan2(s, c)
    return yaw, evidence


def yaw_quat(yaw: FloatArray) -> FloatArray:
    """Rotations about world +Y by ``yaw`` (radians), shape (...,) -> (..., 4)."""
    y = np.asarray(yaw, dtype=np.float64)
    r = np.zeros((*y.shape, 3))
    r[..., 1] = y
    return quat_from_rotvec(r)


def wrap(angle: FloatArray | float) -> FloatArray:
    """Angles wrapped into (-π, π]."""
    a = np.asarray(angle, dtype=np.float64)
    out: FloatArray = np.pi - np.mod(np.pi - a, 2 * np.pi)
    return out


def weighted_median(values: FloatArray, weights: FloatArray) -> float:
    """The weighted median of ``values`` (n,) with positive ``weights`` (n,) (lower median on a tie)."""
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][int(np.searchsorted(cum, 0.5 * cum[-1]))])


# ------------------------------------------------------------------------------------------- estimation
class _Window:
    """One sensor's (t_ns, yaw, evidence) samples, oldest first, in three arrays: the robust estimate reads them as
    they are instead of building an array from tuples at every observation."""

    __slots__ = ("_e", "_end", "_start", "_t", "_y")

    def __init__(self) -> None:
        self._t = np.empty(32, dtype=np.int64)
        self._y = np.empty(32)
        self._e = np.empty(32)
        self._start = self._end = 0  # the live samples: [_start, _end)

    def __len__(self) -> int:
        return self._end - self._start

    def append(self, t_ns: int, yaw: float, evidence: float) -> None:
        if self._end == len(self._t):
            n = len(self)
            size = len(self._t) * (2 if 2 * n > len(self._t) else 1)  # grown only while more than half is live
            for name in ("_t", "_y", "_e"):
                old = getattr(self, name)
                new = np.empty(size, dtype=old.dtype)
                new[:n] = old[self._start : self._end]
                setattr(self, name, new)
            self._start, self._end = 0, n
        self._t[self._end], self._y[self._end], self._e[self._end] = t_ns, yaw, evidence
        self._end += 1

    def drop_older(self, t_ns: int) -> None:
        """Drop samples from the oldest on while they are older than ``t_ns`` (as a deque's popleft would)."""
        newer = self._t[self._start : self._end] >= t_ns
        self._start = self._start + int(np.argmax(newer)) if newer.any() else self._end

    def clear(self) -> None:
        self._start = self._end = 0

    def yaw(self) -> FloatArray:
        """Yaw samples (radians), oldest first (a view), shape (n,)."""
        return self._y[self._start : self._end]

    def evidence(self) -> FloatArray:
        """Their evidence (m²), shape (n,)."""
        return self._e[self._start : self._end]


@dataclass
class SensorHeading:
    """One sensor's state (JSON-able through :meth:`HeadingEstimator.status`)."""

    samples: _Window = field(default_factory=_Window)  # (t_ns, yaw, evidence)
    estimate: float | None = None
    """Robust estimate over the window (radians), None until there are enough samples."""
    applied: float = 0.0
    """The offset in use (radians): follows the estimate at the bounded rate."""
    inliers: int = 0
    rejected: int = 0
    """Samples of the last estimate kept / rejected as outliers."""
    observed_ns: int | None = None
    """When the sensor was last observed (None: never, or frozen since)."""
    frozen: bool = False


class HeadingEstimator:
    """Heading offsets per sensor id from per-frame observations (see the module docstring).

    Feed :meth:`observe` with each frame in which the person is seen by enough cameras, and call :meth:`freeze` for
    the suit's sensors in frames in which they are not; read :meth:`offsets` (radians) to correct the sensors'
    bone orientations as ``R_y(offset) · R_gb``.
    """

    def __init__(self, options: HeadingOptions | None = None) -> None:
        self.options = options if options is not None else HeadingOptions()
        self.sensors: dict[str, SensorHeading] = {}

    def offsets(self, sensors: Sequence[str]) -> FloatArray:
        """The applied offsets (radians) of ``sensors`` (0 for a sensor never estimated), shape (n,)."""
        if not self.options.enabled:
            return np.zeros(len(sensors))
        return np.array([s.applied if (s := self.sensors.get(sid)) is not None else 0.0 for sid in sensors])

    def observe(self, t_ns: int, sensors: Sequence[str], yaw: FloatArray, evidence: FloatArray) -> None:
        """One frame's observations (``yaw``, ``evidence`` as :func:`observe_headings` gives them)."""
        o = self.options
        if not o.enabled:
            return
        window_ns = round(o.window_s * 1e9)
        for sid, y, e in zip(sensors, yaw, evidence, strict=True):
            s = self.sensors.setdefault(sid, SensorHeading())
            if np.isfinite(y) and e >= o.min_evidence_m2:
                s.samples.append(t_ns, float(y), float(e))
            s.samples.drop_older(t_ns - window_ns)
            if len(s.samples) >= o.min_samples:
                s.estimate, s.inliers, s.rejected = self._robust(s.samples.yaw(), s.samples.evidence())
            if s.estimate is not None and s.observed_ns is not None:
                step = np.radians(o.max_rate_deg_s) * max(0, t_ns - s.observed_ns) / 1e9
                s.applied = float(wrap(s.applied + np.clip(wrap(s.estimate - s.applied), -step, step)))
            s.observed_ns = t_ns
            s.frozen = False

    def freeze(self, sensors: Sequence[str]) -> None:
        """The person wearing ``sensors`` is not seen: keep every offset as it is until they are again."""
        for sid in sensors:
            s = self.sensors.get(sid)
            if s is not None and not s.frozen:
                s.frozen = True
                s.observed_ns = None  # the rate limit restarts from the next observation, not across the gap

    def restart(self, sensors: Sequence[str]) -> None:
        """``sensors``' bone orientations changed (new mountings): their window's observations were made of the old
        ones, so they are dropped and gathered anew; the applied offsets stay until the new estimate moves them."""
        for sid in sensors:
            s = self.sensors.get(sid)
            if s is not None:
                s.samples.clear()
                s.estimate = None

    def _robust(self, y: FloatArray, w: FloatArray) -> tuple[float, int, int]:
        """Weighted median of the yaws ``y`` (n,) with evidence ``w`` (n,), outliers (beyond ``outlier_mads`` MADs)
        rejected, inliers' weighted mean."""
        o = self.options
        # Unwrapped around the circular mean: a window near ±180° stays in one piece.
        ref = float(np.arctan2(np.sum(w * np.sin(y)), np.sum(w * np.cos(y))))
        d = wrap(y - ref)
        med = weighted_median(d, w)
        dev = np.abs(d - med)
        mad = 1.4826 * weighted_median(dev, w)
        keep = dev <= max(o.outlier_mads * mad, np.radians(o.outlier_floor_deg))
        mean = float(np.sum(w[keep] * d[keep]) / np.sum(w[keep]))
        return float(wrap(ref + mean)), int(keep.sum()), int((~keep).sum())

    def status(self) -> dict[str, dict[str, Any]]:
        """Per sensor: applied offset and window estimate (degrees), samples, outliers, state."""
        out: dict[str, dict[str, Any]] = {}
        for sid, s in sorted(self.sensors.items()):
            state = "frozen" if s.frozen else ("estimating" if s.estimate is not None else "gathering")
            out[sid] = {
                "offset_deg": round(float(np.degrees(s.applied)), 2),
                "estimate_deg": None if s.estimate is None else round(float(np.degrees(s.estimate)), 2),
                "samples": len(s.samples), "inliers": s.inliers, "rejected": s.rejected, "state": state,
            }  # fmt: skip
        return out

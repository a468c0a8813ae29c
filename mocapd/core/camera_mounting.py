"""Cameras refine the IMU mountings: the first seconds in which the cameras see a suit's wearer give each sensor's
mounting (sensor-to-segment rotation) anew (pure: time is an argument).

A calibration's mounting ``R_ib`` rests on a still posture and priors (:mod:`mocapd.core.imu_calibration`); a sensor
strapped 5-15° askew keeps some of that in every later bone orientation. Cameras see the segments themselves: the
keypoints rigidly attached to a bone (:func:`mocapd.core.heading.bone_vectors`: both hips for the pelvis, hip and
knee for the thigh, eyes and ears for the head) give vectors ``v`` whose coordinates in the bone's frame are known,
triangulated in the world as ``o``. With the sensor's world orientation ``S`` (``R_ig · R_i``),
``o = R_gb · v = S · R_ib⁻¹ · v``, so in the sensor's frame ``u = S⁻¹ · o = R_ib⁻¹ · v``: the mounting is the rotation
that takes the observed ``u`` onto the known ``v`` over the frames, the average of ``R_segmentᵀ · R_sensor`` that the
cameras' segment orientations give (Wahba's problem, closed form by SVD; Markley 1988).

- A bone with one keypoint pair (a limb's two joints) fixes two of the mounting's three degrees of freedom (where the
  limb points in the sensor's frame); the turn about the limb stays the calibration's: the old mounting enters as a
  weak prior (:data:`PRIOR_WEIGHT` of the data's weight) so that the fit is always well posed.
- The sensor's heading may be off (a bent magnetic field, a drifting 6-axis sensor): ``o = R_y(ψ) · S · R_ib⁻¹ · v``.
  A turn about the world's vertical and one in the sensor's frame differ while the bone moves, so ``ψ`` is fitted with
  the mounting (in turn) and left to the heading correction (:mod:`mocapd.core.heading`), which starts over from the
  new mountings: the mounting does not take up the heading's error.
- Robust: frames whose residual is far from the others' (more than :attr:`MountingOptions.outlier_mads` scaled MADs,
  at least :attr:`MountingOptions.outlier_floor_deg`) are dropped (mismatched or mis-triangulated keypoints) and the
  fit repeated; only keypoints the triangulation kept (confident in two views) and vectors at least
  :attr:`MountingOptions.min_vector_m` long count.
- Used only where it is consistent: enough frames (:attr:`MountingOptions.min_frames`), the vectors' RMS misfit at
  most :attr:`MountingOptions.max_misfit_deg`, and a change of at most :attr:`MountingOptions.max_change_deg` (a
  sensor strapped along its segment is within about 15° of the calibration; more is a keypoint on the wrong bone).

:class:`CameraMountingEstimator` gathers, per suit, :attr:`MountingOptions.seconds` of observations from the first
frame the cameras see the wearer, then fits every observed sensor once (:meth:`CameraMountingEstimator.ready`,
:meth:`CameraMountingEstimator.fit`); whoever applies it (the scheduler) installs the new mountings and logs the
change per sensor. With no cameras nothing is observed and nothing changes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.heading import BoneVectors, yaw_quat
from mocapd.core.rotations import quat_angle, quat_canonical, quat_from_matrix, quat_multiply, quat_rotate
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

_CONJ = np.array([1.0, -1.0, -1.0, -1.0])
ALTERNATIONS = 8
"""Rounds of the mounting and the heading error fitted in turn (:func:`fit_mounting`)."""
PRIOR_WEIGHT = 1e-3
"""The calibration's mounting as a prior, weighing this fraction of the observations: it decides only what the
cameras cannot see (a limb's twist about itself)."""


@dataclass(frozen=True)
class MountingOptions:
    """How the cameras refine the mountings (validated on construction)."""

    enabled: bool = True
    """Refine each suit's mountings once from the cameras' first seconds of its wearer (False: never)."""
    seconds: float = 3.0
    """Observations gathered per suit (seconds from the first frame that saw the wearer, and at least
    :attr:`min_frames` frames) before the fit."""
    min_frames: int = 20
    """Frames in which a sensor's bone was observed that its fit needs."""
    min_vector_m: float = 0.05
    """Keypoint pairs closer than this (m) are left out: their direction is mostly keypoint noise."""
    max_misfit_deg: float = 8.0
    """A fit whose vectors stray more than this (RMS, degrees) keeps the calibration's mounting."""
    max_change_deg: float = 20.0
    """A fit that would turn a mounting by more than this (degrees) keeps the calibration's."""
    outlier_mads: float = 3.0
    """Frames whose residual is more than this many scaled MADs above the median are dropped ..."""
    outlier_floor_deg: float = 3.0
    """... but never those within this of it."""

    def __post_init__(self) -> None:
        positive = {"seconds": self.seconds, "min_vector_m": self.min_vector_m, "max_misfit_deg": self.max_misfit_deg,
                    "max_change_deg": self.max_change_deg, "outlier_mads": self.outlier_mads}  # fmt: skip
        for name, value in positive.items():
            if not np.isfinite(value) or value <= 0:
                raise InputError(f"mounting option {name} must be a finite number > 0, got {value!r}")
        if not np.isfinite(self.outlier_floor_deg) or self.outlier_floor_deg < 0:
            raise InputError(f"mounting option outlier_floor_deg must be >= 0, got {self.outlier_floor_deg!r}")
        if self.min_frames < 1:
            raise InputError(f"mounting option min_frames must be >= 1, got {self.min_frames}")


def wahba(u: FloatArray, v: FloatArray, w: FloatArray) -> FloatArray:
    """The rotation (quaternion (4,)) that best takes the vectors ``u`` (n, 3) onto ``v`` (n, 3), weights ``w`` (n,):
    maximises ``Σ w vᵀ R u`` (SVD of ``B = Σ w v uᵀ``, a proper rotation)."""
    b = (v * w[:, None]).T @ u
    left, _, right = np.linalg.svd(b)
    d = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(left) * np.linalg.det(right))) or 1.0])
    return quat_canonical(quat_from_matrix(left @ d @ right))


def _angles(q: FloatArray, u: FloatArray, v: FloatArray) -> FloatArray:
    """The angle (radians, (n,)) between ``R(q) u`` and ``v`` per pair."""
    ru = quat_rotate(q[None], u)
    cos = np.einsum("ij,ij->i", ru, v) / np.maximum(np.linalg.norm(ru, axis=1) * np.linalg.norm(v, axis=1), 1e-12)
    return np.asarray(np.arccos(np.clip(cos, -1.0, 1.0)), dtype=np.float64)


@dataclass(frozen=True, slots=True)
class MountingFit:
    """One sensor's mounting from the cameras (:func:`fit_mounting`)."""

    q_ib: FloatArray  # (4,) the fitted mounting
    change_deg: float  # its angle from the calibration's
    misfit_deg: float  # RMS of the kept vectors' angles after the fit
    frames: int  # frames kept
    rejected: int  # frames dropped as outliers
    used: bool
    reason: str = ""
    heading_deg: float = 0.0  # the sensor's heading error fitted with it (left to the heading correction)

    def as_dict(self) -> dict[str, object]:
        out: dict[str, object] = {"used": self.used, "change_deg": round(self.change_deg, 1),
                                  "misfit_deg": None if not np.isfinite(self.misfit_deg) else round(self.misfit_deg, 1),
                                  "heading_deg": round(self.heading_deg, 1), "frames": self.frames,
                                  "rejected": self.rejected}  # fmt: skip
        return out | ({"reason": self.reason} if self.reason else {})


def fit_mounting(
    q_ib: FloatArray,
    q_sensor: FloatArray,
    o: FloatArray,
    v: FloatArray,
    frame: NDArray[np.intp],
    options: MountingOptions,
) -> MountingFit:
    """A sensor's mounting from observed vectors, with its heading error.

    The sensor's orientation may be off about the vertical (a bent magnetic field; the heading correction of
    :mod:`mocapd.core.heading` estimates it from the same keypoints): ``o = R_y(ψ) · S · R_ib⁻¹ · v``. While the
    bone moves, a turn about the world's vertical and one in the sensor's frame differ, so both are fitted, in turn
    (the mounting by :func:`wahba` with ``u = S⁻¹ · R_y(−ψ) · o``, then ``ψ`` in closed form as
    :func:`mocapd.core.heading.observe_headings` does): the mounting does not take up the heading's error.

    Parameters
    ----------
    q_ib : array, shape (4,)
        The calibration's mounting (the prior, and what the change is measured from).
    q_sensor : array, shape (n, 4)
        The sensor's world orientation ``S`` (``R_ig · R_i``, no heading correction) at each vector's frame.
    o : array, shape (n, 3)
        The observed keypoint vectors (world, metres).
    v : array, shape (n, 3)
        The same vectors in the bone's frame.
    frame : int array, shape (n,)
        Which frame each vector came from (outliers are dropped by frame).
    """
    frames = np.unique(frame)
    if len(frames) < options.min_frames:
        return MountingFit(q_ib, 0.0, float("nan"), len(frames), 0, False,
                           f"{len(frames)} frames, needs {options.min_frames}")  # fmt: skip
    # unit vectors weighed by their length; the prior: the calibration's axes, weighing PRIOR_WEIGHT of the data
    w = np.linalg.norm(v, axis=1)
    o = o / np.maximum(np.linalg.norm(o, axis=1), 1e-12)[:, None]
    v = v / np.maximum(w, 1e-12)[:, None]
    s_inv = np.asarray(q_sensor, dtype=np.float64) * _CONJ
    axes = np.eye(3)
    prior_u = quat_rotate(np.asarray(q_ib)[None] * _CONJ, axes)  # R_ib⁻¹ e_i
    keep = np.ones(len(frames), dtype=bool)
    q, yaw = np.asarray(q_ib, dtype=np.float64), 0.0
    for _ in range(2):  # fit, drop the outlying frames, fit again
        sel = np.isin(frame, frames[keep])
        prior_w = np.full(3, PRIOR_WEIGHT * float(w[sel].sum()) / 3.0)
        for _ in range(ALTERNATIONS):
            u = quat_rotate(s_inv[sel], quat_rotate(yaw_quat(np.array(-yaw))[None], o[sel]))
            q = wahba(np.vstack([u, prior_u]), np.vstack([v[sel], axes]), np.concatenate([w[sel], prior_w]))
            a = quat_rotate(quat_multiply(np.asarray(q_sensor)[sel], (q * _CONJ)[None]), v[sel])
            c = float(np.sum(w[sel] * (a[:, 0] * o[sel, 0] + a[:, 2] * o[sel, 2])))
            yaw = float(np.arctan2(np.sum(w[sel] * (a[:, 2] * o[sel, 0] - a[:, 0] * o[sel, 2])), c))
        ang = _angles(q, quat_rotate(s_inv, quat_rotate(yaw_quat(np.array(-yaw))[None], o)), v)
        per_frame = np.array([np.average(ang[frame == f], weights=w[frame == f]) for f in frames])
        med = float(np.median(per_frame[keep]))
        mad = 1.4826 * float(np.median(np.abs(per_frame[keep] - med)))
        limit = med + max(options.outlier_mads * mad, np.radians(options.outlier_floor_deg))
        keep = per_frame <= limit
    sel = np.isin(frame, frames[keep])
    ang = _angles(q, quat_rotate(s_inv[sel], quat_rotate(yaw_quat(np.array(-yaw))[None], o[sel])), v[sel])
    misfit = float(np.degrees(np.sqrt(np.average(ang**2, weights=w[sel]))))
    change = float(np.degrees(quat_angle(q, q_ib)))
    rejected, kept = int((~keep).sum()), int(keep.sum())
    heading = float(np.degrees(yaw))
    if kept < options.min_frames:
        return MountingFit(q_ib, change, misfit, kept, rejected, False,
                           f"{kept} frames kept, needs {options.min_frames}", heading)  # fmt: skip
    if misfit > options.max_misfit_deg:
        return MountingFit(q_ib, change, misfit, kept, rejected, False,
                           f"misfit {misfit:.1f} deg, above {options.max_misfit_deg:g}", heading)  # fmt: skip
    if change > options.max_change_deg:
        return MountingFit(q_ib, change, misfit, kept, rejected, False,
                           f"would turn the mounting {change:.1f} deg, above {options.max_change_deg:g}",
                           heading)  # fmt: skip
    return MountingFit(q, change, misfit, kept, rejected, True, "", heading)


def observe_vectors(
    vectors: Sequence[BoneVectors], points: FloatArray, ok: NDArray[np.bool_], min_len: float
) -> list[tuple[FloatArray, FloatArray]]:
    """Per sensor bone, this frame's observed keypoint vectors (world) and the same in the bone's frame.

    Parameters
    ----------
    vectors : sequence of n BoneVectors
        Each sensor's bone's rigid keypoint pairs (:func:`mocapd.core.heading.bone_vectors`).
    points : array, shape (n_kp, 3)
        Triangulated keypoints (world, metres); ``ok`` (n_kp,) which were triangulated.
    min_len : float
        Pairs shorter than this (m, in the bone's frame) are left out.

    Returns per bone ``(o, v)``, arrays of shape (m, 3) (m may be 0).
    """
    out = []
    for bv in vectors:
        use = ok[bv.first] & ok[bv.second] & (np.linalg.norm(bv.vectors, axis=1) >= min_len)
        out.append((points[bv.second[use]] - points[bv.first[use]], bv.vectors[use]))
    return out


@dataclass
class _Gathering:
    """One suit's observations: from when, and per sensor the vectors and their frame numbers."""

    since_ns: int
    frames: int = 0
    q: dict[str, list[FloatArray]] = field(default_factory=dict)
    o: dict[str, list[FloatArray]] = field(default_factory=dict)
    v: dict[str, list[FloatArray]] = field(default_factory=dict)
    frame: dict[str, list[NDArray[np.intp]]] = field(default_factory=dict)


class CameraMountingEstimator:
    """Per suit: gathers :attr:`MountingOptions.seconds` of camera observations from the first frame the cameras see
    its wearer, then fits each observed sensor's mounting once (see the module docstring)."""

    def __init__(self, options: MountingOptions | None = None) -> None:
        self.options = options or MountingOptions()
        self._gathering: dict[str, _Gathering] = {}
        self.results: dict[str, dict[str, MountingFit]] = {}
        """Per suit, once fitted: per sensor id its fit (applied or not)."""

    def wants(self, suit: str) -> bool:
        """Whether ``suit`` still needs observations (enabled and not fitted yet)."""
        return self.options.enabled and suit not in self.results

    def observe(
        self,
        suit: str,
        t_ns: int,
        sensors: Sequence[str],
        q_sensor: FloatArray,
        vectors: Sequence[BoneVectors],
        points: FloatArray,
        ok: NDArray[np.bool_],
    ) -> None:
        """One frame of ``suit``'s wearer seen by the cameras: ``sensors`` (n ids) with their world orientations
        ``q_sensor`` (n, 4, no heading correction) and bones' keypoint pairs ``vectors``, the triangulated ``points``
        (n_kp, 3), ``ok``."""
        if not self.wants(suit):
            return
        g = self._gathering.setdefault(suit, _Gathering(t_ns))
        seen = observe_vectors(vectors, points, ok, self.options.min_vector_m)
        for sid, q, (o, v) in zip(sensors, q_sensor, seen, strict=True):
            if len(o) and np.all(np.isfinite(q)):
                g.q.setdefault(sid, []).append(np.repeat(np.asarray(q, dtype=np.float64)[None], len(o), axis=0))
                g.o.setdefault(sid, []).append(o)
                g.v.setdefault(sid, []).append(v)
                g.frame.setdefault(sid, []).append(np.full(len(o), g.frames, dtype=np.intp))
        g.frames += 1

    def ready(self, suit: str, t_ns: int) -> bool:
        """Whether ``suit``'s observations span :attr:`MountingOptions.seconds` and number at least
        :attr:`MountingOptions.min_frames`, and await :meth:`fit`.

        The frames as well as the seconds: a loaded machine observes the wearer less often than every 50 ms, and a fit
        made once, from fewer frames than it needs, would keep every calibration's mounting for good."""
        g = self._gathering.get(suit)
        if g is None or not self.wants(suit):
            return False
        return (t_ns - g.since_ns) / 1e9 >= self.options.seconds and g.frames >= self.options.min_frames

    def fit(self, suit: str, q_ib: Mapping[str, FloatArray]) -> dict[str, MountingFit]:
        """Fit every sensor of ``suit`` (id -> its calibration's mounting (4,)) from what was gathered; once."""
        g = self._gathering.pop(suit, None)
        out: dict[str, MountingFit] = {}
        for sid, q in q_ib.items():
            if g is None or sid not in g.o:
                out[sid] = MountingFit(np.asarray(q), 0.0, float("nan"), 0, 0, False, "not seen by the cameras")
                continue
            out[sid] = fit_mounting(np.asarray(q, dtype=np.float64), np.vstack(g.q[sid]), np.vstack(g.o[sid]),
                                    np.vstack(g.v[sid]), np.concatenate(g.frame[sid]), self.options)  # fmt: skip
        self.results[suit] = out
        return out

    def status(self) -> dict[str, dict[str, object]]:
        """Per suit: ``state`` (``gathering`` with its frames so far, or ``done``) and, once done, per sensor its fit
        (:meth:`MountingFit.as_dict`)."""
        out: dict[str, dict[str, object]] = {}
        for suit, g in self._gathering.items():
            out[suit] = {"state": "gathering", "frames": g.frames}
        for suit, fits in self.results.items():
            out[suit] = {"state": "done", "sensors": {sid: f.as_dict() for sid, f in fits.items()}}
        return out

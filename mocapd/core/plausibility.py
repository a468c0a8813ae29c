"""Anatomical plausibility of solved motion: knees and elbows bending the wrong way, a pelvis facing backwards
while the legs walk forwards (issue 28). Pure.

A human knee and elbow are hinges that bend one way only. A solve in which one bends the other way for more than
a moment is physically impossible; the usual cause is a calibration whose facing direction is mirrored
(``mocapd calibrate imu --facing-from SENSOR:AXIS`` with the wrong sign: every bone's frame turned by 180° about
the vertical, so that every bend of a knee reads as the knee bending backwards), a sensor strapped on another bone
than the assignment says, or a sensor that turned on its strap. Nothing else in the solve notices: the orientation
term is satisfied, and the avatar walks with its knees bent backwards.

Hinge angles (:func:`hinge_angles`) come from a bone's local rotation in its parent's frame, which in the rest
T-pose (DESIGN.md: facing +Z, arms along ±X with palms down) has the hinge's bending plane fixed:

- **knee**: the shank's end moves backwards (−Z of the thigh's frame) as the knee flexes; the flexion is
  ``atan2(−d_z, −d_y)`` of the shank's direction ``d`` (its −Y axis) in the thigh's frame;
- **elbow**: the forearm's end moves forwards (+Z of the upper arm's frame); the flexion is ``atan2(d_z, s·d_x)`` of
  the forearm's direction ``d`` (``s``·X, ``s`` = +1 for the left arm, −1 for the right) in the upper arm's frame.

A hinge is bent the wrong way when its flexion is below ``-wrong_way_deg`` (a knee straightens to a few degrees of
hyperextension, an elbow to ~10°); an **event** is a run of such frames lasting at least ``min_duration_s`` (one
frame of noise is not one).

The pelvis check (:class:`PlausibilityMonitor` only: it needs the root's motion) compares the direction the root
travels (its horizontal velocity over ``travel_window_s``, at ``min_speed`` or faster) with the direction the pelvis
faces (the hips bone's +Z) and with the direction the thighs face: the pelvis faces backwards while the legs walk
forwards when the pelvis is more than ``backwards_deg`` from the direction of travel and the thighs within
``180 - backwards_deg`` of it (someone walking backwards has both facing away from it, and is not flagged).

:func:`bone_hinge_angles` measures the knees and elbows from measured *bone orientations* (the IMU's, through a
calibration), without a solve: what ``calibrate imu --from`` checks a facing direction with.
:func:`facing_from_knees` finds the facing direction from the knees' bending in a take's steps.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.rotations import matrix_from_quat, matrix_from_rotvec, rotvec_from_matrix
from mocapd.core.skeleton import BONE_INDEX, N_BONES, POSE_DIM
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

HINGES: dict[str, tuple[str, str]] = {
    "left_knee": ("LeftUpperLeg", "LeftLowerLeg"),
    "right_knee": ("RightUpperLeg", "RightLowerLeg"),
    "left_elbow": ("LeftUpperArm", "LeftLowerArm"),
    "right_elbow": ("RightUpperArm", "RightLowerArm"),
}
"""Each checked hinge: (parent bone, bone whose local rotation bends it)."""


@dataclass(frozen=True)
class PlausibilityOptions:
    """Thresholds of the checks (see the module docstring)."""

    wrong_way_deg: float = 15.0
    """A hinge bent this far against its bending direction is bent the wrong way."""
    min_duration_s: float = 0.25
    """For at least this long in a row, it is an event (shorter runs are noise or a fast pass)."""
    backwards_deg: float = 120.0
    """The pelvis faces backwards when it is turned this far from the direction of travel."""
    min_speed: float = 0.3
    """m/s: the root must travel at least this fast for a direction of travel."""
    travel_window_s: float = 0.5
    """s: the direction of travel is the root's displacement over this window."""
    backwards_s: float = 1.0
    """s: a pelvis facing backwards while walking forwards for this long is an event."""

    def __post_init__(self) -> None:
        for name in ("wrong_way_deg", "min_duration_s", "backwards_deg", "min_speed", "travel_window_s",
                     "backwards_s"):  # fmt: skip
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise InputError(f"plausibility: {name} must be a positive finite number, got {v!r}")
        if not 90.0 < self.backwards_deg < 180.0:
            raise InputError(f"plausibility: backwards_deg must be in (90, 180), got {self.backwards_deg}")


def _flexion(local: FloatArray, hinge: str) -> FloatArray:
    """Flexion (degrees, positive the right way) of local rotation matrices (..., 3, 3) of a hinge's bone."""
    if hinge.endswith("knee"):
        d = -local[..., :, 1]  # the shank's direction (-Y) in the thigh's frame
        return np.asarray(np.degrees(np.arctan2(-d[..., 2], -d[..., 1])))
    s = 1.0 if hinge.startswith("left") else -1.0
    d = s * local[..., :, 0]  # the forearm's direction (s·X) in the upper arm's frame
    return np.asarray(np.degrees(np.arctan2(d[..., 2], s * d[..., 0])))


def hinge_angles(theta: FloatArray) -> dict[str, FloatArray]:
    """Flexion of every :data:`HINGES` entry (degrees, positive the right way), per frame.

    Parameters
    ----------
    theta : array, shape (n, 66) or (66,)
        Poses.

    Returns
    -------
    dict hinge name -> array, shape (n,) (or a scalar array for one pose)
    """
    th = np.asarray(theta, dtype=np.float64)
    if th.shape[-1] != POSE_DIM:
        raise InputError(f"plausibility: poses must have {POSE_DIM} values, got shape {th.shape}")
    rot = th[..., 6:].reshape(*th.shape[:-1], N_BONES - 1, 3)
    out = {}
    for name, (_, bone) in HINGES.items():
        out[name] = _flexion(matrix_from_rotvec(rot[..., BONE_INDEX[bone] - 1, :]), name)
    return out


def bone_hinge_angles(orientations: Mapping[str, FloatArray]) -> dict[str, FloatArray]:
    """Flexion of the hinges whose two bones both have a measured world orientation (degrees, positive the right
    way).

    Parameters
    ----------
    orientations : mapping bone name -> quaternions, shape (n, 4)
        World bone orientations (w, x, y, z), all on the same frames.
    """
    out = {}
    for name, (parent, bone) in HINGES.items():
        if parent in orientations and bone in orientations:
            Rp = matrix_from_quat(np.asarray(orientations[parent], dtype=np.float64))
            Rb = matrix_from_quat(np.asarray(orientations[bone], dtype=np.float64))
            out[name] = _flexion(np.swapaxes(Rp, -1, -2) @ Rb, name)
    return out


@dataclass(frozen=True)
class HingeEvents:
    """Where one hinge bent the wrong way."""

    events: int
    seconds: float
    worst_deg: float
    """The largest wrong-way bend (degrees, positive) during the events; 0 without an event."""
    first_s: float | None
    """Time of the first event's start (s from the first frame), None without an event."""

    def as_dict(self) -> dict[str, object]:
        return {"events": self.events, "seconds": round(self.seconds, 2), "worst_deg": round(self.worst_deg, 1),
                "first_s": None if self.first_s is None else round(self.first_s, 2)}  # fmt: skip


def wrong_way_events(angles: FloatArray, t_s: FloatArray, options: PlausibilityOptions) -> HingeEvents:
    """The events in one hinge's flexion series (see the module docstring).

    Parameters
    ----------
    angles : array, shape (n,)
        Flexion (degrees), NaN where unknown (ends a run).
    t_s : array, shape (n,)
        Increasing times (s).
    """
    a = np.asarray(angles, dtype=np.float64)
    t = np.asarray(t_s, dtype=np.float64)
    if a.shape != t.shape or a.ndim != 1:
        raise InputError(f"plausibility: angles {a.shape} and times {t.shape} must be matching 1-D arrays")
    bad = np.nan_to_num(a, nan=0.0) < -options.wrong_way_deg
    events, seconds, worst, first = 0, 0.0, 0.0, None
    i, n = 0, a.size
    dt = float(np.median(np.diff(t))) if n > 1 else 0.0
    while i < n:
        if not bad[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and bad[j + 1]:
            j += 1
        length = float(t[j] - t[i]) + dt
        if length >= options.min_duration_s:
            events += 1
            seconds += length
            worst = max(worst, float(-a[i : j + 1].min()))
            first = float(t[i] - t[0]) if first is None else first
        i = j + 1
    return HingeEvents(events, seconds, worst, first)


def check_bone_orientations(
    orientations: Mapping[str, FloatArray], t_s: FloatArray, options: PlausibilityOptions | None = None
) -> dict[str, HingeEvents]:
    """Wrong-way events of every hinge measured by :func:`bone_hinge_angles`."""
    o = options or PlausibilityOptions()
    return {name: wrong_way_events(a, t_s, o) for name, a in bone_hinge_angles(orientations).items()}


# ------------------------------------------------------------------------------------------ facing from steps
MIN_KNEE_BEND_DEG = 20.0
"""A take's knees must bend at least this much (the 90th percentile of their bend) to tell a facing from them."""


def knee_hinge_axis(q_thigh: FloatArray, q_shank: FloatArray) -> tuple[FloatArray, float] | None:
    """The knee's flexion axis in the thigh's frame, from its motion, and how far it bent (degrees).

    A hinge makes ``R_t⁻¹ R_s`` (shank in thigh, any frames) a rotation about one fixed axis ``a`` of the thigh's
    frame, composed with constants: ``R_t(k)⁻¹ R_s(k) (R_t(0)⁻¹ R_s(0))⁻¹ = Rot(a, θ_k − θ_0)``. The axis is the
    principal direction of those rotation vectors, signed so that their mean points along it: walking bends a knee
    (flexes) far more than it straightens past standing, so the sign is the flexion's.

    Parameters
    ----------
    q_thigh, q_shank : arrays, shape (n, 4)
        Orientations of the two sensors (or bones) in one global frame, frame 0 with the knee about straight.

    Returns
    -------
    (axis (3,), bend_deg) or None when the knee did not bend (the 90th percentile of the bend under
    :data:`MIN_KNEE_BEND_DEG`)
    """
    Rt = matrix_from_quat(np.asarray(q_thigh, dtype=np.float64))
    Rs = matrix_from_quat(np.asarray(q_shank, dtype=np.float64))
    rel = np.swapaxes(Rt, -1, -2) @ Rs
    v = rotvec_from_matrix(rel @ rel[0].T)
    bend = np.degrees(np.linalg.norm(v, axis=1))
    if bend.size < 2 or float(np.percentile(bend, 90)) < MIN_KNEE_BEND_DEG:
        return None
    axis = np.linalg.eigh(v.T @ v)[1][:, -1]
    if float((v @ axis).sum()) < 0:
        axis = -axis
    return axis, float(np.percentile(bend, 90))


def facing_from_knees(
    legs: list[tuple[FloatArray, FloatArray]], still: list[FloatArray], up: FloatArray
) -> FloatArray | None:
    """The direction a subject faced, in the global frame, from the way their knees bent.

    A knee flexes about the body's left-right axis, its foot moving backwards: flexion about the axis ``a``
    (:func:`knee_hinge_axis`, in the thigh sensor's frame) turns the shank's downward direction towards
    ``a × (−up)``, so the subject faces ``a × up`` — with ``a`` put into the global frame by the thigh sensor's
    orientation ``R_t`` at the moment wanted (the calibration's still window).

    Parameters
    ----------
    legs : list of (thigh, shank) orientation series, each shape (n, 4)
        One entry per leg whose thigh and shank both wear a sensor, global frame.
    still : list of arrays, shape (4,)
        The thigh sensor's orientation at the moment wanted, per leg.
    up : array, shape (3,)
        The global frame's up direction (ENU: z).

    Returns
    -------
    The horizontal unit vector the subject faced (global frame), shape (3,), or None when no knee bent enough.
    """
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    forward = np.zeros(3)
    for (q_t, q_s), q0 in zip(legs, still, strict=True):
        found = knee_hinge_axis(q_t, q_s)
        if found is None:
            continue
        axis, _ = found
        f = np.cross(matrix_from_quat(np.asarray(q0, dtype=np.float64)) @ axis, u)
        f = f - (f @ u) * u
        norm = float(np.linalg.norm(f))
        if norm > 1e-6:
            forward += f / norm
    norm = float(np.linalg.norm(forward))
    if norm < 1e-6:
        return None
    return forward / norm


# --------------------------------------------------------------------------------------- the live monitor
_MONITORED = ("Hips", "LeftUpperLeg", "RightUpperLeg", *(bone for _, bone in HINGES.values()))
_MONITORED_IDX = np.array([BONE_INDEX[b] for b in _MONITORED], dtype=np.intp)
_HINGE_ENTRIES = tuple(
    (
        name,
        3 + 3 * BONE_INDEX[bone],
        *((7, 4, 1.0) if name.endswith("knee") else (6, 0, 1.0 if "left" in name else -1.0)),
    )
    for name, (_, bone) in HINGES.items()
)
"""Per hinge: its name, its bone's first value in θ, and the entries (row-major) of the bone's rotation ``R`` whose
``atan2(sign·R[num], R[den])`` is :func:`_flexion`'s angle (num, den, sign): a knee's ``atan2(−d_z, −d_y)`` of
``d = −R[:, 1]``, an elbow's ``atan2(d_z, s·d_x)`` of ``d = s·R[:, 0]``."""
_THIGHS = (3 + 3 * BONE_INDEX["LeftUpperLeg"], 3 + 3 * BONE_INDEX["RightUpperLeg"])
"""The thighs' first values in θ (the pelvis check's legs)."""
_MARGIN = 1e-9
"""How close (relative, or degrees for a flexion) to a check's threshold the monitor's plain-float arithmetic
leaves the decision to the array arithmetic: the two round differently (numpy's BLAS dots fuse multiply and add,
its sine and cosine are other routines than :mod:`math`'s), by ~1e-13 at most."""


def _rotation(x: float, y: float, z: float) -> tuple[float, ...]:
    """:func:`~mocapd.core.rotations.matrix_from_rotvec` of one rotation vector in plain floats, row-major 9
    entries: ``I + a K + b K²`` with ``K² = r rᵀ − θ² I`` (equal to the array version to rounding); NaN when the
    vector is not finite."""
    t2 = x * x + y * y + z * z
    if not math.isfinite(t2):
        return (math.nan,) * 9
    if t2 < 1e-12:  # theta < 1e-6, the array version's series branch
        a, b = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    else:
        t = math.sqrt(t2)
        a, b = math.sin(t) / t, (1.0 - math.cos(t)) / t2
    d = 1.0 - b * t2
    return (d + b * x * x, b * x * y - a * z, b * x * z + a * y,
            b * x * y + a * z, d + b * y * y, b * y * z - a * x,
            b * x * z - a * y, b * y * z + a * x, d + b * z * z)  # fmt: skip


def _monitored_rotations(th: FloatArray) -> dict[str, FloatArray]:
    """The monitored bones' rotation matrices in the array arithmetic (one conversion for all)."""
    return dict(zip(_MONITORED, matrix_from_rotvec(th[3:].reshape(N_BONES, 3)[_MONITORED_IDX]), strict=True))


@dataclass
class _Run:
    """A hinge's or the pelvis's current run of implausible frames."""

    start_s: float | None = None
    worst: float = 0.0
    counted: bool = False


@dataclass
class PlausibilityMonitor:
    """Counts the implausible events of one person's solved poses frame by frame (the daemon, ``resolve``).

    Call :meth:`step` with each solved pose in time order; :meth:`status` gives, per hinge and for the pelvis, the
    events counted, their total seconds, the worst bend and whether one is going on now.

    This runs per person and output tick on the daemon's event loop (issue 39), so a step decides in plain floats
    (a flexion not near its threshold, a pelvis not near facing backwards: nearly every frame) and computes a
    hinge's flexion or the pelvis check with the arrays only when the pose is bent the wrong way (the worst bend
    reported is the array value), folded to near ±180° or within :data:`_MARGIN` of a threshold: the counts,
    seconds and worst bends are the array arithmetic's (``tests/test_plausibility_bitwise.py``).
    """

    options: PlausibilityOptions = field(default_factory=PlausibilityOptions)
    events: dict[str, int] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    worst_deg: dict[str, float] = field(default_factory=dict)
    _runs: dict[str, _Run] = field(default_factory=dict)
    _roots: deque[tuple[float, float, float]] = field(default_factory=deque)  # (t_s, x, z) of the root
    _last_s: float | None = None

    def step(self, t_s: float, theta: FloatArray) -> None:
        """One solved pose θ (66,) at time ``t_s`` (s, increasing)."""
        th = np.asarray(theta, dtype=np.float64)
        dt = 0.0 if self._last_s is None else max(0.0, t_s - self._last_s)
        self._last_s = t_s
        v = th.tolist()
        o = self.options
        limit = -o.wrong_way_deg
        exact: dict[str, FloatArray] | None = None
        for name, k, num, den, sign in _HINGE_ENTRIES:
            R = _rotation(v[k], v[k + 1], v[k + 2])
            y, x = sign * R[num], R[den]
            a = math.degrees(math.atan2(y, x))
            # Bent the wrong way, near the threshold, or folded near ±180° (where rounding picks the sign): exact.
            if not (limit + _MARGIN < a < 180.0 - _MARGIN and x * x + y * y > 1e-6):
                exact = _monitored_rotations(th) if exact is None else exact
                a = float(_flexion(exact[HINGES[name][1]], name))
            self._advance(name, t_s, dt, a < limit, -a, o.min_duration_s)
        self._advance("pelvis_backwards", t_s, dt, self._pelvis_backwards(t_s, v, th), 0.0, o.backwards_s)

    def _pelvis_backwards(self, t_s: float, v: list[float], th: FloatArray) -> bool:
        o = self.options
        x, z = v[0], v[2]
        self._roots.append((t_s, x, z))
        while self._roots and self._roots[0][0] < t_s - o.travel_window_s:
            self._roots.popleft()
        t0, x0, z0 = self._roots[0]
        if t_s - t0 < 0.5 * o.travel_window_s:
            return False
        vx, vz = (x - x0) / (t_s - t0), (z - z0) / (t_s - t0)  # as the arrays divide: the same floats
        speed = math.sqrt(vx * vx + vz * vz)
        if speed < o.min_speed * (1.0 - _MARGIN):
            return False
        hips = _rotation(v[3], v[4], v[5])
        legs = [0.0, 0.0]
        for k in _THIGHS:
            Rb = _rotation(v[k], v[k + 1], v[k + 2])
            for n, i in enumerate((0, 6)):  # rows 0 and 2 of hips @ Rb, column 2
                legs[n] += hips[i] * Rb[2] + hips[i + 1] * Rb[5] + hips[i + 2] * Rb[8]
        cos_max = math.cos(math.radians(o.backwards_deg))

        def cos(ax: float, az: float) -> float | None:
            """The cosine to the direction of travel; None when too near a threshold to tell in plain floats."""
            n = math.sqrt(ax * ax + az * az)
            if not math.isfinite(n * speed) or abs(n - 1e-6) <= _MARGIN or speed <= o.min_speed * (1.0 + _MARGIN):
                return None
            c = (ax * vx + az * vz) / (n * speed) if n > 1e-6 else 0.0
            return None if min(abs(c - cos_max), abs(c + cos_max)) <= _MARGIN else c

        facing, walking = cos(hips[2], hips[8]), cos(legs[0], legs[1])
        if facing is None or walking is None:
            return self._pelvis_backwards_arrays(th, np.array([vx, vz]))
        return facing < cos_max and walking > -cos_max

    def _pelvis_backwards_arrays(self, th: FloatArray, travel: FloatArray) -> bool:
        """The pelvis check in the array arithmetic (``travel`` the root's horizontal velocity)."""
        o = self.options
        speed = float(np.linalg.norm(travel))
        if speed < o.min_speed:
            return False
        R = _monitored_rotations(th)
        hips = R["Hips"]
        facing = hips[[0, 2], 2]
        legs = np.zeros(2)
        for b in ("LeftUpperLeg", "RightUpperLeg"):
            legs += (hips @ R[b])[[0, 2], 2]
        cos_max = math.cos(math.radians(o.backwards_deg))

        def cos(a: FloatArray) -> float:
            n = float(np.linalg.norm(a))
            return float(a @ travel) / (n * speed) if n > 1e-6 else 0.0

        return cos(facing) < cos_max and cos(legs) > -cos_max

    def _advance(self, name: str, t_s: float, dt: float, bad: bool, amount: float, min_s: float) -> None:
        run = self._runs.setdefault(name, _Run())
        if not bad:
            run.start_s, run.worst, run.counted = None, 0.0, False
            return
        if run.start_s is None:
            run.start_s = t_s
        run.worst = max(run.worst, amount)
        length = t_s - run.start_s + dt
        if not run.counted and length >= min_s:
            run.counted = True
            self.events[name] = self.events.get(name, 0) + 1
            self.seconds[name] = self.seconds.get(name, 0.0) + length - dt
        if run.counted:
            self.seconds[name] = self.seconds.get(name, 0.0) + dt
            self.worst_deg[name] = max(self.worst_deg.get(name, 0.0), run.worst)

    @property
    def implausible(self) -> bool:
        """Whether any event was counted."""
        return any(self.events.values())

    def active(self) -> list[str]:
        """The checks whose event is going on now."""
        return [name for name, run in self._runs.items() if run.counted]

    def status(self) -> dict[str, object]:
        """Per check with an event: events, seconds, worst bend (hinges); and what is going on now."""
        checks = {
            name: {"events": n, "seconds": round(self.seconds.get(name, 0.0), 2)}
            | ({"worst_deg": round(self.worst_deg.get(name, 0.0), 1)} if name != "pelvis_backwards" else {})
            for name, n in sorted(self.events.items())
        }
        return {"implausible": self.implausible, "events": checks, "now": sorted(self.active())}

    def summary_lines(self) -> list[str]:
        """One line per check with events, for a person's notes."""
        out = []
        for name, n in sorted(self.events.items()):
            what = name.replace("_", " ")
            secs = self.seconds.get(name, 0.0)
            if name == "pelvis_backwards":
                out.append(f"the pelvis faced backwards while the legs walked forwards {n} time(s), {secs:.1f} s")
            else:
                worst = self.worst_deg.get(name, 0.0)
                out.append(f"{what} bent the wrong way {n} time(s), {secs:.1f} s in all, up to {worst:.0f}°")
        return out


CAUSES = (
    "a facing direction mirrored at calibration (calibrate again: facing the heading given, or --facing-from with "
    "the other sign), a sensor on another bone than the assignment says (left and right swapped), or one turned on "
    "its strap"
)
"""What makes a suit wearer's solve implausible (the module docstring), as said to the user."""
CAMERA_CAUSES = (
    "the detector misplacing that limb's keypoints in some views (an occluded or side-on limb, or its left and "
    "right confused) -- a camera-only person has no calibration to redo; more views of the limb help"
)
"""... and a camera-only person's (identity ``track:N``): no IMU calibration is involved, only the keypoints."""


def first_events(monitors: Mapping[str, PlausibilityMonitor], said: set[tuple[str, str]]) -> list[str]:
    """One line per person and check whose first event was counted since ``said`` last saw it (added to ``said``):
    what a live daemon says once, on its console, instead of only counting it in /status."""
    out = []
    for identity, m in sorted(monitors.items()):
        for name, n in sorted(m.events.items()):
            if n <= 0 or (identity, name) in said:
                continue
            said.add((identity, name))
            if name == "pelvis_backwards":
                what = "the pelvis faced backwards while the legs walked forwards"
            else:
                what = f"the {name.replace('_', ' ')} bent the wrong way (up to {m.worst_deg.get(name, 0.0):.0f}°)"
            causes = CAMERA_CAUSES if identity.startswith("track:") else CAUSES
            out.append(f"{identity}: {what}, which no body does: likely {causes} (counted in /status plausibility)")
    return out

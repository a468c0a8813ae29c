"""A root that stays on the ground without cameras: foot contacts place the root translation (issue 14).

Without an absolute position reference (fewer than :attr:`GroundOptions.reference_views` cameras see the
person) nothing in seed 003's cost holds the root translation: the IMU orientation term fixes the bones'
rotations, the acceleration term is off (it would double-integrate noise), and only the floor hinge pushes the
feet up. A warm start that extrapolates the root's velocity then turns every upward push into a velocity that never
decays: on a real MTw recording the root floated from 0.93 m to 2.57 m in 25 s.

IMU-only motion capture places the root the way people walk: a planted foot does not move. Per foot (the points where
it touches the floor, :func:`sole_points`: the heel and the ball of the foot, issue 28), :class:`GroundTracker`

1. **weighs the feet.** The lower foot carries the body: each foot's *support* is a logistic of the two feet's
   height difference (every point measured against its standing height, its height in the skeleton's rest pose,
   which stands on y = 0; the relative heights come from the solved rotations alone), divided by
   ``1 + (a / moving_acceleration)²`` for a foot whose sensor measures a free acceleration ``a`` (an impact, a
   swing) and, while cameras make the solved feet absolute, by ``1 + (v / still_speed)²`` for a foot moving at
   ``v``;
2. **plants and lifts feet.** A foot whose support reaches ``lock_weight`` is planted where it is; a planted foot
   whose support stays below ``free_weight`` for ``hold_s`` is lifted, at once when the hips sensor falls freely
   (``airborne_acceleration``: a run's flight phase, a jump). A foot put down again at once, close by, returns to
   its old anchor, so noise that briefly lifts a standing foot does not move it;
3. **anchors the root.** A planted foot's pivot (its lowest point: the heel after heel strike, passing to the ball at
   heel-off, and back as the foot rocks; a point taken up again in the same stance returns to where it was held) stays
   where it was planted; the root translation is the support-weighted mean of what puts each planted pivot on its
   anchor under the solved rotations. The pivot must be on the sole: a foot turning about a joint 5-7 cm above the
   floor (the ankle and toe joints, used before issue 28) drags the body back at each rocker, and strides came out
   5-14 % short;
4. **makes the floor two-sided for the standing foot.** The root height puts the lowest point of the feet exactly
   on the floor (a free foot above it may only not go through).

With no foot planted the root moves on at its velocity: the hips sensor's free acceleration integrated, corrected
towards the planted feet's velocity whenever a foot stands (``velocity_gain``), decaying without a hips sensor.

The 13-sensor suit gives everything above; without foot sensors the acceleration cue is missing, without a hips
sensor flight phases are not recognised (the last planted foot holds the root through them).

While cameras see the person the solve's root stands (it is absolute); contacts are still tracked at the solved
feet, so that they are ready when the cameras go. At either switch the *published* root starts from where it was
and moves to the new estimate by at most ``blend_step`` per frame: when cameras come back the solver's own root
goes to the cameras' position at once (its warm start is re-centred on the triangulated keypoints), and when they
go, the pose itself changes (the cameras no longer correct the IMUs' mounting errors) and the feet were not exactly
at the floor model's height.

The thresholds were chosen on the development split of ``mocapd/data/eval_splits.toml`` and the synthetic rig's
clips (``mocapd eval ground``, ``docs/imu.md``).

Pure: positions, times and measurements come in as arguments.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import numpy as np
from numpy.typing import NDArray

from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

FOOT_POINTS: tuple[tuple[str, str], tuple[str, str]] = (("LeftFoot", "LeftToes"), ("RightFoot", "RightToes"))
"""Each foot's ankle joint (the foot bone's origin) and toe joint (the toes bone's origin)."""

SOLE_POINTS = ("heel", "ball")
"""Where a foot touches the floor: the sole under and behind the ankle joint (the heel rocker) and under the toe
joint (the forefoot rocker, at the ball of the foot), both on the foot bone. The stance foot rolls from one to the
other; the toes, which no sensor measures, bend at the ball rather than lifting it."""

FOOT_SENSOR_BONES = ("LeftFoot", "RightFoot")


@dataclass(frozen=True)
class GroundOptions:
    """How the root is kept on the ground without cameras (see the module docstring)."""

    enabled: bool = True
    """Place the root from foot contacts below ``reference_views`` (False: the LM's root, as seed 003)."""
    reference_views: int = 2
    """Cameras that must see the person for the solve's root to count as absolute (the acceleration term's
    threshold, ``CostOptions.acceleration_min_views``, by the same reasoning)."""
    height_scale: float = 0.005
    """m: how sharply the lower foot takes the weight (a foot this much lower than the other carries 73 %)."""
    still_speed: float = 0.3
    """m/s: while cameras see the person, a foot moving this fast (in the world) carries half the weight."""
    moving_acceleration: float = 5.0
    """m/s²: a foot sensor's free acceleration at which its foot's weight halves (a moving foot carries less)."""
    lock_weight: float = 0.3
    """A free foot whose support reaches this is planted where it is."""
    free_weight: float = 0.1
    """A planted foot whose support falls below this is lifted (its anchor follows it again)."""
    airborne_acceleration: float = 6.5
    """m/s²: the hips sensor accelerating downwards faster than this means no foot carries the body (free fall
    is 9.8; walking stays above -5.5 on the evaluation clips)."""
    hold_s: float = 0.03
    """s: a planted foot is lifted once its support has stayed below ``free_weight`` this long (one frame of
    noise does not lift it), or at once when the body is airborne."""
    relock_s: float = 0.25
    """s: a foot put down again within this time of being lifted ..."""
    relock_distance: float = 0.03
    """m: ... and this close to where it was held goes back to its old anchor."""
    pivot_hysteresis: float = 0.01
    """m: the pivot passes from one sole point to another when that one is lower by this much."""
    heel_length: float = 0.025
    """Fraction of the body height: how far behind the ankle joint the heel touches the floor (4.4 cm at 1.75 m;
    Vicon markers of a shod walker put the heel rocker 2-5 cm behind the ankle joint centre)."""
    velocity_decay_s: float = 0.5
    """s: with no foot planted and no hips sensor, the time constant of the horizontal velocity's decay."""
    velocity_gain: float = 0.3
    """Per frame, how much of the gap between the predicted root velocity (hips sensor's acceleration integrated)
    and the planted feet's one is closed."""
    blend_step: float = 0.005
    """m per frame: how fast the published root moves to the cameras' one when they come back."""

    def __post_init__(self) -> None:
        if not isinstance(self.reference_views, int) or self.reference_views < 1:
            raise InputError(f"ground: reference_views must be an integer >= 1, got {self.reference_views!r}")
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("enabled", "reference_views"):
                continue
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise InputError(f"ground: {f.name} must be a positive finite number, got {v!r}")
        if not self.free_weight < self.lock_weight <= 1.0:
            raise InputError(
                f"ground: need free_weight < lock_weight <= 1, got {self.free_weight} and {self.lock_weight}"
            )


@dataclass
class FootState:
    """One foot's contact state."""

    planted: bool = False
    pivot: int = 0
    """Which of the foot's contact points (:data:`SOLE_POINTS`) holds it."""
    anchor: FloatArray = field(default_factory=lambda: np.zeros(3))
    """World position of the pivot: held while planted, following the foot while free (m)."""
    weight: float = 0.0
    """How much the foot supports the body this frame, in [0, 1]: being the lower foot (the two feet's height
    shares add up to 1), times its stillness."""
    unsupported_s: float = 0.0
    """For how long (s) the foot's support has been below ``free_weight``."""
    last: FloatArray | None = None
    """World positions of the contact points at the previous frame, shape (k, 3)."""
    held: dict[int, FloatArray] = field(default_factory=dict)
    """Where the other contact points were held when they last were this stance's pivot (a foot rocking between
    heel and toe returns to the same places instead of accumulating its joints' noise)."""

    lifted: tuple[int, FloatArray, dict[int, FloatArray]] | None = None
    """Pivot, anchor and held points when the foot was last lifted (a foot put down again at once, close by,
    goes back to them: noise that briefly lifts a standing foot does not move it)."""
    lifted_s: float = 0.0
    """Time since the foot was lifted (s)."""

    def copy(self) -> FootState:
        out = replace(self)
        out.anchor = self.anchor.copy()
        out.last = None if self.last is None else self.last.copy()
        out.held = {k: v.copy() for k, v in self.held.items()}
        return out


class GroundTracker:
    """One person's foot contacts and root placement, frame by frame.

    Parameters
    ----------
    standing_heights : array, shape (2, k)
        Per foot (left, right), the heights of its k contact points above the floor when it stands flat (the
        skeleton's rest pose, which stands on y = 0).
    floor_height : float
        World y of the floor (m).
    options : GroundOptions
    """

    def __init__(self, standing_heights: FloatArray, floor_height: float, options: GroundOptions) -> None:
        h = np.asarray(standing_heights, dtype=np.float64)
        if h.ndim != 2 or h.shape[0] != 2 or h.shape[1] < 1 or not np.all(np.isfinite(h)):
            raise InputError(f"ground: standing heights must be a finite (2, k) array, got {h.shape}")
        self.heights = h
        self.floor = float(floor_height)
        self.options = options
        self.reset()

    def reset(self) -> None:
        """Forget every contact and the mode (the next frame starts afresh)."""
        self.mode: str | None = None
        self.root = np.zeros(3)
        self.published = np.zeros(3)
        self.velocity = np.zeros(3)
        self.offset = np.zeros(3)
        self.feet = [FootState(), FootState()]

    def copy(self) -> GroundTracker:
        out = GroundTracker.__new__(GroundTracker)
        out.heights, out.floor, out.options = self.heights, self.floor, self.options
        out.mode = self.mode
        out.root, out.published = self.root.copy(), self.published.copy()
        out.velocity, out.offset = self.velocity.copy(), self.offset.copy()
        out.feet = [f.copy() for f in self.feet]
        return out

    @property
    def planted(self) -> tuple[bool, bool]:
        """Whether each foot (left, right) is planted."""
        return self.feet[0].planted, self.feet[1].planted

    # ------------------------------------------------------------------------------------------------ step
    def step(
        self,
        solved_root: FloatArray,
        relative: FloatArray,
        views: int,
        dt: float,
        foot_acc: FloatArray,
        root_acc: FloatArray | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """One frame: where the root is, given the solve.

        Parameters
        ----------
        solved_root : array, shape (3,)
            The root translation the solve ended at.
        relative : array, shape (2, k, 3)
            Per foot, its contact points relative to the root (world axes) under the solved rotations.
        views : int
            Cameras that saw the person this frame.
        dt : float
            Seconds since the previous frame.
        foot_acc : array, shape (2,)
            Free-acceleration magnitude of each foot's sensor (m/s²), NaN where there is none.
        root_acc : array, shape (3,), optional
            The hips sensor's free acceleration (world, gravity removed, m/s²), when there is one: carries the
            root's velocity through steps where no foot is planted.

        Returns
        -------
        root : array, shape (3,)
            The root translation to keep (the next warm start).
        published : array, shape (3,)
            The root translation to publish (differs from ``root`` only while blending to the cameras).
        """
        rel = np.asarray(relative, dtype=np.float64)
        acc = None if root_acc is None else np.asarray(root_acc, dtype=np.float64)
        predicted = self._predict_velocity(acc, dt)
        absolute = views >= self.options.reference_views
        solved = np.asarray(solved_root, dtype=np.float64)
        self._weigh(rel, np.asarray(foot_acc, dtype=np.float64), dt, solved + rel if absolute else None)
        if views >= self.options.reference_views:
            root = np.asarray(solved_root, dtype=np.float64).copy()
            if self.mode == "anchored":  # cameras are back: publish on from the IMU-only root, then blend
                self.offset = self.published + predicted * dt - root
        else:
            lost = self.mode == "camera"
            if lost:  # cameras lost: go on from the published root (anchors move with it)
                shift = self.published - self.root
                for foot in self.feet:
                    foot.anchor = foot.anchor + shift
                self.root = self.published.copy()
                self.offset = np.zeros(3)
            elif self.mode is None:  # a fresh start: the feet stand where the solve put them
                self.root = np.asarray(solved_root, dtype=np.float64).copy()
                self._update_feet(self.root, rel, follow=True)
            root = self._anchored_root(rel, dt, predicted)
            if lost:
                # The pose itself changes when the cameras stop correcting the IMUs' mounting errors (the legs can
                # swing by centimetres), and the feet were not at the floor model's height: publish on from where
                # the root was, blending to the estimate, rather than stepping.
                self.offset = self.root + predicted * dt - root
        supported = any(f.planted for f in self.feet) or views >= self.options.reference_views
        airborne = acc is not None and bool(np.isfinite(acc[1])) and acc[1] < -self.options.airborne_acceleration
        self._update_feet(root, rel, follow=views >= self.options.reference_views, airborne=airborne)
        if dt > 0 and self.mode is not None and supported:
            self.velocity = predicted + self.options.velocity_gain * ((root - self.root) / dt - predicted)
        else:
            self.velocity = predicted
        self.mode = "camera" if views >= self.options.reference_views else "anchored"
        self.root = root
        self.published = root + self.offset
        n = float(np.linalg.norm(self.offset))
        self.offset = self.offset * (max(0.0, n - self.options.blend_step) / n) if n > 0 else self.offset
        return root.copy(), self.published.copy()

    # ------------------------------------------------------------------------------------------- helpers
    def _lows(self, rel: FloatArray) -> FloatArray:
        """Per foot and point, the height above its standing height relative to the root, shape (2, k)."""
        return np.asarray(rel[:, :, 1] - self.heights)

    def _weigh(self, rel: FloatArray, foot_acc: FloatArray, dt: float, world: FloatArray | None) -> None:
        """Each foot's support: the lower foot carries the body (a logistic of the two feet's height difference),
        a foot whose sensor accelerates less so, and, where the cameras make the solved feet absolute (``world``,
        shape (2, k, 3)), a foot that moves less so."""
        o = self.options
        lows = self._lows(rel)
        low = lows.min(axis=1)
        z = float(np.clip((low[1] - low[0]) / o.height_scale, -50.0, 50.0))
        w = np.array([1.0 / (1.0 + math.exp(-z)), 1.0 / (1.0 + math.exp(z))])
        moving = np.where(np.isnan(foot_acc), 0.0, foot_acc) / o.moving_acceleration
        w = w / (1.0 + moving**2)
        for f, foot in enumerate(self.feet):
            if world is not None and foot.last is not None and dt > 0:
                k = int(np.argmin(lows[f]))
                speed = float(np.linalg.norm(world[f, k] - foot.last[k])) / dt
                w[f] /= 1.0 + (speed / o.still_speed) ** 2
            foot.weight = float(w[f])
            foot.unsupported_s = foot.unsupported_s + dt if foot.weight < o.free_weight else 0.0
            foot.lifted_s += dt

    def _predict_velocity(self, root_acc: FloatArray | None, dt: float) -> FloatArray:
        """The root velocity now, from the last one: the hips sensor's acceleration integrated over ``dt``, else
        the last velocity decaying (horizontal only: the floor decides the height)."""
        v = self.velocity.copy()
        if root_acc is not None and np.all(np.isfinite(root_acc)):
            v = v + root_acc * dt
        else:
            v = v * (math.exp(-dt / self.options.velocity_decay_s) if dt > 0 else 1.0)
        v[1] = 0.0
        return v

    def _anchored_root(self, rel: FloatArray, dt: float, velocity: FloatArray) -> FloatArray:
        """The root that keeps the planted feet's pivots on their anchors (weighted) and the lower foot on the
        floor; with no foot planted, the root moves on at the predicted velocity."""
        lows = self._lows(rel)
        planted = [(f, foot) for f, foot in enumerate(self.feet) if foot.planted]
        if planted:
            w = np.array([foot.weight for _, foot in planted]) + 1e-9
            c = np.array([foot.anchor - rel[f, foot.pivot] for f, foot in planted])
            root = (w[:, None] * c).sum(axis=0) / w.sum()
        else:
            root = self.root + velocity * dt
        # The floor is two-sided for the supporting (lower) foot: its lowest point sits on it.
        root[1] = self.floor - float(lows.min())
        return np.asarray(root)

    def _update_feet(self, root: FloatArray, rel: FloatArray, follow: bool, airborne: bool = False) -> None:
        """Plant, lift and re-pivot each foot at the world positions ``root + rel``.

        A foot is planted when its support reaches ``lock_weight``; a planted foot is lifted when its support has
        stayed below ``free_weight`` for ``hold_s``, or at once when the body is ``airborne`` (the hips fall
        freely: a run's flight phase, a jump).
        ``follow``: the root is absolute (cameras): the anchors of planted feet move to the solved feet.
        """
        o = self.options
        world = root + rel  # (2, k, 3)
        lows = self._lows(rel)
        for f, foot in enumerate(self.feet):
            if not foot.planted and foot.weight >= o.lock_weight:
                k = int(np.argmin(lows[f]))
                foot.planted = True
                foot.pivot = k
                foot.anchor = world[f, k].copy()
                foot.held = {}
                if (
                    foot.lifted is not None
                    and not follow
                    and foot.lifted[0] == k
                    and foot.lifted_s < o.relock_s
                    and float(np.linalg.norm((world[f, k] - foot.lifted[1])[[0, 2]])) < o.relock_distance
                ):
                    foot.anchor = foot.lifted[1].copy()
                    foot.held = foot.lifted[2]
        for foot in self.feet:
            if foot.planted and foot.weight < o.free_weight and (airborne or foot.unsupported_s >= o.hold_s):
                foot.planted = False
                foot.lifted = (foot.pivot, foot.anchor.copy(), foot.held)
                foot.lifted_s = 0.0
        for f, foot in enumerate(self.feet):
            foot.last = world[f].copy()
            k = int(np.argmin(lows[f]))
            if not foot.planted or follow:
                foot.pivot = k
                foot.anchor = world[f, k].copy()
                foot.held = {}
            elif k != foot.pivot and lows[f, k] < lows[f, foot.pivot] - o.pivot_hysteresis:
                # The foot rolls on (heel strike to flat, heel-off, onto the toes, or back): the lower point holds
                # it from now on, where it was held before in this stance, else placed from the old anchor by the
                # foot's own geometry (not from the root, which the other foot shares).
                held = foot.held.get(k)
                new = held if held is not None else foot.anchor + rel[f, k] - rel[f, foot.pivot]
                foot.held[foot.pivot] = foot.anchor
                foot.anchor = new.copy()
                foot.pivot = k


def standing_heights(rest_points: FloatArray) -> FloatArray:
    """Per foot, the heights of its contact points in the rest pose, shape (2, k), from their rest positions
    (2, k, 3)."""
    p = np.asarray(rest_points, dtype=np.float64)
    if p.ndim != 3 or p.shape[0] != 2 or p.shape[2] != 3:
        raise InputError(f"ground: rest foot points must have shape (2, k, 3), got {p.shape}")
    return np.asarray(p[:, :, 1])


def sole_points(skeleton: Skeleton, options: GroundOptions) -> tuple[IntArray, FloatArray]:
    """Each foot's :data:`SOLE_POINTS` as points on its bones, from the skeleton's rest pose (which stands flat on
    the floor, y = 0: the calibration posture).

    Returns
    -------
    bones : int array, shape (2, 3)
        Bone index of each point (left foot first).
    offsets : array, shape (2, 3, 3)
        Each point in its bone's frame (m).
    """
    rest = Kinematics(skeleton).forward(skeleton.rest_pose())
    bones = np.zeros((2, len(SOLE_POINTS)), dtype=np.intp)
    offsets = np.zeros((2, len(SOLE_POINTS), 3))
    for f, (ankle, toe) in enumerate(FOOT_POINTS):
        a, t = BONE_INDEX[ankle], BONE_INDEX[toe]
        # Rest rotations are identity: an offset in a bone's frame is the same vector in the world.
        ya = max(float(rest.positions[a, 1]), 0.0)
        yt = max(float(rest.positions[t, 1]), 0.0)
        bones[f] = (a, a)
        offsets[f, 0] = (0.0, -ya, -options.heel_length * skeleton.height)
        offsets[f, 1] = skeleton.offsets[t] + (0.0, -yt, 0.0)
    return bones, offsets

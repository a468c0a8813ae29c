"""A root that stays on the ground without cameras: foot contacts place the root translation (issue 14).

Without an absolute position reference (fewer than :attr:`GroundOptions.reference_views` cameras see the
person) nothing in seed 003's cost holds the root translation: the IMU orientation term fixes the bones'
rotations, the acceleration term is off (it would double-integrate noise), and only the floor hinge pushes the
feet up. A warm start that extrapolates the root's velocity then turns every upward push into a velocity that never
decays: on a real MTw recording the root floated from 0.93 m to 2.57 m in 25 s.

IMU-only motion capture places the root the way people walk: a planted foot does not move. Each foot touches the floor
at its sole (:func:`sole_points`: the heel and the ball of the foot, issue 28) and, past heel-off, at the tip of its
toes, which bend up at the ball (no sensor measures them). :class:`GroundTracker`

1. **weighs the feet.** The lower foot carries the body: each foot's *support* is a logistic of the two feet's
   height difference (every point measured against its standing height, its height in the skeleton's rest pose,
   which stands on y = 0; the relative heights come from the solved rotations alone), divided by
   ``1 + (a / moving_acceleration)²`` where ``a`` is the acceleration of the foot's *contact point* (the foot
   sensor's free acceleration plus the second difference of the contact point relative to the sensor under the solved
   rotations, over ``acceleration_window``: a stance foot rolling or pivoting about its heel or ball accelerates its
   sensor, not its contact point; a swinging foot accelerates both; with both feet measured, relative to the stiller
   foot's), and by ``1 + (v / still_speed)²`` for a foot
   moving at ``v``: while cameras make the solved feet absolute, its world speed; without them, the speed its lowest
   point would have if the root moved at the inertial reference velocity (below), relative to the stiller foot's (a
   sliding foot in a shuffle is as low as the standing one, but moves);
2. **plants and lifts feet.** A foot whose support reaches ``lock_weight`` is planted where it is, unless the body is
   airborne (the hips sensor falls freely: a run's flight phase, a jump; nothing is on the floor then); a planted foot
   whose support stays below ``free_weight`` for ``hold_s`` is lifted, at once when airborne. Unless airborne something
   stands: with no foot planted, the stiller foot is planted if it is still against the inertial reference (slower
   than ``still_speed``), however high the legs' mounting errors show it. A foot put down again at once, close by,
   returns to its old anchor, so noise that briefly lifts a standing foot does not move it;
3. **anchors the root.** A planted foot's pivot (its lowest point: the heel after heel strike, passing to the ball at
   heel-off and to the toe tip at push-off once the foot pitches beyond ``toe_bend``, and back as the foot rocks; a
   point taken up again in the same stance returns to where it was held) stays
   where it was planted; the root translation is the support-weighted mean of what puts each planted pivot on its
   anchor under the solved rotations. Planted feet that together carry less than ``lock_weight`` (a foot rolling off
   at the end of its stance, still held for ``hold_s``) hold it only in that share: the root moving on at its
   velocity (below) takes the rest, else the body stopped with the lifting foot. The pivot must be on the sole: a
   foot turning about a joint 5-7 cm above the floor (the ankle and toe joints, used before issue 28) drags the body
   back at each rocker, and strides came out 5-14 % short; held at the ball through push-off, the real walk against
   Vicon still came out 6 % short (3.7 % with the toe rocker);
4. **places the root's height between two bounds.** No sole point goes through the floor (the lowest sole point of
   the feet on it is the lowest the root may be), and unless airborne some part of a foot touches it: at most as high
   as puts the lowest *toe tip* (:func:`sole_points`: straight toes, on the foot bone, bent up at the ball by
   ``toe_bend``: a foot pitched heel-up by less holds its toes flat) on the floor. Flat on the floor the two bounds
   are one; on the toes (a bouncy walk's push-off, a run) the toes bend, nothing measures them, and the
   hips sensor's vertical acceleration integrated places the root between the bounds; in the air (flight phases,
   hops) it follows that acceleration alone until a foot lands. The acceleration is the sensor's, at its site (12 cm
   behind the root on the sacrum): the height integrated is that point's, the root below it by the site's height
   above the root under the solved rotations (a pelvis tilting through a bouncy stride moves the site, not the body).

With no foot planted the root moves on at its velocity: the hips sensor's free acceleration integrated, corrected
towards the planted feet's velocity whenever a foot stands (``velocity_gain``), decaying without a hips sensor. A
second, *inertial reference* velocity integrates the same acceleration but follows the planted feet only with the
time constant ``reference_time``: a foot held a moment too long, or a noisy frame, does not bend it, so the feet's
motion is judged against it.

The 13-sensor suit gives everything above; without foot sensors the acceleration cue is missing, without a hips
sensor flight phases are not recognised (the last planted foot holds the root through them) and the inertial
reference decays with the velocity.

While cameras see the person the solve's root stands (it is absolute); contacts are still tracked at the solved
feet, so that they are ready when the cameras go. At either switch the *published* root starts from where it was
and moves to the new estimate by at most ``blend_step`` per frame: when cameras come back the solver's own root
goes to the cameras' position at once (its warm start is re-centred on the triangulated keypoints), and when they
go, the pose itself changes (the cameras no longer correct the IMUs' mounting errors) and the feet were not exactly
at the floor model's height.

The thresholds were chosen on the development split of ``mocapd/data/eval_splits.toml`` and the synthetic rig's
clips (``mocapd eval ground``, ``docs/imu.md``); the causes of each change are measured there (issue 28).

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

SOLE_POINTS = ("heel", "ball", "toe_tip")
"""Where a foot touches the floor: the sole under and behind the ankle joint (the heel rocker) and under the toe
joint (the forefoot rocker, at the ball of the foot), both on the foot bone; the stance foot rolls from one to the
other and is held at them. Beyond the ball, the tip of the straight toes (also on the foot bone): no sensor measures
the toes, which lie flat on the floor as the heel rises and bend up at the ball, so the tracker bends this point up
by ``toe_bend`` (the toe rocker at push-off: :class:`GroundTracker`, ``reach``)."""

REACH_POINTS = 1
"""How many of :data:`SOLE_POINTS` (the last ones) are toe tips: bent up at the ball before they hold a foot, and
between the sole on the floor and them the root's height is free."""

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
    """m/s: a foot moving this fast carries half the weight (while cameras see the person, in the world; without
    them, against the inertial reference velocity and relative to the stiller foot)."""
    motion_window: float = 0.05
    """s: the span over which a foot's speed is measured without cameras (a frame's noise in the solved feet, about
    1 cm on the synthetic clips, would otherwise be 0.5 m/s at 60 Hz)."""
    moving_acceleration: float = 5.0
    """m/s²: the acceleration of a foot's contact point (its sensor's free acceleration plus the contact point's
    motion relative to the sensor), beyond the other foot's, at which the foot's weight halves (a moving foot carries
    less)."""
    acceleration_window: float = 0.067
    """s: the span of the second difference that gives a contact point's acceleration (4 frames at 60 Hz: a frame's
    orientation noise over a 10 cm lever would otherwise be tens of m/s²)."""
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
    toe_length: float = 0.04
    """Fraction of the body height: how far beyond the ball of the foot the toes reach (7 cm at 1.75 m; a foot is
    about 0.15 of the height long, its ball about 0.73 of that from the heel)."""
    toe_bend: float = 15.0
    """degrees: how far a foot pitches heel-up before its straight toes would lift the ball (and the root may rise
    above the ball on the floor). The toes bend at the ball, and a few degrees of pitch are the solved foot's error
    (a 5° mounting calibration error tips a rigid toe tip 6 mm below the ball) or a standing foot's roll, not a rise
    onto the toes: with a rigid toe tip the root of a punching clip stood up to 1.8 cm high."""
    velocity_decay_s: float = 0.5
    """s: with no foot planted and no hips sensor, the time constant of the horizontal velocity's decay."""
    velocity_gain: float = 0.3
    """Per frame, how much of the gap between the predicted root velocity (hips sensor's acceleration integrated)
    and the planted feet's one is closed."""
    reference_time: float = 0.3
    """s: the time constant with which the inertial reference velocity follows the planted feet's velocity."""
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


@dataclass
class _Frame:
    """What the tracker keeps of a past frame (for speeds and contact-point accelerations over a window)."""

    rel: FloatArray
    """The pivot-able sole points relative to the root, shape (2, k, 3)."""
    lever: FloatArray
    """Those points relative to each foot's sensor, shape (2, k, 3) (NaN without a sensor site)."""
    acc: FloatArray
    """Each foot sensor's free acceleration as given with the frame, shape (2, 3) (NaN without one)."""


HISTORY = 16
"""Frames kept for the windows (0.05-0.07 s are 3-5 frames at 60 Hz, 5-7 at 100 Hz)."""


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
    reach : int
        How many of the k points (the last ones, :data:`REACH_POINTS`) are the straight toes' tips: bent up at the ball
        by ``toe_bend`` they hold a foot as the others do, and bound the root's height from above only (the toes
        bend, nothing measures them); the others are sole points that hold a foot and that the floor holds up.
    """

    def __init__(
        self, standing_heights: FloatArray, floor_height: float, options: GroundOptions, reach: int = 0
    ) -> None:
        h = np.asarray(standing_heights, dtype=np.float64)
        if h.ndim != 2 or h.shape[0] != 2 or h.shape[1] < 1 or not np.all(np.isfinite(h)):
            raise InputError(f"ground: standing heights must be a finite (2, k) array, got {h.shape}")
        if not 0 <= reach < h.shape[1]:
            raise InputError(f"ground: reach must leave at least one sole point of {h.shape[1]}, got {reach}")
        self.heights = h
        self.reach = reach
        self.floor = float(floor_height)
        self.options = options
        self.reset()

    def reset(self) -> None:
        """Forget every contact and the mode (the next frame starts afresh)."""
        self.mode: str | None = None
        self.root = np.zeros(3)
        self.published = np.zeros(3)
        self.velocity = np.zeros(3)
        self.reference = np.zeros(3)
        """The inertial reference velocity (horizontal, m/s): see the module docstring."""
        self.height: float | None = None
        """The hips sensor's height while anchored, the root's without its site (None: from the feet at the next
        frame)."""
        self.vertical = 0.0
        """That point's vertical velocity while anchored (m/s)."""
        self.offset = np.zeros(3)
        self.feet = [FootState(), FootState()]
        self.history: list[_Frame] = []
        self.speeds: FloatArray | None = None
        """Each foot's horizontal speed against the inertial reference this frame (m/s, shape (2,); None with
        cameras or until the window is filled)."""

    def copy(self) -> GroundTracker:
        out = GroundTracker.__new__(GroundTracker)
        out.heights, out.reach, out.floor, out.options = self.heights, self.reach, self.floor, self.options
        out.mode = self.mode
        out.root, out.published = self.root.copy(), self.published.copy()
        out.velocity, out.reference, out.offset = self.velocity.copy(), self.reference.copy(), self.offset.copy()
        out.height, out.vertical = self.height, self.vertical
        out.feet = [f.copy() for f in self.feet]
        out.history = list(self.history)  # frames are never modified in place
        out.speeds = None if self.speeds is None else self.speeds.copy()
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
        foot_sites: FloatArray | None = None,
        root_site: FloatArray | None = None,
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
        foot_acc : array, shape (2, 3)
            Each foot sensor's free acceleration (world, gravity removed, m/s²), NaN where there is none.
        root_acc : array, shape (3,), optional
            The hips sensor's free acceleration (world, gravity removed, m/s²), when there is one: carries the
            root's velocity through steps where no foot is planted, and its height through flight phases.
        foot_sites : array, shape (2, 3), optional
            Each foot sensor's position relative to the root under the solved rotations (NaN where there is none):
            with it the acceleration cue is the contact point's, without it the sensor's own.
        root_site : array, shape (3,), optional
            The hips sensor's position relative to the root under the solved rotations: ``root_acc`` is that
            point's acceleration, so the height it integrates is that point's (without it, or NaN, the root's).

        Returns
        -------
        root : array, shape (3,)
            The root translation to keep (the next warm start).
        published : array, shape (3,)
            The root translation to publish (differs from ``root`` only while blending to the cameras).
        """
        o = self.options
        every = np.asarray(relative, dtype=np.float64)
        rel, tips = every[:, : every.shape[1] - self.reach], every[:, every.shape[1] - self.reach :]
        acc = None if root_acc is None else np.asarray(root_acc, dtype=np.float64)
        predicted = self._predict_velocity(acc, dt)
        absolute = views >= o.reference_views
        airborne = acc is not None and bool(np.isfinite(acc[1])) and acc[1] < -o.airborne_acceleration
        solved = np.asarray(solved_root, dtype=np.float64)
        sites = np.full((2, 3), np.nan) if foot_sites is None else np.asarray(foot_sites, dtype=np.float64)
        frame = _Frame(rel, rel - sites[:, None, :], np.asarray(foot_acc, dtype=np.float64).reshape(2, 3))
        # The points a planted foot can pivot on: the sole, and the toe tips where the toes are bent.
        piv = np.concatenate([rel, self._toe_tips(rel, tips)], axis=1)
        self._weigh(frame, dt, solved + rel if absolute else None)
        if absolute:
            root = solved.copy()
            self.height = None
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
                self.root = solved.copy()
                self._update_feet(self.root, piv, follow=True)
            lever = 0.0 if root_site is None else float(np.asarray(root_site, dtype=np.float64)[1])
            lever = lever if math.isfinite(lever) else 0.0
            root = self._anchored_root(rel, tips, dt, predicted, acc, airborne, piv, lever)
            if lost:
                # The pose itself changes when the cameras stop correcting the IMUs' mounting errors (the legs can
                # swing by centimetres), and the feet were not at the floor model's height: publish on from where
                # the root was, blending to the estimate, rather than stepping.
                self.offset = self.root + predicted * dt - root
        supported = any(f.planted for f in self.feet) or absolute
        self._update_feet(root, piv, follow=absolute, airborne=airborne)
        if dt > 0 and self.mode is not None and supported:
            self.velocity = predicted + o.velocity_gain * ((root - self.root) / dt - predicted)
        else:
            self.velocity = predicted
        self._update_reference(acc, root, dt, supported)
        self.history = [*self.history[1 - HISTORY :], frame]
        self.mode = "camera" if absolute else "anchored"
        self.root = root
        self.published = root + self.offset
        n = float(np.linalg.norm(self.offset))
        self.offset = self.offset * (max(0.0, n - o.blend_step) / n) if n > 0 else self.offset
        return root.copy(), self.published.copy()

    # ------------------------------------------------------------------------------------------- helpers
    def _lows(self, rel: FloatArray) -> FloatArray:
        """Per foot and sole point, the height above its standing height relative to the root, shape (2, k)."""
        return np.asarray(rel[:, :, 1] - self.heights[:, : rel.shape[1]])

    def _frames(self, window: float, dt: float) -> int:
        """A window (s) in frames of ``dt``, at least 1."""
        return max(1, round(window / dt)) if dt > 0 else 1

    def _weigh(self, frame: _Frame, dt: float, world: FloatArray | None) -> None:
        """Each foot's support: the lower foot carries the body (a logistic of the two feet's height difference),
        a foot whose contact point accelerates less so, and a foot that moves less so: in the world where the
        cameras make the solved feet absolute (``world``, shape (2, k, 3)), else against the inertial reference
        and relative to the stiller foot."""
        o = self.options
        lows = self._lows(frame.rel)
        low = lows.min(axis=1)
        z = float(np.clip((low[1] - low[0]) / o.height_scale, -50.0, 50.0))
        w = np.array([1.0 / (1.0 + math.exp(-z)), 1.0 / (1.0 + math.exp(z))])
        acc = self._contact_accelerations(frame, dt)
        if np.all(np.isfinite(acc)):
            # Relative to the stiller foot, as the motion: the acceleration says which foot stands, not whether one
            # does (a stance foot rolling over its toes accelerates too, and no foot standing is the hips sensor's
            # to say: airborne). Absolute, it lifted the standing foot of backward walks (development -6 … -11 %).
            acc = acc - acc.min()
        moving = acc / o.moving_acceleration
        w = w / (1.0 + np.where(np.isnan(moving), 0.0, moving) ** 2)
        if world is not None:
            self.speeds = None
            for f, foot in enumerate(self.feet):
                if foot.last is not None and dt > 0:
                    k = int(np.argmin(lows[f]))
                    v = float(np.linalg.norm(world[f, k] - foot.last[k])) / dt
                    w[f] /= 1.0 + (v / o.still_speed) ** 2
        else:
            speeds = self.speeds = self._speeds(frame.rel, lows, dt)
            if speeds is not None:
                # Relative to the stiller foot: the motion says which foot stands, not whether one does (a wrong
                # reference velocity would otherwise lift both and never be corrected).
                still = 1.0 / (1.0 + (speeds / o.still_speed) ** 2)
                w = w * still / still.max()
        for f, foot in enumerate(self.feet):
            foot.weight = float(w[f])
            foot.unsupported_s = foot.unsupported_s + dt if foot.weight < o.free_weight else 0.0
            foot.lifted_s += dt

    def _speeds(self, rel: FloatArray, lows: FloatArray, dt: float) -> FloatArray | None:
        """Each foot's horizontal speed (m/s, shape (2,)) over ``motion_window``: its lowest point's motion relative
        to the root plus the inertial reference velocity; None until the window is filled."""
        n = self._frames(self.options.motion_window, dt)
        if dt <= 0 or len(self.history) < n:
            return None
        past = self.history[-n].rel
        out = np.zeros(2)
        for f in range(2):
            k = int(np.argmin(lows[f]))
            u = self.reference + (rel[f, k] - past[f, k]) / (n * dt)
            out[f] = float(np.hypot(u[0], u[2]))
        return out

    def _contact_accelerations(self, frame: _Frame, dt: float) -> FloatArray:
        """|acceleration| (m/s², shape (2,)) of each foot's stillest sole point over ``acceleration_window``: the
        sensor's free acceleration plus the second difference of the point relative to the sensor (rigid-body
        kinematics: a point a rolling or pivoting foot turns about does not accelerate, its sensor does). Without a
        sensor site, or until the window is filled, the sensor's own acceleration; NaN without a sensor."""
        own: FloatArray = np.linalg.norm(frame.acc, axis=1)
        m = max(1, round(self.options.acceleration_window / (2 * dt))) if dt > 0 else 1
        if dt <= 0 or len(self.history) < 2 * m:
            return own
        past = self.history[-2 * m :]
        # The sensor's second difference over m frames from its accelerations (triangular weights 1..m..1 on the
        # 2m - 1 accelerations between), the points' from the solved poses.
        weights = np.r_[np.arange(1, m + 1), np.arange(m - 1, 0, -1)].astype(np.float64)
        accs = np.array([f.acc for f in [*past[1:], frame]])[::-1]  # newest first
        sensor = dt * dt * np.einsum("j,jfx->fx", weights, accs[: 2 * m - 1])
        lever = frame.lever - 2 * past[m].lever + past[0].lever
        point = np.linalg.norm((sensor[:, None, :] + lever) / (m * dt) ** 2, axis=-1).min(axis=1)
        return np.asarray(np.where(np.isfinite(point), point, own))

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

    def _update_reference(self, root_acc: FloatArray | None, root: FloatArray, dt: float, supported: bool) -> None:
        """The inertial reference velocity: the hips sensor's acceleration integrated, following the planted feet's
        velocity with the time constant ``reference_time`` (decaying like the velocity without a hips sensor)."""
        o = self.options
        if root_acc is not None and np.all(np.isfinite(root_acc)):
            self.reference = self.reference + root_acc * dt
        elif dt > 0:
            self.reference = self.reference * math.exp(-dt / o.velocity_decay_s)
        if dt > 0 and self.mode is not None and supported:
            self.reference = self.reference + min(1.0, dt / o.reference_time) * (
                (root - self.root) / dt - self.reference
            )
        self.reference[1] = 0.0

    def _anchored_root(
        self,
        rel: FloatArray,
        tips: FloatArray,
        dt: float,
        velocity: FloatArray,
        root_acc: FloatArray | None,
        airborne: bool,
        piv: FloatArray,
        lever: float = 0.0,
    ) -> FloatArray:
        """The root that keeps the planted feet's pivots on their anchors (weighted), with no foot planted moving on
        at the predicted velocity; its height between the floor's bounds (:meth:`_height`)."""
        planted = [(f, foot) for f, foot in enumerate(self.feet) if foot.planted]
        if planted:
            w = np.array([foot.weight for _, foot in planted]) + 1e-9
            c = np.array([foot.anchor - piv[f, foot.pivot] for f, foot in planted])
            # Planted feet that carry less than a foot needs to be planted (one rolling off at the end of its
            # stance, held for hold_s) do not hold the body alone: the root moving on at the predicted velocity
            # takes the weight they lack. Held by a lifting foot alone, the body stopped with it and carried the
            # slowed velocity into the swing (development backward walks -4 … -11 % over five noise draws).
            coast = max(0.0, self.options.lock_weight - float(w.sum()))
            root = ((w[:, None] * c).sum(axis=0) + coast * (self.root + velocity * dt)) / (w.sum() + coast)
        else:
            root = self.root + velocity * dt
        root[1] = self._height(rel, tips, dt, root_acc, airborne, lever)
        return np.asarray(root)

    def _height(
        self, rel: FloatArray, tips: FloatArray, dt: float, root_acc: FloatArray | None, airborne: bool, lever: float
    ) -> float:
        """The root's height: no sole point below the floor (the lowest bound), and unless airborne no higher than
        puts the lowest toe tip on it (the toes bend up at push-off: between the two the hips sensor's vertical
        acceleration integrated decides); flat on the floor the bounds are one."""
        lowest = self.floor - float(self._lows(rel).min())
        highest = lowest
        if tips.shape[1]:
            highest = max(lowest, self.floor - min(float(self._lows(rel).min()), float(self._reach(rel, tips).min())))
        if self.height is None or dt <= 0:
            self.height, self.vertical = lowest + lever, 0.0
            return lowest
        # The acceleration is the hips sensor's, at its site (``lever`` above the root; 12 cm behind it in the
        # 13-sensor suit): the height integrated is the site's, the root is ``lever`` below it. Integrated as the
        # root's, the pelvis's tilt through a bouncy stride passed for a vertical motion of the body (fed the
        # development walks' true poses, root height p95 2.8 cm; 2.0 cm at the site).
        guess = self.height + self.vertical * dt - lever
        y = max(guess, lowest) if airborne else min(max(guess, lowest), highest)
        ay = float(root_acc[1]) if root_acc is not None and np.isfinite(root_acc[1]) else 0.0
        # Held by a bound, the root moves with it; free, the site moves with the hips sensor's acceleration.
        self.vertical = (y + lever - self.height) / dt if y != guess else self.vertical + ay * dt
        self.height = y + lever
        return y

    def _toe_tips(self, rel: FloatArray, tips: FloatArray) -> FloatArray:
        """The toe tips, bent up at the ball by ``toe_bend`` (flat on the floor while the foot pitches heel-up by
        less: the toes lie on the floor while the heel rises), relative to the root, shape (2, r, 3); ``tips`` are
        the straight toes' tips (on the foot bone)."""
        ball = rel[:, -1:]
        v = tips - ball
        length = np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)
        h = v * np.array([1.0, 0.0, 1.0])
        hn = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-9)
        pitch = np.arcsin(np.clip(-v[..., 1:2] / length, -1.0, 1.0))
        p2 = np.maximum(pitch - math.radians(self.options.toe_bend), 0.0)
        return np.asarray(ball + length * (hn * np.cos(p2) - np.array([0.0, 1.0, 0.0]) * np.sin(p2)))

    def _reach(self, rel: FloatArray, tips: FloatArray) -> FloatArray:
        """How low each foot's toe tips (:meth:`_toe_tips`) reach, against their standing heights, relative to the
        root, shape (2, r)."""
        return np.asarray(self._toe_tips(rel, tips)[:, :, 1] - self.heights[:, self.heights.shape[1] - self.reach :])

    def _plant(self, f: int, world: FloatArray, lows: FloatArray, follow: bool) -> None:
        """Plant foot ``f`` at its lowest point of ``world`` (shape (2, k, 3)); put down again at once, close by, it
        goes back to its old anchor."""
        o = self.options
        foot = self.feet[f]
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

    def _update_feet(self, root: FloatArray, rel: FloatArray, follow: bool, airborne: bool = False) -> None:
        """Plant, lift and re-pivot each foot at the world positions ``root + rel``.

        A foot is planted when its support reaches ``lock_weight``, unless the body is ``airborne`` (the hips fall
        freely: a run's flight phase, a jump: nothing stands on the floor, and a foot planted in the air would stop
        the body); a planted foot is lifted when its support has stayed below ``free_weight`` for ``hold_s``, or at
        once when airborne.
        ``follow``: the root is absolute (cameras): the anchors of planted feet move to the solved feet.
        """
        o = self.options
        world = root + rel  # (2, k, 3)
        lows = self._lows(rel)
        for f, foot in enumerate(self.feet):
            if not foot.planted and foot.weight >= o.lock_weight and not airborne:
                self._plant(f, world, lows, follow)
        for foot in self.feet:
            if foot.planted and foot.weight < o.free_weight and (airborne or foot.unsupported_s >= o.hold_s):
                foot.planted = False
                foot.lifted = (foot.pivot, foot.anchor.copy(), foot.held)
                foot.lifted_s = 0.0
        speeds = self.speeds
        if not airborne and not follow and speeds is not None and not any(foot.planted for foot in self.feet):
            # A foot that does not move against the inertial reference stands, however high it looks: with no foot
            # planted the stiller one is, if it is still, holding the root in its share only (the rest coasts,
            # :meth:`_anchored_root`). Else a standing foot that the legs' mounting errors show a centimetre higher
            # than the one swinging past it (the height cue's scale is 5 mm) planted no foot for frames at a
            # hand-over and the root coasted (development walks with an 8° mounting error: -16.4 % at worst over 40
            # noise draws). Only a still one: in a run's flight, which the hips sensor does not always show, neither
            # foot is, and a foot planted there stops the body.
            f = int(np.argmin(speeds))
            if speeds[f] < o.still_speed and self.feet[f].weight > 0.0:
                self._plant(f, world, lows, follow)
        for f, foot in enumerate(self.feet):
            foot.last = world[f].copy()
            k = int(np.argmin(lows[f]))
            if not foot.planted or follow:
                foot.pivot = k
                foot.anchor = world[f, k].copy()
                foot.held = {}
            elif k != foot.pivot and lows[f, k] < lows[f, foot.pivot] - o.pivot_hysteresis:
                # The foot rolls on (heel strike to flat, heel-off, or back): the lower point holds it from now on,
                # where it was held before in this stance, else placed from the old anchor by the foot's own geometry
                # (not from the root, which the other foot shares).
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
    """Each foot's :data:`SOLE_POINTS` as points on its foot bone, from the skeleton's rest pose (which stands flat on
    the floor, y = 0: the calibration posture): the heel ``heel_length`` behind the ankle, the ball under the toe
    joint and the toe tip ``toe_length`` beyond the ball (straight ahead of the foot), all at floor height.

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
        ahead = skeleton.offsets[t] * np.array([1.0, 0.0, 1.0])
        ahead = ahead / max(float(np.linalg.norm(ahead)), 1e-9)
        bones[f] = a
        offsets[f, 0] = (0.0, -ya, -options.heel_length * skeleton.height)
        offsets[f, 1] = skeleton.offsets[t] + (0.0, -yt, 0.0)
        offsets[f, 2] = offsets[f, 1] + options.toe_length * skeleton.height * ahead
    return bones, offsets

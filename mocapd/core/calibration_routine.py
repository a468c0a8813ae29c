"""The guided IMU calibration routine: stand, walk a few steps, bend the elbows (pure; fed samples as they come).

What the wearer does, in order, and what the routine says at each step (docs/imu.md, "Calibrating a suit live"):

1. **stand**: stand still, facing forward, arms relaxed (a T-pose, an A-pose or arms down: the posture is estimated,
   the hint only helps); done when every sensor has been still for ``window_s`` by both stillness tests
   (:func:`mocapd.core.imu_calibration.stillest_common_window`);
2. **walk**: walk a few steps (forward and back, or on the spot); done when each knee has bent past
   :data:`KNEE_BENT_DEG` and straightened again ``steps`` times in all. The steps give the facing direction
   (:func:`mocapd.core.imu_calibration.facing_heading_from_steps`) and the knees' hinge axes;
3. **elbows**: bend both elbows a few times, palms facing in, upper arms still; done when each elbow has bent past
   :data:`ELBOW_BENT_DEG` and straightened again ``bends`` times;
4. **done**: the calibration from the stand, the facing from the steps, the mountings refined by the knees' and
   elbows' axes (:func:`mocapd.core.functional_calibration.refine_mountings`) and by gravity in the walk's stances
   (:func:`mocapd.core.stance_calibration.refine_from_stances`, where consistent); or **failed** with the reason (a
   step not done within ``step_timeout_s``, a facing the steps could not give, a still window refused).

A step the suit cannot do is skipped (no thigh and shank on either leg: no walking, and the facing must be given;
no upper arm and forearm: no elbows).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.functional_calibration import HINGES, refine_from_recording
from mocapd.core.imu_calibration import (
    MAX_ACC_STD,
    MAX_TURN_DEG,
    ImuCalibration,
    Samples,
    calibrate_recording,
    common_grid,
    facing_heading_from_steps,
    quat_average,
    stillest_common_window,
    window_samples,
)
from mocapd.core.knee_extension import refine_knee_extension
from mocapd.core.rotations import quat_angle, quat_conjugate, quat_multiply
from mocapd.core.stance_calibration import refine_from_stances
from mocapd.errors import CalibrationError, ConfigError

FloatArray = NDArray[np.float64]

KNEE_BENT_DEG = 30.0
"""A knee counts a step when it bends past this from the stand (degrees) and comes back within half of it."""
ELBOW_BENT_DEG = 60.0
"""An elbow counts a bend past this from the stand (degrees), back within half of it."""
MAX_SECONDS = 120.0
"""The most of the routine's samples kept (seconds): a routine that takes longer fails on its step time-out first."""

STEPS = ("stand", "walk", "elbows")

SAY = {
    "stand": "stand still, facing forward, arms relaxed ({pose} hint), for {window:g} s",
    "walk": "walk {steps} steps (forward and back, or on the spot)",
    "elbows": "bend both elbows {bends} times, palms in, upper arms still",
}
"""What the routine asks for at each step."""


@dataclass(frozen=True)
class RoutineOptions:
    """How much of each movement the routine asks for."""

    pose: str = "n-pose"
    """The posture hint of the stand (``"t-pose"``, ``"a-pose"``, ``"n-pose"``)."""
    window_s: float = 1.0
    steps: int = 4
    bends: int = 2
    step_timeout_s: float = 60.0
    max_turn_deg: float = MAX_TURN_DEG
    max_acc_std: float = MAX_ACC_STD
    facing_heading_deg: float | None = None
    """The compass heading faced in the stand, when known; None: from the steps."""
    world_heading: str = "subject"


@dataclass
class _Hinge:
    """A knee's or an elbow's bends counted from the stand."""

    parent: str  # sensor ids
    child: str
    bent: bool = False
    count: int = 0
    reference: FloatArray | None = None  # the relative rotation in the stand (4,)
    seen: float = -np.inf  # the last sample time counted (s)


@dataclass
class CalibrationRoutine:
    """One run of the routine for one suit (``bones``: sensor id -> bone); :meth:`feed` it samples as they come."""

    person: str
    bones: dict[str, str]
    options: RoutineOptions = field(default_factory=RoutineOptions)
    step: str = "stand"
    said: list[tuple[float, str]] = field(default_factory=list)
    """Everything the routine said, with the time (s) it said it."""
    calibration: ImuCalibration | None = None
    report: dict[str, object] = field(default_factory=dict)
    _t: dict[str, list[FloatArray]] = field(default_factory=dict)
    _q: dict[str, list[FloatArray]] = field(default_factory=dict)
    _a: dict[str, list[FloatArray]] = field(default_factory=dict)
    _started: float | None = None
    _step_since: float = 0.0
    _window: tuple[float, float] | None = None
    _walk: tuple[float, float] = (np.inf, -np.inf)
    _hinges: dict[str, _Hinge] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.options.pose not in ("t-pose", "a-pose", "n-pose", "arms-down"):
            raise ConfigError(f"calibration routine: pose hint must be t-pose, a-pose or n-pose, got "
                              f"{self.options.pose!r}")  # fmt: skip
        by_bone = {b: sid for sid, b in self.bones.items()}
        for name, (parent, child, _) in HINGES.items():
            if parent in by_bone and child in by_bone:
                self._hinges[name] = _Hinge(by_bone[parent], by_bone[child])
        if not self._knees() and self.options.facing_heading_deg is None:
            raise ConfigError("calibration routine: no thigh and shank on either leg to take the facing from the "
                              "steps; give the heading faced (facing_heading)")  # fmt: skip

    def _knees(self) -> list[_Hinge]:
        return [h for n, h in self._hinges.items() if n.endswith("knee")]

    def _elbows(self) -> list[_Hinge]:
        return [h for n, h in self._hinges.items() if n.endswith("elbow")]

    # ------------------------------------------------------------------------------------------ what it says
    def instruction(self) -> str:
        """What the wearer is asked to do now."""
        o = self.options
        if self.step in SAY:
            return SAY[self.step].format(pose=o.pose, window=o.window_s, steps=o.steps, bends=o.bends)
        return "done" if self.step == "done" else "failed"

    def progress(self) -> str:
        """How far the current step is (what it still needs)."""
        if self.step == "walk":
            return f"steps {sum(h.count for h in self._knees())}/{self.options.steps}"
        if self.step == "elbows":
            return ", ".join(f"{n.split('_')[0]} elbow {h.count}/{self.options.bends}"
                             for n, h in self._hinges.items() if n.endswith("elbow"))  # fmt: skip
        return ""

    def status(self, now_s: float) -> dict[str, object]:
        """The routine's state for /status and the WebSocket: the step, what to do, progress, what it said."""
        return {
            "person": self.person,
            "step": self.step,
            "do": self.instruction(),
            "progress": self.progress(),
            "step_s": round(now_s - self._step_since, 1) if self._started is not None else 0.0,
            "said": [{"s": round(t - (self._started or t), 1), "text": text} for t, text in self.said[-12:]],
            **({"result": self.report} if self.report else {}),
        }

    def _say(self, now_s: float, text: str) -> None:
        self.said.append((now_s, text))

    def _next(self, now_s: float, done: str) -> None:
        """Say what was done and move to the next step the suit can do."""
        order = [s for s in STEPS if s != "walk" or self._knees()]
        order = [s for s in order if s != "elbows" or self._elbows()]
        following = order[order.index(self.step) + 1] if order.index(self.step) + 1 < len(order) else "done"
        self.step, self._step_since = following, now_s
        if following == "done":
            self._say(now_s, f"{done}; calibrating")
            self._finish(now_s)
        else:
            self._say(now_s, f"{done}; now {self.instruction()}")

    def cancel(self, now_s: float, reason: str) -> None:
        """Stop the routine (it fails with ``reason``)."""
        self._fail(now_s, reason)

    def _fail(self, now_s: float, reason: str) -> None:
        self.step = "failed"
        self.report = {"error": reason}
        self._say(now_s, f"failed: {reason}")

    # ------------------------------------------------------------------------------------------ samples
    def start(self, now_s: float) -> None:
        """Begin (says the first instruction)."""
        self._started = self._step_since = now_s
        self._say(now_s, self.instruction())

    def feed(self, now_s: float, samples: Mapping[str, tuple[FloatArray, FloatArray, FloatArray]]) -> None:
        """New samples per sensor (times s (n,), device-frame orientations (n, 4), specific force (n, 3)), then the
        step's test. Sensors of other suits are ignored."""
        if self._started is None:
            self.start(now_s)
        if self.step in ("done", "failed"):
            return
        for sid, (t, q, a) in samples.items():
            if sid in self.bones and len(t):
                self._t.setdefault(sid, []).append(np.asarray(t, dtype=np.float64))
                self._q.setdefault(sid, []).append(np.asarray(q, dtype=np.float64))
                self._a.setdefault(sid, []).append(np.asarray(a, dtype=np.float64))
        if now_s - self._step_since > self.options.step_timeout_s:
            self._fail(now_s, f"no {self.step} within {self.options.step_timeout_s:g} s ({self.instruction()}"
                              + (f"; {self.progress()}" if self.progress() else "") + ")")  # fmt: skip
            return
        if self.step == "stand":
            self._test_stand(now_s)
        elif self.step in ("walk", "elbows"):
            self._count(now_s, self._knees() if self.step == "walk" else self._elbows())

    def samples(self) -> dict[str, tuple[FloatArray, FloatArray, FloatArray]]:
        """Everything recorded so far, per sensor (times, orientations, accelerations)."""
        out = {}
        for sid in self._t:
            t = np.concatenate(self._t[sid])
            keep = t >= t[-1] - MAX_SECONDS
            out[sid] = (t[keep], np.concatenate(self._q[sid])[keep], np.concatenate(self._a[sid])[keep])
            self._t[sid], self._q[sid], self._a[sid] = [out[sid][0]], [out[sid][1]], [out[sid][2]]
        return out

    def _test_stand(self, now_s: float) -> None:
        samples = self.samples()
        if set(samples) != set(self.bones):
            return  # a sensor not heard yet
        o = self.options
        t_end = min(float(t[-1]) for t, _, _ in samples.values())
        span = (max(t_end - 2.0 * o.window_s, self._step_since - 1.0), t_end)
        try:
            start, end = stillest_common_window(samples, o.window_s, span, max_turn_deg=o.max_turn_deg,
                                                max_acc_std=o.max_acc_std)  # fmt: skip
            calibrate_recording(self.person, samples, self.bones, facing_heading_deg=0.0, window_s=o.window_s,
                                span=(start, end), pose=o.pose, max_turn_deg=o.max_turn_deg,
                                max_acc_std=o.max_acc_std)  # fmt: skip
        except CalibrationError:
            return  # not still yet (or not long enough)
        self._window = (start, end)
        for h in self._hinges.values():
            h.reference = _relative(samples, h, start, end)
        self._next(now_s, f"still stand {start:.1f}-{end:.1f} s")

    def _count(self, now_s: float, hinges: list[_Hinge]) -> None:
        samples = self.samples()
        for h in hinges:
            if h.parent not in samples or h.child not in samples or h.reference is None:
                continue
            limit = KNEE_BENT_DEG if self.step == "walk" else ELBOW_BENT_DEG
            for t, a in zip(*_bend_since(samples, h, self._step_since - 0.5), strict=True):
                if not h.bent and a > limit:
                    h.bent = True
                    if self.step == "walk":  # the walk's span: from its first bend to its last straightening
                        self._walk = (min(self._walk[0], float(t) - 0.5), self._walk[1])
                elif h.bent and a < limit / 2:
                    h.bent = False
                    h.count += 1
                    if self.step == "walk":
                        self._walk = (self._walk[0], max(self._walk[1], float(t) + 0.2))
        needed = self.options.steps if self.step == "walk" else self.options.bends
        total = sum(h.count for h in hinges)
        done = total >= needed if self.step == "walk" else all(h.count >= needed for h in hinges)
        if done:
            what = f"{total} steps" if self.step == "walk" else "elbow bends " + self.progress()
            self._next(now_s, what)

    def _finish(self, now_s: float) -> None:
        samples = self.samples()
        assert self._window is not None
        o = self.options
        heading = o.facing_heading_deg
        if heading is None:
            # from the walk alone: the knees bend through most of it (the stand and the elbows would dilute them)
            stand, walk = self._window, self._walk
            kept = {sid: (t[sel], q[sel], a[sel]) for sid, (t, q, a) in samples.items()
                    for sel in [((t >= stand[0]) & (t < stand[1])) | ((t >= walk[0]) & (t <= walk[1]))]}  # fmt: skip
            heading = facing_heading_from_steps(kept, self.bones, stand)
            if heading is None:
                self._fail(now_s, "the steps gave no facing direction (did the knees bend?)")
                return
        try:
            calib, window = calibrate_recording(self.person, samples, self.bones, facing_heading_deg=heading,
                                                world_heading=o.world_heading, window_s=o.window_s, span=self._window,
                                                pose=o.pose, max_turn_deg=o.max_turn_deg,
                                                max_acc_std=o.max_acc_std)  # fmt: skip
        except CalibrationError as exc:
            self._fail(now_s, str(exc))
            return
        refined = refine_from_recording(calib, samples, window)
        extended = refine_knee_extension(refined.calibration, samples, window)
        by_stances = refine_from_stances(extended.calibration, samples, window)
        self.calibration = by_stances.calibration
        self.report = {"facing_heading_deg": round(heading, 1), "window_s": [round(v, 2) for v in window],
                       "hinge_axes": refined.hinges, "knee_extension": extended.knees,
                       "stance_gravity": by_stances.sensors, **self.calibration.summary()}  # fmt: skip
        worst = self.calibration.summary()["worst"]
        tail = f", worst residual {worst['residual_deg']} deg ({worst['bone']})" if isinstance(worst, dict) else ""
        self._say(now_s, f"done: facing {heading:.0f} deg from the steps{tail}")


def _relative(samples: Samples, h: _Hinge, start: float, end: float) -> FloatArray:
    """The child sensor's orientation in the parent's, averaged over the stand (4,)."""
    t, q = common_grid(samples, [h.parent, h.child])
    sel = window_samples(t, start, end)
    return quat_average(quat_multiply(quat_conjugate(q[h.parent][sel]), q[h.child][sel]))


def _bend_since(samples: Samples, h: _Hinge, since: float) -> tuple[FloatArray, FloatArray]:
    """The times (s) of the samples from ``since`` on not yet counted and how far the joint had turned from the
    stand at each (degrees)."""
    assert h.reference is not None
    t, q = common_grid(samples, [h.parent, h.child])
    sel = t > max(since, h.seen)
    if sel.any():
        h.seen = float(t[sel][-1])
    rel = quat_multiply(quat_conjugate(q[h.parent][sel]), q[h.child][sel])
    return t[sel], np.asarray(np.degrees(quat_angle(rel, h.reference)), dtype=np.float64)

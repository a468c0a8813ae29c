"""Predicted output: each suit wearer's solved pose carried from the solve instant to the IMUs' newest instant.

The scheduler solves ``t = now - latency`` with every input (the cameras are what is late); in ``"predicted"``
output the pose of a person wearing a suit is then carried forward to ``t'``, the newest instant every live sensor of
the suit has measured (one IMU sample and the transport behind ``now``), with what the sensors measured between
``t`` and ``t'`` (:func:`mocapd.core.prediction.carry_forward`):

- bone rotations: each sensor's own rotation over the interval (heading-free), spine and neck sharing the change
  between the sensors around them, other bones following their parents;
- root position: the pelvis sensor's site ``s`` (where its accelerations are measured) moves as
  ``s(t') = s(t) + v·(t' - t) + ∫∫ w(τ) a(τ)``: ``v`` the velocity of the fused solution (least-squares slope of
  the solved site over the last ``velocity_window_s``, which is the velocity at the window's middle, advanced to
  ``t`` with the measured acceleration), ``a`` the sensor's free acceleration (world frame, gravity removed), its
  weight ``w`` decaying as ``exp(-(τ - t)/acceleration_decay_s)`` so a long gap falls back to velocity only, and
  the acceleration's part bounded by ``max_acceleration_displacement_m``. The root is then the site minus the
  mount offset turned by the carried pelvis rotation.

A sensor whose newest sample is more than ``stalled_s`` older than the suit's newest (unplugged, stalled USB) is
left out (its bone follows its parent) rather than holding everyone back; with no live sensor, or without a newer
sample than ``t``, the delayed pose is published unchanged (``t' = t``).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.prediction import CarryPlan, carry_forward, carry_plan
from mocapd.core.rotations import (
    matrix_from_quat,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_slerp,
)
from mocapd.core.skeleton import N_BONES
from mocapd.errors import InputError
from mocapd.pipeline.ringbuffer import RingBuffer

FloatArray = NDArray[np.float64]
OUTPUTS = ("delayed", "predicted")
GRAVITY = 9.81


@dataclass(frozen=True)
class PredictionOptions:
    """What the scheduler publishes for suit wearers (validated on construction)."""

    output: str = "delayed"
    """"delayed": the solve at ``now - latency``; "predicted": that solve carried to the IMUs' newest instant."""
    max_horizon_s: float = 0.5
    """Never carry a pose further than this past its solve instant (seconds)."""
    stalled_s: float = 0.05
    """A sensor this much behind its suit's newest sample is left out of the prediction (seconds)."""
    velocity_window_s: float = 0.3
    """Solved positions the root velocity is fitted over (seconds)."""
    acceleration_decay_s: float = 0.5
    """Time constant of the weight of the pelvis sensor's acceleration over the gap (seconds)."""
    max_acceleration_displacement_m: float = 0.1
    """Bound on the acceleration's share of the root displacement (metres)."""
    max_speed_m_s: float = 10.0
    """Bound on the fitted root speed (a glitch in the solved history must not fling the root)."""

    def __post_init__(self) -> None:
        if self.output not in OUTPUTS:
            raise InputError(f"output must be one of {list(OUTPUTS)}, got {self.output!r}")
        for name in ("max_horizon_s", "stalled_s", "velocity_window_s", "acceleration_decay_s",
                     "max_acceleration_displacement_m", "max_speed_m_s"):  # fmt: skip
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise InputError(f"prediction option {name} must be a finite number > 0, got {v!r}")

    @property
    def predicted(self) -> bool:
        return self.output == "predicted"


@dataclass(frozen=True)
class SuitState:
    """What the scheduler knows about one suit at the solve instant ``t``.

    Attributes
    ----------
    bones : int array, shape (n,)
        Bone index of each sensor.
    q_ib : array, shape (n, 4)
        Mounting rotations (sensor → bone).
    q_wg : array, shape (n, 4)
        Each sensor's global frame → world (heading alignment, with any heading correction applied).
    q_i : array, shape (n, 4)
        Sensor orientations at ``t`` (device frame), valid where ``mask``.
    mask : bool array, shape (n,)
    buffers : list of RingBuffer or None, length n
        Each sensor's buffer (None: no stream).
    offsets_ns : int array, shape (n,)
        Each sensor's configured time offset (its buffered times run this far ahead of the host clock).
    hips : int or None
        Index of the pelvis sensor, if the suit has one.
    hips_site : array, shape (3,)
        That sensor's position on the pelvis (bone frame, metres).
    """

    bones: NDArray[np.intp]
    q_ib: FloatArray
    q_wg: FloatArray
    q_i: FloatArray
    mask: NDArray[np.bool_]
    buffers: Sequence[RingBuffer | None]
    offsets_ns: NDArray[np.int64]
    hips: int | None
    hips_site: FloatArray


@dataclass(frozen=True)
class Prediction:
    theta: FloatArray  # (66,)
    t_ns: int  # the instant the pose is for
    sensors: int  # sensors that measured the interval


class PosePredictor:
    """Carries suit wearers' solved poses forward (see the module docstring); one per scheduler."""

    def __init__(self, options: PredictionOptions | None = None, gravity: float = GRAVITY) -> None:
        self.options = options if options is not None else PredictionOptions()
        self.gravity = np.array([0.0, gravity, 0.0])
        self._sites: dict[str, deque[tuple[int, FloatArray]]] = {}
        self._plans: dict[tuple[tuple[int, ...], tuple[int, ...]], CarryPlan] = {}

    def forget(self, keep: set[str]) -> None:
        """Drop the history of identities not in ``keep``."""
        for identity in [k for k in self._sites if k not in keep]:
            del self._sites[identity]

    def predict(
        self, identity: str, theta: FloatArray, parents: Sequence[int], t_ns: int, suit: SuitState
    ) -> Prediction:
        """The pose of ``identity`` solved at ``t_ns`` (θ (66,)) carried to its suit's newest instant."""
        o = self.options
        site = self._record(identity, theta, t_ns, suit)
        newest = np.full(len(suit.bones), np.iinfo(np.int64).min, dtype=np.int64)
        for i, buf in enumerate(suit.buffers):
            if buf is not None and suit.mask[i] and len(buf):
                newest[i] = int(buf.times()[-1]) - int(suit.offsets_ns[i])
        live = newest > t_ns
        if not live.any():
            return Prediction(theta, t_ns, 0)
        live &= newest >= newest.max() - round(o.stalled_s * 1e9)
        t1 = int(min(newest[live].min(), t_ns + round(o.max_horizon_s * 1e9)))
        idx = np.flatnonzero(live)
        q1, ok = _orientations_at([suit.buffers[i] for i in idx.tolist()], t1 + suit.offsets_ns[idx])
        live[idx[~ok]] = False  # (before idx shrinks: one tuple assignment would index with the new idx)
        idx = idx[ok]
        if not live.any():
            return Prediction(theta, t_ns, 0)
        turn = quat_multiply(quat_conjugate(suit.q_i[idx]), q1[ok])  # each sensor's own rotation, t -> t1
        deltas = np.tile([1.0, 0.0, 0.0, 0.0], (N_BONES, 1))
        deltas[suit.bones[idx]] = quat_multiply(quat_multiply(suit.q_ib[idx], turn), quat_conjugate(suit.q_ib[idx]))
        if not live.any():
            return Prediction(theta, t_ns, 0)
        key = (tuple(parents), tuple(int(b) for b in suit.bones[live]))
        plan = self._plans.get(key)
        if plan is None:
            plan = self._plans[key] = carry_plan(parents, key[1])
        out = carry_forward(theta, parents, plan, deltas, np.zeros(3))
        # Root: move the pelvis sensor's site, then hang the root from it with the carried pelvis rotation.
        s1 = site + self._site_displacement(identity, t_ns, t1, suit)
        out[0:3] = s1 - _rotate(out[3:6], suit.hips_site)
        return Prediction(out, t1, int(live.sum()))

    # ------------------------------------------------------------------------------------------ root
    def _record(self, identity: str, theta: FloatArray, t_ns: int, suit: SuitState) -> FloatArray:
        """The solved pelvis-sensor site at ``t_ns`` (world), kept for the velocity fit."""
        site = theta[0:3] + _rotate(theta[3:6], suit.hips_site)
        hist = self._sites.setdefault(identity, deque(maxlen=64))
        if hist and t_ns <= hist[-1][0]:
            hist.clear()  # a replay restarted, or a re-solve of the same instant: start over
        hist.append((t_ns, site))
        while hist and hist[0][0] < t_ns - round(2 * self.options.velocity_window_s * 1e9):
            hist.popleft()
        return site

    def _site_displacement(self, identity: str, t0: int, t1: int, suit: SuitState) -> FloatArray:
        """How far the pelvis sensor's site moves from ``t0`` to ``t1`` (metres, world).

        The solved sites over the last ``velocity_window_s`` are fitted by ``s0 + v·τ + D(τ)``, with ``D`` the
        measured acceleration integrated twice from ``t0`` (least squares in ``s0`` and ``v``): the acceleration
        explains the curvature, so a window long enough to average out the solves' noise adds no lag. Forward,
        the displacement is ``v·dt`` plus the double integral of the acceleration weighted by its decay.
        """
        o = self.options
        hist = [(t, s) for t, s in self._sites.get(identity, ()) if t >= t0 - round(o.velocity_window_s * 1e9)]
        if len(hist) < 2:
            return np.zeros(3)
        ts = np.array([(t - t0) / 1e9 for t, _ in hist])
        xs = np.array([s for _, s in hist])
        dt = (t1 - t0) / 1e9
        acc = self._free_acceleration(suit, t0, t0 + round(ts[0] * 1e9), t1)
        disp = np.zeros(3)
        if acc is not None:
            grid, a = acc
            back, ahead = grid <= 0.0, grid >= 0.0
            d_back = _double_integral(grid[back], a[back])
            xs = xs - np.stack([np.interp(ts, grid[back], d_back[:, k]) for k in range(3)], axis=1)
            tau = grid[ahead]
            disp = _double_integral(tau, a[ahead] * np.exp(-tau / o.acceleration_decay_s)[:, None])[-1]
            norm = float(np.linalg.norm(disp))
            if norm > o.max_acceleration_displacement_m:
                disp *= o.max_acceleration_displacement_m / norm
        tc = float(ts.mean())
        v = ((ts - tc)[:, None] * (xs - xs.mean(axis=0))).sum(axis=0) / float(((ts - tc) ** 2).sum())
        speed = float(np.linalg.norm(v))
        if speed > o.max_speed_m_s:
            v *= o.max_speed_m_s / speed
        out: FloatArray = v * dt + disp
        return out

    def _free_acceleration(self, suit: SuitState, t0: int, t_a: int, t_b: int) -> tuple[FloatArray, FloatArray] | None:
        """The pelvis sensor's free acceleration (world, m/s², gravity removed) from ``t_a`` to ``t_b``: on the
        buffered samples' times plus ``t_a``, ``t0`` and ``t_b`` (linear between samples), times in seconds since
        ``t0``; None when the buffer does not cover the interval."""
        h = suit.hips
        buf = suit.buffers[h] if h is not None and suit.mask[h] else None
        if h is None or buf is None or len(buf) < 2:
            return None
        times = buf.times() - int(suit.offsets_ns[h])
        if times[0] > t_a or times[-1] < t_b:
            return None
        lo = max(int(np.searchsorted(times, t_a, side="right")) - 1, 0)
        hi = int(np.searchsorted(times, t_b, side="left")) + 1
        rows = buf.rows()[lo:hi]
        if not np.all(np.isfinite(rows[:, 0:7])):
            return None
        world = quat_multiply(suit.q_wg[h][None], quat_normalize(rows[:, 0:4]))
        acc = np.einsum("nij,nj->ni", matrix_from_quat(world), rows[:, 4:7]) - self.gravity
        t = (times[lo:hi] - t0) / 1e9
        ends = np.array([(t_a - t0) / 1e9, 0.0, (t_b - t0) / 1e9])
        inside = t[(t > ends[0]) & (t < ends[2]) & (t != 0.0)]
        grid = np.sort(np.concatenate([inside, ends]))
        return grid, np.stack([np.interp(grid, t, acc[:, k]) for k in range(3)], axis=1)


def _rotate(rotvec: FloatArray, v: FloatArray) -> FloatArray:
    """``v`` (3,) turned by the rotation vector ``rotvec`` (3,) (Rodrigues on plain floats: one vector, where
    numpy's per-call overhead would dominate)."""
    x, y, z = (float(c) for c in rotvec)
    vx, vy, vz = (float(c) for c in v)
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-12:
        return np.array([vx, vy, vz])
    kx, ky, kz = x / angle, y / angle, z / angle
    c, s = math.cos(angle), math.sin(angle)
    dot = (kx * vx + ky * vy + kz * vz) * (1.0 - c)
    cx, cy, cz = ky * vz - kz * vy, kz * vx - kx * vz, kx * vy - ky * vx
    return np.array([vx * c + cx * s + kx * dot, vy * c + cy * s + ky * dot, vz * c + cz * s + kz * dot])


def _orientations_at(
    buffers: Sequence[RingBuffer | None], times: NDArray[np.int64]
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Slerped orientations (n, 4) of n buffers at their own times (n,), and which were inside the data.

    :meth:`RingBuffer.sample`'s rules (no extrapolation, no interpolation across a gap), for all sensors at once.
    """
    n = len(buffers)
    a = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    b = a.copy()
    alpha = np.zeros(n)
    ok = np.zeros(n, dtype=bool)
    for i, (buf, t) in enumerate(zip(buffers, times.tolist(), strict=True)):
        if buf is None or not len(buf):
            continue
        ts = buf.times()
        k = int(np.searchsorted(ts, t, side="right")) - 1
        if k < 0 or t > ts[-1]:
            continue
        k1 = min(k + 1, len(ts) - 1)
        if ts[k1] - ts[k] > buf.max_gap_ns:
            continue
        rows = buf.rows()
        a[i], b[i] = rows[k, 0:4], rows[k1, 0:4]
        alpha[i] = 0.0 if k1 == k else (t - ts[k]) / (ts[k1] - ts[k])
        ok[i] = True
    return quat_slerp(quat_normalize(a), quat_normalize(b), alpha), ok


def _double_integral(grid: FloatArray, a: FloatArray) -> FloatArray:
    """``D(τ) = ∫∫ a`` on ``grid`` (m,) for ``a`` (m, 3), zero value and zero slope at ``τ = 0``, which is one
    end of the grid (trapezoidal)."""
    step = np.diff(grid)[:, None]
    vel = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (a[1:] + a[:-1]) * step, axis=0)])
    pos = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (vel[1:] + vel[:-1]) * step, axis=0)])
    k = int(np.argmin(np.abs(grid)))  # τ = 0 is an end of the grid
    out: FloatArray = pos - pos[k] - vel[k] * (grid - grid[k])[:, None]
    return out

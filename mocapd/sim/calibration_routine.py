"""A wearer doing the guided IMU calibration routine, for the simulated suit (tests and demos).

The routine of ``docs/imu.md`` ("Calibrating a suit live"): stand still in a relaxed posture (upper arms 25° below
horizontal, elbows 15° bent, knees 4° bent: what a person holds when told to stand straight), march a few steps on
the spot, stand, bend both elbows a few times, stand. The world's person 0 plays it (forwards, then backwards: the
world's loop) and its suit's sensors are strapped as a person straps them: each case along its segment, turned
5-15° about a random axis.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from mocapd.core.imu_calibration import _AXIS_ALIGNED
from mocapd.core.rotations import quat_from_rotvec, quat_multiply
from mocapd.core.skeleton import BONE_INDEX
from mocapd.sim.world import TRUTH_FPS, SyntheticWorld

FloatArray = NDArray[np.float64]

STAND_S = 3.0
"""Seconds of the first still stand."""
MARCH_S = 5.0
"""Seconds marching on the spot (a step of each leg a second, knees to 65°)."""
PAUSE_S = 1.5
"""Seconds standing between the marching and the elbows, and at the end."""
ELBOWS_S = 4.0
"""Seconds bending both elbows (three bends, 15° to 110°)."""
ROUTINE_S = STAND_S + MARCH_S + PAUSE_S + ELBOWS_S + PAUSE_S
"""One pass of the routine (the world plays it forwards, then backwards)."""


def _smooth(x: FloatArray) -> FloatArray:
    """0 -> 1 without a jump in speed (a raised cosine of ``x`` clipped to [0, 1])."""
    return np.asarray(0.5 - 0.5 * np.cos(np.pi * np.clip(x, 0.0, 1.0)), dtype=np.float64)


def routine_motion(rest: FloatArray, fps: float = TRUTH_FPS) -> FloatArray:
    """θ (n, 66) of the routine from a rest pose θ (66,) (its root kept where it is)."""
    t = np.arange(round(ROUTINE_S * fps)) / fps
    theta = np.repeat(rest[None], len(t), axis=0)

    def turn(bone: str, axis: int, angle_deg: FloatArray) -> None:
        theta[:, 3 + 3 * BONE_INDEX[bone] + axis] += np.radians(angle_deg)

    march = (t >= STAND_S) & (t < STAND_S + MARCH_S)
    ramp = _smooth((t - STAND_S) / 0.5) * _smooth((STAND_S + MARCH_S - t) / 0.5)
    elbows_t = t - (STAND_S + MARCH_S + PAUSE_S)
    bend = np.where((elbows_t >= 0) & (elbows_t < ELBOWS_S), 0.5 - 0.5 * np.cos(2 * np.pi * 3 * elbows_t / ELBOWS_S),
                    0.0)  # fmt: skip
    for side, s, phase in (("Left", 1.0, 0.0), ("Right", -1.0, np.pi)):
        step = np.where(march, np.maximum(0.0, np.sin(2 * np.pi * (t - STAND_S) + phase)), 0.0) * ramp
        turn(f"{side}UpperLeg", 0, -40.0 * step)  # the thigh forward
        turn(f"{side}LowerLeg", 0, 65.0 * step)  # the knee bent
        turn(f"{side}Foot", 0, -25.0 * step)
        # the relaxed stand: upper arms 25° down, elbows 15°, knees 4° bent
        turn(f"{side}UpperArm", 2, np.full(len(t), -s * 25.0))
        turn(f"{side}LowerArm", 1, -s * (15.0 + 95.0 * bend))
        turn(f"{side}UpperLeg", 0, np.full(len(t), -2.0))
        turn(f"{side}LowerLeg", 0, np.full(len(t), 4.0))
        turn(f"{side}Foot", 0, np.full(len(t), -2.0))
    return theta


def strapped_mountings(n: int, rng: np.random.Generator) -> FloatArray:
    """``n`` mountings (n, 4): each a case along its segment (one of the 24 ways), turned 5-15° about a random axis."""
    axis = rng.normal(size=(n, 3))
    askew = quat_from_rotvec(np.radians(rng.uniform(5.0, 15.0, n))[:, None] * axis / np.linalg.norm(axis, axis=1)[:,
                             None])  # fmt: skip
    return np.asarray(quat_multiply(askew, _AXIS_ALIGNED[rng.integers(len(_AXIS_ALIGNED), size=n)]))


def routine_world(seed: int = 0) -> SyntheticWorld:
    """A one-person, one-suit world whose wearer does the routine (:func:`routine_motion`) with realistic mountings."""
    world = SyntheticWorld(0, 1, 1, seed=seed, motion="procedural", loop_s=ROUTINE_S)
    rest = world.skeleton.rest_pose()
    rest[:3] = world.truth[0][0, :3]
    motion = routine_motion(rest)
    world.truth[0] = motion
    world.loop_s = (len(motion) - 1) / TRUTH_FPS
    suit = world.suits[0]
    world.suits[0] = replace(suit, q_ib=strapped_mountings(len(suit.sensor_ids), np.random.default_rng(seed + 7)))
    return world

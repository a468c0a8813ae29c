"""Carrying a solved pose forward in time with what the IMUs measured since (pure math; no buffers, no clocks).

The fixed-latency scheduler solves the instant ``t = now - latency`` with every camera and IMU; a live consumer (a VR
avatar) wants ``now``. The IMUs are only a sample behind ``now``, so the pose at ``t`` can be carried to their
newest common instant ``t'`` (:mod:`mocapd.pipeline.prediction` finds it and reads the buffers):

- a bone with a sensor turns by what its sensor turned: with ``R_gb = R_ig R_i R_ib⁻¹`` (Eq. 8),
  ``R_gb(t') = R_gb(t) · R_ib (R_i(t)⁻¹ R_i(t')) R_ib⁻¹`` — the sensor's own rotation between the two
  instants, expressed in the bone's frame; the heading alignment ``R_ig`` cancels, so a heading error does not
  enter, and the solved ``R_gb(t)`` (cameras and IMUs fused) is the starting point;
- a bone without a sensor between two bones with one (the spine between pelvis and sternum, the neck between
  sternum and head) takes its share of the change between them: with ``C`` the chain's rotation from the upper
  sensor bone ``a`` to the lower one ``s`` (``Q_a⁻¹ Q_s``) before and ``C'`` after, ``Δ = C' C⁻¹``, the k-th of
  n bones down the chain gets ``Q'_k = Q'_a Δ^(k/n) Q_a⁻¹ Q_k``, which ends exactly at ``Q'_s``;
- any other bone without a sensor (hands, toes, the feet of a 6-IMU suit) keeps its local rotation: it follows its
  parent;
- the root moves by a displacement the caller works out (velocity of the fused solution plus the hips sensor's
  acceleration, :mod:`mocapd.pipeline.prediction`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.rotations import quat_conjugate, quat_from_rotvec, quat_multiply, quat_normalize, rotvec_from_quat
from mocapd.core.skeleton import N_BONES, POSE_DIM
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CarryPlan:
    """How every bone of a skeleton moves, given which bones have a (live) sensor.

    Attributes
    ----------
    sensor : tuple of bool, length 21
    chain : tuple of (anchor, end, k, n) or None, length 21
        For a sensor-less bone inside a chain between two sensor bones: the upper sensor bone, the lower one, the
        bone's position down the chain (1 .. n-1) and the chain's length in joints (n); None: follows its parent.
    """

    sensor: tuple[bool, ...]
    chain: tuple[tuple[int, int, int, int] | None, ...]


def carry_plan(parents: Sequence[int], sensor_bones: Sequence[int]) -> CarryPlan:
    """The :class:`CarryPlan` for a skeleton (``parents``, parents before children) and its sensor bones.

    A sensor-less bone is in a chain when it has a sensor ancestor with only sensor-less bones in between and
    exactly one nearest sensor descendant (so its share of the change is defined).
    """
    n = len(parents)
    has = [False] * n
    for b in sensor_bones:
        has[b] = True
    children: list[list[int]] = [[] for _ in range(n)]
    for b, p in enumerate(parents):
        if p >= 0:
            children[p].append(b)

    def nearest_sensors(b: int) -> list[int]:
        out: list[int] = []
        for c in children[b]:
            out.extend([c] if has[c] else nearest_sensors(c))
        return out

    chain: list[tuple[int, int, int, int] | None] = [None] * n
    for b in range(n):
        if has[b]:
            continue
        below = nearest_sensors(b)
        k, a = 1, parents[b]
        while a >= 0 and not has[a]:
            k, a = k + 1, parents[a]
        if a < 0 or len(below) != 1:
            continue
        s = below[0]
        rest, m = 0, s
        while m != b:
            rest, m = rest + 1, parents[m]
        chain[b] = (a, s, k, k + rest)
    return CarryPlan(tuple(has), tuple(chain))


Quat = tuple[float, float, float, float]


def _mul(a: Quat, b: Quat) -> Quat:
    """Hamilton product on plain floats: the per-bone loop below runs ~100 of them, where numpy's per-call
    overhead (~30 µs) would cost milliseconds per person and tick."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)  # fmt: skip


def _conj(q: Quat) -> Quat:
    return (q[0], -q[1], -q[2], -q[3])


def _power(q: Quat, f: float) -> Quat:
    """``q^f``: the rotation about the same axis by ``f`` times the angle, on the shorter arc."""
    w, x, y, z = q if q[0] >= 0 else (-q[0], -q[1], -q[2], -q[3])
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-12:
        return (1.0, 0.0, 0.0, 0.0)
    half = f * math.atan2(s, w)
    k = math.sin(half) / s
    return (math.cos(half), k * x, k * y, k * z)


def carry_forward(theta: FloatArray, parents: Sequence[int], plan: CarryPlan, deltas: FloatArray,
                  displacement: FloatArray) -> FloatArray:  # fmt: skip
    """The pose ``theta`` carried forward (see the module docstring).

    Parameters
    ----------
    theta : array, shape (66,)
        The solved pose at ``t``.
    parents : sequence of int, length 21
        Parent of each bone (-1 for the root), parents listed before children.
    plan : CarryPlan
        From :func:`carry_plan` with the bones whose sensors measured the interval.
    deltas : array, shape (21, 4)
        Per bone, its rotation from ``t`` to ``t'`` in its own frame, ``R_ib (R_i(t)⁻¹ R_i(t')) R_ib⁻¹``
        (used only for sensor bones of the plan).
    displacement : array, shape (3,)
        Root translation from ``t`` to ``t'`` (metres).

    Returns
    -------
    array, shape (66,)
    """
    theta = np.asarray(theta, dtype=np.float64)
    if theta.shape != (POSE_DIM,) or deltas.shape != (N_BONES, 4):
        raise InputError(f"carry_forward: theta (66,) and deltas (21, 4) expected, got {theta.shape}, {deltas.shape}")
    local: list[Quat] = [tuple(q) for q in quat_from_rotvec(theta[3:].reshape(N_BONES, 3)).tolist()]
    delta: list[Quat] = [tuple(q) for q in np.asarray(deltas, dtype=np.float64).tolist()]
    glob: list[Quat] = []
    for b, p in enumerate(parents):
        glob.append(local[b] if p < 0 else _mul(glob[p], local[b]))
    new: list[Quat] = [_mul(glob[b], delta[b]) if plan.sensor[b] else local[b] for b in range(N_BONES)]
    for b, p in enumerate(parents):
        link = plan.chain[b]
        if plan.sensor[b]:
            continue
        if link is None:
            new[b] = local[b] if p < 0 else _mul(new[p], local[b])
            continue
        a, s, k, n = link
        inv_a = _conj(glob[a])
        change = _mul(_mul(_conj(new[a]), new[s]), _conj(_mul(inv_a, glob[s])))
        new[b] = _mul(new[a], _mul(_power(change, k / n), _mul(inv_a, glob[b])))
    glob_new = quat_normalize(np.array(new))
    parent_new = glob_new[[max(p, 0) for p in parents]]
    local_new = quat_multiply(quat_conjugate(parent_new), glob_new)
    roots = [b for b, p in enumerate(parents) if p < 0]
    local_new[roots] = glob_new[roots]
    out = theta.copy()
    out[3:] = rotvec_from_quat(local_new).reshape(-1)
    out[0:3] += np.asarray(displacement, dtype=np.float64)
    return out

"""Coordinate conventions of the engines we stream to, and the one conversion from mocapd's world frame.

mocapd's world (DESIGN.md): right-handed, +Y up, metres, rest pose facing +Z, so the subject's left is +X.
Every outgoing format converts here and nowhere else. A convention is a change of basis ``C`` (3×3, rows are the
target axes written in mocapd axes, det ±1) and a length scale:

==========  ============================  ==========================================  =====
name        handedness, up, forward       target axes in mocapd axes                  scale
==========  ============================  ==========================================  =====
``native``  RH, +Y up, +Z forward         x = +X, y = +Y, z = +Z                      1 (m)
``unity``   LH, +Y up, +Z forward         x = −X (subject's right), y = +Y, z = +Z    1 (m)
``unreal``  LH, +Z up, +X forward         x = +Z, y = −X (right), z = +Y              100 (cm)
``mvn``     RH, +Z up, +X forward         x = +Z, y = +X (left), z = +Y               1 (m)
==========  ============================  ==========================================  =====

A position maps as ``p' = s · C p``. A rotation matrix maps as ``R' = C R Cᵀ`` — for a mirror (det C = −1) this is
still a proper rotation, with the axis mirrored and the sense flipped, which is what left-handed engines expect.
Quaternions are converted through that rule without matrices: with ``q = (w, v)``, ``q' = (w, det(C) · C v)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Convention:
    """A target coordinate frame: change of basis ``basis`` (3, 3) from mocapd axes, and a length scale."""

    name: str
    basis: FloatArray
    scale: float
    left_handed: bool

    def positions(self, p: FloatArray) -> FloatArray:
        """Points or translations ``(..., 3)`` in metres (mocapd) → ``(..., 3)`` in this frame and unit."""
        return self.scale * (np.asarray(p, dtype=np.float64) @ self.basis.T)

    def directions(self, v: FloatArray) -> FloatArray:
        """Free vectors ``(..., 3)`` (no scaling): axes, unit directions."""
        return np.asarray(v, dtype=np.float64) @ self.basis.T

    def quaternions(self, q: FloatArray) -> FloatArray:
        """Rotations ``(..., 4)`` as (w, x, y, z) in mocapd axes → ``(..., 4)`` (w, x, y, z) in this frame."""
        q = np.asarray(q, dtype=np.float64)
        out = np.empty_like(q)
        out[..., 0] = q[..., 0]
        sign = -1.0 if self.left_handed else 1.0  # the vector part is a pseudovector: a mirror flips its sense
        out[..., 1:] = sign * (q[..., 1:] @ self.basis.T)
        return out

    def matrices(self, R: FloatArray) -> FloatArray:
        """Rotation matrices ``(..., 3, 3)`` → ``C R Cᵀ`` ``(..., 3, 3)``."""
        return self.basis @ np.asarray(R, dtype=np.float64) @ self.basis.T


def _convention(name: str, rows: list[list[float]], scale: float) -> Convention:
    basis = np.array(rows, dtype=np.float64)
    det = float(np.linalg.det(basis))
    return Convention(name, basis, scale, left_handed=det < 0)


NATIVE = _convention("native", [[1, 0, 0], [0, 1, 0], [0, 0, 1]], 1.0)
UNITY = _convention("unity", [[-1, 0, 0], [0, 1, 0], [0, 0, 1]], 1.0)
UNREAL = _convention("unreal", [[0, 0, 1], [-1, 0, 0], [0, 1, 0]], 100.0)
MVN = _convention("mvn", [[0, 0, 1], [1, 0, 0], [0, 1, 0]], 1.0)

CONVENTIONS: dict[str, Convention] = {c.name: c for c in (NATIVE, UNITY, UNREAL, MVN)}


def convention(name: str) -> Convention:
    """Look a convention up by name (``native``, ``unity``, ``unreal``, ``mvn``); ``KeyError`` names the choices."""
    try:
        return CONVENTIONS[name]
    except KeyError:
        raise KeyError(f"unknown coordinate convention {name!r}; choose one of {sorted(CONVENTIONS)}") from None

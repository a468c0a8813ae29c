"""Forward kinematics of the 21-bone skeleton and its analytic Jacobians.

Pose vector θ (66,) = root translation (3) + 21 local rotation vectors (seed 003 §3.1). For bone b with parent
p(b), local rotation ``R_b = exp(θ_b)`` and rest offset ``o_b``::

    Q_b = Q_p(b) R_b          global rotation (Eq. 1 / Eq. 9 of seed 003)
    x_b = x_p(b) + Q_p(b) o_b  global joint position; x_0 = θ[0:3]

A track target ``(bone, c)`` is the point ``x_b + Q_b c``.

Jacobians use the additive update of θ (the solver's parameterisation). Perturbing ``θ_k`` by ``d`` rotates
everything below joint k about ``x_k`` by the *global* angle ``ω = A_k d`` with ``A_k = Q_k Jr(θ_k)``, so::

    ∂(target)/∂θ_k = -[target - x_k]× A_k     for every ancestor k of the target's bone (itself included)
    ∂(target)/∂θ[0:3] = I
    ∂ω_b/∂θ_k = A_k                           (global angular velocity of bone b)

Everything here broadcasts over leading "frame" dimensions for batch FK.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.rotations import matrix_from_rotvec, so3_right_jacobian
from mocapd.core.skeleton import N_BONES, POSE_DIM, Skeleton
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class FKState:
    """Result of forward kinematics.

    Attributes
    ----------
    rotations : array, shape (..., 21, 3, 3)
        Global bone rotations Q_b (bone frame -> world).
    positions : array, shape (..., 21, 3)
        Global joint positions x_b (metres).
    local : array, shape (..., 21, 3, 3)
        Local rotations R_b = exp(θ_b).
    """

    rotations: FloatArray
    positions: FloatArray
    local: FloatArray


def _levels(skeleton: Skeleton) -> list[tuple[IntArray, IntArray]]:
    """Bones grouped by depth (excluding the root), with their parents, for level-parallel FK."""
    depths = np.asarray(skeleton.depths)
    parents = np.asarray(skeleton.parents)
    out: list[tuple[IntArray, IntArray]] = []
    for d in range(1, int(depths.max()) + 1):
        idx = np.flatnonzero(depths == d)
        out.append((idx, parents[idx]))
    return out


class Kinematics:
    """Forward kinematics and Jacobians for one sized skeleton (precomputes the traversal order)."""

    def __init__(self, skeleton: Skeleton) -> None:
        self.skeleton = skeleton
        self._levels = _levels(skeleton)
        self._offsets = skeleton.offsets

    # -- forward kinematics -------------------------------------------------------------------------------
    def forward(self, theta: FloatArray) -> FKState:
        """Global rotations and joint positions.

        Parameters
        ----------
        theta : array, shape (..., 66)

        Returns
        -------
        FKState
        """
        theta = np.asarray(theta, dtype=np.float64)
        if theta.shape[-1] != POSE_DIM:
            raise InputError(f"pose θ must have shape (..., {POSE_DIM}), got {theta.shape}")
        lead = theta.shape[:-1]
        local = matrix_from_rotvec(theta[..., 3:].reshape(*lead, N_BONES, 3))
        Q = np.empty_like(local)
        x = np.empty((*lead, N_BONES, 3))
        Q[..., 0, :, :] = local[..., 0, :, :]
        x[..., 0, :] = theta[..., 0:3]
        for idx, par in self._levels:
            Qp = Q[..., par, :, :]
            Q[..., idx, :, :] = Qp @ local[..., idx, :, :]
            x[..., idx, :] = x[..., par, :] + np.einsum("...ij,...j->...i", Qp, self._offsets[idx])
        return FKState(rotations=Q, positions=x, local=local)

    @staticmethod
    def targets(state: FKState, bones: IntArray, offsets: FloatArray) -> FloatArray:
        """Global positions of track targets ``(bone, offset)``.

        Parameters
        ----------
        bones : int array, shape (n,)
        offsets : array, shape (n, 3)
            Offsets in the bone frame (metres).

        Returns
        -------
        array, shape (..., n, 3)
        """
        Q = state.rotations[..., bones, :, :]
        return np.asarray(state.positions[..., bones, :] + np.einsum("...ij,...j->...i", Q, offsets))

    # -- Jacobians ----------------------------------------------------------------------------------------
    @staticmethod
    def angular_axes(state: FKState, theta: FloatArray) -> FloatArray:
        """``A_k = Q_k Jr(θ_k)``: global rotation axes of each bone's rotation-vector parameters.

        Parameters
        ----------
        theta : array, shape (66,)

        Returns
        -------
        array, shape (21, 3, 3)
        """
        return state.rotations @ so3_right_jacobian(theta[3:].reshape(N_BONES, 3))

    def chain_pairs(self, bones: IntArray) -> tuple[IntArray, IntArray]:
        """All (row, ancestor bone) pairs for a list of target bones.

        Returns
        -------
        rows, ancestors : int arrays, shape (n_pairs,)
            ``rows[j]`` indexes ``bones``; ``ancestors[j]`` is a bone whose rotation moves that target.
        """
        anc = self.skeleton.ancestors[np.asarray(bones, dtype=np.intp)]
        rows, ks = np.nonzero(anc)
        return rows.astype(np.intp), ks.astype(np.intp)

    @staticmethod
    def point_jacobian(
        state: FKState,
        axes: FloatArray,
        points: FloatArray,
        pairs: tuple[IntArray, IntArray],
        out: FloatArray | None = None,
    ) -> FloatArray:
        """Jacobian of global points attached to the skeleton w.r.t. θ.

        Parameters
        ----------
        axes : array, shape (21, 3, 3)
            From :meth:`angular_axes`.
        points : array, shape (n, 3)
            Current global positions of the points.
        pairs : from :meth:`chain_pairs` for the points' bones.
        out : array, shape (n, 3, 66), optional
            Preallocated output (overwritten).

        Returns
        -------
        array, shape (n, 3, 66)
        """
        rows, ks = pairs
        n = points.shape[0]
        J = np.zeros((n, 3, POSE_DIM)) if out is None else out
        if out is not None:
            J.fill(0.0)
        J[:, 0, 0] = 1.0
        J[:, 1, 1] = 1.0
        J[:, 2, 2] = 1.0
        d = points[rows] - state.positions[ks]
        A = axes[ks]
        # -[d]x A, column by column: cross(A[:, :, i], d) = -d x A_i.
        blk = np.cross(A, d[:, :, None], axisa=1, axisb=1, axisc=1)
        J.reshape(n, 3, N_BONES + 1, 3)[rows, :, ks + 1, :] = blk
        return J

    @staticmethod
    def angular_jacobian(
        axes: FloatArray, pairs: tuple[IntArray, IntArray], n: int, out: FloatArray | None = None
    ) -> FloatArray:
        """Jacobian of the global angular perturbation ω of bones w.r.t. θ.

        Parameters
        ----------
        axes : array, shape (21, 3, 3)
        pairs : from :meth:`chain_pairs` for the bones of interest.
        n : number of rows (bones of interest).

        Returns
        -------
        array, shape (n, 3, 66)
        """
        rows, ks = pairs
        J = np.zeros((n, 3, POSE_DIM)) if out is None else out
        if out is not None:
            J.fill(0.0)
        J.reshape(n, 3, N_BONES + 1, 3)[rows, :, ks + 1, :] = axes[ks]
        return J

"""Compiled (numba) E_J: the learned 3D joint observations' cost and normal equations (issue 30).

The same mathematics as :meth:`mocapd.core.solver.PoseSolver._learned` (numpy, the tested reference), in one call
per LM iteration like :mod:`mocapd.core._kernel`, whose forward kinematics, robust loss, corrector and row
spreading it reuses: every joint is one 3-residual block whose Jacobian is its row of the kinematic chain. The
numpy version cost ~30 ms a solve (a thousand small array operations per iteration); this one a few µs per
iteration. A test holds the two equal.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mocapd.core._kernel import _corrector, _forward, _joint_axes, _loss, _spread_row

FloatArray = NDArray[np.float64]


@nb.njit(cache=True, nogil=True)
def learned_term(
    theta: FloatArray,
    jac: bool,
    parents: FloatArray,
    offsets: FloatArray,
    targets: FloatArray,
    weights: FloatArray,
    lam: float,
    loss_code: int,
    loss_scale: float,
    H: FloatArray,
    g: FloatArray,
) -> float:
    """E_J's cost ``½ Σ ρ(||sqrt(λ w_j)(x_j - y_j)||²)`` (returned) and, with ``jac``, its corrected normal
    equations written into ``H`` (66, 66) and ``g`` (66,) (overwritten).

    Parameters
    ----------
    targets : (n_bones, 3) learned joint positions; weights : (n_bones,) w_j >= 0 (0: no observation).
    """
    nb_ = parents.shape[0]
    Rl = np.empty((nb_, 3, 3))
    Jr = np.empty((nb_, 3, 3))
    Q = np.empty((nb_, 3, 3))
    X = np.empty((nb_, 3))
    _forward(theta, parents, offsets, Rl, Jr, Q, X, jac)
    if jac:
        for i in range(H.shape[0]):
            g[i] = 0.0
            for j in range(H.shape[1]):
                H[i, j] = 0.0
    axes = _joint_axes(Q, Jr) if jac else np.empty((nb_, 3, 3))
    cols = np.empty(3 + 3 * nb_)
    Jrow = np.empty((3, 3 + 3 * nb_))
    Mrow = np.empty((3, 3 + 3 * nb_))
    H3 = np.empty((3, 3))
    g3 = np.empty(3)
    f = np.empty(3)
    cost = 0.0
    for j in range(nb_):
        w = weights[j]
        if w <= 0.0:
            continue
        sw = math.sqrt(lam * w)
        s = 0.0
        for a in range(3):
            f[a] = sw * (X[j, a] - targets[j, a])
            s += f[a] * f[a]
        rho, rho1, rho2 = _loss(loss_code, loss_scale, s)
        cost += 0.5 * rho
        if not jac:
            continue
        wc, beta = _corrector(s, rho1, rho2)
        # G = sw I: gp = Gᵀf = sw f; H3 = wc (GᵀG - beta gp gpᵀ); g3 = wc gp
        for a in range(3):
            g3[a] = wc * sw * f[a]
            for b in range(3):
                H3[a, b] = wc * ((sw * sw if a == b else 0.0) - beta * sw * f[a] * sw * f[b])
        _spread_row(H, g, H3, g3, j, X[j], False, parents, X, axes, cols, Jrow, Mrow)
    return cost

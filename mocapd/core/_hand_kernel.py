"""Compiled (numba) cost and normal equations of one hand's solve (:mod:`mocapd.core.hand_solver`).

The same mathematics as :meth:`HandSolver._evaluate` (the numpy reference, checked against finite differences),
written as scalar loops: the numpy path issues some hundred small array operations per evaluation, and their call
overhead, not the arithmetic, is its cost. A test asserts both give the same cost, gradient and ``JᵀJ``.

Each landmark's Gauss–Newton 3×3 block is summed over the views first, then spread into the 27×27 matrix once
through the landmark's 3×27 kinematic Jacobian. Compiled with ``cache=True`` (the first call in a fresh
environment compiles: :func:`warm_up`).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@nb.njit(cache=True)
def _rot(a: FloatArray, angle: float, out: FloatArray) -> None:
    c, s = math.cos(angle), math.sin(angle)
    t = 1.0 - c
    x, y, z = a[0], a[1], a[2]
    out[0, 0], out[0, 1], out[0, 2] = c + t * x * x, t * x * y - s * z, t * x * z + s * y
    out[1, 0], out[1, 1], out[1, 2] = t * x * y + s * z, c + t * y * y, t * y * z - s * x
    out[2, 0], out[2, 1], out[2, 2] = t * x * z - s * y, t * y * z + s * x, c + t * z * z


@nb.njit(cache=True)
def evaluate(
    angles: FloatArray,  # (21,)
    rotation: FloatArray,  # (3, 3)
    wrist: FloatArray,  # (3,)
    axes: FloatArray,  # (21, 3)
    slots: NDArray[np.intp],  # (15, 3): hinge per slot, n_hinges = empty
    bone_of: NDArray[np.intp],  # (21,)
    offsets: FloatArray,  # (15, 3)
    tips: FloatArray,  # (5, 3)
    lm_bone: NDArray[np.intp],  # (21,)
    lm_tip: NDArray[np.bool_],  # (21,)
    depends: NDArray[np.bool_],  # (21 landmarks, 21 hinges)
    P: FloatArray,  # (n_cams, 3, 4)
    uv: FloatArray,  # (n_cams, 21, 2)
    conf: FloatArray,  # (n_cams, 21)
    prior: FloatArray,  # (4, 21): mean, sigma, lower, upper (only mean and sigma used here)
    coupled: NDArray[np.intp],  # (n_coupled, 2): pip, dip
    scalars: FloatArray,  # prior weight, coupling sigma and ratio, rotation and position sigma, sigma px, cauchy
    body_rotation: FloatArray,
    body_wrist: FloatArray,
    JtJ: FloatArray,  # (27, 27) out
    g: FloatArray,  # (27,) out
) -> float:
    nh = angles.shape[0]
    npar = nh + 6
    prior_w, c_sigma, c_ratio, r_sigma, p_sigma, sigma_px, cauchy = (
        scalars[0], scalars[1], scalars[2], scalars[3], scalars[4], scalars[5], scalars[6])  # fmt: skip
    for i in range(npar):
        g[i] = 0.0
        for j in range(npar):
            JtJ[i, j] = 0.0
    # hinge rotations, each bone's prefix products and local rotation
    H = np.empty((nh + 1, 3, 3))
    for k in range(nh):
        _rot(axes[k], angles[k], H[k])
    H[nh] = np.eye(3)
    nb_ = offsets.shape[0]
    prefix = np.empty((nb_, 4, 3, 3))
    for b in range(nb_):
        prefix[b, 0] = np.eye(3)
        for k in range(3):
            prefix[b, k + 1] = prefix[b, k] @ H[slots[b, k]]
    G = np.empty((nb_, 3, 3))
    Gp = np.empty((nb_, 3, 3))
    J = np.empty((nb_, 3))
    for level in range(3):
        for f in range(5):
            b = 3 * f + level
            if level == 0:
                Gp[b] = rotation
                px = wrist
            else:
                Gp[b] = G[b - 1]
                px = J[b - 1]
            J[b] = px + Gp[b] @ offsets[b]
            G[b] = Gp[b] @ prefix[b, 3]
    nl = lm_bone.shape[0]
    L = np.empty((nl, 3))
    for lm in range(nl):
        b = lm_bone[lm]
        if b < 0:
            L[lm] = wrist
        elif lm_tip[lm]:
            L[lm] = J[b] + G[b] @ tips[b // 3]
        else:
            L[lm] = J[b]
    W = np.empty((nh, 3))  # world hinge axes
    for k in range(nh):
        b = bone_of[k]
        s = 0
        for q in range(3):
            if slots[b, q] == k:
                s = q
        W[k] = Gp[b] @ (prefix[b, s] @ axes[k])
    cost = 0.0
    c2 = cauchy * cauchy
    s2 = sigma_px * sigma_px
    D = np.zeros((3, npar))
    for lm in range(nl):
        A = np.zeros((3, 3))
        bvec = np.zeros(3)
        used = False
        for c in range(P.shape[0]):
            cf = conf[c, lm]
            if cf <= 0.0:
                continue
            X0 = P[c, 0, 0] * L[lm, 0] + P[c, 0, 1] * L[lm, 1] + P[c, 0, 2] * L[lm, 2] + P[c, 0, 3]
            X1 = P[c, 1, 0] * L[lm, 0] + P[c, 1, 1] * L[lm, 1] + P[c, 1, 2] * L[lm, 2] + P[c, 1, 3]
            X2 = P[c, 2, 0] * L[lm, 0] + P[c, 2, 1] * L[lm, 1] + P[c, 2, 2] * L[lm, 2] + P[c, 2, 3]
            if X2 <= 1e-3:
                continue
            u, v = X0 / X2, X1 / X2
            eu, ev = u - uv[c, lm, 0], v - uv[c, lm, 1]
            sq = eu * eu + ev * ev
            cost += cf * c2 * math.log1p(sq / c2) / s2
            w = cf / (1.0 + sq / c2) / s2
            du = np.empty(3)
            dv = np.empty(3)
            for j in range(3):
                du[j] = (P[c, 0, j] - u * P[c, 2, j]) / X2
                dv[j] = (P[c, 1, j] - v * P[c, 2, j]) / X2
            for i in range(3):
                bvec[i] += w * (du[i] * eu + dv[i] * ev)
                for j in range(3):
                    A[i, j] += w * (du[i] * du[j] + dv[i] * dv[j])
            used = True
        if not used:
            continue
        # the landmark's kinematic Jacobian D (3, 27)
        for i in range(3):
            for p in range(npar):
                D[i, p] = 0.0
        for k in range(nh):
            if depends[lm, k]:
                jb = J[bone_of[k]]
                rx, ry, rz = L[lm, 0] - jb[0], L[lm, 1] - jb[1], L[lm, 2] - jb[2]
                D[0, k] = W[k, 1] * rz - W[k, 2] * ry
                D[1, k] = W[k, 2] * rx - W[k, 0] * rz
                D[2, k] = W[k, 0] * ry - W[k, 1] * rx
        rx, ry, rz = L[lm, 0] - wrist[0], L[lm, 1] - wrist[1], L[lm, 2] - wrist[2]
        for j in range(3):  # -[rel]x R
            D[0, nh + j] = -(-rz * rotation[1, j] + ry * rotation[2, j])
            D[1, nh + j] = -(rz * rotation[0, j] - rx * rotation[2, j])
            D[2, nh + j] = -(-ry * rotation[0, j] + rx * rotation[1, j])
            D[j, nh + 3 + j] = 1.0
        AD = A @ D
        for p in range(npar):
            gp = 0.0
            for i in range(3):
                gp += D[i, p] * bvec[i]
            g[p] += gp
            for q in range(p, npar):
                acc = 0.0
                for i in range(3):
                    acc += D[i, p] * AD[i, q]
                JtJ[p, q] += acc
    for p in range(npar):
        for q in range(p + 1, npar):
            JtJ[q, p] = JtJ[p, q]
    # priors
    for k in range(nh):
        r = (angles[k] - prior[0, k]) / prior[1, k]
        cost += prior_w * r * r
        JtJ[k, k] += prior_w / (prior[1, k] * prior[1, k])
        g[k] += prior_w * r / prior[1, k]
    for i in range(coupled.shape[0]):
        pip, dip = coupled[i, 0], coupled[i, 1]
        r = (angles[dip] - c_ratio * angles[pip]) / c_sigma
        cost += prior_w * r * r
        jd, jp = 1.0 / c_sigma, -c_ratio / c_sigma
        JtJ[dip, dip] += prior_w * jd * jd
        JtJ[pip, pip] += prior_w * jp * jp
        JtJ[dip, pip] += prior_w * jd * jp
        JtJ[pip, dip] += prior_w * jd * jp
        g[dip] += prior_w * r * jd
        g[pip] += prior_w * r * jp
    A = body_rotation.T @ rotation
    rr = np.empty(3)
    rr[0], rr[1], rr[2] = 0.5 * (A[2, 1] - A[1, 2]), 0.5 * (A[0, 2] - A[2, 0]), 0.5 * (A[1, 0] - A[0, 1])
    for i in range(3):
        r = rr[i] / r_sigma
        cost += r * r
        JtJ[nh + i, nh + i] += 1.0 / (r_sigma * r_sigma)
        g[nh + i] += r / r_sigma
        r = (wrist[i] - body_wrist[i]) / p_sigma
        cost += r * r
        JtJ[nh + 3 + i, nh + 3 + i] += 1.0 / (p_sigma * p_sigma)
        g[nh + 3 + i] += r / p_sigma
    return cost

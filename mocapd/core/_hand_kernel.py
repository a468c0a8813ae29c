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

from mocapd.core._kernel import cholesky_solve

FloatArray = NDArray[np.float64]


@nb.njit(cache=True, nogil=True)
def _rot(a: FloatArray, angle: float, out: FloatArray) -> None:
    c, s = math.cos(angle), math.sin(angle)
    t = 1.0 - c
    x, y, z = a[0], a[1], a[2]
    out[0, 0], out[0, 1], out[0, 2] = c + t * x * x, t * x * y - s * z, t * x * z + s * y
    out[1, 0], out[1, 1], out[1, 2] = t * x * y + s * z, c + t * y * y, t * y * z - s * x
    out[2, 0], out[2, 1], out[2, 2] = t * x * z - s * y, t * y * z + s * x, c + t * z * z


@nb.njit(cache=True, nogil=True)
def _mm(a: FloatArray, b: FloatArray, out: FloatArray) -> None:
    """out = a @ b for 3x3 (numba's @ goes through BLAS: slow for 3x3)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]


@nb.njit(cache=True, nogil=True)
def _mv(a: FloatArray, v: FloatArray, out: FloatArray) -> None:
    for i in range(3):
        out[i] = a[i, 0] * v[0] + a[i, 1] * v[1] + a[i, 2] * v[2]


@nb.njit(cache=True, nogil=True)
def local_rotations(angles: FloatArray, axes: FloatArray, slots: NDArray[np.intp], prefix: FloatArray) -> None:
    """Each bone's products of its first k hinges, ``prefix`` (15, 4, 3, 3); ``prefix[:, 3]`` the local rotation."""
    nh = angles.shape[0]
    H = np.empty((nh + 1, 3, 3))
    for k in range(nh):
        _rot(axes[k], angles[k], H[k])
    H[nh] = np.eye(3)
    for b in range(prefix.shape[0]):
        prefix[b, 0] = np.eye(3)
        for k in range(3):
            _mm(prefix[b, k], H[slots[b, k]], prefix[b, k + 1])


@nb.njit(cache=True, nogil=True)
def apply_step(
    angles: FloatArray, rotation: FloatArray, wrist: FloatArray, step: FloatArray, lower: FloatArray, upper: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The state moved by an LM step: angles projected onto their limits, the rotation on the right."""
    nh = angles.shape[0]
    new_angles = np.empty(nh)
    for k in range(nh):
        new_angles[k] = min(max(angles[k] + step[k], lower[k]), upper[k])
    w = step[nh : nh + 3]
    angle = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    E = np.eye(3)
    if angle > 1e-15:
        _rot(w / angle, angle, E)
    new_rotation = np.empty((3, 3))
    _mm(rotation, E, new_rotation)
    new_wrist = wrist + step[nh + 3 :]
    return new_angles, new_rotation, new_wrist


@nb.njit(cache=True, nogil=True)
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
    nb_ = offsets.shape[0]
    prefix = np.empty((nb_, 4, 3, 3))
    local_rotations(angles, axes, slots, prefix)
    G = np.empty((nb_, 3, 3))
    Gp = np.empty((nb_, 3, 3))
    J = np.empty((nb_, 3))
    tmp = np.empty(3)
    for level in range(3):
        for f in range(5):
            b = 3 * f + level
            if level == 0:
                Gp[b] = rotation
                J[b] = wrist
            else:
                Gp[b] = G[b - 1]
                J[b] = J[b - 1]
            _mv(Gp[b], offsets[b], tmp)
            J[b] += tmp
            _mm(Gp[b], prefix[b, 3], G[b])
    nl = lm_bone.shape[0]
    L = np.empty((nl, 3))
    for lm in range(nl):
        b = lm_bone[lm]
        if b < 0:
            L[lm] = wrist
        elif lm_tip[lm]:
            _mv(G[b], tips[b // 3], tmp)
            L[lm] = J[b] + tmp
        else:
            L[lm] = J[b]
    W = np.empty((nh, 3))  # world hinge axes
    tmp2 = np.empty(3)
    for k in range(nh):
        b = bone_of[k]
        s = 0
        for q in range(3):
            if slots[b, q] == k:
                s = q
        _mv(prefix[b, s], axes[k], tmp)
        _mv(Gp[b], tmp, tmp2)
        W[k] = tmp2
    cost = 0.0
    c2 = cauchy * cauchy
    s2 = sigma_px * sigma_px
    D = np.zeros((3, npar))
    A = np.empty((3, 3))
    bvec = np.empty(3)
    du = np.empty(3)
    dv = np.empty(3)
    AD = np.empty((3, npar))
    for lm in range(nl):
        A[:] = 0.0
        bvec[:] = 0.0
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
        for i in range(3):
            for p in range(npar):
                AD[i, p] = A[i, 0] * D[0, p] + A[i, 1] * D[1, p] + A[i, 2] * D[2, p]
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
    for i in range(3):
        for j in range(3):
            A[i, j] = (
                body_rotation[0, i] * rotation[0, j]
                + body_rotation[1, i] * rotation[1, j]
                + (body_rotation[2, i] * rotation[2, j])
            )
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


@nb.njit(cache=True, nogil=True)
def solve_lm(
    angles: FloatArray,
    rotation: FloatArray,
    wrist: FloatArray,
    axes: FloatArray,
    slots: NDArray[np.intp],
    bone_of: NDArray[np.intp],
    offsets: FloatArray,
    tips: FloatArray,
    lm_bone: NDArray[np.intp],
    lm_tip: NDArray[np.bool_],
    depends: NDArray[np.bool_],
    P: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    prior: FloatArray,  # (4, 21): mean, sigma, lower, upper
    coupled: NDArray[np.intp],
    scalars: FloatArray,
    body_rotation: FloatArray,
    body_wrist: FloatArray,
    max_iterations: int,
    tolerance: float,
) -> tuple[FloatArray, FloatArray, FloatArray, float, int]:
    """The whole Levenberg–Marquardt loop of :meth:`HandSolver.solve` in one call (the same steps as its numpy
    path): returns angles, rotation, wrist, cost and iterations."""
    npar = angles.shape[0] + 6
    JtJ = np.empty((npar, npar))
    g = np.empty(npar)
    tJ = np.empty((npar, npar))
    tg = np.empty(npar)
    args = (axes, slots, bone_of, offsets, tips, lm_bone, lm_tip, depends, P, uv, conf, prior, coupled, scalars)
    cost = evaluate(angles, rotation, wrist, *args, body_rotation, body_wrist, JtJ, g)
    lam = 1e-3
    iterations = 0
    damped = np.empty((npar, npar))
    while iterations < max_iterations:
        iterations += 1
        for i in range(npar):
            for j in range(npar):
                damped[i, j] = JtJ[i, j]
            damped[i, i] += lam * (JtJ[i, i] + 1e-9)
        step, ok = cholesky_solve(damped, -g)
        if not ok:
            lam *= 4.0
            if lam > 1e6:
                break
            continue
        a2, r2, w2 = apply_step(angles, rotation, wrist, step, prior[2], prior[3])
        t_cost = evaluate(a2, r2, w2, *args, body_rotation, body_wrist, tJ, tg)
        if t_cost < cost:
            change = 0.0
            for k in range(angles.shape[0]):
                change = max(change, abs(a2[k] - angles[k]))
            small = (cost - t_cost) < tolerance * cost or change < tolerance
            angles, rotation, wrist, cost = a2, r2, w2, t_cost
            JtJ[:] = tJ
            g[:] = tg
            lam = max(lam / 3.0, 1e-7)
            if small:
                break
        else:
            lam *= 4.0
            if lam > 1e6:
                break
    return angles, rotation, wrist, cost, iterations

"""Compiled (numba) evaluation of the cost and the normal equations for the LM inner loop.

This is the same mathematics as :mod:`mocapd.core.terms` + :class:`mocapd.core.solver.PoseSolver`'s numpy
reference path, written as scalar loops: per LM iteration the numpy path issues about a thousand small array
operations whose call overhead (not arithmetic) dominates; here the whole evaluation is one call. A test
asserts that both paths give the same cost, gradient and ``JᵀJ`` to round-off, and the finite-difference tests
check the numpy path; so the kernel is checked twice.

Kinematic-chain sparsity: every kinematic residual depends on θ through one 3-D row (a point or a bone's
global rotation) whose Jacobian is non-zero only in the columns of the bone's ancestors (at most 8 of the 21
bones). Each row's 3×3 Gauss–Newton block is first summed over all its residuals (e.g. all cameras), then
spread into the 66×66 matrix once, using only those columns.

Compiled with ``cache=True``: the first call in a fresh environment compiles (seconds, reported by
:func:`warm_up`); later processes load the cache. And with ``nogil=True``, as every kernel of
``mocapd/core/_*kernel.py`` (tests/test_kernels_nogil.py): a solve on the tick thread or the solve pool leaves the
interpreter lock to the event loop while it runs.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

LOSS_TRIVIAL = 0
LOSS_CAUCHY = 1
LOSS_HUBER = 2

T_POSITION, T_ORIENTATION, T_ACCELERATION, T_PRIOR_PROJECTION, T_PRIOR_DEVIATION, T_FLOOR = range(6)

_MIN_DEPTH = 1e-3  # keep equal to camera.MIN_DEPTH


@nb.njit(cache=True, nogil=True)
def _loss(code: int, scale: float, s: float) -> tuple[float, float, float]:
    if code == LOSS_CAUCHY:
        b = scale * scale
        c = 1.0 / b
        inv = 1.0 / (1.0 + s * c)
        return b * math.log1p(s * c), inv, -c * inv * inv
    if code == LOSS_HUBER:
        b = scale * scale
        if s > b:
            r = math.sqrt(s)
            rho1 = max(scale / r, 1e-300)
            return 2.0 * scale * r - b, rho1, -0.5 * rho1 / s
        return s, 1.0, 0.0
    return s, 1.0, 0.0


@nb.njit(cache=True, nogil=True)
def _corrector(s: float, rho1: float, rho2: float) -> tuple[float, float]:
    """(w, beta) of Ceres's corrector: J~ᵀJ~ = w (JᵀJ - beta (Jᵀf)(Jᵀf)ᵀ), J~ᵀf~ = w Jᵀf."""
    if s > 0.0 and rho2 > 0.0:
        d = 1.0 + 2.0 * s * rho2 / rho1
        alpha = 1.0 - math.sqrt(max(d, 0.0))
        return rho1, (2.0 * alpha - alpha * alpha) / s
    return rho1, 0.0


@nb.njit(cache=True, nogil=True)
def _rodrigues(r: FloatArray, R: FloatArray, Jr: FloatArray, need_jr: bool) -> None:
    x, y, z = r[0], r[1], r[2]
    t2 = x * x + y * y + z * z
    t = math.sqrt(t2)
    if t < 1e-6:
        a = 1.0 - t2 / 6.0
        b = 0.5 - t2 / 24.0
    else:
        a = math.sin(t) / t
        b = (1.0 - math.cos(t)) / t2
    # K = [r]x ; K² = r rᵀ - t² I
    R[0, 0] = 1.0 + b * (x * x - t2)
    R[0, 1] = -a * z + b * x * y
    R[0, 2] = a * y + b * x * z
    R[1, 0] = a * z + b * x * y
    R[1, 1] = 1.0 + b * (y * y - t2)
    R[1, 2] = -a * x + b * y * z
    R[2, 0] = -a * y + b * x * z
    R[2, 1] = a * x + b * y * z
    R[2, 2] = 1.0 + b * (z * z - t2)
    if need_jr:
        if t < 1e-4:
            c1 = 0.5 - t2 / 24.0
            c2 = 1.0 / 6.0 - t2 / 120.0
        else:
            c1 = (1.0 - math.cos(t)) / t2
            c2 = (t - math.sin(t)) / (t2 * t)
        # Jr = I - c1 K + c2 K²
        Jr[0, 0] = 1.0 + c2 * (x * x - t2)
        Jr[0, 1] = c1 * z + c2 * x * y
        Jr[0, 2] = -c1 * y + c2 * x * z
        Jr[1, 0] = -c1 * z + c2 * x * y
        Jr[1, 1] = 1.0 + c2 * (y * y - t2)
        Jr[1, 2] = c1 * x + c2 * y * z
        Jr[2, 0] = c1 * y + c2 * x * z
        Jr[2, 1] = -c1 * x + c2 * y * z
        Jr[2, 2] = 1.0 + c2 * (z * z - t2)


@nb.njit(cache=True, nogil=True)
def _quat_from_matrix(M: FloatArray, q: FloatArray) -> None:
    tr = M[0, 0] + M[1, 1] + M[2, 2]
    if tr >= M[0, 0] and tr >= M[1, 1] and tr >= M[2, 2]:
        s = math.sqrt(1.0 + tr) * 2.0
        q[0] = 0.25 * s
        q[1] = (M[2, 1] - M[1, 2]) / s
        q[2] = (M[0, 2] - M[2, 0]) / s
        q[3] = (M[1, 0] - M[0, 1]) / s
    elif M[0, 0] >= M[1, 1] and M[0, 0] >= M[2, 2]:
        s = math.sqrt(1.0 + M[0, 0] - M[1, 1] - M[2, 2]) * 2.0
        q[0] = (M[2, 1] - M[1, 2]) / s
        q[1] = 0.25 * s
        q[2] = (M[0, 1] + M[1, 0]) / s
        q[3] = (M[0, 2] + M[2, 0]) / s
    elif M[1, 1] >= M[2, 2]:
        s = math.sqrt(1.0 + M[1, 1] - M[0, 0] - M[2, 2]) * 2.0
        q[0] = (M[0, 2] - M[2, 0]) / s
        q[1] = (M[0, 1] + M[1, 0]) / s
        q[2] = 0.25 * s
        q[3] = (M[1, 2] + M[2, 1]) / s
    else:
        s = math.sqrt(1.0 + M[2, 2] - M[0, 0] - M[1, 1]) * 2.0
        q[0] = (M[1, 0] - M[0, 1]) / s
        q[1] = (M[0, 2] + M[2, 0]) / s
        q[2] = (M[1, 2] + M[2, 1]) / s
        q[3] = 0.25 * s
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    sg = 1.0 / n if q[0] >= 0.0 else -1.0 / n
    for i in range(4):
        q[i] *= sg


@nb.njit(cache=True, nogil=True)
def _accumulate_block(
    H3: FloatArray, g3: FloatArray, row: int, G: FloatArray, f: FloatArray, k: int, w: float, beta: float
) -> None:
    """H3[row] += w (GᵀG - beta gp gpᵀ), g3[row] += w gp with gp = Gᵀf; G (k, 3), f (k,)."""
    gp0 = 0.0
    gp1 = 0.0
    gp2 = 0.0
    for a in range(k):
        gp0 += G[a, 0] * f[a]
        gp1 += G[a, 1] * f[a]
        gp2 += G[a, 2] * f[a]
    gp = (gp0, gp1, gp2)
    for i in range(3):
        g3[row, i] += w * gp[i]
        for j in range(3):
            acc = 0.0
            for a in range(k):
                acc += G[a, i] * G[a, j]
            H3[row, i, j] += w * (acc - beta * gp[i] * gp[j])


@nb.njit(cache=True, nogil=True)
def _joint_axes(Q: FloatArray, Jr: FloatArray) -> FloatArray:
    """Each joint's rotation-vector Jacobian in world axes, Q_b · Jr_b (nb, 3, 3): the columns a row's derivative
    is spread along (:func:`_spread_row`)."""
    nb_ = Q.shape[0]
    axes = np.empty((nb_, 3, 3))
    for b in range(nb_):
        for i in range(3):
            for j in range(3):
                axes[b, i, j] = Q[b, i, 0] * Jr[b, 0, j] + Q[b, i, 1] * Jr[b, 1, j] + Q[b, i, 2] * Jr[b, 2, j]
    return axes


@nb.njit(cache=True, nogil=True)
def _spread_row(
    H: FloatArray,
    g: FloatArray,
    H3r: FloatArray,
    g3r: FloatArray,
    bone: int,
    point: FloatArray,
    angular: bool,
    parents: FloatArray,
    positions: FloatArray,
    axes: FloatArray,
    cols: FloatArray,
    J: FloatArray,
    M: FloatArray,
) -> None:
    """Add Jᵀ H3 J and Jᵀ g3 of one table row to H, g using only the row's non-zero columns."""
    n = 0
    if not angular:
        for i in range(3):
            cols[n] = i
            for a in range(3):
                J[a, n] = 1.0 if a == i else 0.0
            n += 1
    k = bone
    while k >= 0:
        base = 3 + 3 * k
        if angular:
            for i in range(3):
                cols[n + i] = base + i
                for a in range(3):
                    J[a, n + i] = axes[k, a, i]
        else:
            d0 = point[0] - positions[k, 0]
            d1 = point[1] - positions[k, 1]
            d2 = point[2] - positions[k, 2]
            for i in range(3):
                cols[n + i] = base + i
                a0 = axes[k, 0, i]
                a1 = axes[k, 1, i]
                a2 = axes[k, 2, i]
                # cross(A_i, d) = -[d]x A_i
                J[0, n + i] = a1 * d2 - a2 * d1
                J[1, n + i] = a2 * d0 - a0 * d2
                J[2, n + i] = a0 * d1 - a1 * d0
        n += 3
        k = int(parents[k])
    for j in range(n):
        for a in range(3):
            M[a, j] = H3r[a, 0] * J[0, j] + H3r[a, 1] * J[1, j] + H3r[a, 2] * J[2, j]
    for i in range(n):
        ci = int(cols[i])
        g[ci] += J[0, i] * g3r[0] + J[1, i] * g3r[1] + J[2, i] * g3r[2]
        for j in range(n):
            H[ci, int(cols[j])] += J[0, i] * M[0, j] + J[1, i] * M[1, j] + J[2, i] * M[2, j]


@nb.njit(cache=True, nogil=True)
def _forward(
    theta: FloatArray,
    parents: FloatArray,
    offsets: FloatArray,
    Rl: FloatArray,
    Jr: FloatArray,
    Q: FloatArray,
    X: FloatArray,
    need_jr: bool,
) -> None:
    """Forward kinematics into preallocated arrays (bones topologically ordered: parents first).

    Rl, Jr, Q : (n_bones, 3, 3) local rotations, their right Jacobians (if ``need_jr``), global rotations;
    X : (n_bones, 3) joint positions.
    """
    for b in range(parents.shape[0]):
        _rodrigues(theta[3 + 3 * b : 6 + 3 * b], Rl[b], Jr[b], need_jr)
        p = int(parents[b])
        if p < 0:
            Q[b] = Rl[b]
            X[b, 0] = theta[0]
            X[b, 1] = theta[1]
            X[b, 2] = theta[2]
        else:
            for i in range(3):
                X[b, i] = X[p, i] + Q[p, i, 0] * offsets[b, 0] + Q[p, i, 1] * offsets[b, 1] + Q[p, i, 2] * offsets[b, 2]
                for j in range(3):
                    Q[b, i, j] = Q[p, i, 0] * Rl[b, 0, j] + Q[p, i, 1] * Rl[b, 1, j] + Q[p, i, 2] * Rl[b, 2, j]


@nb.njit(cache=True, nogil=True)
def _attach(Q: FloatArray, X: FloatArray, bones: FloatArray, point_offsets: FloatArray) -> FloatArray:
    """World positions of points ``(bone, offset)``: X_b + Q_b c, shape (n, 3)."""
    out = np.empty((bones.shape[0], 3))
    for r in range(bones.shape[0]):
        b = int(bones[r])
        for i in range(3):
            out[r, i] = (
                X[b, i]
                + Q[b, i, 0] * point_offsets[r, 0]
                + Q[b, i, 1] * point_offsets[r, 1]
                + Q[b, i, 2] * point_offsets[r, 2]
            )
    return out


@nb.njit(cache=True, nogil=True)
def evaluate(
    theta: FloatArray,
    jac: bool,
    parents: FloatArray,
    offsets: FloatArray,
    point_bones: FloatArray,
    point_offsets: FloatArray,
    n_kp: int,
    n_imu: int,
    K: FloatArray,
    dist: FloatArray,
    Rc: FloatArray,
    tc: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    q_meas: FloatArray,
    acc_meas: FloatArray,
    imu_mask: FloatArray,
    prev1: FloatArray,
    prev2: FloatArray,
    dt: float,
    mu: FloatArray,
    A_pp: FloatArray,
    A_pd: FloatArray,
    AtA_pp: FloatArray,
    AtA_pd: FloatArray,
    lambdas: FloatArray,
    loss_codes: FloatArray,
    loss_scales: FloatArray,
    enabled: FloatArray,
    floor_radius: float,
    floor_height: float,
    H: FloatArray,
    g: FloatArray,
    term_costs: FloatArray,
) -> float:
    """Cost ``½ Σ ρ`` (returned), per-term costs, and if ``jac`` the corrected normal equations H, g.

    Array arguments follow :class:`mocapd.core.solver.PoseSolver`'s layout; integer-valued arrays are passed
    as float64 to keep a single compiled signature. ``enabled`` holds 0/1 per term (TERM order).
    """
    nb_ = parents.shape[0]
    n_pts = point_bones.shape[0]
    Rl = np.empty((nb_, 3, 3))
    Jr = np.empty((nb_, 3, 3))
    Q = np.empty((nb_, 3, 3))
    X = np.empty((nb_, 3))
    _forward(theta, parents, offsets, Rl, Jr, Q, X, jac)
    P = _attach(Q, X, point_bones, point_offsets)

    for i in range(6):
        term_costs[i] = 0.0
    n_rows = n_pts + n_imu
    H3 = np.zeros((n_rows, 3, 3))
    g3 = np.zeros((n_rows, 3))
    Gb = np.empty((3, 3))
    fb = np.empty(3)

    # -- E_P: reprojection
    if enabled[T_POSITION] > 0.5:
        lam = lambdas[T_POSITION]
        code = int(loss_codes[T_POSITION])
        scale = loss_scales[T_POSITION]
        for c in range(K.shape[0]):
            fx, fy, cx, cy = K[c, 0, 0], K[c, 1, 1], K[c, 0, 2], K[c, 1, 2]
            k1, k2, p1, p2, k3 = dist[c, 0], dist[c, 1], dist[c, 2], dist[c, 3], dist[c, 4]
            for p in range(n_kp):
                w_c = conf[c, p]
                if w_c <= 0.0:
                    continue
                xc0 = Rc[c, 0, 0] * P[p, 0] + Rc[c, 0, 1] * P[p, 1] + Rc[c, 0, 2] * P[p, 2] + tc[c, 0]
                xc1 = Rc[c, 1, 0] * P[p, 0] + Rc[c, 1, 1] * P[p, 1] + Rc[c, 1, 2] * P[p, 2] + tc[c, 1]
                xc2 = Rc[c, 2, 0] * P[p, 0] + Rc[c, 2, 1] * P[p, 1] + Rc[c, 2, 2] * P[p, 2] + tc[c, 2]
                if xc2 <= _MIN_DEPTH:
                    continue
                iz = 1.0 / xc2
                x = xc0 * iz
                y = xc1 * iz
                x2, y2, xy = x * x, y * y, x * y
                r2 = x2 + y2
                radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
                yd = y * radial + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
                sw = math.sqrt(lam * w_c)
                fb[0] = sw * (fx * xd + cx - uv[c, p, 0])
                fb[1] = sw * (fy * yd + cy - uv[c, p, 1])
                s = fb[0] * fb[0] + fb[1] * fb[1]
                rho, rho1, rho2 = _loss(code, scale, s)
                term_costs[T_POSITION] += 0.5 * rho
                if jac:
                    drad = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))
                    a00 = radial + x * drad * x + 2.0 * p1 * y + 6.0 * p2 * x
                    a01 = x * drad * y + 2.0 * p1 * x + 2.0 * p2 * y
                    a10 = y * drad * x + 2.0 * p1 * x + 2.0 * p2 * y
                    a11 = radial + y * drad * y + 6.0 * p1 * y + 2.0 * p2 * x
                    ga = sw * fx * iz
                    gb = sw * fy * iz
                    j00, j01, j02 = ga * a00, ga * a01, -ga * (a00 * x + a01 * y)
                    j10, j11, j12 = gb * a10, gb * a11, -gb * (a10 * x + a11 * y)
                    for j in range(3):
                        Gb[0, j] = j00 * Rc[c, 0, j] + j01 * Rc[c, 1, j] + j02 * Rc[c, 2, j]
                        Gb[1, j] = j10 * Rc[c, 0, j] + j11 * Rc[c, 1, j] + j12 * Rc[c, 2, j]
                    w, beta = _corrector(s, rho1, rho2)
                    _accumulate_block(H3, g3, p, Gb, fb, 2, w, beta)

    # -- E_R: IMU orientation
    if enabled[T_ORIENTATION] > 0.5:
        sl = math.sqrt(lambdas[T_ORIENTATION])
        code = int(loss_codes[T_ORIENTATION])
        scale = loss_scales[T_ORIENTATION]
        qh = np.empty(4)
        for i in range(n_imu):
            if imu_mask[i] < 0.5:
                continue
            b = int(point_bones[n_kp + i])
            _quat_from_matrix(Q[b], qh)
            # q_e = conj(qh) ⊗ qm
            aw, ax, ay, az = qh[0], -qh[1], -qh[2], -qh[3]
            bw, bx, by, bz = q_meas[i, 0], q_meas[i, 1], q_meas[i, 2], q_meas[i, 3]
            ew = aw * bw - ax * bx - ay * by - az * bz
            ex = aw * bx + ax * bw + ay * bz - az * by
            ey = aw * by - ax * bz + ay * bw + az * bx
            ez = aw * bz + ax * by - ay * bx + az * bw
            if ew < 0.0:
                ew, ex, ey, ez = -ew, -ex, -ey, -ez
            fb[0], fb[1], fb[2] = sl * ex, sl * ey, sl * ez
            s = fb[0] * fb[0] + fb[1] * fb[1] + fb[2] * fb[2]
            rho, rho1, rho2 = _loss(code, scale, s)
            term_costs[T_ORIENTATION] += 0.5 * rho
            if jac:
                # D = -w I + [v]x ; G = 0.5 sl D Qᵀ
                D00, D01, D02 = -ew, -ez, ey
                D10, D11, D12 = ez, -ew, -ex
                D20, D21, D22 = -ey, ex, -ew
                for j in range(3):
                    Gb[0, j] = 0.5 * sl * (D00 * Q[b, j, 0] + D01 * Q[b, j, 1] + D02 * Q[b, j, 2])
                    Gb[1, j] = 0.5 * sl * (D10 * Q[b, j, 0] + D11 * Q[b, j, 1] + D12 * Q[b, j, 2])
                    Gb[2, j] = 0.5 * sl * (D20 * Q[b, j, 0] + D21 * Q[b, j, 1] + D22 * Q[b, j, 2])
                w, beta = _corrector(s, rho1, rho2)
                _accumulate_block(H3, g3, n_pts + i, Gb, fb, 3, w, beta)

    # -- E_A: IMU acceleration (window t, t-1, t-2; previous solves fixed)
    if enabled[T_ACCELERATION] > 0.5:
        sl = math.sqrt(lambdas[T_ACCELERATION])
        code = int(loss_codes[T_ACCELERATION])
        scale = loss_scales[T_ACCELERATION]
        inv = 1.0 / (dt * dt)
        for i in range(n_imu):
            if imu_mask[i] < 0.5:
                continue
            r = n_kp + i
            s = 0.0
            for a in range(3):
                fb[a] = sl * ((P[r, a] - 2.0 * prev1[i, a] + prev2[i, a]) * inv - acc_meas[i, a])
                s += fb[a] * fb[a]
            rho, rho1, rho2 = _loss(code, scale, s)
            term_costs[T_ACCELERATION] += 0.5 * rho
            if jac:
                for a in range(3):
                    for j in range(3):
                        Gb[a, j] = sl * inv if a == j else 0.0
                w, beta = _corrector(s, rho1, rho2)
                _accumulate_block(H3, g3, r, Gb, fb, 3, w, beta)

    # -- E_FP: floor penetration (hinge)
    if enabled[T_FLOOR] > 0.5:
        sl = math.sqrt(lambdas[T_FLOOR])
        code = int(loss_codes[T_FLOOR])
        scale = loss_scales[T_FLOOR]
        for r in range(n_kp + n_imu, n_pts):
            pen = floor_radius - (P[r, 1] - floor_height)
            if pen <= 0.0:
                continue
            fb[0] = sl * pen
            s = fb[0] * fb[0]
            rho, rho1, rho2 = _loss(code, scale, s)
            term_costs[T_FLOOR] += 0.5 * rho
            if jac:
                Gb[0, 0] = 0.0
                Gb[0, 1] = -sl
                Gb[0, 2] = 0.0
                w, beta = _corrector(s, rho1, rho2)
                _accumulate_block(H3, g3, r, Gb, fb, 1, w, beta)

    if jac:
        for i in range(H.shape[0]):
            g[i] = 0.0
            for j in range(H.shape[1]):
                H[i, j] = 0.0

    # -- PCA prior terms (dense, constant Jacobians)
    dp = mu.shape[0]
    if dp > 0 and (enabled[T_PRIOR_PROJECTION] > 0.5 or enabled[T_PRIOR_DEVIATION] > 0.5):
        d = np.empty(dp)
        for i in range(dp):
            d[i] = theta[6 + i] - mu[i]
        for term in (T_PRIOR_PROJECTION, T_PRIOR_DEVIATION):
            if enabled[term] < 0.5:
                continue
            A = A_pp if term == T_PRIOR_PROJECTION else A_pd
            AtA = AtA_pp if term == T_PRIOR_PROJECTION else AtA_pd
            m = A.shape[0]
            f = A @ d
            s = 0.0
            for i in range(m):
                s += f[i] * f[i]
            rho, rho1, rho2 = _loss(int(loss_codes[term]), loss_scales[term], s)
            term_costs[term] += 0.5 * rho
            if jac:
                w, beta = _corrector(s, rho1, rho2)
                gp = A.T @ f
                for i in range(dp):
                    g[6 + i] += w * gp[i]
                    for j in range(dp):
                        H[6 + i, 6 + j] += w * (AtA[i, j] - beta * gp[i] * gp[j])

    cost = 0.0
    for i in range(6):
        cost += term_costs[i]
    if not jac:
        return cost

    # -- spread per-row blocks into the 66×66 system along each row's kinematic chain
    axes = _joint_axes(Q, Jr)
    cols = np.empty(3 + 3 * nb_)
    Jrow = np.empty((3, 3 + 3 * nb_))
    Mrow = np.empty((3, 3 + 3 * nb_))
    for r in range(n_rows):
        nz = False
        for i in range(3):
            if g3[r, i] != 0.0:
                nz = True
            for j in range(3):
                if H3[r, i, j] != 0.0:
                    nz = True
        if not nz:
            continue
        if r < n_pts:
            _spread_row(H, g, H3[r], g3[r], int(point_bones[r]), P[r], False, parents, X, axes, cols, Jrow, Mrow)
        else:
            b = int(point_bones[n_kp + (r - n_pts)])
            _spread_row(H, g, H3[r], g3[r], b, P[0], True, parents, X, axes, cols, Jrow, Mrow)
    return cost


@nb.njit(cache=True, nogil=True)
def cholesky_solve(A: FloatArray, b: FloatArray) -> tuple[FloatArray, bool]:
    """x with A x = b for symmetric positive definite A (n small); False when A is not (the body's LM step and
    the hand solve's, :mod:`mocapd.core._hand_kernel`)."""
    n = A.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        d = A[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:
            return np.zeros(n), False
        L[j, j] = math.sqrt(d)
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    y = np.empty(n)
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return x, True


@nb.njit(cache=True, nogil=True)
def lm_step(
    H: FloatArray, g: FloatArray, radius: float, min_diag: float, max_diag: float
) -> tuple[FloatArray, float, bool]:
    """Solve ``(H + diag(clip(diag H))/radius) δ = -g`` by Cholesky.

    Returns
    -------
    step : (n,); model_reduction : ``-(gᵀδ + ½ δᵀHδ)``; ok : False when the system is not positive definite.
    """
    n = H.shape[0]
    A = H.copy()
    for i in range(n):
        A[i, i] += min(max(H[i, i], min_diag), max_diag) / radius
    x, ok = cholesky_solve(A, -g)
    if not ok:
        return np.zeros(n), 0.0, False
    red = 0.0
    for i in range(n):
        hx = 0.0
        for k in range(n):
            hx += H[i, k] * x[k]
        red -= g[i] * x[i] + 0.5 * x[i] * hx
    return x, red, True


@nb.njit(cache=True, nogil=True)
def skeleton_points(
    theta: FloatArray, parents: FloatArray, offsets: FloatArray, bones: FloatArray, point_offsets: FloatArray
) -> FloatArray:
    """World positions of points ``(bone, offset)`` for θ, shape (n, 3) (forward kinematics only)."""
    nb_ = parents.shape[0]
    Rl = np.empty((nb_, 3, 3))
    Jr = np.empty((nb_, 3, 3))
    Q = np.empty((nb_, 3, 3))
    X = np.empty((nb_, 3))
    _forward(theta, parents, offsets, Rl, Jr, Q, X, False)
    return _attach(Q, X, bones, point_offsets)

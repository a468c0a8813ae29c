"""Bundle adjustment of cameras and 3D points: Levenberg-Marquardt on the Schur complement, robust weights.

Unknowns: each camera's pose (a rotation perturbation ``R ← exp([ω]) R`` and a translation step, 6 values; one
camera held fixed for the gauge), optionally its focal length (one factor ``e^κ`` on fx and fy) and principal
point, and every 3D point. Residuals: projected minus observed pixels (OpenCV distortion, held fixed), weighted
by each observation's confidence and, for robustness, the soft-L1 loss ``ρ(s) = 2(√(1+s) − 1)`` of
``s = e²/σ²`` (iteratively reweighted: weight ``1/√(1+s)``).

The point blocks (3×3) are eliminated per point, leaving a dense system in the camera parameters only
(``6 + intrinsics`` per camera): a minute of walking is tens of thousands of points but a handful of cameras,
and each iteration is a few vectorised passes over the observations. The Jacobians are analytic
(:func:`mocapd.core.camera.project_points` gives ∂uv/∂X; ∂X_cam/∂ω = −[R X]×).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera, project_points, stack_cameras
from mocapd.core.rotations import matrix_from_rotvec, skew

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class AdjustResult:
    """Adjusted cameras (same order, intrinsics refined where asked), points (n_points, 3), final residual norms
    per observation (pixels), iterations run and the robust cost before and after."""

    cameras: list[Camera]
    points: FloatArray
    errors_px: FloatArray
    iterations: int
    cost_before: float
    cost_after: float


def _residuals(
    cams: list[Camera], X: FloatArray, cam: IntArray, point: IntArray, uv: FloatArray, jac: bool
) -> tuple[FloatArray, FloatArray | None, FloatArray]:
    K, dist, R, t = stack_cameras(cams)
    proj, J, valid = project_points(K[cam], dist[cam], R[cam], t[cam], X[point][:, None, :], jacobian=jac)
    r = proj[:, 0] - uv
    r[~valid[:, 0]] = 1e4  # behind the camera: a large, flat residual (the robust loss caps its pull)
    return r, (None if J is None else J[:, 0]), proj[:, 0]


def _sum_by(index: IntArray, values: FloatArray, n: int) -> FloatArray:
    """The rows of ``values`` summed by ``index``: ``out[k] = Σ values[i] over i with index[i] = k``.

    Parameters
    ----------
    index : int array, shape (m,)
        Row of the output each value goes to (0 <= index < n).
    values : array, shape (m, ...)
    n : int
        Rows of the output.

    Returns
    -------
    array, shape (n, ...)
        ``np.add.at`` into zeros, with the same additions in the same order (so the same floats): one
        ``np.bincount`` per component, several times faster than ``np.add.at`` on these (m, 3, 3) blocks.
    """
    flat = values.reshape(len(values), -1)
    sums = [np.bincount(index, weights=flat[:, k], minlength=n) for k in range(flat.shape[1])]
    return np.asarray(np.stack(sums, axis=1).reshape(n, *values.shape[1:]), dtype=np.float64)


def _cost(r: FloatArray, w: FloatArray, sigma: float) -> float:
    s = np.sum(r * r, axis=1) / sigma**2
    return float(np.sum(w * sigma**2 * 2.0 * (np.sqrt(1.0 + s) - 1.0)))


def adjust(
    cameras: list[Camera],
    points: FloatArray,
    cam: IntArray,
    point: IntArray,
    uv: FloatArray,
    weight: FloatArray,
    *,
    sigma_px: float = 2.0,
    fixed: int = 0,
    intrinsics: int = 0,
    iterations: int = 40,
) -> AdjustResult:
    """Adjust ``cameras`` and ``points`` to the observations.

    Parameters
    ----------
    cameras : list of n_cams Camera
        Initial poses and intrinsics.
    points : array, shape (n_points, 3)
        Initial points (finite).
    cam, point : int arrays, shape (m,)
        Camera and point of each observation (at most one observation of a point per camera).
    uv : array, shape (m, 2)
        Observed (distorted) pixels.
    weight : array, shape (m,)
        Confidence of each observation (> 0).
    sigma_px : float
        Scale of the soft-L1 loss: residuals well beyond it pull with a force that no longer grows.
    fixed : int
        The camera whose pose is held (the gauge; the scale stays free and is set by the caller).
    intrinsics : int
        0: poses only; 1: also a focal-length factor per camera; 3: also the principal point.
    iterations : int
        Most Levenberg-Marquardt iterations.
    """
    cams = list(cameras)
    X = np.asarray(points, dtype=np.float64).copy()
    n_cams, n_pts, m = len(cams), len(X), len(cam)
    D = 6 + intrinsics
    table = np.full((n_pts, n_cams), -1, dtype=np.intp)
    table[point, cam] = np.arange(m)
    r, J, proj = _residuals(cams, X, cam, point, uv, True)
    cost0 = cost = _cost(r, weight, sigma_px)
    lam = 1e-3
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 (the count is reported)
        assert J is not None
        e2 = np.sum(r * r, axis=1)
        W = weight / np.sqrt(1.0 + e2 / sigma_px**2)
        K, _, R, _ = stack_cameras(cams)
        Jc_cam = J @ np.transpose(R[cam], (0, 2, 1))  # ∂uv/∂X_cam
        RX = np.einsum("mij,mj->mi", R[cam], X[point])
        parts = [Jc_cam @ -skew(RX), Jc_cam]
        if intrinsics >= 1:
            parts.append((proj - K[cam][:, :2, 2])[:, :, None])
        if intrinsics == 3:
            parts.append(np.broadcast_to(np.eye(2), (m, 2, 2)))
        Jcam = np.concatenate(parts, axis=2)  # (m, 2, D)
        JtW = np.swapaxes(J, 1, 2) * W[:, None, None]  # (m, 3, 2)
        JcW = np.swapaxes(Jcam, 1, 2) * W[:, None, None]  # (m, D, 2)
        Hpp = _sum_by(point, JtW @ J, n_pts)
        gp = _sum_by(point, (JtW @ r[:, :, None])[:, :, 0], n_pts)
        Hcc = _sum_by(cam, JcW @ Jcam, n_cams)
        gc = _sum_by(cam, (JcW @ r[:, :, None])[:, :, 0], n_cams)
        Hcp = JcW @ J  # (m, D, 3)
        while True:
            Hpp_d = Hpp + lam * Hpp * np.eye(3) + 1e-9 * np.eye(3)
            Hpp_inv = np.linalg.inv(Hpp_d)
            Y = Hcp @ Hpp_inv[point]  # (m, D, 3)
            S = np.zeros((n_cams, n_cams, D, D))
            for a in range(n_cams):
                S[a, a] = Hcc[a] + lam * np.diag(np.diag(Hcc[a])) + 1e-9 * np.eye(D)
                for b in range(n_cams):
                    both = (table[:, a] >= 0) & (table[:, b] >= 0)
                    ia, ib = table[both, a], table[both, b]
                    # Σ_n Y_n Hcp_nᵀ as one matrix product
                    S[a, b] -= Y[ia].transpose(1, 0, 2).reshape(D, -1) @ Hcp[ib].transpose(1, 0, 2).reshape(D, -1).T
            rhs = -gc.copy()
            np.add.at(rhs, cam, (Y @ gp[point][:, :, None])[:, :, 0])
            S_flat = S.transpose(0, 2, 1, 3).reshape(n_cams * D, n_cams * D)
            rhs_flat = rhs.reshape(-1)
            hold = np.arange(fixed * D, fixed * D + 6)
            S_flat[hold, :] = 0.0
            S_flat[:, hold] = 0.0
            S_flat[hold, hold] = 1.0
            rhs_flat[hold] = 0.0
            dc = _solve(S_flat, rhs_flat).reshape(n_cams, D)
            back = _sum_by(point, (np.swapaxes(Hcp, 1, 2) @ dc[cam][:, :, None])[:, :, 0], n_pts)
            dp = (Hpp_inv @ (-gp - back)[:, :, None])[:, :, 0]
            trial = _step(cams, dc, intrinsics)
            Xt = X + dp
            rt, Jt, pt = _residuals(trial, Xt, cam, point, uv, True)
            ct = _cost(rt, weight, sigma_px)
            if ct < cost:
                done = (cost - ct) < 1e-7 * cost
                cams, X, r, J, proj, cost = trial, Xt, rt, Jt, pt, ct
                lam = max(lam / 3.0, 1e-9)
                break
            lam *= 4.0
            if lam > 1e8:
                done = True
                break
        if done:
            break
    return AdjustResult(cams, X, np.linalg.norm(r, axis=1), it, cost0, cost)


def _solve(A: FloatArray, b: FloatArray) -> FloatArray:
    try:
        return np.asarray(np.linalg.solve(A, b), dtype=np.float64)
    except np.linalg.LinAlgError:  # singular even with the damping: the least-squares step
        return np.asarray(np.linalg.lstsq(A, b, rcond=None)[0], dtype=np.float64)


def _step(cams: list[Camera], dc: FloatArray, intrinsics: int) -> list[Camera]:
    out = []
    for c, cam in enumerate(cams):
        R = matrix_from_rotvec(dc[c, :3]) @ cam.R
        # Re-orthonormalise: many small steps must not drift off SO(3).
        u, _, vt = np.linalg.svd(R)
        R = u @ vt
        K = cam.K.copy()
        if intrinsics >= 1:
            k = float(np.exp(np.clip(dc[c, 6], -0.5, 0.5)))
            K[0, 0] *= k
            K[1, 1] *= k
        if intrinsics == 3:
            K[0, 2] += dc[c, 7]
            K[1, 2] += dc[c, 8]
        out.append(replace(cam, R=R, t=cam.t + dc[c, 3:6], K=K))
    return out

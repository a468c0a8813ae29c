"""Compiled (numba) core of the left/right flip search (:func:`mocapd.core.lr_flips.choose_swaps`).

Why compiled. The search runs for every person on every tick: per group of keypoint pairs seen by the same views it
triangulates every swap hypothesis (2^(n-1) for n views, two points each), projects the points into every view and
sums the capped reprojection errors. The arithmetic is tiny (a 4x4 eigenproblem per point); as numpy it was ~30
array calls a group whose call overhead, not arithmetic, cost ~0.6 ms a person a tick, 39 % of the tick on the
live camera demo (issue 39's profile), on the event loop. Here it is one call per group, and ``nogil``: the daemon
solves people on worker threads, and this lets two of them search at once.

The same mathematics as the numpy reference (:func:`mocapd.core.lr_flips._best_hypotheses`, kept for the tests
that compare the two): confidence-weighted DLT with unit-normalised rows, the point from the smallest eigenvector
of the 4x4 normal matrix, errors capped at ``cap`` px and counted only where the observation has weight.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@nb.njit(cache=True, nogil=True)
def _swapped(h: int, v: int, n: int) -> bool:
    """Whether hypothesis ``h`` swaps view ``v`` (view 0 never; the others are the bits of ``h``, view 1 highest,
    in the order of ``itertools.product``)."""
    if v == 0:
        return False
    return ((h >> (n - 1 - v)) & 1) == 1


@nb.njit(cache=True, nogil=True)
def _triangulate(P: FloatArray, uv: FloatArray, w: FloatArray, h: int, k: int, label: int, X: FloatArray) -> bool:
    """Point ``label`` of pair ``k`` under hypothesis ``h`` into ``X`` (3,); False where it has fewer than two
    weighted views or lies at infinity."""
    n = P.shape[0]
    M = np.zeros((4, 4))
    views = 0
    row = np.empty(4)
    for v in range(n):
        lab = 1 - label if _swapped(h, v, n) else label
        wt = w[v, k, lab]
        if not wt > 0.0:
            continue
        views += 1
        for axis in range(2):
            coord = uv[v, k, lab, axis]
            norm = 0.0
            for j in range(4):
                row[j] = coord * P[v, 2, j] - P[v, axis, j]
                norm += row[j] * row[j]
            norm = math.sqrt(norm)
            scale = wt / norm if norm > 0.0 else wt
            for i in range(4):
                ri = row[i] * scale
                for j in range(4):
                    M[i, j] += ri * row[j] * scale
    if views < 2:
        return False
    vec = _smallest_eigenvector(M)
    hw = vec[3]
    if not abs(hw) > 1e-12:
        return False
    for i in range(3):
        X[i] = vec[i] / hw
        if not math.isfinite(X[i]):
            return False
    return True


@nb.njit(cache=True, nogil=True)
def _smallest_eigenvector(M: FloatArray) -> FloatArray:
    """The unit eigenvector of the smallest eigenvalue of a symmetric 4x4 matrix, by cyclic Jacobi rotations.

    LAPACK's ``syevd`` through numba costs microseconds of call overhead per 4x4 matrix, more than the search's
    whole arithmetic; a handful of Jacobi sweeps reaches the same vector to round-off (sign aside, which the
    division by the homogeneous coordinate removes)."""
    A = M.copy()
    V = np.eye(4)
    for _ in range(12):
        off = 0.0
        for p in range(3):
            for q in range(p + 1, 4):
                off += A[p, q] * A[p, q]
        if off <= 1e-30 * (A[0, 0] * A[0, 0] + A[1, 1] * A[1, 1] + A[2, 2] * A[2, 2] + A[3, 3] * A[3, 3]):
            break
        for p in range(3):
            for q in range(p + 1, 4):
                apq = A[p, q]
                if apq == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                sn = t * c
                for k in range(4):  # A <- A J (columns p and q)
                    akp, akq = A[k, p], A[k, q]
                    A[k, p] = c * akp - sn * akq
                    A[k, q] = sn * akp + c * akq
                for k in range(4):  # A <- J^T A (rows p and q)
                    apk, aqk = A[p, k], A[q, k]
                    A[p, k] = c * apk - sn * aqk
                    A[q, k] = sn * apk + c * aqk
                for k in range(4):
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p] = c * vkp - sn * vkq
                    V[k, q] = sn * vkp + c * vkq
    best = 0
    for i in range(1, 4):
        if A[i, i] < A[best, best]:
            best = i
    return V[:, best].copy()


@nb.njit(cache=True, nogil=True)
def best_hypotheses(
    P: FloatArray, uv: FloatArray, w: FloatArray, cap: float, margin: float
) -> tuple[IntArray, FloatArray, FloatArray]:
    """For each of K pairs seen by the same n views, the swap hypothesis of least capped reprojection error.

    Parameters
    ----------
    P : array, shape (n, 3, 4)
        Projection matrices (undistorted pixels).
    uv : array, shape (n, K, 2, 2)
        Each view's (left, right) undistorted pixels of each pair (finite where ``w`` > 0).
    w : array, shape (n, K, 2)
        Observation weights (confidence where usable, else 0).
    cap, margin : float
        Error cap per observation (px); the least gain per view (px) for a swap to win.

    Returns
    -------
    best : int array, shape (K,)
        Winning hypothesis per pair (its bits: :func:`_swapped`), 0 (no swap) where none beats no swap by
        ``margin``.
    gain : array, shape (K,)
        Error the winner saves against no swap, px per view (0 where none wins).
    X : array, shape (K, 2, 3)
        The pair's two points under the winner, NaN where a point has too few views.
    """
    n, K = uv.shape[0], uv.shape[1]
    H = 1 << (n - 1)
    cost = np.zeros((H, K))
    Xall = np.full((H, K, 2, 3), np.nan)
    Xp = np.empty(3)
    for h in range(H):
        for k in range(K):
            total = 0.0
            for label in range(2):
                good = _triangulate(P, uv, w, h, k, label, Xp)
                if good:
                    for i in range(3):
                        Xall[h, k, label, i] = Xp[i]
                for v in range(n):
                    lab = 1 - label if _swapped(h, v, n) else label
                    if not w[v, k, lab] > 0.0:
                        continue
                    err = cap
                    if good:
                        px = P[v, 0, 3] + P[v, 0, 0] * Xp[0] + P[v, 0, 1] * Xp[1] + P[v, 0, 2] * Xp[2]
                        py = P[v, 1, 3] + P[v, 1, 0] * Xp[0] + P[v, 1, 1] * Xp[1] + P[v, 1, 2] * Xp[2]
                        pz = P[v, 2, 3] + P[v, 2, 0] * Xp[0] + P[v, 2, 1] * Xp[1] + P[v, 2, 2] * Xp[2]
                        if pz > 1e-6:
                            dx = px / pz - uv[v, k, lab, 0]
                            dy = py / pz - uv[v, k, lab, 1]
                            e = math.sqrt(dx * dx + dy * dy)
                            if math.isfinite(e):
                                err = min(e, cap)
                    total += err
            cost[h, k] = total
    best = np.zeros(K, dtype=np.int64)
    gain = np.zeros(K)
    X = np.empty((K, 2, 3))
    for k in range(K):
        b = 0
        for h in range(1, H):
            if cost[h, k] < cost[b, k]:
                b = h
        g = (cost[0, k] - cost[b, k]) / n
        if b != 0 and g > margin:
            best[k] = b
            gain[k] = g
        X[k] = Xall[b, k]
    return best, gain, X

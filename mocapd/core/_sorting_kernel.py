"""Compiled candidate generation for detection sorting (Algorithm 1, lines 1–17).

One call per frame: undistort every keypoint, triangulate every pair of 2D people across every pair of views
(two-ray midpoint on keypoints confident in both; each left/right pair of keypoints as labelled or with the second
view's labels exchanged, whichever fits better), keep pairs whose mean reprojection error is under the limit,
and cluster them in order of increasing reprojection error (each pair joins the first earlier *leader* within
the same-person distance that does not already hold a different 2D person of one of its cameras).
:mod:`mocapd.core.sorting` turns the result into candidates; its tests exercise this kernel end to end.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@nb.njit(cache=True, nogil=True)
def _undistort(K: FloatArray, dist: FloatArray, u: float, v: float) -> tuple[float, float]:
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    xd = (u - K[0, 2]) / K[0, 0]
    yd = (v - K[1, 2]) / K[1, 1]
    x, y = xd, yd
    for _ in range(10):  # fixed-point iteration, as OpenCV's undistortPoints
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return x, y


@nb.njit(cache=True, nogil=True, inline="always")
def _pair_point(
    rays: FloatArray,
    centres: FloatArray,
    xy: FloatArray,
    R: FloatArray,
    t: FloatArray,
    K: FloatArray,
    a: int,
    b: int,
    pa: int,
    ja: int,
    pb: int,
    jb: int,
    min_depth: float,
    X: FloatArray,
) -> tuple[bool, float, float]:
    """Closest approach of the rays of keypoint ``ja`` of person ``pa`` (camera ``a``) and keypoint ``jb`` of ``pb``
    (camera ``b``): the midpoint into ``X``; returns (ok, reprojection error in a, in b) in px, ok False when the
    rays are parallel or the point is behind a camera."""
    da = rays[pa, ja]
    db = rays[pb, jb]
    w0 = centres[a] - centres[b]
    A = da[0] * da[0] + da[1] * da[1] + da[2] * da[2]
    B = da[0] * db[0] + da[1] * db[1] + da[2] * db[2]
    C = db[0] * db[0] + db[1] * db[1] + db[2] * db[2]
    D = da[0] * w0[0] + da[1] * w0[1] + da[2] * w0[2]
    E = db[0] * w0[0] + db[1] * w0[1] + db[2] * w0[2]
    den = A * C - B * B
    if abs(den) < 1e-12:
        return False, 0.0, 0.0
    s = (B * E - C * D) / den
    u = (A * E - B * D) / den
    for i in range(3):
        X[i] = 0.5 * (centres[a, i] + s * da[i] + centres[b, i] + u * db[i])
    e = (0.0, 0.0)
    for side in range(2):
        c = a if side == 0 else b
        p = pa if side == 0 else pb
        j = ja if side == 0 else jb
        xc0 = R[c, 0, 0] * X[0] + R[c, 0, 1] * X[1] + R[c, 0, 2] * X[2] + t[c, 0]
        xc1 = R[c, 1, 0] * X[0] + R[c, 1, 1] * X[1] + R[c, 1, 2] * X[2] + t[c, 1]
        xc2 = R[c, 2, 0] * X[0] + R[c, 2, 1] * X[1] + R[c, 2, 2] * X[2] + t[c, 2]
        if xc2 <= min_depth:
            return False, 0.0, 0.0
        err = math.hypot(xc0 / xc2 - xy[p, j, 0], xc1 / xc2 - xy[p, j, 1]) * 0.5 * (K[c, 0, 0] + K[c, 1, 1])
        e = (err, e[1]) if side == 0 else (e[0], err)
    return True, e[0], e[1]


@nb.njit(cache=True, nogil=True)
def candidate_pairs(
    keypoints: FloatArray,
    usable: NDArray[np.bool_],
    camera_of: IntArray,
    person_of: IntArray,
    K: FloatArray,
    dist: FloatArray,
    R: FloatArray,
    t: FloatArray,
    widths: FloatArray,
    max_error_fraction: float,
    min_shared: int,
    same_person: float,
    min_depth: float,
    partner: IntArray,
    flips: bool,
    prune: bool,
) -> tuple[FloatArray, IntArray, FloatArray]:
    """All viable cross-view pairs of 2D people, clustered into 3D person candidates.

    Parameters
    ----------
    keypoints : (n, k, 2) pixels of all 2D people of all cameras; usable : (n, k) confident keypoints;
    camera_of, person_of : (n,) camera index and per-camera person index of each 2D person;
    K, dist, R, t : stacked cameras; widths : (n_cams,) image widths;
    partner : (k,) each keypoint's left/right counterpart (itself where it has none);
    flips : pair a left/right pair of keypoints with the second view's labels exchanged where that fits better
    (a view that confused the person's left and right still pairs with the others);
    prune : stop triangulating a pair of 2D people once its mean reprojection error must fail the limit however
    the keypoints left turn out (the sum so far over as many keypoints as could still be shared: errors are not
    negative, and rounding is monotone, so the final mean cannot come in under it); only where both people's
    keypoints are finite (a NaN error would make the final mean NaN, which passes). Pairs of two different people
    stop after a few keypoints (issue 39: this runs on every output tick); the result is the same as without.

    Returns
    -------
    points : (n_clusters, k, 3) keypoints of each candidate (its first pair's, gaps filled by later pairs);
    members : (n_clusters, n_cams) the 2D person of each camera in the candidate (-1: none);
    member_errors : (n_clusters, n_cams) mean reprojection error of that person's view (px, undistorted).
    """
    n, k = keypoints.shape[0], keypoints.shape[1]
    n_cams = K.shape[0]
    # Normalised undistorted image points and world rays.
    xy = np.empty((n, k, 2))
    rays = np.empty((n, k, 3))
    centres = np.empty((n_cams, 3))
    for c in range(n_cams):
        for i in range(3):
            centres[c, i] = -(R[c, 0, i] * t[c, 0] + R[c, 1, i] * t[c, 1] + R[c, 2, i] * t[c, 2])
    for p in range(n):
        c = camera_of[p]
        for j in range(k):
            x, y = _undistort(K[c], dist[c], keypoints[p, j, 0], keypoints[p, j, 1])
            xy[p, j, 0] = x
            xy[p, j, 1] = y
            for i in range(3):  # Rᵀ (x, y, 1)
                rays[p, j, i] = R[c, 0, i] * x + R[c, 1, i] * y + R[c, 2, i]
    finite = np.empty(n, dtype=np.bool_)  # every keypoint of the 2D person finite (undistorted)
    for p in range(n):
        finite[p] = np.isfinite(xy[p]).all()
    m_max = n * n
    points = np.full((m_max, k, 3), np.nan)
    sources = np.empty((m_max, 4), dtype=np.int64)
    errors = np.empty((m_max, 2))
    # Per cluster, the 2D person it holds in each camera (-1: none): one camera sees a person only once.
    members = np.full((m_max, n_cams), -1, dtype=np.int64)
    n_leaders = 0
    m = 0
    X = np.empty(3)
    cand = np.empty((4, 3))  # the four pairings of a left/right pair: (j, j), (q, q), (j, q), (q, j)
    cand_e = np.empty((4, 2))
    cand_ok = np.empty(4, dtype=np.bool_)
    for pa in range(n):
        a = camera_of[pa]
        for pb in range(n):
            b = camera_of[pb]
            if b <= a:
                continue
            shared = 0
            ea = 0.0
            eb = 0.0
            limit = max_error_fraction * 0.5 * (widths[a] + widths[b])
            can_prune = prune and finite[pa] and finite[pb]
            hopeless = False
            for j in range(k):
                if can_prune and shared > 0 and 0.5 * (ea + eb) / (shared + k - j) >= limit:
                    hopeless = True  # at most k - j more keypoints: the mean cannot come under the limit
                    break
                q = partner[j] if flips else j
                if q < j:
                    continue  # done with its left/right partner
                if q == j:
                    if not (usable[pa, j] and usable[pb, j]):
                        continue
                    ok, e0, e1 = _pair_point(rays, centres, xy, R, t, K, a, b, pa, j, pb, j, min_depth, X)
                    if ok:
                        shared += 1
                        ea += e0
                        eb += e1
                        for i in range(3):
                            points[m, j, i] = X[i]
                    continue
                # A left/right pair: as labelled, or with b's labels exchanged (a flipped view); the one of smaller
                # mean error (a flipped view would otherwise fail the limit, or pull the pairing apart).
                for h in range(4):
                    ja = j if h in (0, 2) else q
                    jb = j if h in (0, 3) else q
                    cand_ok[h] = False
                    if usable[pa, ja] and usable[pb, jb]:
                        ok, cand_e[h, 0], cand_e[h, 1] = _pair_point(
                            rays, centres, xy, R, t, K, a, b, pa, ja, pb, jb, min_depth, X
                        )
                        cand_ok[h] = ok
                    if cand_ok[h]:
                        for i in range(3):
                            cand[h, i] = X[i]
                n_straight = int(cand_ok[0]) + int(cand_ok[1])
                n_crossed = int(cand_ok[2]) + int(cand_ok[3])
                s_straight = (cand_e[0, 0] + cand_e[0, 1]) * cand_ok[0] + (cand_e[1, 0] + cand_e[1, 1]) * cand_ok[1]
                s_crossed = (cand_e[2, 0] + cand_e[2, 1]) * cand_ok[2] + (cand_e[3, 0] + cand_e[3, 1]) * cand_ok[3]
                crossed = (
                    flips
                    and n_crossed > 0
                    and (n_crossed > n_straight or (n_crossed == n_straight and s_crossed < s_straight))
                )
                first, second = (2, 3) if crossed else (0, 1)
                for h, jj in ((first, j), (second, q)):
                    if cand_ok[h]:
                        shared += 1
                        ea += cand_e[h, 0]
                        eb += cand_e[h, 1]
                        for i in range(3):
                            points[m, jj, i] = cand[h, i]
            if hopeless or shared < min_shared or 0.5 * (ea + eb) / shared >= limit:
                for j in range(k):
                    points[m, j, 0] = np.nan
                    points[m, j, 1] = np.nan
                    points[m, j, 2] = np.nan
                continue
            sources[m, 0] = a
            sources[m, 1] = person_of[pa]
            sources[m, 2] = b
            sources[m, 3] = person_of[pb]
            errors[m, 0] = ea / shared
            errors[m, 1] = eb / shared
            m += 1
    # Cluster in order of increasing reprojection error: true pairings (consistent to a pixel or two) form
    # the clusters first; a mismatched pairing of two different people comes later and, contradicting them
    # in a view, stays on its own (and is dropped when detections are claimed).
    order = np.argsort(errors[:m, 0] + errors[:m, 1])
    points, sources, errors = points[order], sources[order], errors[order]
    cluster_points = np.full((m, k, 3), np.nan)
    member_errors = np.full((m, n_cams), np.inf)
    for u in range(m):
        a, pa, b, pb = sources[u, 0], sources[u, 1], sources[u, 2], sources[u, 3]
        joined = -1
        for q in range(n_leaders):
            if (members[q, a] >= 0 and members[q, a] != pa) or (members[q, b] >= 0 and members[q, b] != pb):
                continue  # a different person of camera a or b is already in this cluster
            total = 0.0
            cnt = 0
            for j in range(k):
                if np.isnan(points[u, j, 0]) or np.isnan(cluster_points[q, j, 0]):
                    continue
                total += math.sqrt(
                    (points[u, j, 0] - cluster_points[q, j, 0]) ** 2
                    + (points[u, j, 1] - cluster_points[q, j, 1]) ** 2
                    + (points[u, j, 2] - cluster_points[q, j, 2]) ** 2
                )
                cnt += 1
            if cnt > 0 and total / cnt < same_person:
                joined = q
                break
        if joined < 0:
            joined = n_leaders
            n_leaders += 1
        q = joined
        members[q, a] = pa
        members[q, b] = pb
        member_errors[q, a] = min(member_errors[q, a], errors[u, 0])
        member_errors[q, b] = min(member_errors[q, b], errors[u, 1])
        for j in range(k):
            if np.isnan(cluster_points[q, j, 0]):
                cluster_points[q, j] = points[u, j]
    return cluster_points[:n_leaders], members[:n_leaders], member_errors[:n_leaders]

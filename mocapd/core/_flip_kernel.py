"""Compiled (numba) left/right flip search: the whole decision of :func:`mocapd.core.lr_flips.choose_swaps`.

Why compiled, whole. The search runs for every person on every tick: per keypoint pair it triangulates every swap
hypothesis (2^(n-1) for n views, two points each), projects the points into every view and sums the capped
reprojection errors, then picks which of the two mirror labellings is the person's left. The arithmetic is tiny (a
4x4 eigenproblem per point). As numpy it was ~30 array calls a group of pairs (0.6 ms a person a tick, issue 39's
profile); with only the hypothesis search compiled, the grouping of pairs by views, the fancy-indexed copies, the
mirror decision and the per-pair loop stayed Python (2.4 ms mean a person a tick on the 2-core camera rig, 62 %
of the person's cost, holding the interpreter lock). Here the whole decision is one call, ``nogil``, with no
allocation but its outputs and one scratch block per call.

Incremental. A person's flip memo (:class:`mocapd.core.lr_flips.FlipMemo`) keeps, per pair, the inputs the
search read (which views see each keypoint, their weights and pixels, the projection matrices, the options) and
what it found (the winning hypothesis, its gain, its two points). When a pair's inputs are bit-for-bit those of
the previous call, the search is not run again: its result is a function of exactly those inputs, so the decision
cannot differ. The mirror decision (cheap, and it depends on the previous pose, which moves every tick) is always
made again.

The same mathematics as the numpy reference (:func:`mocapd.core.lr_flips._best_hypotheses`, kept for the tests
that compare the two): confidence-weighted DLT with unit-normalised rows, the point from the smallest eigenvector
of the 4x4 normal matrix, errors capped at ``cap`` px and counted only where the observation has weight; sums that
decide a comparison are taken in numpy's order.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

# Offsets into the per-call scratch block (float64).
_M, _A, _V, _ROW, _VEC, _X, _XB = 0, 16, 32, 48, 52, 56, 62
_SCRATCH = 68
#: Memo key per view and pair: left seen, right seen, left weight, right weight, left (u, v), right (u, v).
MEMO_KEY = 8
#: Options in the memo's context, after the projection matrices: min_confidence, cap, margin, max_views.
MEMO_OPTIONS = 4


@nb.njit(cache=True, nogil=True)
def _swapped(h: int, v: int, n: int) -> bool:
    """Whether hypothesis ``h`` swaps view ``v`` (view 0 never; the others are the bits of ``h``, view 1 highest,
    in the order of ``itertools.product``)."""
    if v == 0:
        return False
    return ((h >> (n - 1 - v)) & 1) == 1


@nb.njit(cache=True, nogil=True)
def _same(a: float, b: float) -> bool:
    """Bit-for-bit equal (0.0 and -0.0 differ: the arithmetic may carry the sign)."""
    return a == b and math.copysign(1.0, a) == math.copysign(1.0, b)


@nb.njit(cache=True, nogil=True)
def _seen(uv: FloatArray, conf: FloatArray, c: int, j: int, min_conf: float) -> bool:
    """Whether view ``c`` takes part with keypoint ``j``: confident enough, finite pixels."""
    return conf[c, j] >= min_conf and math.isfinite(uv[c, j, 0]) and math.isfinite(uv[c, j, 1])


@nb.njit(cache=True, nogil=True)
def _triangulate(
    P: FloatArray, views: IntArray, uvv: FloatArray, wv: FloatArray, n: int, h: int, label: int, s: FloatArray
) -> bool:
    """Point ``label`` under hypothesis ``h`` into ``s[_X + 3 label:]``; False where it has fewer than two
    weighted views or lies at infinity.

    ``uvv`` (n, 2 labels, 2) and ``wv`` (n, 2): the pair's pixels and weights in its views ``views[:n]``."""
    for i in range(16):
        s[_M + i] = 0.0
    count = 0
    for v in range(n):
        lab = 1 - label if _swapped(h, v, n) else label
        wt = wv[v, lab]
        if not wt > 0.0:
            continue
        count += 1
        c = views[v]
        for axis in range(2):
            coord = uvv[v, lab, axis]
            norm = 0.0
            for j in range(4):
                s[_ROW + j] = coord * P[c, 2, j] - P[c, axis, j]
                norm += s[_ROW + j] * s[_ROW + j]
            norm = math.sqrt(norm)
            scale = wt / norm if norm > 0.0 else wt
            for i in range(4):
                ri = s[_ROW + i] * scale
                for j in range(4):
                    s[_M + 4 * i + j] += ri * s[_ROW + j] * scale
    if count < 2:
        return False
    _smallest_eigenvector(s)
    hw = s[_VEC + 3]
    if not abs(hw) > 1e-12:
        return False
    for i in range(3):
        x = s[_VEC + i] / hw
        s[_X + 3 * label + i] = x
        if not math.isfinite(x):
            return False
    return True


@nb.njit(cache=True, nogil=True)
def _smallest_eigenvector(s: FloatArray) -> None:
    """The unit eigenvector of the smallest eigenvalue of the symmetric 4x4 matrix ``s[_M:_M + 16]`` into
    ``s[_VEC:_VEC + 4]``, by cyclic Jacobi rotations.

    LAPACK's ``syevd`` through numba costs microseconds of call overhead per 4x4 matrix, more than the search's
    whole arithmetic; a handful of Jacobi sweeps reaches the same vector to round-off (sign aside, which the
    division by the homogeneous coordinate removes)."""
    for i in range(16):
        s[_A + i] = s[_M + i]
        s[_V + i] = 1.0 if i % 5 == 0 else 0.0
    for _ in range(12):
        off = 0.0
        for p in range(3):
            for q in range(p + 1, 4):
                off += s[_A + 4 * p + q] * s[_A + 4 * p + q]
        a00, a11, a22, a33 = s[_A], s[_A + 5], s[_A + 10], s[_A + 15]
        if off <= 1e-30 * (a00 * a00 + a11 * a11 + a22 * a22 + a33 * a33):
            break
        for p in range(3):
            for q in range(p + 1, 4):
                apq = s[_A + 4 * p + q]
                if apq == 0.0:
                    continue
                theta = (s[_A + 5 * q] - s[_A + 5 * p]) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                sn = t * c
                for k in range(4):  # A <- A J (columns p and q)
                    akp, akq = s[_A + 4 * k + p], s[_A + 4 * k + q]
                    s[_A + 4 * k + p] = c * akp - sn * akq
                    s[_A + 4 * k + q] = sn * akp + c * akq
                for k in range(4):  # A <- J^T A (rows p and q)
                    apk, aqk = s[_A + 4 * p + k], s[_A + 4 * q + k]
                    s[_A + 4 * p + k] = c * apk - sn * aqk
                    s[_A + 4 * q + k] = sn * apk + c * aqk
                for k in range(4):
                    vkp, vkq = s[_V + 4 * k + p], s[_V + 4 * k + q]
                    s[_V + 4 * k + p] = c * vkp - sn * vkq
                    s[_V + 4 * k + q] = sn * vkp + c * vkq
    best = 0
    for i in range(1, 4):
        if s[_A + 5 * i] < s[_A + 5 * best]:
            best = i
    for k in range(4):
        s[_VEC + k] = s[_V + 4 * k + best]


@nb.njit(cache=True, nogil=True)
def _block_sum(a: FloatArray, lo: int, n: int) -> float:
    """numpy's pairwise summation of ``a[lo:lo + n]`` for ``n`` <= 128: eight accumulators, then the rest."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return float(res)


@nb.njit(cache=True, nogil=True)
def _pairwise_sum(a: FloatArray, lo: int, n: int) -> float:
    """``a[lo:lo + n].sum()`` in numpy's own order, so that a comparison of two sums decides as the numpy
    reference's does, to the last bit: above 128 values numpy halves the run (at a multiple of 8) and adds the
    halves' sums. Numba's cache cannot hold a recursive function, so the halving is walked with an explicit stack
    (post-order: a run is added once both its halves are)."""
    if n <= 128:
        return _block_sum(a, lo, n)
    # Each entry: a run (start, length) and whether its halves are done; values of finished runs on ``vals``.
    runs = np.empty((64, 3), dtype=np.int64)
    vals = np.empty(64)
    top, nv = 0, 0
    runs[0, 0], runs[0, 1], runs[0, 2] = lo, n, 0
    while top >= 0:
        start, length, expanded = runs[top, 0], runs[top, 1], runs[top, 2]
        if length <= 128:
            vals[nv] = _block_sum(a, start, length)
            nv += 1
            top -= 1
        elif expanded:
            vals[nv - 2] = vals[nv - 2] + vals[nv - 1]
            nv -= 1
            top -= 1
        else:
            half = length // 2
            half -= half % 8
            runs[top, 2] = 1
            runs[top + 1, 0], runs[top + 1, 1], runs[top + 1, 2] = start + half, length - half, 0
            runs[top + 2, 0], runs[top + 2, 1], runs[top + 2, 2] = start, half, 0
            top += 2
    return float(vals[0])


@nb.njit(cache=True, nogil=True)
def _views_confidence(
    conf: FloatArray, views: IntArray, n: int, flags: BoolArray, pick: bool, buf: FloatArray
) -> float:
    """Sum of every keypoint's confidence over the views ``views[i]`` with ``flags[i] == pick``, as numpy sums
    ``conf[views][mask]`` (rows in view order, flattened)."""
    m = 0
    for i in range(n):
        if flags[i] == pick:
            for j in range(conf.shape[1]):
                buf[m] = conf[views[i], j]
                m += 1
    return _pairwise_sum(buf, 0, m)


@nb.njit(cache=True, nogil=True)
def _distance(X: FloatArray, a: int, ref: FloatArray, j: int) -> float:
    """Euclidean distance of point ``a`` of ``X`` (6,) to ``ref[j]``, summed in numpy's order."""
    d0 = X[3 * a] - ref[j, 0]
    d1 = X[3 * a + 1] - ref[j, 1]
    d2 = X[3 * a + 2] - ref[j, 2]
    return math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@nb.njit(cache=True, nogil=True)
def _memo_context_matches(P: FloatArray, options: FloatArray, memo_ctx: FloatArray) -> bool:
    """Whether the memo was filled with these projection matrices and options; if not, it now holds them."""
    flat = P.ravel()
    same = True
    for i in range(flat.size):
        if not _same(flat[i], memo_ctx[i]):
            same = False
    for i in range(MEMO_OPTIONS):
        if not _same(options[i], memo_ctx[flat.size + i]):
            same = False
    if not same:
        memo_ctx[: flat.size] = flat
        memo_ctx[flat.size :] = options
    return same


@nb.njit(cache=True, nogil=True)
def _search(
    P: FloatArray, views: IntArray, uvv: FloatArray, wv: FloatArray, n: int, cap: float, s: FloatArray
) -> tuple[int, float, float]:
    """The hypothesis of least capped reprojection error for one pair (the first such), its cost and no swap's;
    its two points in ``s[_XB:_XB + 6]`` (NaN where a point has too few views)."""
    H = 1 << (n - 1)
    best = 0
    best_cost = 0.0
    cost0 = 0.0
    for h in range(H):
        total = 0.0
        for label in range(2):
            good = _triangulate(P, views, uvv, wv, n, h, label, s)
            if not good:
                for i in range(3):
                    s[_X + 3 * label + i] = np.nan
            for v in range(n):
                lab = 1 - label if _swapped(h, v, n) else label
                if not wv[v, lab] > 0.0:
                    continue
                err = cap
                if good:
                    c = views[v]
                    x0, x1, x2 = s[_X + 3 * label], s[_X + 3 * label + 1], s[_X + 3 * label + 2]
                    px = P[c, 0, 3] + P[c, 0, 0] * x0 + P[c, 0, 1] * x1 + P[c, 0, 2] * x2
                    py = P[c, 1, 3] + P[c, 1, 0] * x0 + P[c, 1, 1] * x1 + P[c, 1, 2] * x2
                    pz = P[c, 2, 3] + P[c, 2, 0] * x0 + P[c, 2, 1] * x1 + P[c, 2, 2] * x2
                    if pz > 1e-6:
                        dx = px / pz - uvv[v, lab, 0]
                        dy = py / pz - uvv[v, lab, 1]
                        e = math.sqrt(dx * dx + dy * dy)
                        if math.isfinite(e):
                            err = min(e, cap)
                total += err
        if h == 0:
            cost0 = total
        if h == 0 or total < best_cost:
            best, best_cost = h, total
            for i in range(6):
                s[_XB + i] = s[_X + i]
    return best, best_cost, cost0


@nb.njit(cache=True, nogil=True)
def choose_swaps(
    P: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    pairs: IntArray,
    reference: FloatArray,
    options: FloatArray,
    memo_ctx: FloatArray,
    memo_key: FloatArray,
    memo_best: IntArray,
    memo_gain: FloatArray,
    memo_X: FloatArray,
) -> tuple[BoolArray, FloatArray, int, int]:
    """Per view and pair, whether the detected labels are swapped (:func:`mocapd.core.lr_flips.choose_swaps`).

    Parameters
    ----------
    P : array, shape (n_cams, 3, 4)
        Projection matrices (undistorted pixels).
    uv : array, shape (n_cams, n_kp, 2)
        Undistorted pixels of one person's detections.
    conf : array, shape (n_cams, n_kp)
    pairs : int array, shape (n_pairs, 2)
        (left, right) keypoint indices.
    reference : array, shape (n_kp, 3) or (0, 3)
        The person's keypoints a moment ago (world); no rows: none.
    options : array, shape (4,)
        min_confidence, cap_px, margin_px, max_views.
    memo_ctx : array, shape (n_cams * 12 + 4,)
    memo_key : array, shape (n_cams, n_pairs, MEMO_KEY)
    memo_best : int array, shape (n_pairs,)
        -1 where the pair holds no result.
    memo_gain : array, shape (n_pairs,)
    memo_X : array, shape (n_pairs, 2, 3)
        The person's flip memo, read and updated in place; ``memo_best`` of another length than ``n_pairs`` (an
        empty one): no memo, every pair is searched.

    Returns
    -------
    swaps : bool array, shape (n_cams, n_pairs)
    gain : array, shape (n_pairs,)
        Error the chosen labelling saves against the detected one, px per view (0 where nothing is swapped).
    searched, reused : int
        Pairs whose hypotheses were searched, and whose search result came from the memo (the others: too few
        views see them).
    """
    n_cams, n_kp, n_pairs = uv.shape[0], uv.shape[1], pairs.shape[0]
    min_conf, cap, margin, max_views = options[0], options[1], options[2], int(options[3])
    swaps = np.zeros((n_cams, n_pairs), dtype=np.bool_)
    gains = np.zeros(n_pairs)
    # One scratch block: the numbers of the 4x4 solve, the pair's views, weights and pixels, the flags, the rows
    # summed by the mirror decision.
    s = np.empty(_SCRATCH + n_cams * (7 + n_kp))
    views = np.empty(n_cams, dtype=np.int64)
    flags = np.empty(n_cams, dtype=np.bool_)
    wv = s[_SCRATCH : _SCRATCH + 2 * n_cams].reshape((n_cams, 2))
    uvv = s[_SCRATCH + 2 * n_cams : _SCRATCH + 6 * n_cams].reshape((n_cams, 2, 2))
    rows = s[_SCRATCH + 6 * n_cams :]
    use_memo = memo_best.shape[0] == n_pairs and n_pairs > 0
    if use_memo and not _memo_context_matches(P, options, memo_ctx):
        memo_best[:] = -1
    has_ref = reference.shape[0] > 0
    searched = reused = 0
    for p in range(n_pairs):
        left, right = pairs[p, 0], pairs[p, 1]
        # The views that see the pair (either keypoint), the first max_views of them.
        n = 0
        seen = 0
        for c in range(n_cams):
            ok_l = _seen(uv, conf, c, left, min_conf)
            ok_r = _seen(uv, conf, c, right, min_conf)
            if (ok_l or ok_r) and n < max_views:
                views[n] = c
                for lab in range(2):
                    j = left if lab == 0 else right
                    w = conf[c, j] if (ok_l if lab == 0 else ok_r) else 0.0
                    wv[n, lab] = w
                    for axis in range(2):
                        uvv[n, lab, axis] = uv[c, j, axis] if w > 0.0 else 0.0
                n += 1
                seen += int(ok_l) + int(ok_r)
        if n < 2 or seen < 3:
            continue
        # The memo's result stands when every input the search reads is what it read then.
        hit = use_memo and memo_best[p] >= 0
        if use_memo:
            for c in range(n_cams):
                key = memo_key[c, p]
                for lab in range(2):
                    j = left if lab == 0 else right
                    ok = _seen(uv, conf, c, j, min_conf)
                    w = conf[c, j] if ok else 0.0
                    x = uv[c, j, 0] if w > 0.0 else 0.0
                    y = uv[c, j, 1] if w > 0.0 else 0.0
                    if hit:
                        hit = (
                            _same(key[lab], 1.0 if ok else 0.0)
                            and _same(key[2 + lab], w)
                            and _same(key[4 + 2 * lab], x)
                            and _same(key[5 + 2 * lab], y)
                        )
                    if not hit:
                        key[lab], key[2 + lab], key[4 + 2 * lab], key[5 + 2 * lab] = 1.0 if ok else 0.0, w, x, y
        if hit:
            reused += 1
            b, g = memo_best[p], memo_gain[p]
            for i in range(6):
                s[_XB + i] = memo_X[p, i // 3, i % 3]
        else:
            searched += 1
            b, best_cost, cost0 = _search(P, views, uvv, wv, n, cap, s)
            g = (cost0 - best_cost) / n
            if use_memo:
                memo_best[p], memo_gain[p] = b, g
                for i in range(6):
                    memo_X[p, i // 3, i % 3] = s[_XB + i]
        if b == 0 or not g > margin:
            continue
        n_swapped = 0
        for i in range(n):
            flags[i] = _swapped(b, i, n)
            n_swapped += int(flags[i])
        # Swapping every view is the mirror image of swapping none: which of the two labellings is the person's
        # left comes from the previous pose where there is one, else the fewer (then the less confident) views.
        known = has_ref
        if has_ref:
            for i in range(3):
                known = known and math.isfinite(reference[left, i]) and math.isfinite(reference[right, i])
        mirror = False
        if known:
            finite = True
            for i in range(6):
                finite = finite and math.isfinite(s[_XB + i])
            Xb = s[_XB : _XB + 6]
            d_as = _distance(Xb, 0, reference, left) + _distance(Xb, 1, reference, right)
            d_mirror = _distance(Xb, 1, reference, left) + _distance(Xb, 0, reference, right)
            mirror = finite and d_mirror < d_as
        else:
            n_mirror = n - n_swapped
            mirror = n_mirror < n_swapped or (
                n_mirror == n_swapped
                and _views_confidence(conf, views, n, flags, False, rows)
                < _views_confidence(conf, views, n, flags, True, rows)
            )
        any_swap = False
        for i in range(n):
            f = flags[i] != mirror
            swaps[views[i], p] = f
            any_swap = any_swap or f
        gains[p] = g if any_swap else 0.0
    return swaps, gains, searched, reused

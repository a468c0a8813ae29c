"""Collapsed left/right pairs of 2D detections: both wrists (elbows, knees, ...) put on one limb in one view.

Besides swapping a person's sides (:mod:`mocapd.core.lr_flips`), 2D pose networks put the left *and* the right
keypoint of a pair on the same limb, with high confidence, when the person turns fast or one limb hides the other:
on the Pose2Sim multi-person demo the acrobat's two wrists and elbows lie within 5-16 % of his size of each other in
cam01 (frames 36, 45-54) and cam03 (48-99), where the two other cameras see them 50-80 % apart. A swap cannot mend
that (either labelling puts both points on one arm), and the robust reprojection term cannot tell which views are
wrong when two say "one arm" and two say "both arms": the live solve followed the collapsed views and held both
arms up while one hung down (elbows and wrists 200-500 px off in the other views, the wrists' p90 of the held-out
error 364 px for that performer against 123 for the other).

A view's pair is *collapsed* when its two keypoints lie closer than :attr:`CollapseOptions.collapsed` × the person's
size in that view while the pair, seen from the views that do not collapse it (two or more: their triangulation),
else the person's previous pose, projects at least :attr:`CollapseOptions.apart` × the size apart there. Such a view
says nothing about which of the two points is where: both are left out of that view's solve (the others decide). A
pair that really projects onto itself (arms along the camera's line of sight) projects close together from the
other views too, and is kept.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core import _collapse_kernel
from mocapd.core.camera import triangulate_arrays
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class CollapseOptions:
    """When a view's left/right pair counts as collapsed."""

    enabled: bool = True
    min_confidence: float = 0.3
    """A keypoint takes part when its detector confidence is at least this."""
    collapsed: float = 0.15
    """The pair's two detected keypoints closer than this fraction of the person's size in the view (the largest
    extent of their confident keypoints) is a candidate. On the Pose2Sim demos the collapsed wrists lie 3-16 %
    apart, the others 33-97 %."""
    apart: float = 0.3
    """... and a collapse when the other views (or the previous pose) place the pair at least this fraction of the
    size apart in that view."""
    min_keypoints: int = 4
    """A view with fewer confident keypoints has no size to judge by: left alone."""


def collapsed_pairs(
    P: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    pairs: tuple[tuple[int, int], ...],
    reference: FloatArray | None = None,
    options: CollapseOptions | None = None,
) -> BoolArray:
    """Per view and pair: whether the view collapsed the pair onto one limb (see the module docstring).

    Parameters
    ----------
    P : array, shape (n_cams, 3, 4)
        Projection matrices (undistorted pixels).
    uv : array, shape (n_cams, n_kp, 2)
        Undistorted pixels of one person's detections (any value where the confidence is 0).
    conf : array, shape (n_cams, n_kp)
        Detector confidence; 0 where the view did not see the person.
    pairs : sequence of (left, right) keypoint indices
    reference : array, shape (n_kp, 3), optional
        The person's keypoints a moment ago (world): the pair's separation where fewer than two other views have it.
    options : CollapseOptions

    Returns
    -------
    bool array, shape (n_cams, n_pairs)
    """
    o = options if options is not None else CollapseOptions()
    uv = np.asarray(uv, dtype=np.float64)
    conf = np.asarray(conf, dtype=np.float64)
    n_cams = P.shape[0]
    if uv.shape[:2] != conf.shape or uv.shape[0] != n_cams:
        raise InputError(f"uv {uv.shape} and conf {conf.shape} must cover the {n_cams} cameras")
    out = np.zeros((n_cams, len(pairs)), dtype=bool)
    if not o.enabled or not pairs:
        return out
    lr = _pair_index(tuple(pairs))  # (n_pairs, 2)
    # The keypoints taking part, each view's size and the candidates (both keypoints in, a size, a gap under
    # `collapsed` of it), in one compiled call: the NumPy screen's arithmetic (kept as the reference in
    # tests/test_lr_collapse_bitwise.py)
    ok = np.empty(conf.shape, dtype=bool)
    size = np.empty(n_cams)
    candidate = np.empty(out.shape, dtype=bool)
    if not _collapse_kernel.screen(np.ascontiguousarray(uv), np.ascontiguousarray(conf), lr[:, 0], lr[:, 1],
                                   float(o.min_confidence), int(o.min_keypoints), float(o.collapsed), ok, size,
                                   candidate):  # fmt: skip
        return out  # nothing to check, no triangulation
    views, which = np.nonzero(candidate)
    sep = expected_gaps(P, uv, conf, ok, candidate, lr, views, which, reference)
    out[views, which] = np.isfinite(sep) & (sep >= o.apart * size[views])
    return out


@functools.lru_cache(maxsize=16)
def _pair_index(pairs: tuple[tuple[int, int], ...]) -> NDArray[np.intp]:
    """The pairs as an index array (n_pairs, 2), made once per pair list (every person solve asks); read-only,
    Fortran-ordered (its two columns contiguous: the compiled screen's left and right)."""
    lr = np.asfortranarray(np.array(pairs, dtype=np.intp).reshape(-1, 2))
    lr.flags.writeable = False
    return lr


def expected_gaps(
    P: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    ok: BoolArray,
    candidate: BoolArray,
    lr: NDArray[np.intp],
    views: NDArray[np.intp],
    which: NDArray[np.intp],
    reference: FloatArray | None,
) -> FloatArray:
    """Per candidate (``views[k]``, pair ``which[k]``): the pair's separation in that view (px) as the views that
    do not collapse it triangulate it, else as ``reference`` projects it; NaN when neither can say.

    Every candidate at once: the eyes and ears are candidates in every view on every solve (they lie a few per
    cent of a person's size apart), so one triangulation per candidate was ~17 small NumPy triangulations a person
    and tick (issue 39). The DLT rows are :func:`~mocapd.core.camera.weighted_dlt_rows`' (element-wise, the same
    floats whichever points share the call), the SVD of the stack solves each system on its own, and the
    projections are a stack of the same matrix products: the same floats as one candidate at a time
    (``tests/test_lr_collapse_bitwise.py``).

    Returns
    -------
    array, shape (n_candidates,)
    """
    n = views.size
    pair = lr[which]  # (n, 2) keypoint indices
    others = ~candidate[:, which].T & ok[:, pair].all(axis=2).T  # (n, n_cams): views that see both, not collapsing
    others[np.arange(n), views] = False
    # Each candidate's two points where known (rows of X not known are never read): triangulated points are
    # finite (triangulate_arrays' ok), the previous pose's are taken only where finite
    X = np.empty((n, 2, 3))
    known = np.zeros(n, dtype=bool)
    by_views = np.count_nonzero(others, axis=1) >= 2
    if by_views.any():
        k = np.flatnonzero(by_views)
        # (n_cams, 2 k): each candidate's two keypoints as points of one triangulation call
        cols = pair[k].ravel()
        uv_k = uv[:, cols]
        w_k = np.where(others[k].repeat(2, axis=0).T, conf[:, cols], 0.0)
        pts, good = triangulate_arrays(P, uv_k, w_k)
        both_good = good.reshape(-1, 2).all(axis=1)
        X[k[both_good]] = pts.reshape(-1, 2, 3)[both_good]
        known[k[both_good]] = True
    if reference is not None:
        fall_back = ~known & np.isfinite(reference[pair]).all(axis=(1, 2))
        X[fall_back] = reference[pair[fall_back]]
        known |= fall_back
    sep = np.full(n, np.nan)
    known_at = np.flatnonzero(known)
    Pv = P[views[known_at]]
    h = Pv[:, :, :3] @ X[known_at].transpose(0, 2, 1) + Pv[:, :, 3:4]  # (known, 3, 2)
    front = ~(h[:, 2] <= 1e-6).any(axis=1)
    px = h[front, :2] / h[front, 2:3]
    d = px[:, :, 0] - px[:, :, 1]
    # the norm of a vector as np.linalg.norm takes it: sqrt of its dot product with itself (a dot per candidate)
    sep[known_at[front]] = np.sqrt((d[:, None, :] @ d[:, :, None])[:, 0, 0])
    return sep


def drop_collapsed(conf: FloatArray, collapsed: BoolArray, pairs: tuple[tuple[int, int], ...]) -> FloatArray:
    """``conf`` (n_cams, n_kp) with both keypoints of every collapsed (view, pair) at confidence 0."""
    out = np.array(conf, dtype=np.float64, copy=True)
    for c, p in zip(*np.nonzero(collapsed), strict=True):
        out[c, list(pairs[p])] = 0.0
    return out

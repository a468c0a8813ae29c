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

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import triangulate_projections
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
    ok = (conf >= o.min_confidence) & np.all(np.isfinite(uv), axis=-1)
    size = np.zeros(n_cams)
    for c in range(n_cams):
        if np.count_nonzero(ok[c]) >= o.min_keypoints:
            size[c] = float(np.ptp(uv[c, ok[c]], axis=0).max())
    lr = np.array(pairs, dtype=np.intp)  # (n_pairs, 2)
    both = ok[:, lr[:, 0]] & ok[:, lr[:, 1]] & (size[:, None] > 0)  # (n_cams, n_pairs)
    gap = np.linalg.norm(uv[:, lr[:, 0]] - uv[:, lr[:, 1]], axis=-1)
    candidate = both & (gap < o.collapsed * size[:, None])
    if not candidate.any():
        return out  # the common case: nothing to check, no triangulation
    views, pair_idx = np.nonzero(candidate)
    seps = _expected_gaps(P, uv, conf, ok, candidate, lr, views, pair_idx, reference)
    out[views, pair_idx] = np.isfinite(seps) & (seps >= o.apart * size[views])
    return out


def _expected_gaps(
    P: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    ok: BoolArray,
    candidate: BoolArray,
    lr: NDArray[np.intp],
    views: NDArray[np.intp],
    pair_idx: NDArray[np.intp],
    reference: FloatArray | None,
) -> FloatArray:
    """Each candidate's pair separation in its view (px, one per ``views[k]``, ``pair_idx[k]``) as the views that do
    not collapse the pair triangulate it, else as the reference projects it; NaN when neither can say.

    Every candidate's triangulation is one DLT system of its own (its pair's two points, weighted by the views
    that see the pair without collapsing it, the candidate's view left out): they are solved in one
    :func:`~mocapd.core.camera.triangulate_projections` call, whose rows and SVD are computed per point, so each
    point is the float its own call would give (``tests/test_lr_collapse_bitwise.py``); a call per candidate
    cost the synthetic rig's tick ~0.1 ms each, several per person (a small person's eyes and ears are always
    close).
    """
    n = len(views)
    pairs = lr[pair_idx]  # (n, 2)
    # others[k, c]: camera c sees candidate k's pair and does not collapse it; never the candidate's own view
    others = (~candidate[:, pair_idx] & ok[:, pairs].all(axis=2)).T
    others[np.arange(n), views] = False
    tri = np.count_nonzero(others, axis=1) >= 2
    X = np.full((n, 2, 3), np.nan)
    found = np.zeros(n, dtype=bool)
    if tri.any():
        cols = pairs[tri].reshape(-1)  # two points per triangulated candidate
        w = np.where(np.repeat(others[tri].T, 2, axis=1), conf[:, cols], 0.0)
        pts, good = triangulate_projections(P, uv[:, cols], w)
        found[tri] = good.reshape(-1, 2).all(axis=1)
        X[tri] = pts.reshape(-1, 2, 3)
    if reference is not None:
        fallback = ~found & np.isfinite(reference[pairs]).all(axis=(1, 2))
        X[fallback] = reference[pairs[fallback]]
        found |= fallback
    # Each candidate's pair projected into its view: (n, 3, 2), one 3x3 by 3x2 product per candidate as before
    Pv = P[views]
    h = Pv[:, :, :3] @ X.transpose(0, 2, 1) + Pv[:, :, 3:4]
    found &= ~np.any(h[:, 2] <= 1e-6, axis=1)
    d = h[:, :2, 0] / h[:, 2:3, 0] - h[:, :2, 1] / h[:, 2:3, 1]  # (n, 2)
    seps = np.full(n, np.nan)
    for k in np.flatnonzero(found):  # each 2-vector's norm as np.linalg.norm takes it: the root of its dot product
        seps[k] = math.sqrt(d[k].dot(d[k]))
    return seps


def drop_collapsed(conf: FloatArray, collapsed: BoolArray, pairs: tuple[tuple[int, int], ...]) -> FloatArray:
    """``conf`` (n_cams, n_kp) with both keypoints of every collapsed (view, pair) at confidence 0."""
    out = np.array(conf, dtype=np.float64, copy=True)
    for c, p in zip(*np.nonzero(collapsed), strict=True):
        out[c, list(pairs[p])] = 0.0
    return out

"""Left/right flips of 2D detections: a per-view L/R hypothesis for each keypoint pair, chosen by the other views.

2D pose networks confuse a person's left and right, mostly on views that see the back (the Pose2Sim demos show it
on every camera at some point). A flipped view averaged with the others pulls both limbs to the body's midline:
the held-out camera then sees a skeleton narrower than the person, and a robust loss cannot tell which of the two
labels is the outlier when the two limbs are half a metre apart.

For each left/right keypoint pair (shoulders, elbows, wrists, hips, knees, ankles, eyes, ears) and each view that
sees it, the labels are either as detected or swapped. Every combination of swaps across the views is
triangulated (confidence-weighted DLT in undistorted pixels, all hypotheses in one batch) and the one with the
smallest total reprojection error wins, when it beats "no swap" by ``margin_px`` per view. Swapping every view is
the mirror image of swapping none (same error), so which of the two 3D points is the person's left comes from
elsewhere: the person's previous pose where there is one (the label assignment whose points lie nearer the
previous left and right points), else the views themselves (the assignment that swaps fewer of them; the detector
is right more often than not).

The whole decision is one compiled call (:mod:`mocapd.core._flip_kernel`; the numpy reference beside it), and
incremental with a person's :class:`FlipMemo`: a pair whose inputs are bit-for-bit those of the previous tick is not
searched again. :func:`choose_swaps` returns the decision, :func:`apply_swaps` applies it to the keypoints.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache
from itertools import product

import numpy as np
from numpy.typing import NDArray

from mocapd.core import _flip_kernel
from mocapd.core.camera import Camera, triangulate_projections
from mocapd.core.lr_collapse import CollapseOptions, collapsed_pairs
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]

COCO17_LR_PAIRS: tuple[tuple[int, int], ...] = ((1, 2), (3, 4), (5, 6), (7, 8), (9, 10), (11, 12), (13, 14), (15, 16))
"""(left, right) keypoint indices of COCO-17: eyes, ears, shoulders, elbows, wrists, hips, knees, ankles."""


def lr_pairs(names: tuple[str, ...] | list[str]) -> tuple[tuple[int, int], ...]:
    """(left, right) index pairs of a keypoint set's names (``left_knee`` with ``right_knee``, ...)."""
    index = {n: i for i, n in enumerate(names)}
    return tuple(
        (i, index["right_" + n[5:]]) for i, n in enumerate(names) if n.startswith("left_") and "right_" + n[5:] in index
    )


@dataclass(frozen=True)
class FlipOptions:
    """How per-view left/right flips are found."""

    enabled: bool = True
    min_confidence: float = 0.3
    """A keypoint takes part when its detector confidence is at least this."""
    margin_px: float = 4.0
    """A swap is made only when it lowers the pair's reprojection error by more than this per view (px): where the
    two keypoints project close together (a side view) both labellings fit and the detection is left alone."""
    cap_px: float = 80.0
    """Each observation's reprojection error counts at most this much (px), so one wrong view cannot decide."""
    max_views: int = 10
    """Views of one pair searched exhaustively (2^(n-1) hypotheses); further views keep their labels."""
    min_views_alone: int = 3
    """Without the person's previous pose, at least this many views must see them (two views cannot say which of
    them is flipped)."""
    collapse: CollapseOptions = field(default_factory=CollapseOptions)
    """When a view's pair collapsed onto one limb sits out (:mod:`mocapd.core.lr_collapse`): run with the flips."""


@dataclass(frozen=True)
class SwapDecision:
    """Per view and pair: whether the detected labels are swapped.

    Attributes
    ----------
    swaps : bool array, shape (n_cams, n_pairs)
    gain_px : array, shape (n_pairs,)
        How much the chosen labelling lowered the pair's reprojection error against the detected one (px per
        view; 0 where nothing was swapped).
    """

    swaps: BoolArray
    gain_px: FloatArray

    @property
    def count(self) -> int:
        return int(np.count_nonzero(self.swaps))


class FlipMemo:
    """One person's flip-search results, kept between ticks (:func:`choose_swaps` reads and updates it).

    Per pair: the inputs the search read (which views see each keypoint, their weights and pixels; the projection
    matrices and options for all pairs) and what it found. Only bit-for-bit equal inputs reuse a result, so a
    decision with the memo is the decision without it. Not shared between threads: one per person, and a person
    is solved by one thread at a time.
    """

    def __init__(self, n_cams: int, n_pairs: int) -> None:
        self.ctx = np.full(n_cams * 12 + _flip_kernel.MEMO_OPTIONS, np.nan)
        self.key = np.zeros((n_cams, n_pairs, _flip_kernel.MEMO_KEY))
        self.best = np.full(n_pairs, -1, dtype=np.int64)
        self.gain = np.zeros(n_pairs)
        self.X = np.zeros((n_pairs, 2, 3))
        self.searched = 0
        """Pairs searched by the last call."""
        self.reused = 0
        """Pairs whose search result the last call took from the memo (their inputs had not changed)."""

    def fits(self, n_cams: int, n_pairs: int) -> bool:
        return self.key.shape[:2] == (n_cams, n_pairs)


def undistorted(cameras: list[Camera], uv: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Projection matrices (n_cams, 3, 4) and undistorted pixels (n_cams, n_kp, 2) of distorted ``uv``."""
    P = np.stack([c.projection_matrix for c in cameras])
    und = np.stack([c.undistort_points(np.nan_to_num(uv[i])) for i, c in enumerate(cameras)])
    return P, und


def _project(P: FloatArray, X: FloatArray) -> FloatArray:
    """Undistorted pixels of points X (n, 3) in every camera: (n_cams, n, 2)."""
    h = np.einsum("cij,nj->cni", P[:, :, :3], X) + P[:, None, :, 3]
    z = h[..., 2:3]
    return np.where(z > 1e-6, h[..., :2] / np.where(z > 1e-6, z, 1.0), np.nan)


def choose_swaps(
    P: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    pairs: tuple[tuple[int, int], ...] = COCO17_LR_PAIRS,
    reference: FloatArray | None = None,
    options: FlipOptions | None = None,
    *,
    compiled: bool = True,
    memo: FlipMemo | None = None,
) -> SwapDecision:
    """The per-view left/right labelling of each keypoint pair that the views agree on best.

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
        The person's keypoints a moment ago (world): decides which of the two mirror-image labellings is right.
    options : FlipOptions
    compiled : bool
        Decide in the compiled kernel (:mod:`mocapd.core._flip_kernel`); False: the numpy reference, the same
        decisions at many times the cost.
    memo : FlipMemo, optional
        The person's results of the previous call (compiled only): pairs whose inputs did not change are not
        searched again; updated in place.
    """
    o = options if options is not None else FlipOptions()
    uv = np.asarray(uv, dtype=np.float64)
    conf = np.asarray(conf, dtype=np.float64)
    n_cams = P.shape[0]
    if uv.shape[:2] != conf.shape or uv.shape[0] != n_cams:
        raise InputError(f"uv {uv.shape} and conf {conf.shape} must cover the {n_cams} cameras")
    if reference is not None and (
        np.ndim(reference) != 2
        or np.shape(reference)[1] != 3
        or np.shape(reference)[0] <= max((max(p) for p in pairs), default=-1)
    ):
        raise InputError(f"reference {np.shape(reference)} must hold a 3D point for every keypoint paired")
    if not o.enabled:
        return SwapDecision(np.zeros((n_cams, len(pairs)), dtype=bool), np.zeros(len(pairs)))
    if compiled:
        return _choose_swaps_compiled(P, uv, conf, pairs, reference, o, memo)
    swaps = np.zeros((n_cams, len(pairs)), dtype=bool)
    gains = np.zeros(len(pairs))
    ok = (conf >= o.min_confidence) & np.all(np.isfinite(uv), axis=-1)
    # The pairs seen by the same views are searched together, in one batch (one DLT, one projection): per pair
    # and hypothesis the arithmetic is tiny, so numpy's per-call overhead is what costs (the scheduler runs this
    # for every person on every tick).
    groups: dict[tuple[int, ...], list[int]] = {}
    for p, (left, right) in enumerate(pairs):
        views = np.flatnonzero(ok[:, left] | ok[:, right])[: o.max_views]
        if views.size < 2 or np.count_nonzero(ok[views, left]) + np.count_nonzero(ok[views, right]) < 3:
            continue
        groups.setdefault(tuple(int(v) for v in views), []).append(p)
    for key, members in groups.items():
        views = np.array(key, dtype=np.intp)
        cols = np.array([pairs[p] for p in members], dtype=np.intp)  # (K, 2)
        uv_v, conf_v, ok_v = uv[views][:, cols], conf[views][:, cols], ok[views][:, cols]
        best, gain, X = _best_hypotheses(P[views], uv_v, conf_v, ok_v, o)
        # Which of the two mirror labellings lies nearer the previous pose, where there is one: (K,) flags.
        known = np.zeros(len(members), dtype=bool)
        take_mirror = np.zeros(len(members), dtype=bool)
        if reference is not None:
            ref = reference[cols]  # (K, 2, 3)
            d_as = np.sqrt(((X - ref) ** 2).sum(-1)).sum(-1)
            d_mirror = np.sqrt(((X[:, ::-1] - ref) ** 2).sum(-1)).sum(-1)
            known = np.asarray(np.isfinite(ref).all(axis=(1, 2)))
            take_mirror = known & np.isfinite(X).all(axis=(1, 2)) & (d_mirror < d_as)
        for k, p in enumerate(members):
            if best[k] is None:
                continue
            flags = np.asarray(best[k], dtype=bool)
            mirror = ~flags
            if known[k]:
                if take_mirror[k]:
                    flags = mirror
            elif np.count_nonzero(mirror) < np.count_nonzero(flags) or (
                np.count_nonzero(mirror) == np.count_nonzero(flags)
                and conf[views][mirror].sum() < conf[views][flags].sum()
            ):
                flags = mirror  # swap the fewer (then the less confident) views
            swaps[views, p] = flags
            gains[p] = gain[k] if flags.any() else 0.0
    return SwapDecision(swaps, gains)


@cache
def _hypotheses(n: int) -> BoolArray:
    """The swap vectors of ``n`` views with the first view as detected, shape (2^(n-1), n); row 0 swaps none.
    Built once per view count (this runs for every person on every tick), read-only."""
    hyps = np.array([(False, *rest) for rest in product((False, True), repeat=n - 1)], dtype=bool)
    hyps.setflags(write=False)
    return hyps


@cache
def _pairs_array(pairs: tuple[tuple[int, int], ...]) -> IntArray:
    """The pairs as the kernel takes them, (n_pairs, 2) int64, built once per pair set (read-only)."""
    out = np.array(pairs, dtype=np.int64).reshape(len(pairs), 2)
    out.setflags(write=False)
    return out


_NO_REFERENCE = np.zeros((0, 3))
_NO_MEMO = FlipMemo(0, 0)


def _choose_swaps_compiled(
    P: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    pairs: tuple[tuple[int, int], ...],
    reference: FloatArray | None,
    o: FlipOptions,
    memo: FlipMemo | None,
) -> SwapDecision:
    """:func:`choose_swaps` in one compiled call. The arrays go in C-contiguous float64 (int64 pairs), whatever
    the caller passed, so the kernel runs the one signature :func:`warm_up` compiled."""
    n_cams, n_pairs = P.shape[0], len(pairs)
    if memo is not None and not memo.fits(n_cams, n_pairs):
        raise InputError(f"the flip memo is for {memo.key.shape[:2]} cameras and pairs, not ({n_cams}, {n_pairs})")
    m = memo if memo is not None else _NO_MEMO  # no memo: empty arrays, never written
    options = np.array([o.min_confidence, o.cap_px, o.margin_px, float(o.max_views)])
    ref = _NO_REFERENCE if reference is None else np.ascontiguousarray(reference, dtype=np.float64)
    swaps, gains, searched, reused = _flip_kernel.choose_swaps(
        np.ascontiguousarray(P, dtype=np.float64),
        np.ascontiguousarray(uv),
        np.ascontiguousarray(conf),
        _pairs_array(tuple(pairs)),
        ref,
        options,
        m.ctx,
        m.key,
        m.best,
        m.gain,
        m.X,
    )
    if memo is not None:
        memo.searched, memo.reused = int(searched), int(reused)
    return SwapDecision(swaps, gains)


def _best_hypotheses(
    P: FloatArray, uv: FloatArray, conf: FloatArray, ok: BoolArray, o: FlipOptions
) -> tuple[list[tuple[bool, ...] | None], FloatArray, FloatArray]:
    """For each of K pairs seen by the same n views: among the swap vectors with the first view as detected, the
    one of least capped reprojection error, when it beats no swap by ``margin_px`` per view (else None).

    Parameters
    ----------
    P : array, shape (n, 3, 4)
    uv : array, shape (n, K, 2, 2)
        Each view's (left, right) pixels of each pair.
    conf, ok : arrays, shape (n, K, 2)

    Returns
    -------
    best : list of K swap vectors (n bools) or None
    gain : array, shape (K,)
        Reprojection error the winner saves against no swap, px per view (0 where none wins).
    X : array, shape (K, 2, 3)
        The pair's two points triangulated under the winner (NaN where a point has too few views).
    """
    n, K = uv.shape[0], uv.shape[1]
    hyps = _hypotheses(n)  # (H, n)
    H = hyps.shape[0]
    # Observations per hypothesis: (H, n, K, 2 points, 2) pixels and (H, n, K, 2) weights, the two labels
    # exchanged in swapped views.
    uv_h = np.where(hyps[:, :, None, None, None], uv[None, :, :, ::-1], uv[None])
    w = conf * ok
    w_h = np.where(hyps[:, :, None, None], w[None, :, :, ::-1], w[None])
    # One DLT batch: points are (hypothesis, pair, label), cameras the views.
    X, good = triangulate_projections(
        P,
        uv_h.transpose(1, 0, 2, 3, 4).reshape(n, H * K * 2, 2),
        w_h.transpose(1, 0, 2, 3).reshape(n, H * K * 2),
        normal_equations=True,
    )
    proj = _project(P, np.where(good[:, None], X, 0.0)).reshape(n, H, K, 2, 2).transpose(1, 0, 2, 3, 4)
    err = np.linalg.norm(proj - uv_h, axis=-1)  # (H, n, K, 2)
    err = np.where(np.isfinite(err), np.minimum(err, o.cap_px), o.cap_px)
    err = np.where(good.reshape(H, K, 2)[:, None], err, o.cap_px)
    cost = np.where(w_h > 0, err, 0.0).sum(axis=(1, 3))  # (H, K): the same observations under every hypothesis
    k = np.argmin(cost, axis=0)
    col = np.arange(K)
    gain = (cost[0] - cost[k, col]) / n
    win = (k != 0) & (gain > o.margin_px)
    best = [tuple(bool(v) for v in hyps[k[j]]) if win[j] else None for j in range(K)]
    Xb = X.reshape(H, K, 2, 3)[k, col]
    return best, np.where(win, gain, 0.0), Xb


def warm_up(cameras: list[Camera], n_kp: int) -> None:
    """Load (or compile, the first time on a machine) the compiled search and the collapse check's screen for these
    cameras, with the arrays the scheduler passes: a first compile inside a live tick would hold it for seconds."""
    P, und = undistorted(cameras, np.full((len(cameras), max(n_kp, 2), 2), 100.0))
    conf = np.ones(und.shape[:2])
    choose_swaps(P, und, conf, ((0, 1),))  # one pair compiles what every pair runs
    choose_swaps(P, und, conf, ((0, 1),), np.zeros((und.shape[1], 3)), memo=FlipMemo(len(cameras), 1))
    collapsed_pairs(P, und, conf, ((0, 1),))  # the collapse check's compiled screen, which every solve then runs


def apply_swaps(
    kp: FloatArray, conf: FloatArray, swaps: BoolArray, pairs: tuple[tuple[int, int], ...] = COCO17_LR_PAIRS
) -> tuple[FloatArray, FloatArray]:
    """Keypoints (n_cams, n_kp, 2) and confidences (n_cams, n_kp) with each view's flagged pairs exchanged (new
    arrays)."""
    kp = np.asarray(kp, dtype=np.float64)
    conf = np.asarray(conf, dtype=np.float64)
    if not _disjoint(tuple(pairs)):  # a keypoint in two pairs: exchanged pair after pair, in order
        kp, conf = kp.copy(), conf.copy()
        for p, (left, right) in enumerate(pairs):
            views = np.flatnonzero(swaps[:, p])
            if views.size:
                kp[views, left], kp[views, right] = kp[views, right].copy(), kp[views, left].copy()
                conf[views, left], conf[views, right] = conf[views, right].copy(), conf[views, left].copy()
        return kp, conf
    # One gather per array: the eight-pair loop of fancy-indexed exchanges cost ~85 µs a call, as much as the
    # compiled search itself, and the scheduler ran it twice a person a tick.
    perm = swap_permutation(swaps, pairs, kp.shape[1])
    return np.take_along_axis(kp, perm[..., None], axis=1), np.take_along_axis(conf, perm, axis=1)


def swap_permutation(swaps: BoolArray, pairs: tuple[tuple[int, int], ...], n_kp: int) -> NDArray[np.intp]:
    """Per view, the keypoint each column takes after the flagged (disjoint) pairs are exchanged, (n_cams, n_kp)."""
    lr = _pairs_array(tuple(pairs))
    perm = np.broadcast_to(np.arange(n_kp, dtype=np.intp), (swaps.shape[0], n_kp)).copy()
    if len(lr):
        left, right = lr[:, 0], lr[:, 1]
        perm[:, left] = np.where(swaps, right, left)
        perm[:, right] = np.where(swaps, left, right)
    return perm


@cache
def _disjoint(pairs: tuple[tuple[int, int], ...]) -> bool:
    """Whether no keypoint is in two pairs (so every exchange can be made at once)."""
    flat = [k for pair in pairs for k in pair]
    return len(flat) == len(set(flat))

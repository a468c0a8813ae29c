"""Collapsed left/right pairs judged for every candidate at once (issue 39) give what one candidate at a time
gave (the old loop and ``_expected_gap``, kept here verbatim as the oracle): the same separations, bit for bit, so
the same pairs dropped."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core import _collapse_kernel
from mocapd.core.camera import triangulate_projections
from mocapd.core.keypoints import coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.lr_collapse import CollapseOptions, collapsed_pairs, expected_gaps
from mocapd.core.lr_flips import COCO17_LR_PAIRS, undistorted
from mocapd.core.skeleton import Skeleton
from mocapd.core.synthetic import moving_sequence, ring_rig

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


# The NumPy screen the compiled one (mocapd.core._collapse_kernel.screen) must equal, bit for bit: the collapse
# check's code before it was compiled.


def pair_gaps(uv: FloatArray, lr: NDArray[np.intp]) -> FloatArray:
    """Per view and pair, the distance (px) between the pair's two keypoints, shape (n_cams, n_pairs):
    ``np.linalg.norm(uv[:, lr[:, 0]] - uv[:, lr[:, 1]], axis=-1)`` to the bit (numpy takes a 2-vector's norm as the
    square root of ``x * x + y * y``), without its wrapper: every person solve asks."""
    d = uv[:, lr[:, 0]] - uv[:, lr[:, 1]]
    x, y = d[..., 0], d[..., 1]
    gap: FloatArray = np.sqrt(x * x + y * y)
    return gap


def view_sizes(uv: FloatArray, ok: BoolArray, min_keypoints: int) -> FloatArray:
    """Per view, the person's size there: the larger extent (px) of the keypoints ``ok`` holds; 0 with fewer than
    ``min_keypoints`` of them. Every view at once (maxima and minima are exact: the floats of one view at a time).

    Parameters
    ----------
    uv : array, shape (n_cams, n_kp, 2)
    ok : bool array, shape (n_cams, n_kp)

    Returns
    -------
    array, shape (n_cams,)
    """
    hi = np.where(ok[..., None], uv, -np.inf).max(axis=1)  # (n_cams, 2)
    lo = np.where(ok[..., None], uv, np.inf).min(axis=1)
    extent = (hi - lo).max(axis=1)
    return np.where(np.count_nonzero(ok, axis=1) >= min_keypoints, extent, 0.0)


def old_expected_gap(
    P: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    ok: BoolArray,
    collapsed_views: BoolArray,
    pair: NDArray[np.intp],
    view: int,
    reference: FloatArray | None,
) -> float:
    """``lr_collapse._expected_gap`` before issue 39, verbatim."""
    others = ~collapsed_views & ok[:, pair].all(axis=1)
    others[view] = False
    X: FloatArray | None = None
    if np.count_nonzero(others) >= 2:
        w = np.where(others[:, None], conf[:, pair], 0.0)
        pts, good = triangulate_projections(P, uv[:, pair], w)
        if good.all():
            X = pts
    if X is None and reference is not None and np.isfinite(reference[pair]).all():
        X = np.asarray(reference[pair], dtype=np.float64)
    if X is None:
        return float("nan")
    h = P[view, :, :3] @ X.T + P[view, :, 3:4]  # (3, 2)
    if np.any(h[2] <= 1e-6):
        return float("nan")
    px = h[:2] / h[2]
    return float(np.linalg.norm(px[:, 0] - px[:, 1]))


def _candidates(uv: FloatArray, conf: FloatArray, o: CollapseOptions) -> tuple[BoolArray, BoolArray, FloatArray]:
    """``collapsed_pairs``' candidates before issue 39, verbatim: ok keypoints, candidates, sizes (one view at a
    time)."""
    ok = (conf >= o.min_confidence) & np.all(np.isfinite(uv), axis=-1)
    size = np.zeros(uv.shape[0])
    for c in range(uv.shape[0]):
        if np.count_nonzero(ok[c]) >= o.min_keypoints:
            size[c] = float(np.ptp(uv[c, ok[c]], axis=0).max())
    lr = np.array(COCO17_LR_PAIRS, dtype=np.intp)
    both = ok[:, lr[:, 0]] & ok[:, lr[:, 1]] & (size[:, None] > 0)
    gap = np.linalg.norm(uv[:, lr[:, 0]] - uv[:, lr[:, 1]], axis=-1)
    return ok, both & (gap < o.collapsed * size[:, None]), size


def _scenes(rng: np.random.Generator) -> list[tuple[FloatArray, FloatArray, FloatArray, FloatArray | None]]:
    """People of a 4- and a 6-camera ring walking, some views with arms collapsed, keypoints missing, low
    confidence, NaN; with and without the previous pose (which may be partly NaN)."""
    sk = Skeleton.from_height(1.75)
    kin, targets = Kinematics(sk), coco17_targets(sk)
    thetas = moving_sequence(sk, 60, seed=3)
    out = []
    for n_cams in (4, 6):
        cams = ring_rig(n_cams, radius=4.5)
        for frame in range(0, 60, 3):
            theta = thetas[frame].copy()
            theta[3:6] = rng.normal(0.0, 0.4, 3)
            X = kin.targets(kin.forward(theta), targets.bones, targets.offsets)
            uv = np.stack([c.project(X) for c in cams]) + rng.normal(0.0, 1.0, (n_cams, 17, 2))
            for c in rng.choice(n_cams, int(rng.integers(0, 3)), replace=False):
                uv[c, [8, 10]] = uv[c, [7, 9]] + rng.normal(0.0, 2.0, (2, 2))  # right arm put on the left one
            conf = rng.uniform(0.2, 1.0, (n_cams, 17))
            conf[rng.random((n_cams, 17)) < 0.1] = 0.0
            if rng.random() < 0.3:
                conf[int(rng.integers(0, n_cams))] = 0.0  # a view without the person
            if rng.random() < 0.2:
                uv[0, 3] = np.nan
            P, und = undistorted(cams, uv)
            ref = X + rng.normal(0.0, 0.02, X.shape)
            if rng.random() < 0.3:
                ref[int(rng.integers(0, 17))] = np.nan
            out += [(P, und, conf, None), (P, und, conf, ref)]
    return out


def test_every_candidates_separation_is_the_old_one() -> None:
    rng = np.random.default_rng(5)
    o = CollapseOptions()
    lr = np.array(COCO17_LR_PAIRS, dtype=np.intp)
    seen = 0
    for P, und, conf, ref in _scenes(rng):
        ok, candidate, size = _candidates(und, conf, o)
        assert view_sizes(und, ok, o.min_keypoints).tobytes() == size.tobytes()
        views, which = np.nonzero(candidate)
        new = expected_gaps(P, und, conf, ok, candidate, lr, views, which, ref)
        old = np.array([old_expected_gap(P, und, conf, ok, candidate[:, p], lr[p], int(c), ref)
                        for c, p in zip(views, which, strict=True)])  # fmt: skip
        assert new.tobytes() == old.tobytes()
        expected = np.zeros(candidate.shape, dtype=bool)
        for k, (c, p) in enumerate(zip(views, which, strict=True)):
            expected[c, p] = bool(np.isfinite(old[k]) and old[k] >= o.apart * size[c])
        assert np.array_equal(collapsed_pairs(P, und, conf, COCO17_LR_PAIRS, ref), expected)
        seen += int(expected.sum())
    assert seen > 20  # collapsed views were found, not only the eyes' and ears' candidates kept


def test_the_pairs_gaps_are_numpys_norms_to_the_bit() -> None:
    """``pair_gaps`` (the candidates' test on every person solve) gives ``np.linalg.norm``'s floats, the code it
    replaced, on pixels of every scale, with NaN and inf, for COCO-17's pairs and any others."""
    rng = np.random.default_rng(11)
    lr = np.array(COCO17_LR_PAIRS, dtype=np.intp)
    for scale in (1e-3, 1.0, 640.0, 1e6):
        uv = rng.normal(0.0, scale, (6, 17, 2))
        uv[rng.random((6, 17, 2)) < 0.05] = np.nan
        uv[rng.random((6, 17, 2)) < 0.02] = np.inf
        for pairs in (lr, rng.integers(0, 17, (5, 2))):
            with np.errstate(invalid="ignore"):  # inf - inf is NaN in both, as in numpy's norm
                old = np.linalg.norm(uv[:, pairs[:, 0]] - uv[:, pairs[:, 1]], axis=-1)
                assert pair_gaps(uv, pairs).tobytes() == old.tobytes()


def numpy_screen(
    uv: FloatArray, conf: FloatArray, lr: NDArray[np.intp], o: CollapseOptions
) -> tuple[BoolArray, FloatArray, BoolArray]:
    """``collapsed_pairs``' screen before the compiled one (issue 39, eighth session), verbatim: ok keypoints,
    sizes, candidates."""
    ok = (conf >= o.min_confidence) & np.all(np.isfinite(uv), axis=-1)
    size = view_sizes(uv, ok, o.min_keypoints)
    both = ok[:, lr[:, 0]] & ok[:, lr[:, 1]] & (size[:, None] > 0)  # (n_cams, n_pairs)
    candidate = both & (pair_gaps(uv, lr) < o.collapsed * size[:, None])
    return ok, size, candidate


def test_the_compiled_screen_is_the_numpy_one_to_the_bit() -> None:
    """The compiled screen gives the NumPy screen's keypoint mask, sizes and candidates on 2 to 8 views of pixels of
    every scale, with NaN and infinite pixels and confidences, confidences at the threshold, views of fewer keypoints
    than a size needs or all on one pixel (size 0), gaps near the limit, COCO-17's pairs and overlapping others, and
    every option's edge; and the whole check then decides as the NumPy screen's check did."""
    rng = np.random.default_rng(12)
    compared = candidates = 0
    for trial in range(3000):
        n_cams, n_kp = int(rng.integers(2, 9)), int(rng.choice([5, 17, 26]))
        scale = float(rng.choice([1e-3, 1.0, 640.0, 1e5]))
        uv = rng.normal(0.0, scale, (n_cams, n_kp, 2))
        conf = rng.uniform(0.0, 1.0, (n_cams, n_kp))
        o = CollapseOptions(min_confidence=float(rng.choice([0.0, 0.3, 0.9])),
                            collapsed=float(rng.choice([0.15, 0.6, 2.0])),
                            min_keypoints=int(rng.choice([0, 1, 4, 9])))  # fmt: skip
        conf[rng.random(conf.shape) < 0.1] = o.min_confidence  # at the threshold: in
        conf[rng.random(conf.shape) < 0.03] = np.nan
        conf[rng.random(conf.shape) < 0.02] = np.inf
        uv[rng.random(uv.shape) < 0.03] = np.nan
        uv[rng.random(uv.shape) < 0.02] = -np.inf
        if trial % 7 == 0:
            uv[0] = uv[0, 0]  # every keypoint on one pixel: size 0
        pairs = np.array(COCO17_LR_PAIRS, dtype=np.intp) if n_kp == 17 and trial % 2 else rng.integers(0, n_kp, (6, 2))
        if trial % 5 == 0:  # the right keypoint near the limit from the left one
            size = view_sizes(uv, (conf >= o.min_confidence) & np.all(np.isfinite(uv), axis=-1), o.min_keypoints)
            step = o.collapsed * size[:, None] * rng.choice([1.0, 1 - 2e-16, 1 + 2e-16], (n_cams, len(pairs)))
            step = np.where(np.isfinite(step), step, 0.0)
            angle = rng.uniform(0.0, 2 * np.pi, step.shape)  # on a slant: the sum of squares rounds
            uv[:, pairs[:, 1], 0] = uv[:, pairs[:, 0], 0] + step * np.cos(angle)
            uv[:, pairs[:, 1], 1] = uv[:, pairs[:, 0], 1] + step * np.sin(angle)
        with np.errstate(invalid="ignore"):
            want = numpy_screen(uv, conf, pairs, o)
        lr = np.asfortranarray(pairs)
        got = (np.empty(conf.shape, dtype=bool), np.empty(n_cams), np.empty(want[2].shape, dtype=bool))
        found = _collapse_kernel.screen(uv, conf, lr[:, 0], lr[:, 1], o.min_confidence, o.min_keypoints, o.collapsed,
                                        *got)  # fmt: skip
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[2], want[2])
        assert got[1].tobytes() == want[1].tobytes()
        assert found == bool(want[2].any())
        compared += 1
        candidates += int(want[2].sum())
    assert compared == 3000 and candidates > 1000

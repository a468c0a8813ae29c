"""The collapsed-pair check made cheaper for the tick (issue 45's soak: ~1.5 ms a person on the synthetic rig, one
triangulation per candidate view and pair, and a small person's eyes and ears are candidates in every view): every
candidate's triangulation now goes into one ``triangulate_projections`` call and gives the separation the old
per-candidate call gave, to the bit. The old code is kept here, verbatim but for names, as the reference."""

from __future__ import annotations

import numpy as np

from mocapd.core.camera import triangulate_projections
from mocapd.core.lr_collapse import CollapseOptions, _expected_gaps, collapsed_pairs
from mocapd.core.lr_flips import COCO17_LR_PAIRS, undistorted
from tests.test_lr_flips import _person

FloatArray = np.ndarray
BoolArray = np.ndarray


def _old_expected_gap(
    P: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    ok: BoolArray,
    collapsed_views: BoolArray,
    pair: np.ndarray,
    view: int,
    reference: FloatArray | None,
) -> float:
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


def _old_collapsed_pairs(
    P: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    pairs: tuple[tuple[int, int], ...],
    reference: FloatArray | None = None,
    options: CollapseOptions | None = None,
) -> BoolArray:
    o = options if options is not None else CollapseOptions()
    n_cams = P.shape[0]
    out = np.zeros((n_cams, len(pairs)), dtype=bool)
    ok = (conf >= o.min_confidence) & np.all(np.isfinite(uv), axis=-1)
    size = np.zeros(n_cams)
    for c in range(n_cams):
        if np.count_nonzero(ok[c]) >= o.min_keypoints:
            size[c] = float(np.ptp(uv[c, ok[c]], axis=0).max())
    lr = np.array(pairs, dtype=np.intp)
    both = ok[:, lr[:, 0]] & ok[:, lr[:, 1]] & (size[:, None] > 0)
    gap = np.linalg.norm(uv[:, lr[:, 0]] - uv[:, lr[:, 1]], axis=-1)
    candidate = both & (gap < o.collapsed * size[:, None])
    if not candidate.any():
        return out
    for c, p in zip(*np.nonzero(candidate), strict=True):
        sep = _old_expected_gap(P, uv, conf, ok, candidate[:, p], lr[p], int(c), reference)
        out[c, p] = bool(np.isfinite(sep) and sep >= o.apart * size[c])
    return out


def _cases(n: int) -> list[tuple[FloatArray, FloatArray, FloatArray, FloatArray | None]]:
    """People of every kind the tick meets: walking or arms out, noisy pixels, pairs collapsed in some views,
    confidences below the threshold, views that miss the person, NaN pixels, a previous pose or none (or one with a
    NaN keypoint), a far camera that sees the person tiny (every pair a candidate)."""
    rng = np.random.default_rng(45)
    out = []
    for i in range(n):
        cams, X, uv = _person(frame=int(rng.integers(0, 60)), arms_out=bool(i % 5 == 0))
        uv = uv + rng.normal(0.0, rng.choice([0.5, 3.0]), uv.shape)
        if i % 4 == 1:  # a far view: the person small, every pair within 15 % of the size
            uv[0] = uv[0].mean(axis=0) + (uv[0] - uv[0].mean(axis=0)) * 0.05
        for _ in range(int(rng.integers(0, 4))):  # one limb's pair put on the other limb in a view or two
            c = int(rng.integers(0, 4))
            left, right = COCO17_LR_PAIRS[int(rng.integers(0, len(COCO17_LR_PAIRS)))]
            uv[c, right] = uv[c, left] + rng.normal(0.0, 2.0, 2)
        conf = rng.uniform(0.1, 1.0, uv.shape[:2])
        if i % 3 == 0:
            conf[int(rng.integers(0, 4))] = 0.0  # a view without the person
        if i % 7 == 0:
            uv[int(rng.integers(0, 4)), int(rng.integers(0, 17))] = np.nan
        P, und = undistorted(cams, uv)
        reference: FloatArray | None = None
        if i % 2 == 0:
            reference = X + rng.normal(0.0, 0.05, X.shape)
            if i % 8 == 0:
                reference[int(rng.integers(0, 17))] = np.nan
        out.append((P, und, conf, reference))
    return out


def test_the_candidates_separations_are_the_old_per_candidate_calls_to_the_bit() -> None:
    options = CollapseOptions()
    checked = triangulated = 0
    for P, und, conf, reference in _cases(160):
        ok = (conf >= options.min_confidence) & np.all(np.isfinite(und), axis=-1)
        lr = np.array(COCO17_LR_PAIRS, dtype=np.intp)
        # every (view, pair) seen in that view is a candidate here: more triangulations than the size test lets in
        candidate = ok[:, lr[:, 0]] & ok[:, lr[:, 1]]
        if not candidate.any():
            continue
        views, pair_idx = np.nonzero(candidate)
        new = _expected_gaps(P, und, conf, ok, candidate, lr, views, pair_idx, reference)
        old = np.array([
            _old_expected_gap(P, und, conf, ok, candidate[:, p], lr[p], int(c), reference)
            for c, p in zip(views, pair_idx, strict=True)
        ])  # fmt: skip
        assert new.tobytes() == old.tobytes()
        checked += len(views)
        triangulated += int(np.isfinite(old).sum())
    assert checked > 1000 and triangulated > 500  # the cases reach both the triangulation and the fallbacks


def test_collapsed_pairs_answers_as_the_old_code_did() -> None:
    found = 0
    for P, und, conf, reference in _cases(160):
        for options in (CollapseOptions(), CollapseOptions(collapsed=0.4, apart=0.2)):
            new = collapsed_pairs(P, und, conf, COCO17_LR_PAIRS, reference, options)
            np.testing.assert_array_equal(new, _old_collapsed_pairs(P, und, conf, COCO17_LR_PAIRS, reference, options))
            found += int(new.sum())
    assert found > 50  # collapses are found, not only "nothing collapsed"

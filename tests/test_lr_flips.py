"""Per-view left/right flips (mocapd.core.lr_flips), the flip-aware pairing of detection sorting, and the
scheduler undoing a flipped view before the solve."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.camera import Camera
from mocapd.core.keypoints import COCO17, coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.lr_collapse import CollapseOptions, collapsed_pairs, drop_collapsed
from mocapd.core.lr_flips import (
    COCO17_LR_PAIRS,
    FlipOptions,
    apply_swaps,
    choose_swaps,
    lr_pairs,
    undistorted,
)
from mocapd.core.skeleton import Skeleton
from mocapd.core.sorting import Detections2D, DetectionSorter, SortingOptions
from mocapd.core.synthetic import moving_sequence, ring_rig

FloatArray = np.ndarray


def _person(frame: int = 40, arms_out: bool = False) -> tuple[list[Camera], FloatArray, FloatArray]:
    """A walking person (or one standing with the arms out, the rest pose) seen by a 4-camera ring: their 17
    keypoints in 3D and as every camera sees them."""
    sk = Skeleton.from_height(1.75)
    theta = sk.rest_pose() if arms_out else moving_sequence(sk, frame + 1, seed=3)[frame]
    theta[3:6] = [0.0, 0.5, 0.0]  # turned a little: no view sees the person exactly side-on
    kin = Kinematics(sk)
    targets = coco17_targets(sk)
    X = kin.targets(kin.forward(theta), targets.bones, targets.offsets)
    cams = ring_rig(4, radius=4.5)
    uv = np.stack([c.project(X) for c in cams])
    return cams, X, uv


def _flip(uv: FloatArray, view: int) -> FloatArray:
    out = uv.copy()
    for left, right in COCO17_LR_PAIRS:
        out[view, [left, right]] = uv[view, [right, left]]
    return out


def test_lr_pairs_from_keypoint_names() -> None:
    assert lr_pairs(tuple(n for n, _, _ in COCO17)) == COCO17_LR_PAIRS
    assert lr_pairs(("nose", "left_knee", "right_knee", "left_toe")) == ((1, 2),)


def test_the_flipped_view_is_found_and_undone_by_the_majority() -> None:
    cams, _, uv = _person()
    rng = np.random.default_rng(0)
    seen = uv + rng.normal(0.0, 1.5, uv.shape)
    conf = np.full(uv.shape[:2], 0.9)
    bad = _flip(seen, 2)
    P, und = undistorted(cams, bad)
    decision = choose_swaps(P, und, conf)
    # Pairs whose two keypoints project apart in view 2 are swapped there, and only there.
    assert decision.swaps[[0, 1, 3]].sum() == 0
    assert decision.swaps[2, 2:].all(), decision.swaps  # shoulders, elbows, wrists, hips, knees, ankles
    fixed, _ = apply_swaps(bad, conf, decision.swaps)
    assert np.allclose(fixed[2, 5:], seen[2, 5:])
    # Nothing to undo in views that agree: no swap at all.
    P, und = undistorted(cams, seen)
    assert choose_swaps(P, und, conf).count == 0


def test_the_previous_pose_decides_which_mirror_labelling_is_right() -> None:
    cams, X, uv = _person()
    conf = np.full(uv.shape[:2], 0.9)
    two_flipped = _flip(_flip(uv, 1), 2)  # two views of four: the majority cannot tell
    P, und = undistorted(cams, two_flipped)
    decision = choose_swaps(P, und, conf, reference=X)
    assert decision.swaps[[1, 2], 2:].all() and not decision.swaps[[0, 3]].any()
    mirrored = X.copy()
    for left, right in COCO17_LR_PAIRS:
        mirrored[[left, right]] = X[[right, left]]
    other = choose_swaps(P, und, conf, reference=mirrored)
    assert other.swaps[[0, 3], 2:].all() and not other.swaps[[1, 2]].any()


def test_disabled_or_unseen_pairs_are_left_alone() -> None:
    cams, _, uv = _person()
    conf = np.full(uv.shape[:2], 0.9)
    P, und = undistorted(cams, _flip(uv, 2))
    assert choose_swaps(P, und, conf, options=FlipOptions(enabled=False)).count == 0
    low = conf.copy()
    low[:, [15, 16]] = 0.1  # ankles not confidently seen anywhere
    assert not choose_swaps(P, und, low).swaps[:, 7].any()


@pytest.mark.parametrize("flip_aware", [False, True])
def test_sorting_keeps_a_flipped_view_in_the_person_only_when_flip_aware(flip_aware: bool) -> None:
    cams, _, uv = _person(arms_out=True)  # the hands 1.6 m apart: a flipped view is far off as labelled
    rng = np.random.default_rng(1)
    seen = _flip(uv + rng.normal(0.0, 1.0, uv.shape), 2)
    dets = [Detections2D(seen[c][None], np.full((1, 17), 0.9)) for c in range(4)]
    sorter = DetectionSorter(cams, SortingOptions(flip_aware=flip_aware))
    cands = sorter.candidates(dets)
    views = max(len(c.sources) for c in cands)
    assert views == (4 if flip_aware else 3)


def test_pairs_searched_together_decide_as_each_pair_alone() -> None:
    """choose_swaps searches the pairs seen by the same views in one batch: the decision and gain of every pair
    are what the pair gets searched alone, also when the pairs' view sets differ (views missing some keypoints)
    and with or without a previous pose."""
    rng = np.random.default_rng(7)
    checked = swapped = 0
    for trial in range(40):
        cams, X, uv = _person(frame=int(rng.integers(0, 60)))
        seen = uv + rng.normal(0.0, rng.uniform(0.5, 15.0), uv.shape)
        for view in range(4):
            if rng.random() < 0.3:
                seen = _flip(seen, view)
        conf = rng.uniform(0.0, 1.0, uv.shape[:2])
        conf[rng.random(conf.shape) < 0.2] = 0.0
        P, und = undistorted(cams, seen)
        reference = None if trial % 3 == 0 else X + rng.normal(0.0, 0.05, X.shape)
        together = choose_swaps(P, und, conf, reference=reference)
        for p, pair in enumerate(COCO17_LR_PAIRS):
            alone = choose_swaps(P, und, conf, pairs=(pair,), reference=None if reference is None else reference)
            assert np.array_equal(together.swaps[:, p], alone.swaps[:, 0]), (trial, pair)
            assert together.gain_px[p] == pytest.approx(alone.gain_px[0], abs=1e-9)
            checked += 1
        swapped += together.count
    assert checked == 40 * len(COCO17_LR_PAIRS) and swapped > 20  # the cases exercised swaps, not only no-ops


def test_the_compiled_search_decides_as_the_numpy_reference() -> None:
    """The compiled hypothesis search (the one the scheduler runs every tick) makes the numpy reference's
    decisions, gains and triangulated points on random scenes: noise, flipped views, missing keypoints, with and
    without a previous pose, 2 to 6 views."""
    rng = np.random.default_rng(11)
    swapped = 0
    for trial in range(300):
        cams, X, uv = _person(frame=int(rng.integers(0, 60)))
        n = int(rng.integers(2, 5))
        views = rng.permutation(4)[:n]
        seen = uv[views] + rng.normal(0.0, rng.uniform(0.5, 15.0), (n, *uv.shape[1:]))
        for view in range(n):
            if rng.random() < 0.3:
                seen = _flip(seen, view)
        conf = rng.uniform(0.0, 1.0, seen.shape[:2])
        conf[rng.random(conf.shape) < 0.2] = 0.0
        P, und = undistorted([cams[v] for v in views], seen)
        reference = None if trial % 3 == 0 else X + rng.normal(0.0, 0.05, X.shape)
        fast = choose_swaps(P, und, conf, reference=reference)
        slow = choose_swaps(P, und, conf, reference=reference, compiled=False)
        assert np.array_equal(fast.swaps, slow.swaps), trial
        assert np.allclose(fast.gain_px, slow.gain_px, atol=1e-6), trial
        swapped += fast.count
    assert swapped > 50  # the scenes exercised swaps, not only no-ops


def test_the_warm_up_compiles_what_the_tick_runs() -> None:
    """The daemon's warm-up compiles the flip search before the first tick; a tick that then met another array
    layout compiled a second signature inside itself (~10 s of the tick thread on a fresh machine: issue 39)."""
    from mocapd.core import _flip_kernel, lr_flips

    cams = ring_rig(4)
    lr_flips.warm_up(cams, 17)
    compiled = len(_flip_kernel.best_hypotheses.signatures)
    rng = np.random.default_rng(0)
    P, und = lr_flips.undistorted(cams, rng.uniform(100, 500, (4, 17, 2)))
    lr_flips.choose_swaps(P, und, rng.uniform(0.3, 1.0, (4, 17)), lr_flips.COCO17_LR_PAIRS)
    assert len(_flip_kernel.best_hypotheses.signatures) == compiled


def test_a_view_that_puts_both_wrists_on_one_arm_is_found_and_a_true_overlap_kept() -> None:
    """Issue 41: two views of four put the right elbow and wrist on the left ones. Those two views' elbow and wrist
    pairs are collapsed (the two other views triangulate them apart); nothing else is, and a view whose pair really
    projects onto itself (the arms along its line of sight) is left alone."""
    cams, X, uv = _person(arms_out=True)
    conf = np.full(uv.shape[:2], 0.9)
    bad = uv.copy()
    for c in (0, 2):
        bad[c, [8, 10]] = bad[c, [7, 9]] + 1.5
    P, und = undistorted(cams, bad)
    got = collapsed_pairs(P, und, conf, COCO17_LR_PAIRS)
    elbows, wrists = COCO17_LR_PAIRS.index((7, 8)), COCO17_LR_PAIRS.index((9, 10))
    expected = np.zeros_like(got)
    expected[[0, 2], elbows] = expected[[0, 2], wrists] = True
    np.testing.assert_array_equal(got, expected)
    dropped = drop_collapsed(conf, got, COCO17_LR_PAIRS)
    assert (dropped[[0, 2]][:, [7, 8, 9, 10]] == 0).all() and (dropped[[1, 3]] == 0.9).all()
    # The same with only the previous pose to say where the pair lies (one other view sees it).
    one_other = conf.copy()
    one_other[3] = 0.0
    assert collapsed_pairs(P, und, one_other, COCO17_LR_PAIRS)[[0, 2]].sum() == 0  # nothing to judge by
    assert collapsed_pairs(P, und, one_other, COCO17_LR_PAIRS, reference=X)[[0, 2]][:, [elbows, wrists]].all()
    # Clean views: nothing collapsed, also where two keypoints of a pair lie close (the eyes of a small person).
    P, und = undistorted(cams, uv)
    assert not collapsed_pairs(P, und, conf, COCO17_LR_PAIRS).any()
    # A true overlap: the right wrist on camera 1's line of sight through the left one, 30 cm further. View 1 sees
    # the two wrists on top of each other and the other views triangulate them so: kept.
    Y = X.copy()
    centre = -cams[1].R.T @ cams[1].t
    ray = (X[9] - centre) / np.linalg.norm(X[9] - centre)
    Y[10] = X[9] + 0.3 * ray
    uv_y = np.stack([c.project(Y) for c in cams])
    P, und = undistorted(cams, uv_y)
    assert np.linalg.norm(und[1, 9] - und[1, 10]) < 2.0  # they overlap in view 1
    assert not collapsed_pairs(P, und, conf, COCO17_LR_PAIRS)[:, wrists].any()
    # Disabled: nothing.
    P, und = undistorted(cams, bad)
    assert not collapsed_pairs(P, und, conf, COCO17_LR_PAIRS, options=CollapseOptions(enabled=False)).any()

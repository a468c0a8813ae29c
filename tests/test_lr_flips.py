"""Per-view left/right flips (mocapd.core.lr_flips), the flip-aware pairing of detection sorting, and the
scheduler undoing a flipped view before the solve."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.camera import Camera, triangulate_projections
from mocapd.core.keypoints import COCO17, coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.lr_collapse import CollapseOptions, collapsed_pairs, drop_collapsed
from mocapd.core.lr_flips import (
    COCO17_LR_PAIRS,
    FlipMemo,
    FlipOptions,
    apply_swaps,
    choose_swaps,
    lr_pairs,
    undistorted,
)
from mocapd.core.skeleton import Skeleton
from mocapd.core.sorting import Detections2D, DetectionSorter, SortingOptions
from mocapd.core.synthetic import moving_sequence, ring_rig
from mocapd.errors import InputError

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
    compiled = len(_flip_kernel.choose_swaps.signatures)
    rng = np.random.default_rng(0)
    P, und = lr_flips.undistorted(cams, rng.uniform(100, 500, (4, 17, 2)))
    conf = rng.uniform(0.3, 1.0, (4, 17))
    lr_flips.choose_swaps(P, und, conf, lr_flips.COCO17_LR_PAIRS)
    # as the scheduler calls it (a person's memo, their previous pose), and with Fortran-ordered and strided inputs
    memo = lr_flips.FlipMemo(4, len(lr_flips.COCO17_LR_PAIRS))
    ref = rng.uniform(-1.0, 1.0, (17, 3))
    lr_flips.choose_swaps(P, und, conf, lr_flips.COCO17_LR_PAIRS, ref, memo=memo)
    lr_flips.choose_swaps(P[:, :, :], np.asfortranarray(und), conf.T.copy().T, lr_flips.COCO17_LR_PAIRS, ref)
    assert len(_flip_kernel.choose_swaps.signatures) == compiled == 1


def _random_scene(rng: np.random.Generator) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray | None]:
    """Projections, undistorted pixels, confidences and maybe a previous pose of a random walking person seen by 2
    to 4 views of a ring: noise, flipped views, missing and NaN keypoints, confidences around the threshold."""
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
    und[rng.random(und.shape[:2]) < 0.05] = np.nan  # keypoints nobody saw
    reference = None if rng.random() < 0.35 else X + rng.normal(0.0, 0.05, X.shape)
    if reference is not None and rng.random() < 0.1:
        reference[rng.integers(0, 17)] = np.nan  # a joint the previous solve did not place
    return P, und, conf, reference


def _same_decision(P: FloatArray, und: FloatArray, conf: FloatArray, ref: FloatArray | None, **kw: object) -> int:
    """The compiled decision is the numpy reference's: every swap flag, every gain (round-off of the two eigen
    solvers aside); returns the swaps made."""
    fast = choose_swaps(P, und, conf, reference=ref, **kw)  # type: ignore[arg-type]
    slow = choose_swaps(P, und, conf, reference=ref, compiled=False, **kw)  # type: ignore[arg-type]
    assert np.array_equal(fast.swaps, slow.swaps)
    assert np.allclose(fast.gain_px, slow.gain_px, rtol=0.0, atol=1e-6)
    assert fast.swaps.dtype == bool and fast.gain_px.dtype == np.float64
    return fast.count


def test_the_compiled_decision_is_the_numpy_reference_on_random_scenes() -> None:
    """The whole decision compiled (grouping, search, mirror choice) against the numpy reference on 600 random
    scenes, with the options varied (confidence floors, few views searched, other margins and caps)."""
    rng = np.random.default_rng(23)
    swapped = 0
    for trial in range(600):
        P, und, conf, ref = _random_scene(rng)
        o = FlipOptions(
            # not 0: a view seeing neither keypoint would then take part with no weight, and a hypothesis that swaps
            # it ties exactly with one that does not, a tie the two eigen solvers' round-off breaks either way
            min_confidence=float(rng.choice([0.05, 0.3, 0.6])),
            margin_px=float(rng.choice([0.0, 4.0, 12.0])),
            cap_px=float(rng.choice([30.0, 80.0])),
            max_views=int(rng.choice([2, 3, 10])),
        )
        swapped += _same_decision(P, und, conf, ref, options=o)
        assert trial >= 0
    assert swapped > 200  # the scenes exercised swaps, not only no-ops


def test_ties_of_the_mirror_choice_are_broken_as_numpy_sums() -> None:
    """Without a previous pose, equal counts of swapped views are decided by comparing two confidence sums: the
    kernel sums in numpy's pairwise order, so even sums that differ in the last bit compare the same way."""
    from mocapd.core import _flip_kernel

    rng = np.random.default_rng(5)
    for n in (*range(0, 20), 63, 64, 127, 128, 129, 200, 517, 1000):
        a = rng.standard_normal(n) * 10.0 ** rng.integers(-6, 6, n)
        assert _flip_kernel._pairwise_sum(a, 0, n) == a.sum(), n
    cams, _, uv = _person()
    P, und = undistorted(cams, _flip(_flip(uv, 1), 2))
    conf = np.full(uv.shape[:2], 0.9)
    for _ in range(50):  # two views of four flipped, no previous pose: the less confident pair of views swaps
        c = conf + rng.normal(0.0, 1e-12, conf.shape)
        _same_decision(P, und, c, None)


@pytest.fixture(scope="module")
def demo_frames() -> tuple[list[Camera], list[tuple[FloatArray, FloatArray]]]:
    """The single-person Pose2Sim demo as the real detector sees it (first 40 frames, the most confident person
    of every view): its cameras and, per frame, the (4, 17, 2) pixels and (4, 17) confidences."""
    from mocapd.eval.video_input import detect_take, pose2sim_take
    from mocapd.pipeline.detector import OnnxPoseDetector
    from mocapd.pipeline.detector_config import ModelSpec

    take = pose2sim_take("Demo_SinglePerson")
    dets = detect_take(take, lambda: OnnxPoseDetector(ModelSpec(), intra_op_threads=2), n_frames=40)
    return take.cameras, dets.most_confident()


def test_the_compiled_decision_is_the_numpy_reference_on_the_demo(
    demo_frames: tuple[list[Camera], list[tuple[FloatArray, FloatArray]]],
) -> None:
    """Real detections (the Pose2Sim demo), as detected and with views flipped and keypoints dropped at random,
    with the triangulated previous frame as the previous pose or none: compiled and numpy decide the same."""
    cams, frames = demo_frames
    rng = np.random.default_rng(3)
    swapped = 0
    previous = None
    for kp, cf in frames:
        for variant in range(4):
            seen, conf = kp.copy(), cf.copy()
            if variant:
                for view in range(4):
                    if rng.random() < 0.35:
                        seen = _flip(seen, view)
                conf[rng.random(conf.shape) < 0.1] = 0.0
            P, und = undistorted(cams, seen)
            swapped += _same_decision(P, und, conf, previous if variant % 2 else None)
        P, und = undistorted(cams, kp)
        X, _ = triangulate_projections(P, und, np.where(cf >= 0.3, cf, 0.0))
        previous = X
    assert swapped > 50


def test_a_person_s_memo_changes_no_decision_and_searches_only_the_pairs_that_changed() -> None:
    """With a person's memo, pairs whose inputs are bit-for-bit those of the previous call take the previous
    search result (the mirror choice is made again: the previous pose moves); the decisions over a sequence of
    held, nudged and flipped frames are those without the memo."""
    rng = np.random.default_rng(17)
    cams, X, uv = _person()
    P, und0 = undistorted(cams, _flip(uv + rng.normal(0.0, 1.0, uv.shape), 2))
    conf0 = np.full(uv.shape[:2], 0.9)
    memo = FlipMemo(4, len(COCO17_LR_PAIRS))
    searched = reused = 0
    und, conf = und0.copy(), conf0.copy()
    for step in range(200):
        change = rng.random()
        if change < 0.3:  # one keypoint of one view moves: its pair alone is searched again
            und = und.copy()
            und[rng.integers(0, 4), rng.integers(0, 17)] += rng.normal(0.0, 3.0, 2)
        elif change < 0.4:  # a view flips
            und = _flip(und, int(rng.integers(0, 4)))
        elif change < 0.5:  # a confidence crosses the threshold
            conf = conf.copy()
            conf[rng.integers(0, 4), rng.integers(0, 17)] = rng.choice([0.1, 0.9])
        elif change < 0.55:
            und, conf = und0.copy(), conf0.copy()
        ref = None if step % 5 == 0 else X + rng.normal(0.0, 0.3, X.shape)  # sometimes nearer the mirror
        with_memo = choose_swaps(P, und, conf, reference=ref, memo=memo)
        without = choose_swaps(P, und, conf, reference=ref)
        assert np.array_equal(with_memo.swaps, without.swaps), step
        assert np.array_equal(with_memo.gain_px, without.gain_px), step  # the same arithmetic, to the bit
        searched += memo.searched
        reused += memo.reused
    assert reused > 3 * searched > 0
    # Other projection matrices (a recalibration) or options: nothing is reused.
    choose_swaps(P, und, conf, memo=memo)
    assert memo.searched == 0
    choose_swaps(P * 1.0000001, und, conf, memo=memo)
    assert memo.reused == 0 and memo.searched > 0
    choose_swaps(P * 1.0000001, und, conf, memo=memo, options=FlipOptions(cap_px=79.0))
    assert memo.reused == 0 and memo.searched > 0


def _exchange_in_order(
    kp: FloatArray, conf: FloatArray, swaps: np.ndarray, pairs: tuple[tuple[int, int], ...]
) -> tuple[FloatArray, FloatArray]:
    """The exchanges made pair after pair (apply_swaps as it was written first): the reference."""
    kp, conf = kp.copy(), conf.copy()
    for p, (left, right) in enumerate(pairs):
        views = np.flatnonzero(swaps[:, p])
        kp[views, left], kp[views, right] = kp[views, right].copy(), kp[views, left].copy()
        conf[views, left], conf[views, right] = conf[views, right].copy(), conf[views, left].copy()
    return kp, conf


def test_apply_swaps_exchanges_the_flagged_pairs_as_one_after_another_would() -> None:
    """apply_swaps gathers every exchange at once: the arrays are those of exchanging pair after pair, for the
    COCO-17 pairs, for pairs sharing a keypoint (made in order) and with no pair at all; the inputs are not
    touched."""
    rng = np.random.default_rng(9)
    for pairs in (COCO17_LR_PAIRS, ((1, 2), (2, 3), (5, 6)), ()):
        for _ in range(50):
            kp, conf = rng.normal(size=(4, 17, 2)), rng.random((4, 17))
            kp_in, conf_in = kp.copy(), conf.copy()
            swaps = rng.random((4, len(pairs))) < 0.4
            got = apply_swaps(kp, conf, swaps, pairs)
            want = _exchange_in_order(kp, conf, swaps, pairs)
            assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
            assert np.array_equal(kp, kp_in) and np.array_equal(conf, conf_in)


def test_no_pairs_and_a_short_previous_pose_are_answered_clearly() -> None:
    """No pair to search: nothing swapped (with a previous pose too); a previous pose without a point for every
    paired keypoint is refused with a clear message, compiled or not (it would be read past its end)."""
    cams, X, uv = _person()
    P, und = undistorted(cams, uv)
    conf = np.full(uv.shape[:2], 0.9)
    for compiled in (True, False):
        none = choose_swaps(P, und, conf, (), X, compiled=compiled)
        assert none.swaps.shape == (4, 0) and none.gain_px.shape == (0,)
        with pytest.raises(InputError, match="every keypoint paired"):
            choose_swaps(P, und, conf, reference=X[:10], compiled=compiled)


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

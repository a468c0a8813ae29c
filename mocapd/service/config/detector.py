"""The ``[detector]`` section (with ``[detector.model]``, ``[detector.packing]`` and ``[detector.tracking]``): the 2D
keypoint detector and the keypoint tracking between its detections.

The pipeline's plain :class:`~mocapd.pipeline.detector_config.DetectorConfig` (with its
:class:`~mocapd.pipeline.detector_config.ModelSpec` and :class:`~mocapd.pipeline.detector_config.PackingConfig`)
is built from it by :meth:`DetectorSection.options`; the keys and defaults are the same.
"""

from __future__ import annotations

import re
from typing import Annotated, Literal

from pydantic import AfterValidator, BeforeValidator, Field

from mocapd.pipeline.detector_config import DetectorConfig, ModelSpec, PackingConfig, TrackingConfig
from mocapd.service.config.schema import Allowed, PathStr, Section, Seq, as_tuple, unique

_M, _P, _D, _T = ModelSpec(), PackingConfig(), DetectorConfig(), TrackingConfig()
_PROVIDER = re.compile(r"(?i:auto|tensorrt|cuda|openvino|cpu)|[A-Za-z0-9]{1,40}ExecutionProvider")
_PROVIDER_WORDS = (
    '"auto", "tensorrt", "cuda", "openvino", "cpu" or an onnxruntime provider name ("...ExecutionProvider")'
)


def _provider(name: str) -> str:
    if not _PROVIDER.fullmatch(name):
        raise ValueError(f"not a provider; allowed: {_PROVIDER_WORDS}")
    return name


def _canvas(size: int) -> int:
    if size % 32:
        raise ValueError("must be 0 (the model's input size) or a multiple of 32")
    return size


def _tile_height(fraction: float) -> float:
    if 0.0 < fraction < 0.1:
        raise ValueError("must be 0 (off) or in [0.1, 1]")
    return fraction


Provider = Annotated[str, Field(max_length=64), AfterValidator(_provider), Allowed(_PROVIDER_WORDS)]
#: a pixel level of one channel (mean), in 0..255 units or those of the model's training
Level = Annotated[float, Field(ge=-1000.0, le=1000.0)]
Spread = Annotated[float, Field(gt=0.0, le=1000.0)]
Triple = Annotated[tuple[Level, Level, Level], BeforeValidator(as_tuple)]
PositiveTriple = Annotated[tuple[Spread, Spread, Spread], BeforeValidator(as_tuple)]


class ModelSection(Section):
    """``[detector.model]``: what the runtime must know about the ONNX pose model."""

    path: PathStr = _M.path
    input_width: int = Field(_M.input_width, ge=32, le=8192)
    input_height: int = Field(_M.input_height, ge=32, le=8192)
    layout: Literal["NCHW", "NHWC"] = "NCHW"
    channel_order: Literal["RGB", "BGR"] = "RGB"
    pixel_scale: float = Field(_M.pixel_scale, gt=0.0, le=1000.0)
    mean: Triple = _M.mean
    std: PositiveTriple = _M.std
    pad_value: int = Field(_M.pad_value, ge=0, le=255)
    decoder: Literal["yolo_pose"] = "yolo_pose"
    keypoint_format: Literal["coco17", "body25", "halpe26", "blazepose33"] = "coco17"
    score_threshold: float = Field(_M.score_threshold, ge=0.0, le=1.0)
    iou_threshold: float = Field(_M.iou_threshold, ge=0.0, le=1.0)
    max_people: int = Field(_M.max_people, ge=1, le=1000)


class PackingSection(Section):
    """``[detector.packing]``: ROI packing and temporal sub-sampling (seed 000 §3.3)."""

    ordered = (("min_scale_ratio", "<=", "max_scale_ratio"), ("n_o", "<=", "n_p"))

    enabled: Annotated[bool | Literal["auto"], Allowed('true, false or "auto"')] = "auto"
    roi_margin: float = Field(_P.roi_margin, ge=0.0, le=2.0)
    gap: int = Field(_P.gap, ge=0, le=64)
    canvas_width: Annotated[int, Field(ge=0, le=8192), AfterValidator(_canvas)] = _P.canvas_width
    canvas_height: Annotated[int, Field(ge=0, le=8192), AfterValidator(_canvas)] = _P.canvas_height
    canvas_model_path: PathStr = _P.canvas_model_path
    align_stride: int = Field(_P.align_stride, ge=0, le=256)
    min_scale_ratio: float = Field(_P.min_scale_ratio, ge=0.1, le=4.0)
    max_scale_ratio: float = Field(_P.max_scale_ratio, ge=0.1, le=4.0)
    max_tile_height: Annotated[float, Field(ge=0.0, le=1.0), AfterValidator(_tile_height)] = _P.max_tile_height
    refresh_every: int = Field(_P.refresh_every, ge=0, le=10_000)
    refresh_scale_ratio: float = Field(_P.refresh_scale_ratio, ge=0.1, le=1.0)
    n_o: int = Field(_P.n_o, ge=1, le=1000)
    n_p: int = Field(_P.n_p, ge=1, le=1000)


def _odd(size: int) -> int:
    if size % 2 == 0:
        raise ValueError("must be odd")
    return size


def _factor(factor: int) -> int:
    if factor not in (1, 2, 4):
        raise ValueError('must be 1, 2, 4 or "auto"')
    return factor


class TrackingSection(Section):
    """``[detector.tracking]``: keypoints carried between detections on every camera frame."""

    enabled: bool = _T.enabled
    rate_hz: float = Field(_T.rate_hz, ge=1.0, le=1000.0)
    downsample: Annotated[int, Field(ge=1, le=4), AfterValidator(_factor)] | Literal["auto"] = "auto"
    window_px: Annotated[int, Field(ge=5, le=63), AfterValidator(_odd)] = _T.window_px
    levels: int = Field(_T.levels, ge=0, le=6)
    max_fb_px: float = Field(_T.max_fb_px, gt=0.0, le=100.0)
    lost_confidence: float = Field(_T.lost_confidence, ge=0.0, le=1.0)
    half_life_s: float = Field(_T.half_life_s, gt=0.0, le=60.0)
    max_age_s: float = Field(_T.max_age_s, gt=0.0, le=60.0)
    min_keypoints: int = Field(_T.min_keypoints, ge=1, le=1000)
    history_s: float = Field(_T.history_s, gt=0.0, le=60.0)
    thread: Literal["capture", "pool"] = "capture"
    workers: int = Field(_T.workers, ge=1, le=64)


class DetectorSection(Section):
    """The ``[detector]`` section."""

    providers: Annotated[Seq[Provider], Field(min_length=1, max_length=8), AfterValidator(unique)] = _D.providers
    precision: Literal["auto", "fp32", "int8", "bf16"] = "auto"
    intra_op_threads: int = Field(_D.intra_op_threads, ge=0, le=256)
    inter_op_threads: int = Field(_D.inter_op_threads, ge=0, le=256)
    workers: Annotated[int, Field(ge=1, le=64)] | Literal["auto"] = "auto"
    intra_op_spinning: bool = _D.intra_op_spinning
    batch: bool | Literal["auto"] = "auto"
    fitted_inputs: bool | Literal["auto"] = "auto"
    landmarks: Literal["off", "full", "heavy", "auto"] = "off"
    hands: Literal["off", "on", "auto"] = "off"
    model: ModelSection = Field(default_factory=ModelSection)
    packing: PackingSection = Field(default_factory=PackingSection)
    tracking: TrackingSection = Field(default_factory=TrackingSection)

    def options(self) -> DetectorConfig:
        """The pipeline's :class:`DetectorConfig` of this section."""
        return DetectorConfig(
            providers=self.providers,
            precision=self.precision,
            intra_op_threads=self.intra_op_threads,
            inter_op_threads=self.inter_op_threads,
            workers=self.workers,
            intra_op_spinning=self.intra_op_spinning,
            batch=self.batch,
            fitted_inputs=self.fitted_inputs,
            landmarks=self.landmarks,
            hands=self.hands,
            model=self.model.build(ModelSpec),
            packing=self.packing.build(PackingConfig),
            tracking=self.tracking.build(TrackingConfig),
        )

"""Typed configuration of the 2D keypoint detector: ``[detector]``, ``[detector.model]``, ``[detector.packing]``.

Plain frozen dataclasses, built from ``config.toml`` by the schema in :mod:`mocapd.service.config.detector`
(which declares each key's type and range and names bad keys); the checks here guard programmatic
construction (tools, tests) with the same rules. ``config.toml`` documents every key.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

from mocapd.core.keypoints import FORMATS
from mocapd.core.roi_packing import SubsampleSchedule
from mocapd.errors import ConfigError

DECODERS = ("yolo_pose",)
LAYOUTS = ("NCHW", "NHWC")
CHANNEL_ORDERS = ("RGB", "BGR")
PRECISIONS = ("auto", "fp32", "int8", "bf16")
LANDMARKS = ("off", "full", "heavy", "auto")
HANDS = ("off", "on", "auto")
#: The body keypoint sets hand crops are placed from (``[detector] hands``): BlazePose's wrist, index and pinky, or
#: COCO-17's forearm.
HAND_BODIES = ("coco17", "blazepose33")
#: ``[detector] workers = "auto"``: one inference session per this many cores (tools/bench_sessions.py)
CORES_PER_SESSION = 2


@dataclass(frozen=True)
class ModelSpec:
    """What the runtime must know about an ONNX pose model to feed it and read its output."""

    path: str = ""
    """ONNX file; "" = the default YOLO11n-pose export for this input size in the cache (mocapd model fetch)."""
    input_width: int = 640
    """Model input width in pixels (the export's fixed size)."""
    input_height: int = 640
    """Model input height in pixels."""
    layout: str = "NCHW"
    """Input tensor layout: NCHW or NHWC."""
    channel_order: str = "RGB"
    """Channel order the model was trained on: RGB or BGR."""
    pixel_scale: float = 1.0 / 255.0
    """Input = (pixel - mean) * pixel_scale / std, per channel, after channel reordering."""
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    std: tuple[float, float, float] = (1.0, 1.0, 1.0)
    pad_value: int = 114
    """Grey level of letterbox and packing padding (0..255)."""
    decoder: str = "yolo_pose"
    """Output decoding: yolo_pose = (1, 5 + 3K, N) boxes cx,cy,w,h + score + K × (x, y, conf)."""
    keypoint_format: str = "coco17"
    """coco17, body25, halpe26 or blazepose33."""
    score_threshold: float = 0.25
    """Person score below which candidates are dropped (0..1)."""
    iou_threshold: float = 0.65
    """NMS IoU threshold (0..1)."""
    max_people: int = 20
    """At most this many people per detector image."""

    def __post_init__(self) -> None:
        _choice("detector.model.decoder", self.decoder, DECODERS)
        _choice("detector.model.layout", self.layout, LAYOUTS)
        _choice("detector.model.channel_order", self.channel_order, CHANNEL_ORDERS)
        _choice("detector.model.keypoint_format", self.keypoint_format, tuple(FORMATS))
        if self.input_width < 32 or self.input_height < 32:
            raise ConfigError(f"detector.model input size must be >= 32, got {self.input_width}x{self.input_height}")
        if not 0 <= self.pad_value <= 255:
            raise ConfigError(f"detector.model.pad_value must be 0..255, got {self.pad_value}")
        for key in ("score_threshold", "iou_threshold"):
            v = getattr(self, key)
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"detector.model.{key} must be in [0, 1], got {v}")
        if self.max_people < 1:
            raise ConfigError(f"detector.model.max_people must be >= 1, got {self.max_people}")
        if len(self.mean) != 3 or len(self.std) != 3 or min(self.std) <= 0:
            raise ConfigError(f"detector.model mean/std need 3 values with std > 0, got {self.mean} {self.std}")


@dataclass(frozen=True)
class PackingConfig:
    """ROI packing and temporal sub-sampling (seed 000 §3.3)."""

    enabled: bool | str = "auto"
    """Pack camera ROIs into shared detector images (False: one image per camera frame; "auto": whichever of
    the two delivers more camera frames with people per second on this rig, measured while the daemon runs)."""
    roi_margin: float = 0.075
    """ROI = union box of the last detections grown on each side by this fraction of its larger side."""
    gap: int = 0
    """Canvas pixels between packed tiles (0: tiles touch; each ROI's margin already keeps its people away from
    its edges, and a gap that is not a multiple of align_stride would cost alignment slack)."""
    canvas_width: int = 0
    """Width of the packed canvases in pixels (0 = the model's input width). A larger size runs the same
    network exported at that size (``mocapd model fetch --size WxH``) on canvases that hold more tiles."""
    canvas_height: int = 0
    """Height of the packed canvases (0 = the model's input height)."""
    canvas_model_path: str = ""
    """ONNX file of the canvas-sized model when the canvas size differs from the model's ("" = the default
    YOLO11n-pose export for that size)."""
    align_stride: int = 32
    """> 0: place every tile at its camera's whole-frame letterbox scale, its pixels shifted by a multiple of
    this many pixels (the network's largest stride), so that packed detection sees exactly the pixels
    whole-frame detection sees; min/max_scale_ratio are then unused. 0: one common scale per canvas."""
    min_scale_ratio: float = 1.0
    """A packed tile is never scaled below this × the scale a whole-frame pass of that camera would get;
    ROIs that do not fit at that scale go to a further canvas (1.0: packing never loses resolution)."""
    max_scale_ratio: float = 1.0
    """A packed tile is never scaled above this × the whole-frame scale (1.0 with min_scale_ratio 1.0: tiles
    at exactly the whole-frame scale, so packed and unpacked detection see people at the same size)."""
    max_tile_height: float = 0.0
    """A person's tile is never taller than this fraction of the canvas height: a taller ROI is scaled down
    to that height (keeping its aspect) instead of its whole-frame scale, so that two large people stack on
    one canvas. The model still sees such a person over ``max_tile_height`` x canvas height pixels, far above
    what it needs; only these tiles lose stride alignment. 0 = off (every tile at its whole-frame scale)."""
    refresh_every: int = 8
    """Every this many packed calls, each camera also sees its whole frame once (cameras staggered, so a
    4-camera rig refreshes one camera every other call with the default): people who are new, or whom a
    partial detection's ROI keeps cutting, are found there and re-seed the ROIs. 0 = never."""
    refresh_scale_ratio: float = 0.5
    """Scale of that whole-frame refresh tile, as a multiple of the whole-frame letterbox scale (0.1..1):
    it only has to find people, not to place their keypoints (its detections are used where no ROI found
    the person)."""
    n_o: int = 2
    """Temporal sub-sampling: detect the first N_o frames of every N_p (seed 000 §4.1.2)."""
    n_p: int = 2
    """See n_o; 2/2 detects every frame and packs frame pairs, 2/8 detects a quarter of them."""

    def __post_init__(self) -> None:
        SubsampleSchedule(self.n_o, self.n_p)  # validates
        if self.enabled not in (True, False, "auto"):
            raise ConfigError(f'detector.packing.enabled must be true, false or "auto", got {self.enabled!r}')
        if not 0.0 <= self.roi_margin <= 2.0:
            raise ConfigError(f"detector.packing.roi_margin must be in [0, 2], got {self.roi_margin}")
        for key in ("canvas_width", "canvas_height"):
            v = getattr(self, key)
            if v != 0 and (v < 32 or v % 32):
                raise ConfigError(f"detector.packing.{key} must be 0 or a multiple of 32, got {v}")
        if self.align_stride < 0 or self.align_stride > 256:
            raise ConfigError(f"detector.packing.align_stride must be in [0, 256], got {self.align_stride}")
        if not (self.max_tile_height == 0.0 or 0.1 <= self.max_tile_height <= 1.0):
            raise ConfigError(f"detector.packing.max_tile_height must be 0 or in [0.1, 1], got {self.max_tile_height}")
        if self.refresh_every < 0:
            raise ConfigError(f"detector.packing.refresh_every must be >= 0, got {self.refresh_every}")
        if not 0.1 <= self.refresh_scale_ratio <= 1.0:
            raise ConfigError(
                f"detector.packing.refresh_scale_ratio must be in [0.1, 1], got {self.refresh_scale_ratio}"
            )
        if not 0 <= self.gap <= 64:
            raise ConfigError(f"detector.packing.gap must be in [0, 64], got {self.gap}")
        if not 0.1 <= self.min_scale_ratio <= self.max_scale_ratio <= 4.0:
            raise ConfigError(
                "detector.packing needs 0.1 <= min_scale_ratio <= max_scale_ratio <= 4, got "
                f"{self.min_scale_ratio} and {self.max_scale_ratio}"
            )


THREADS = ("capture", "pool")
#: "auto" downsampling keeps at least this many pixels on the tracking image's shorter side (544x960 demo frames
#: are tracked at 272x480: more keypoints kept than at full size, 55 % of its CPU; tools/track_quality.py)
MIN_TRACKING_SIDE = 240


@dataclass(frozen=True)
class TrackingConfig:
    """Keypoints carried between detections on every camera frame (:mod:`mocapd.pipeline.keypoint_tracker`)."""

    enabled: bool = True
    """Track each detected person's keypoints on the frames between two detections of their camera (pyramidal
    Lucas-Kanade), so that the scheduler has keypoints at the camera rate; False: detections only (their interval
    then sets the latency, see ``mocapd/config.toml``)."""
    rate_hz: float = 60.0
    """Track a camera's frames this often on average, at most every frame (a 60 fps camera: every frame; 30: every
    other); the frames the detector takes are tracked too."""
    downsample: int | str = "auto"
    """Track on the camera image downsampled by this factor (1, 2 or 4; block means: a Bayer camera's 2x2 cells
    need no demosaicing); "auto": 2 where that leaves at least :data:`MIN_TRACKING_SIDE` pixels on the image's
    shorter side, else 1 (:meth:`factor_for`)."""
    window_px: int = 15
    """Side of the Lucas-Kanade window, in pixels of the tracking image (odd, 5..63)."""
    levels: int = 3
    """Pyramid levels above the tracking image (0..6)."""
    max_fb_px: float = 1.0
    """A keypoint tracked to the next frame and back that misses its start by more than this (camera pixels) is
    lost until the next detection."""
    lost_confidence: float = 0.5
    """A keypoint the tracker lost follows its person's median motion until the next detection, with the
    detector's confidence times this (0: it is dropped, confidence 0)."""
    half_life_s: float = 2.0
    """A tracked keypoint's confidence is the detector's, halved every this many seconds after the detection."""
    max_age_s: float = 2.0
    """Nobody is kept longer than this after the last detection of the camera (then the camera reports nobody
    until the detector finds people again)."""
    min_keypoints: int = 4
    """A person with fewer of their confidently detected keypoints still tracked is dropped."""
    history_s: float = 1.0
    """Tracked frames kept (their image pyramids, ~0.2 MB a frame at 272x480) to carry a detection from its frame to
    the newest one; a detection older than that is counted late and only re-seeds the tracking at the next
    detection."""
    thread: str = "capture"
    """Where tracking runs: "capture" (each camera's capture thread, right after the frame arrives) or "pool"
    (worker threads fed from the event loop)."""
    workers: int = 1
    """Tracking worker threads with ``thread = "pool"``."""

    def __post_init__(self) -> None:
        _choice("detector.tracking.thread", self.thread, THREADS)
        if not 1.0 <= self.rate_hz <= 1000.0:
            raise ConfigError(f"detector.tracking.rate_hz must be in [1, 1000], got {self.rate_hz}")
        if self.downsample not in (1, 2, 4, "auto"):
            raise ConfigError(f'detector.tracking.downsample must be 1, 2, 4 or "auto", got {self.downsample!r}')
        if not (5 <= self.window_px <= 63 and self.window_px % 2 == 1):
            raise ConfigError(f"detector.tracking.window_px must be odd, 5..63, got {self.window_px}")
        if not 0 <= self.levels <= 6:
            raise ConfigError(f"detector.tracking.levels must be 0..6, got {self.levels}")
        if not 0.0 < self.max_fb_px <= 100.0:
            raise ConfigError(f"detector.tracking.max_fb_px must be in (0, 100], got {self.max_fb_px}")
        if not 0.0 <= self.lost_confidence <= 1.0:
            raise ConfigError(f"detector.tracking.lost_confidence must be in [0, 1], got {self.lost_confidence}")
        for key in ("half_life_s", "max_age_s", "history_s"):
            if not 0.0 < getattr(self, key) <= 60.0:
                raise ConfigError(f"detector.tracking.{key} must be in (0, 60], got {getattr(self, key)}")
        if not 1 <= self.min_keypoints <= 1000 or not 1 <= self.workers <= 64:
            raise ConfigError("detector.tracking needs min_keypoints in 1..1000 and workers in 1..64")

    def factor_for(self, width: int, height: int) -> int:
        """The downsampling factor of the tracking image for a camera of ``width`` x ``height``."""
        if self.downsample != "auto":
            return int(self.downsample)
        return 2 if min(width, height) >= 2 * MIN_TRACKING_SIDE else 1


@dataclass(frozen=True)
class DetectorConfig:
    """The ``[detector]`` section."""

    providers: tuple[str, ...] = ("auto",)
    """onnxruntime execution providers in order of preference; "auto" = TensorRT, CUDA, OpenVINO, then CPU,
    whichever this onnxruntime build has; a provider named explicitly must be in the build."""
    precision: str = "auto"
    """Default model variant: "fp32", "int8" (the statically quantized model ``mocapd model fetch --int8``
    builds beside the FP32 one) or "auto" (INT8 on CPU providers, FP32 on GPU ones). Ignored for a model given by
    path (that file is used as it is)."""
    intra_op_threads: int = 0
    """Threads inside one inference (0 = this process's cores shared among the ``workers``: :meth:`sessions`)."""
    inter_op_threads: int = 1
    """Threads across graph branches (1 is best for these sequential networks)."""
    intra_op_spinning: bool = False
    """Let the intra-op threads spin-wait for work between operators (onnxruntime's default) instead of sleeping;
    off, because live the detector shares the cores with the tick and the capture."""
    workers: int | str = "auto"
    """Inference sessions in flight at once, each on its own worker thread (whole-frame workers, or the packed
    group's passes over disjoint cameras); "auto" = :meth:`sessions` from the cores."""
    batch: bool | Literal["auto"] = "auto"
    """Run the canvases of a packed pass in one inference (fixed-batch copies of the model, made at load):
    "auto" = on GPU providers (TensorRT, CUDA), where it pays; True/False = always/never."""
    fitted_inputs: bool | Literal["auto"] = "auto"
    """Detect a whole frame on the default model's export at the camera's aspect (384x640 for a 9:16 portrait
    camera: the same pixels on the same stride grid as the square letterbox, ~40 % less work): "auto" = where
    that export is in the model cache, True = it must be, False = never."""
    landmarks: str = "off"
    """BlazePose landmarks per person after YOLO (:mod:`mocapd.pipeline.landmarks`): "off" (YOLO's keypoints),
    "full" or "heavy" (that landmark model; the output becomes ``blazepose33``), "auto" (heavy, full or none per
    pass from the measured costs, :mod:`mocapd.pipeline.landmark_auto`; the output is ``blazepose33``)."""
    hands: str = "off"
    """Hand landmarks per person after the body's keypoints (:mod:`mocapd.pipeline.hand_landmarks`): "off", "on" (the
    output becomes ``<body>_hands``), "auto" (beside the body landmarks, per pass from the measured costs:
    :meth:`hands_decision`)."""
    model: ModelSpec = field(default_factory=ModelSpec)
    packing: PackingConfig = field(default_factory=PackingConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)

    def __post_init__(self) -> None:
        _choice("detector.precision", self.precision, PRECISIONS)
        _choice("detector.landmarks", self.landmarks, LANDMARKS)
        _choice("detector.hands", self.hands, HANDS)
        body = self.body_format
        if self.hands == "on" and body not in HAND_BODIES:
            raise ConfigError(
                f'detector.hands = "on" places its crops from the wrists and elbows of {list(HAND_BODIES)}; '
                f"the body keypoints are {body!r}"
            )
        if self.landmarks != "off" and self.model.keypoint_format != "coco17":
            raise ConfigError(
                f"detector.landmarks = {self.landmarks!r} places its crops from COCO-17 hips and shoulders; "
                f"detector.model.keypoint_format is {self.model.keypoint_format!r}"
            )
        if self.batch not in ("auto", True, False):
            raise ConfigError(f"detector.batch = {self.batch!r} is not one of ['auto', true, false]")
        if self.fitted_inputs not in ("auto", True, False):
            raise ConfigError(f"detector.fitted_inputs = {self.fitted_inputs!r} is not one of ['auto', true, false]")
        if self.workers != "auto" and (not isinstance(self.workers, int) or self.workers < 1):
            raise ConfigError(f'detector.workers must be >= 1 or "auto", got {self.workers!r}')
        if self.intra_op_threads < 0 or self.inter_op_threads < 0:
            raise ConfigError(
                f"detector threads must be >= 0, got intra={self.intra_op_threads} inter={self.inter_op_threads}"
            )

    @property
    def landmark_model(self) -> str | None:
        """The one landmark model that runs on every pass ("full", "heavy"), or None (none, or "auto": chosen per
        pass)."""
        return self.landmarks if self.landmarks in ("full", "heavy") else None

    @property
    def body_format(self) -> str:
        """The body's keypoint set: ``blazepose33`` with landmarks (fixed or "auto"), else the model's own."""
        return "blazepose33" if self.landmarks != "off" else self.model.keypoint_format

    def hands_decision(self) -> tuple[bool, str]:
        """Whether the hand landmark model runs, and why (``/status`` ``detector.hands``).

        ``"auto"`` runs the model only beside the body landmark front end (the hand crops are then placed from
        BlazePose's wrist, index and pinky; the forearm alone places them poorly), and there per pass from its
        measured cost, after the body landmarks' (:mod:`mocapd.pipeline.hand_auto`: off first when the budget is
        short; ``/status`` ``detector.hands.auto`` says the rate and why).
        """
        if self.hands == "off":
            return False, "detector.hands is off"
        if self.hands == "on":
            return True, f"detector.hands is on (crops from {self.body_format})"
        if self.landmarks == "off":
            return False, "auto: the body landmark front end does not run (detector.landmarks), so hands stay off"
        return True, (
            f"auto: beside the body landmarks ({self.landmarks}), per pass from the measured costs, off first "
            "when the budget is short (detector.hands.auto)"
        )

    @property
    def output_format(self) -> str:
        """The keypoint set the detector delivers: the body's (:attr:`body_format`), followed by both hands'
        (``<body>_hands``) when the hand model runs."""
        return f"{self.body_format}_hands" if self.hands_decision()[0] else self.body_format

    def sessions(self, cores: int, cameras: int) -> tuple[int, int]:
        """(sessions, intra-op threads of each) on a process with ``cores`` cores and ``cameras`` cameras.

        ``workers = "auto"``: one session per :data:`CORES_PER_SESSION` cores, at most one per camera (a packed pass
        holds its cameras; more sessions than cameras would wait) and at least one. ``intra_op_threads = 0``: the
        cores shared among the sessions (at least one thread each).
        """
        auto = max(1, min(max(1, cameras), cores // CORES_PER_SESSION))
        n = auto if self.workers == "auto" else int(self.workers)
        threads = self.intra_op_threads or max(1, cores // n)
        return n, threads

    def with_sessions(self, cores: int, cameras: int) -> DetectorConfig:
        """This config with ``workers`` and ``intra_op_threads`` made concrete (:meth:`sessions`)."""
        n, threads = self.sessions(cores, cameras)
        return dataclasses.replace(self, workers=n, intra_op_threads=threads)


def _choice(key: str, value: str, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ConfigError(f"{key} = {value!r} is not one of {list(allowed)}")

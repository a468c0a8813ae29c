"""The 2D pose detector on onnxruntime, and an asyncio-friendly wrapper that runs it in worker threads.

:class:`OnnxPoseDetector` owns one ``onnxruntime.InferenceSession``; it letterboxes an image (padding grey
114, like the Ultralytics training pipeline), runs the network and decodes the output with the pure functions
of :mod:`mocapd.core.pose2d`. onnxruntime releases the GIL while it computes, so a small thread pool
(:class:`AsyncPoseDetector`) keeps the event loop free without pickling images across processes.
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import queue
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Literal, TypeVar

import cv2
import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray

from mocapd.core.keypoints import KeypointFormat, keypoint_format
from mocapd.core.pose2d import (
    Letterbox,
    PoseDetections,
    decode_yolo_pose,
    detections_to_source,
    fitted_input_size,
    letterbox_geometry,
)
from mocapd.errors import InputError, ModelError
from mocapd.io.model_batch import fixed_batch, load_model
from mocapd.io.model_quant import model_path
from mocapd.io.native_logs import quiet_session_options
from mocapd.io.os_threads import worker_thread_setup
from mocapd.pipeline.detector_config import DetectorConfig, ModelSpec

Image = NDArray[np.uint8]
R = TypeVar("R")
log = logging.getLogger(__name__)

# Preference order of "auto": the fastest provider this onnxruntime build offers comes first.
_AUTO_PROVIDERS = (
    "TensorrtExecutionProvider",
    "CUDAExecutionProvider",
    "OpenVINOExecutionProvider",
    "CPUExecutionProvider",
)
# Providers whose device waits on kernel launches at batch 1: "auto" batches the canvases of a pass there.
_GPU_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider")
_OPENVINO = "OpenVINOExecutionProvider"
WARM_BATCHES = 4  # batch sizes whose sessions a batched detector makes and runs once when it loads: 1..this
MAX_BATCH = 8  # canvases per call at most (a pass has 1-3 on the demo rig; bounds the device memory of one call)
# onnxruntime's load errors derive from Exception directly, not from RuntimeError.
_ORT_LOAD_ERRORS: tuple[type[Exception], ...] = tuple(
    getattr(ort.capi.onnxruntime_pybind11_state, name)
    for name in ("Fail", "InvalidArgument", "InvalidGraph", "InvalidProtobuf", "NoSuchFile", "NotImplemented")
    if hasattr(ort.capi.onnxruntime_pybind11_state, name)
)
_LOAD_ERRORS: tuple[type[Exception], ...] = (RuntimeError, ValueError, *_ORT_LOAD_ERRORS)
_SHORT_NAMES = {
    "tensorrt": "TensorrtExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "openvino": "OpenVINOExecutionProvider",
    "cpu": "CPUExecutionProvider",
}
# Which install extra of mocapd brings a provider (onnxruntime-gpu, onnxruntime-openvino replace onnxruntime).
_EXTRA = {
    "TensorrtExecutionProvider": "pip install mocapd[gpu] (onnxruntime-gpu, with TensorRT installed)",
    "CUDAExecutionProvider": "pip install mocapd[gpu] (onnxruntime-gpu)",
    "OpenVINOExecutionProvider": "pip install mocapd[openvino] (onnxruntime-openvino)",
}


def resolve_providers(requested: Sequence[str], available: Sequence[str] | None = None) -> list[str]:
    """Execution provider names for onnxruntime from config names ("auto", "cuda", "openvino", "cpu", full names).

    "auto" takes TensorRT, CUDA, OpenVINO and CPU in that order, as far as this onnxruntime build has them.
    A provider named explicitly must be in the build: a user who asked for "cuda" and silently got the CPU
    would measure the wrong thing. The CPU provider is always appended last (onnxruntime runs nodes another
    provider cannot take there).

    Parameters
    ----------
    requested : sequence of str
        ``[detector] providers``.
    available : sequence of str, optional
        The build's providers (default ``onnxruntime.get_available_providers()``).

    Raises
    ------
    ModelError
        A provider named explicitly is not in this onnxruntime build (the message names the extra to install).
    """
    have = set(ort.get_available_providers() if available is None else available)
    out: list[str] = []
    for name in requested:
        if name.lower() == "auto":
            names: tuple[str, ...] = tuple(p for p in _AUTO_PROVIDERS if p in have)
        else:
            full = _SHORT_NAMES.get(name.lower(), name)
            if full not in have:
                hint = _EXTRA.get(full, "install an onnxruntime build that has it")
                raise ModelError(
                    f"detector.providers: {name!r} ({full}) is not in this onnxruntime build "
                    f"(it has {sorted(have)}); {hint}"
                )
            names = (full,)
        out.extend(p for p in names if p not in out)
    if "CPUExecutionProvider" not in out:
        out.append("CPUExecutionProvider")
    return out


def _check_session_providers(requested: Sequence[str], resolved: Sequence[str], used: Sequence[str]) -> None:
    """A provider named explicitly must be one the session runs: onnxruntime falls back on its own (TensorRT to
    CUDA when the TensorRT libraries are missing, any provider to the CPU when its device cannot start) and only
    prints that. "auto" may fall back: it asks for the best there is.

    Raises
    ------
    ModelError
        An explicitly named provider is not among the session's providers.
    """
    explicit = {_SHORT_NAMES.get(n.lower(), n) for n in requested if n.lower() != "auto"}
    missing = [p for p in resolved if p in explicit and p not in used]
    if missing:
        raise ModelError(
            f"detector.providers: onnxruntime could not start {', '.join(missing)} (its message is above; "
            f"the session fell back to {list(used)}): check the GPU driver and the CUDA/cuDNN/TensorRT libraries "
            "(docs/detection.md), or name the provider that runs"
        )


def provider_options(providers: Sequence[str], precision: str, intra_op_threads: int = 0) -> list[dict[str, str]]:
    """onnxruntime's per-provider options (parallel to ``providers``) for a detector of ``precision``.

    OpenVINO gets its arithmetic precision set outright, BF16 for "bf16" and FP32 otherwise: on CPUs with AMX
    its own default is BF16, so "fp32" there would silently not be FP32 (and the float head of the INT8 model
    would run in BF16 too). It also gets ``intra_op_threads`` (when > 0) as its thread count, which it does not
    take from the session options.
    """
    out: list[dict[str, str]] = []
    for p in providers:
        opts: dict[str, str] = {}
        if p == _OPENVINO:
            hint = "bf16" if precision == "bf16" else "f32"
            opts["load_config"] = json.dumps({"CPU": {"INFERENCE_PRECISION_HINT": hint}})
            if intra_op_threads > 0:
                opts["num_of_threads"] = str(intra_op_threads)
        out.append(opts)
    return out


def check_bf16(provider: str, flags: Sequence[str]) -> None:
    """``precision = "bf16"`` needs OpenVINO first (no other provider of these builds computes the FP32 model in
    BF16 on a CPU) and a CPU with BF16 instructions (elsewhere OpenVINO would emulate them, slower than FP32).

    Raises
    ------
    ModelError
        Either is missing.
    """
    if provider != _OPENVINO:
        raise ModelError(
            f'detector.precision = "bf16" runs on OpenVINO only (providers = ["openvino"], pip install '
            f'mocapd[openvino]); the first provider here is {provider}: use "auto", "fp32" or "int8"'
        )
    if not flags:
        raise ModelError(
            'detector.precision = "bf16" needs a CPU with BF16 instructions (avx512_bf16 or amx_bf16 in '
            '/proc/cpuinfo); this one has neither: use "auto", "fp32" or "int8"'
        )


def bf16_flags(cpuinfo: str) -> list[str]:
    """The BF16 arithmetic flags (``avx512_bf16``, ``amx_bf16``) of the first processor in ``/proc/cpuinfo`` text."""
    for line in cpuinfo.splitlines():
        if line.startswith("flags"):
            return [f for f in line.partition(":")[2].split() if f in ("avx512_bf16", "amx_bf16")]
    return []


@functools.cache
def cpu_bf16_flags() -> tuple[str, ...]:
    """This machine's BF16 flags (none where ``/proc/cpuinfo`` is missing: not Linux)."""
    try:
        return tuple(bf16_flags(Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace")))
    except OSError:
        return ()


def auto_precision(provider: str, int8: Path, bf16: Sequence[str] = ()) -> tuple[str, str]:
    """``[detector] precision = "auto"``: the precision to load on ``provider`` (the first the session runs) and
    why, given the INT8 model's path and the CPU's BF16 flags (:func:`cpu_bf16_flags`): BF16 on OpenVINO where
    the CPU computes in BF16 (on the 2-core laptop 1.7x the speed of FP32 there and 1.3x that of INT8, keypoints
    0.6 px median from FP32's against INT8's 2.2), INT8 on the other CPU providers (1.2-1.7x FP32, 2.3 px), FP32
    on GPU ones (the INT8 QDQ model ran slower than FP32 on CUDA, H100) or where the INT8 file is missing (said in
    the log)."""
    if provider in _GPU_PROVIDERS:
        return "fp32", f"auto: FP32 on {provider} (INT8 ran slower than FP32 on CUDA)"
    if provider == _OPENVINO and bf16:
        return "bf16", f"auto: BF16 on {provider} (this CPU has {', '.join(bf16)}; faster than INT8 and closer to FP32)"
    if not int8.is_file():
        log.warning("detector precision auto: %s not built (`mocapd model fetch --int8`), running FP32", int8.name)
        return "fp32", f"auto: {int8.name} not built (`mocapd model fetch --int8`)"
    return "int8", f"auto: INT8 on {provider} (faster than FP32 there, keypoints 2.3 px median from FP32's)"


def letterbox_image(image: Image, lb: Letterbox, dst_w: int, dst_h: int, pad_value: int) -> Image:
    """Resize ``image (H, W, 3)`` by ``lb`` and pad to ``(dst_h, dst_w, 3)`` with grey ``pad_value``."""
    canvas = np.full((dst_h, dst_w, 3), pad_value, dtype=np.uint8)
    resized = cv2.resize(image, (lb.new_w, lb.new_h), interpolation=cv2.INTER_LINEAR)
    x, y = int(lb.pad_x), int(lb.pad_y)
    canvas[y : y + lb.new_h, x : x + lb.new_w] = resized
    return canvas


class OnnxPoseDetector:
    """One onnxruntime session of a pose model described by a :class:`ModelSpec`.

    Parameters
    ----------
    spec : ModelSpec
        Model file, input size, layout and decoding.
    providers : sequence of str
        Config provider names (see :func:`resolve_providers`).
    precision : {"auto", "fp32", "int8", "bf16"}
        Which default model file to load when ``spec.path`` is empty (an explicit path is used as it is), and in
        what arithmetic: "bf16" runs the FP32 file in BF16 on OpenVINO (a CPU with ``avx512_bf16`` or
        ``amx_bf16`` only, :func:`check_bf16`). "auto" (:func:`auto_precision`): BF16 on OpenVINO where the CPU
        has it, INT8 on the other CPU providers, where it measured faster than FP32, FP32 on GPU ones (TensorRT,
        CUDA), where the INT8 QDQ model ran slower; FP32 (said once in the log and in :meth:`describe`) where the
        INT8 file is missing.
    intra_op_threads, inter_op_threads : int
        onnxruntime thread counts (0 = its default).
    intra_op_spinning : bool
        Let onnxruntime's intra-op threads spin-wait for work between operators (its own default) instead of
        sleeping: faster alone on an idle machine, slower live where the detector shares the cores.
    batch : bool or "auto"
        Run several canvases per inference (:meth:`run_canvases`) through fixed-batch copies of the model
        (:mod:`mocapd.io.model_batch`); "auto": when the first provider is a GPU one (TensorRT, CUDA).
    fitted_inputs : bool or "auto"
        Run on the default model's exports at smaller inputs where the picture allows: :meth:`detect` a whole
        frame at the camera's aspect (:func:`~mocapd.core.pose2d.fitted_input_size`: 384×640 for a portrait 9:16
        camera) instead of letterboxed into the square input, and :meth:`run_canvases` a packed canvas cropped to
        its tiles (its top-left 384×640 or 640×384) when they fit: the same pixels on the same stride grid, so
        nearly the same keypoints for ~40 % less work. "auto": where that export is in the model cache (the set-up
        builds the 9:16 and 16:9 ones), else the model's own input, said once in the log and in :meth:`describe`;
        True: a camera's whole-frame export must be there; False: never. A model given by path is used as it is
        ("auto"; True refuses it). Not with ``batch`` (a batch runs one size).

    Raises
    ------
    ModelError
        The file is missing, is not a loadable ONNX model, its input/output shapes contradict ``spec``, a
        provider named explicitly is not in this onnxruntime build or did not start, a batched detector's
        model cannot be batched, or ``fitted_inputs=True`` meets a camera whose fitted export is missing.
    """

    def __init__(
        self,
        spec: ModelSpec,
        *,
        providers: Sequence[str] = ("auto",),
        precision: str = "fp32",
        intra_op_threads: int = 0,
        inter_op_threads: int = 1,
        batch: bool | Literal["auto"] = "auto",
        fitted_inputs: bool | Literal["auto"] = "auto",
        intra_op_spinning: bool = False,
    ) -> None:
        self.spec = spec
        self.format: KeypointFormat = keypoint_format(spec.keypoint_format)
        self.providers = resolve_providers(providers)
        self.precision_note = ""
        if precision == "auto" and spec.path:
            precision, self.precision_note = "fp32", "detector.model.path is set: that model runs as it is"
        elif precision == "auto":
            int8 = model_path(spec.input_width, spec.input_height, "int8")
            precision, self.precision_note = auto_precision(self.providers[0], int8, cpu_bf16_flags())
        elif precision == "bf16":
            check_bf16(self.providers[0], cpu_bf16_flags())
        # BF16 is arithmetic, not a file: the FP32 model runs in it (model_path gives FP32's file).
        path = Path(spec.path) if spec.path else model_path(spec.input_width, spec.input_height, precision)
        if path.exists() and not path.is_file():  # a FIFO, a device, a folder: not "not found" (issue 45)
            raise ModelError(f"detector model {path}: not a regular file; give the ONNX model file")
        if not path.is_file():
            fetch = "mocapd model fetch" + (" --int8" if precision == "int8" and not spec.path else "")
            raise ModelError(f"detector model {path} not found; run `{fetch}` (or set detector.model.path)")
        self.precision = precision
        self.path = path
        opts = quiet_session_options(ort.SessionOptions())  # a failing run raises; its caller says it, rate-limited
        opts.intra_op_num_threads = intra_op_threads
        opts.inter_op_num_threads = inter_op_threads
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        # onnxruntime's intra-op threads spin between operators waiting for work by default. Beside the 60 Hz
        # tick and the capture threads that burns the cores they need and stalls the detector's own parallel
        # sections when one of its threads is preempted: on the 2-core laptop the live camera demo's e2e p50 went
        # from 563-599 ms spinning to 403-491 ms not, three runs each (docs/daemon.md, "Issue 15: detector threads
        # that sleep").
        opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if intra_op_spinning else "0")
        if batch not in ("auto", True, False):
            raise ModelError(f'detector.batch = {batch!r}; allowed: "auto", true, false')
        if fitted_inputs not in ("auto", True, False):
            raise ModelError(f'detector.fitted_inputs = {fitted_inputs!r}; allowed: "auto", true, false')
        if fitted_inputs is True and spec.path:
            raise ModelError(
                "detector.fitted_inputs = true needs the default model (detector.model.path is set: a model "
                'given by path has no exports at other sizes); use "auto" or false'
            )
        self.fitted_inputs = fitted_inputs
        # "auto": batch on GPU providers, where one canvas per call leaves the device waiting on launches; on a
        # CPU a batch costs what its canvases cost one by one (mocapd/io/model_batch.py).
        self.batched: bool = self.providers[0] in _GPU_PROVIDERS if batch == "auto" else bool(batch)
        self._opts = opts
        self._provider_options = provider_options(self.providers, precision, intra_op_threads)
        self.session = self._new_session(str(path), str(path))
        _check_session_providers(providers, self.providers, self.session.get_providers())
        # The batch-1 model, checked for the rewrite now; a session per batch size, made when first needed.
        self._model = load_model(path) if self.batched else None
        self._batch_sessions: dict[int, ort.InferenceSession] = {1: self.session}
        self.intra_op_threads = intra_op_threads
        self._check_shapes()
        inp = self.session.get_inputs()[0]
        self._input_name: str = inp.name
        self._input_dtype = np.float16 if "float16" in inp.type else np.float32
        self._scale = (np.float32(spec.pixel_scale) / np.asarray(spec.std, dtype=np.float32)).astype(np.float32)
        self._mean = np.asarray(spec.mean, dtype=np.float32)
        # OpenCV's blob conversion does resize-free (x - mean) * scale, channel swap and HWC -> CHW in one C++
        # pass: 1.5 ms against numpy's 6.4 ms per 640x640 canvas on the 2-core laptop, 1.8 vs 12 ms on the H100
        # host, where it was most of a detection's time. It takes one scale for all channels.
        self._blob = spec.layout == "NCHW" and bool(np.all(self._scale == self._scale[0]))
        w, h = self.input_size
        self._blank = np.full((h, w, 3), spec.pad_value, np.uint8)
        self.inference_ns = 0  # time inside onnxruntime's run, all sessions (a pass's rest is mocapd's own work)
        # Whole frames at the camera's aspect: per source (w, h), the fitted input size and its session, or None
        # where the model's own input runs them; per fitted size, why it is not used (for describe()).
        self._fitted: dict[tuple[int, int], tuple[int, int, ort.InferenceSession] | None] = {}
        self._fitted_by_size: dict[tuple[int, int], ort.InferenceSession] = {}
        self.unfitted: dict[str, str] = {}
        self.cropped_canvases = 0  # canvases run cropped to their tiles (run_canvases)
        # One RunOptions for every run: terminate() sets its flag, and a run in flight stops at its next node
        # (a CPU inference takes up to a second; a daemon stopping must not wait for it).
        self._run_options = ort.RunOptions()
        if self.batched:
            # The batch sizes a packed pass meets (1-3 canvases on a 4-camera rig), made and run once now: a
            # session's first run on a GPU tunes its kernels. The camera benchmark's 20-pass detector-alone packed
            # rate on the H100 was 28 camera-frames/s with these sessions made inside its passes, 215 with them
            # made here (docs/daemon.md, "Issue 15: on a GPU"). Larger batches are made when first met.
            for k in range(1, WARM_BATCHES + 1):
                self._session_for(k).run(None, {self._input_name: self.to_batch([self._blank] * k)})
        # Packed canvases cropped to their tiles: the exports at a smaller input that the cache holds, loaded now.
        self.crop_sizes: list[tuple[int, int]] = self._crop_sizes()

    def describe(self) -> dict[str, object]:
        """What runs, for ``/status``: the providers the session really uses (after "auto"), precision, model."""
        return {
            "providers": list(self.session.get_providers()),
            "precision": self.precision,
            "precision_note": self.precision_note,
            "batched_canvases": self.batched,
            "model": str(self.path),
            "input_size": list(self.input_size),
            # Whole frames by camera size: the input they run at ("384x640"), and why not fitted where not.
            "whole_frame_inputs": {
                f"{sw}x{sh}": f"{f[0]}x{f[1]}" if f is not None else "x".join(map(str, self.input_size))
                for (sw, sh), f in self._fitted.items()
            },
            "unfitted": dict(self.unfitted),
            "canvas_crops": [f"{w}x{h}" for w, h in self.crop_sizes],
        }

    def terminate(self) -> None:
        """Abort the inference in flight (it raises in its thread) and refuse further runs: at shutdown."""
        self._run_options.terminate = True

    @staticmethod
    def from_config(cfg: DetectorConfig, image_sizes: Sequence[tuple[int, int]] = ()) -> OnnxPoseDetector:
        """A detector built from the ``[detector]`` section, with the whole-frame inputs of cameras of
        ``image_sizes`` (width, height) made now (:meth:`fit_to`)."""
        det = OnnxPoseDetector(
            cfg.model,
            providers=cfg.providers,
            precision=cfg.precision,
            intra_op_threads=cfg.intra_op_threads,
            inter_op_threads=cfg.inter_op_threads,
            batch=cfg.batch,
            fitted_inputs=cfg.fitted_inputs,
            intra_op_spinning=cfg.intra_op_spinning,
        )
        for w, h in dict.fromkeys(image_sizes):
            det.fit_to(w, h)
        return det

    def _check_shapes(self) -> None:
        spec = self.spec
        shape = list(self.session.get_inputs()[0].shape)
        if len(shape) != 4:
            raise ModelError(f"{spec.path}: expected a 4-D image input, got shape {shape}")
        hw = shape[2:4] if spec.layout == "NCHW" else shape[1:3]
        for got, want, what in zip(hw, (spec.input_height, spec.input_width), ("height", "width"), strict=True):
            if isinstance(got, int) and got != want:
                raise ModelError(f"{spec.path}: input {what} is {got} but detector.model says {want}")
        out = list(self.session.get_outputs()[0].shape)
        rows = 5 + 3 * self.format.n_keypoints
        if len(out) != 3 or (isinstance(out[1], int) and out[1] != rows):
            raise ModelError(
                f"{spec.path}: output shape {out} does not match {spec.decoder} with "
                f"{self.format.n_keypoints} keypoints ({spec.keypoint_format}): expected (1, {rows}, N)"
            )

    @property
    def input_size(self) -> tuple[int, int]:
        """(width, height) of the model input."""
        return self.spec.input_width, self.spec.input_height

    def to_tensor(self, canvas: Image) -> NDArray[np.float32]:
        """A model-sized BGR ``(H, W, 3)`` uint8 image → the network input tensor."""
        return self.to_batch([canvas])

    def to_batch(self, canvases: Sequence[Image], size: tuple[int, int] | None = None) -> NDArray[np.float32]:
        """Model-sized BGR ``(H, W, 3)`` uint8 images → one network input tensor, shape ``(len(canvases), ...)``
        (``size``: the (width, height) of a fitted export's input instead of the model's)."""
        w, h = size or self.input_size
        for canvas in canvases:
            if canvas.shape != (h, w, 3) or canvas.dtype != np.uint8:
                raise InputError(f"detector canvas must be uint8 ({h}, {w}, 3), got {canvas.dtype} {canvas.shape}")
        if self._blob:
            x = cv2.dnn.blobFromImages(list(canvases), float(self._scale[0]), mean=tuple(float(m) for m in self._mean),
                                       swapRB=self.spec.channel_order == "RGB", crop=False,
                                       ddepth=cv2.CV_32F)  # fmt: skip
        else:
            x = self.numpy_batch(canvases)
        return np.ascontiguousarray(x).astype(self._input_dtype, copy=False)

    def numpy_batch(self, canvases: Sequence[Image]) -> NDArray[np.float32]:
        """The per-channel numpy conversion of :meth:`to_batch` (models with per-channel scales or NHWC input; the
        reference the blob is tested and timed against). Not validated, maybe not contiguous."""
        img = np.stack(canvases)
        x = (img[..., ::-1] if self.spec.channel_order == "RGB" else img).astype(np.float32)
        x = (x - self._mean) * self._scale
        return x.transpose(0, 3, 1, 2) if self.spec.layout == "NCHW" else x

    def _decode(self, out: NDArray[np.float32]) -> PoseDetections:
        spec = self.spec
        return decode_yolo_pose(
            out,
            self.format.n_keypoints,
            score_threshold=spec.score_threshold,
            iou_threshold=spec.iou_threshold,
            max_people=spec.max_people,
        )

    def _infer(self, session: ort.InferenceSession, x: NDArray[np.float32]) -> NDArray[np.float32]:
        t0 = time.perf_counter_ns()
        (out,) = session.run(None, {self._input_name: x}, self._run_options)[:1]
        self.inference_ns += time.perf_counter_ns() - t0
        return np.asarray(out)

    def run_canvas(self, canvas: Image, extent: tuple[int, int] | None = None) -> PoseDetections:
        """Detect people on a model-sized image; coordinates in that image's pixels.

        ``extent``: the (width, height) of the canvas's top-left part that holds anything; the canvas then runs
        cropped to the smallest of :attr:`crop_sizes` that holds it (the origin, so the pixels and their stride
        grid, unchanged), or whole where none does.
        """
        size = self._crop_for(extent) if extent is not None else None
        if size is None:
            return self._decode(self._infer(self.session, self.to_tensor(canvas)))
        w, h = size
        self.cropped_canvases += 1
        x = self.to_batch([np.ascontiguousarray(canvas[:h, :w])], size)
        return self._decode(self._infer(self._fitted_by_size[size], x))

    def run_canvases(
        self, canvases: Sequence[Image], extents: Sequence[tuple[int, int]] | None = None
    ) -> list[PoseDetections]:
        """:meth:`run_canvas` of each canvas (with its ``extents`` entry): in calls of up to :data:`MAX_BATCH`
        canvases when the session is batched (uncropped), else one call each."""
        if not self.batched or len(canvases) < 2:
            ext = list(extents) if extents is not None else [None] * len(canvases)
            return [self.run_canvas(c, e) for c, e in zip(canvases, ext, strict=True)]
        found: list[PoseDetections] = []
        for i in range(0, len(canvases), MAX_BATCH):
            x = self.to_batch(canvases[i : i + MAX_BATCH])
            out = self._infer(self._session_for(len(x)), x)
            found.extend(self._decode(out[k : k + 1]) for k in range(len(x)))
        return found

    def _session_for(self, k: int) -> ort.InferenceSession:
        """The session of batch size ``k`` (made the first time it is needed)."""
        session = self._batch_sessions.get(k)
        if session is None:
            assert self._model is not None
            data = fixed_batch(self._model, k).SerializeToString()
            session = self._new_session(data, f"the batch-{k} copy of {self.path}")
            self._batch_sessions[k] = session
        return session

    def detect(self, image: Image) -> PoseDetections:
        """Detect people in a BGR image of any size (letterboxed to the model, or to its export at the image's
        aspect, see ``fitted_inputs``); source-image pixels."""
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise InputError(f"detector input must be a uint8 (H, W, 3) BGR image, got {image.dtype} {image.shape}")
        fitted = self.fit_to(image.shape[1], image.shape[0])
        w, h, session = fitted if fitted is not None else (*self.input_size, self.session)
        lb = letterbox_geometry(image.shape[1], image.shape[0], w, h)
        canvas = letterbox_image(image, lb, w, h, self.spec.pad_value)
        out = self._infer(session, self.to_batch([canvas], (w, h)))
        return detections_to_source(self._decode(out), lb)

    def fit_to(self, src_w: int, src_h: int) -> tuple[int, int, ort.InferenceSession] | None:
        """The fitted input (width, height, session) that whole ``src_w × src_h`` frames run at, or None for the
        model's own input. Its session is made (and run once) the first time a size is met; the daemon calls this
        for its cameras when it loads, so that a missing export is said at start and a GPU's kernel tuning does
        not land in a live pass.

        Raises
        ------
        ModelError
            ``fitted_inputs`` is True and the fitted export is missing or does not load.
        """
        key = (src_w, src_h)
        if key in self._fitted:
            return self._fitted[key]
        fw, fh = fitted_input_size(src_w, src_h, *self.input_size)
        found = None
        if self.fitted_inputs is not False and (fw, fh) != self.input_size:
            session = self._fitted_session(fw, fh)
            found = (fw, fh, session) if session is not None else None
        self._fitted[key] = found
        return found

    def _crop_sizes(self) -> list[tuple[int, int]]:
        """The smaller inputs (the full width or height kept) whose exports are in the cache, their sessions made,
        smallest first; none for a batched detector (a batch runs one size) or a model given by path."""
        if self.fitted_inputs is False or self.spec.path or self.batched:
            return []
        cw, ch = self.input_size
        sizes = [(w, ch) for w in range(cw - 32, 0, -32)] + [(cw, h) for h in range(ch - 32, 0, -32)]
        found = [s for s in sizes if model_path(*s, self.precision).is_file()]
        for w, h in found:
            self._fitted_session(w, h)
        return sorted(found, key=lambda s: s[0] * s[1])

    def input_for_extent(self, extent: tuple[int, int]) -> tuple[int, int]:
        """The input (width, height) a canvas whose tiles cover its top-left ``extent`` runs at (:meth:`run_canvas`):
        the smallest crop export that holds it, else the model's input; batched: always the model's input."""
        crop = None if self.batched else self._crop_for(extent)
        return crop if crop is not None else self.input_size

    def whole_frame_input(self, src_w: int, src_h: int) -> tuple[int, int]:
        """The input (width, height) a whole ``src_w x src_h`` frame runs at (:meth:`detect`, :meth:`fit_to`)."""
        fitted = self.fit_to(src_w, src_h)
        return (fitted[0], fitted[1]) if fitted is not None else self.input_size

    def _crop_for(self, extent: tuple[int, int]) -> tuple[int, int] | None:
        return next((s for s in self.crop_sizes if s[0] >= extent[0] and s[1] >= extent[1]), None)

    def _new_session(self, model: str | bytes, what: str) -> ort.InferenceSession:
        """A session of ``model`` (a path or serialized bytes) with this detector's options and providers."""
        try:
            return ort.InferenceSession(
                model, sess_options=self._opts, providers=self.providers, provider_options=self._provider_options
            )
        except _LOAD_ERRORS as exc:
            raise ModelError(f"onnxruntime cannot load {what}: {exc}") from exc

    def _fitted_session(self, fw: int, fh: int) -> ort.InferenceSession | None:
        session = self._fitted_by_size.get((fw, fh))
        if session is not None:
            return session
        size = f"{fw}x{fh}"
        if self.spec.path:
            self.unfitted[size] = "detector.model.path is set: that model runs whole frames at its own size"
            return None
        path = model_path(fw, fh, self.precision)
        if not path.is_file():
            fetch = f"mocapd model fetch --size {size}" + (" --int8" if self.precision == "int8" else "")
            if self.fitted_inputs is True:
                raise ModelError(f"detector model {path} not found (detector.fitted_inputs = true); run `{fetch}`")
            if size not in self.unfitted:
                w, h = self.input_size
                log.warning("whole frames run letterboxed at %dx%d: `%s` builds %s, which runs them in ~60 %% of "
                            "the time", w, h, fetch, path.name)  # fmt: skip
            self.unfitted[size] = f"{path.name} not built (`{fetch}`)"
            return None
        session = self._new_session(str(path), str(path))
        shape = list(session.get_inputs()[0].shape)
        want = [1, 3, fh, fw] if self.spec.layout == "NCHW" else [1, fh, fw, 3]
        if shape != want:
            raise ModelError(f"{path}: input shape {shape}, expected {want} (rebuild it: mocapd model fetch --force)")
        blank = np.full((fh, fw, 3), self.spec.pad_value, np.uint8)
        session.run(None, {self._input_name: self.to_batch([blank], (fw, fh))}, self._run_options)
        self._fitted_by_size[(fw, fh)] = session
        return session


class AsyncPoseDetector:
    """Runs detection in worker threads so that the asyncio event loop never blocks on inference.

    Each worker thread has its own :class:`OnnxPoseDetector` (sessions are not shared between concurrent
    runs); ``await detect(image)`` hands the image to a free one.
    """

    def __init__(self, cfg: DetectorConfig) -> None:
        self._pool: queue.SimpleQueue[OnnxPoseDetector] = queue.SimpleQueue()
        workers = cfg.workers if isinstance(cfg.workers, int) else 1
        for _ in range(workers):
            self._pool.put(OnnxPoseDetector.from_config(cfg))
        # Named at the OS level too, as the daemon's detector workers are (detector_pool.detector_executor).
        self._executor = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="mocapd-detect",
                                            initializer=worker_thread_setup, initargs=("mocapd-detect", 0))  # fmt: skip

    def _with_detector(self, fn: Callable[[OnnxPoseDetector], R]) -> R:
        det = self._pool.get()
        try:
            return fn(det)
        finally:
            self._pool.put(det)

    async def call(self, fn: Callable[[OnnxPoseDetector], R]) -> R:
        """Run ``fn(detector)`` on a worker thread with a free detector (e.g. a packed detection)."""
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._executor, self._with_detector, fn)

    async def detect(self, image: Image) -> PoseDetections:
        """Detect people in ``image`` (BGR) on a worker thread; source-image pixels."""
        return await self.call(lambda det: det.detect(image))

    def close(self) -> None:
        """Wait for running detections and stop the workers."""
        self._executor.shutdown(wait=True)

    async def __aenter__(self) -> AsyncPoseDetector:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await asyncio.get_running_loop().run_in_executor(None, self.close)

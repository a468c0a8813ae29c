"""Where one detection's time goes, per execution provider, and what several canvases per call cost.

Prints one JSON object. For each provider (``--providers``, config names) and source image size (the demo videos
at half size, 544x960, as the camera demo serves them, and at full size), over ``--reps`` frames of the Pose2Sim
multi-person demo: the median milliseconds of the letterbox, the input conversion (``to_tensor_numpy``: the
per-channel numpy path mocapd used before; ``to_tensor``: what the detector uses now, OpenCV's one-pass blob where
the model allows it), ``session.run`` at batch 1, the decoding, and a whole ``detect()``; then ``session.run`` of
fixed-batch copies of the model (:func:`mocapd.io.model_batch.fixed_batch`) for 2, 4 and 8 canvases, per call and
per canvas, with the largest difference of their outputs from batch-1 runs.

    .venv/bin/python tools/profile_detector.py --providers cpu --reps 30
"""

from __future__ import annotations

import argparse
import json
import os
import time
from statistics import median
from typing import Any

import cv2
import numpy as np
import onnxruntime as ort

from mocapd.core.pose2d import letterbox_geometry
from mocapd.io.model_batch import fixed_batch, load_model
from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.pipeline.detector import Image, OnnxPoseDetector, letterbox_image
from mocapd.pipeline.detector_config import ModelSpec


def demo_frames(per_camera: int, scale: float) -> list[Image]:
    """``per_camera`` frames of each multi-person demo camera, resized by ``scale``, BGR."""
    out: list[Image] = []
    for cam in CAMERAS:
        cap = cv2.VideoCapture(str(demo_video("Demo_MultiPerson", cam)))
        for _ in range(per_camera):
            ok, img = cap.read()
            if not ok:
                break
            if scale != 1.0:
                img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            out.append(np.asarray(img, dtype=np.uint8))
        cap.release()
    return out


def profile(provider: str, images: list[Image], reps: int, warm: int = 5) -> dict[str, Any]:
    """Stage medians (ms) of ``reps`` detections on ``images`` (cycled), then the batch runs."""
    det = OnnxPoseDetector(ModelSpec(), providers=[provider], batch=False)
    w, h = det.input_size
    spec = det.spec
    stages: dict[str, list[float]] = {k: [] for k in ("letterbox", "to_tensor_numpy", "to_tensor", "run",
                                                      "decode", "detect")}  # fmt: skip
    for i in range(reps + warm):
        img = images[i % len(images)]
        t0 = time.perf_counter()
        lb = letterbox_geometry(img.shape[1], img.shape[0], w, h)
        canvas = letterbox_image(img, lb, w, h, spec.pad_value)
        t1 = time.perf_counter()
        np.ascontiguousarray(det.numpy_batch([canvas]))  # what the detector did before the blob
        t2 = time.perf_counter()
        x = det.to_tensor(canvas)
        t3 = time.perf_counter()
        (out,) = det.session.run(None, {det._input_name: x})[:1]
        t4 = time.perf_counter()
        det._decode(np.asarray(out))
        t5 = time.perf_counter()
        det.detect(img)
        t6 = time.perf_counter()
        if i >= warm:
            for name, (a, b) in zip(stages, ((t0, t1), (t1, t2), (t2, t3), (t3, t4), (t4, t5), (t5, t6)), strict=True):
                stages[name].append(1e3 * (b - a))
    res: dict[str, Any] = {k: round(median(v), 2) for k, v in stages.items()}
    res["providers"] = det.session.get_providers()
    model = load_model(det.path)
    canvases = [det.to_tensor(letterbox_image(im, letterbox_geometry(im.shape[1], im.shape[0], w, h), w, h, 114))
                for im in images[:8]]  # fmt: skip
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    for k in (2, 4, 8):
        session = ort.InferenceSession(fixed_batch(model, k).SerializeToString(), sess_options=opts,
                                       providers=det.session.get_providers())  # fmt: skip
        xk = np.concatenate([canvases[j % len(canvases)] for j in range(k)])
        for _ in range(warm):
            session.run(None, {det._input_name: xk})
        times: list[float] = []
        for _ in range(max(10, reps // k)):
            t0 = time.perf_counter()
            session.run(None, {det._input_name: xk})
            times.append(1e3 * (time.perf_counter() - t0))
        (batched,) = session.run(None, {det._input_name: xk})[:1]
        diff = max(float(np.abs(batched[j] - det.session.run(None, {det._input_name: xk[j : j + 1]})[0][0]).max())
                   for j in range(k))  # fmt: skip
        res[f"run_batch{k}_ms"] = round(median(times), 2)
        res[f"run_batch{k}_per_canvas_ms"] = round(median(times) / k, 2)
        res[f"batch{k}_max_abs_output_diff"] = diff
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--providers", nargs="+", default=["cpu"], help="config provider names (cpu, cuda, openvino)")
    ap.add_argument("--reps", type=int, default=30, help="timed detections per provider and size")
    args = ap.parse_args(argv)
    report: dict[str, Any] = {"cpus": os.cpu_count(), "onnxruntime": ort.__version__, "opencv": cv2.__version__}
    for scale in (0.5, 1.0):
        images = demo_frames(10, scale)
        for provider in args.providers:
            report[f"{provider}@{images[0].shape[1]}x{images[0].shape[0]}"] = profile(provider, images, args.reps)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

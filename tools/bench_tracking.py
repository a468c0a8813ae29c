"""CPU of the keypoint tracking per camera frame, and of its parts, on the camera demo's frames (issue 39).

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

The Pose2Sim multi-person demo at the camera demo's size (``--scale`` of 1088x1920: 544x960), each frame mosaicked as
the fake cameras send it (BayerRG8) and read as the daemon reads it (the mosaic's 2x2-cell gray image, 272x480);
the shipped detector on every ``--interval``-th frame, its detections reaching the tracker ``--delay`` frames later,
the tracker stepping on every frame (60 Hz), the clip played forwards then backwards. Thread CPU time (which a shared
machine distorts less than wall time), the least of ``--reps`` repetitions:

* ``tracker_ms_per_frame``: :meth:`KeypointTracker.step` per tracked frame, catch-up of late detections included
  (what ``/status`` ``cameras[i].tracking.tracker.cpu_ms_per_step`` reports live);
* ``parts_ms``: the gray image from the mosaic, one pyramid build, one forward-backward flow call on the
  detections' keypoints, and the same pair of calls through ``cv2.calcOpticalFlowPyrLK`` (what the tracker ran
  before issue 39: both images' pyramids built inside every call);
* ``detector_ms``: what a whole-frame detection of one camera frame costs by stage (the daemon's path: the
  mosaic demosaiced into the ring's slot, copied out, RGB to BGR, letterboxed, the input tensor, onnxruntime's
  run (the whole process's CPU: onnxruntime's threads), the decoding), for where the detector's CPU goes beside
  the tracking.

    .venv/bin/python tools/bench_tracking.py --cameras 2
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.pose2d import letterbox_geometry
from mocapd.core.sorting import Detections2D
from mocapd.eval.keypoint_tracking import Schedule, replay_tracker
from mocapd.io.pixels import bayer_gray, convert_into, from_rgb, pixel_format
from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.pipeline.detector import OnnxPoseDetector, letterbox_image
from mocapd.pipeline.detector_config import TrackingConfig
from mocapd.pipeline.optical_flow import LKOptions, build_pyramid, forward_backward
from mocapd.service.bench.machine import machine
from mocapd.service.config import load_config
from mocapd.sim.fake_gige import load_video_rgb

FPS = 60.0


def _least_ms(fn: Callable[[], object], n: int, reps: int, clock: Callable[[], int] = time.thread_time_ns) -> float:
    """The least CPU per call of ``fn`` over ``reps`` runs of ``n`` calls, ms: of this thread, or ``clock``'s."""
    best = np.inf
    for _ in range(reps):
        c0 = clock()
        for _ in range(n):
            fn()
        best = min(best, (clock() - c0) / n / 1e6)
    return round(float(best), 4)


def _camera(
    name: str, args: argparse.Namespace, detector: OnnxPoseDetector
) -> tuple[list[NDArray[np.uint8]], list[NDArray[np.uint8]], dict[int, Detections2D]]:
    """A camera's raw mosaics and gray images (bounced clip) and the detections of every interval-th frame."""
    fmt = pixel_format("BayerRG8")
    w, h = round(1088 * args.scale), round(1920 * args.scale)
    rgb = load_video_rgb(demo_video("Demo_MultiPerson", name), 100, (w, h))
    lap = list(range(len(rgb))) + list(range(len(rgb) - 2, 0, -1))
    seq = [lap[k % len(lap)] for k in range(round(args.seconds * FPS))]
    raws = [from_rgb(f, fmt) for f in rgb]
    grays = [bayer_gray(fmt, r, h, w, 2) for r in raws]
    found: dict[int, Detections2D] = {}
    for f in range(0, len(seq), args.interval):
        i = seq[f]
        image = np.empty((h, w, 3), np.uint8)
        convert_into(fmt, raws[i], h, w, image)
        d = detector.detect(np.asarray(cv2.cvtColor(image, cv2.COLOR_RGB2BGR), np.uint8))
        found[f] = Detections2D(d.keypoints[..., :2].astype(np.float64), d.keypoints[..., 2].astype(np.float64))
    return [raws[i] for i in seq], [grays[i] for i in seq], found


def _measure(
    name: str, args: argparse.Namespace, detector: OnnxPoseDetector, options: TrackingConfig, lk: LKOptions
) -> dict[str, Any]:
    """One camera: the tracker replayed, then its parts timed."""
    fmt = pixel_format("BayerRG8")
    w, h = round(1088 * args.scale), round(1920 * args.scale)
    raws, grays, found = _camera(name, args, detector)
    schedule = Schedule(FPS, args.interval, args.delay, 1)
    best, tracker = np.inf, None
    for _ in range(args.reps):
        c0 = time.thread_time_ns()
        _, tracker = replay_tracker(grays, found, schedule, dataclasses.replace(options, downsample=2), 2)
        best = min(best, (time.thread_time_ns() - c0) / 1e6)
    assert tracker is not None
    st = tracker.status()
    # The parts, on the first detection's keypoints (camera px -> the half-size image's) and frames 0 -> 1.
    first = found[min(found)]
    pts = ((first.keypoints[first.confidences > 0] - 0.5) / 2).astype(np.float32)
    p0, p1 = build_pyramid(grays[0], lk), build_pyramid(grays[1], lk)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, lk.max_iterations, lk.epsilon_px)

    def opencv_pair() -> None:
        win = (lk.window_px, lk.window_px)
        fwd, _, _ = cv2.calcOpticalFlowPyrLK(grays[0], grays[1], pts.reshape(-1, 1, 2), None, winSize=win,  # type: ignore[call-overload]
                                             maxLevel=lk.levels, criteria=criteria)  # fmt: skip
        cv2.calcOpticalFlowPyrLK(grays[1], grays[0], fwd, None, winSize=win, maxLevel=lk.levels,  # type: ignore[call-overload]
                                 criteria=criteria)  # fmt: skip

    n, reps = 50, args.reps * 4
    return {
        "camera": name, "tracked_frames": st["steps"],
        "people_per_frame": round(st["people_steps"] / st["steps"], 2), "keypoints_timed": int(pts.shape[0]),
        "flow_calls": st["lk_calls"], "pyramids_built": st["pyramids_built"],
        "retracked_frames": st["retracked_frames"], "tracker_ms_per_frame": round(best / st["steps"], 4),
        "error_vs_detection_px": st["error_vs_detection_px"]["all"],
        "parts_ms": {
            "gray_from_mosaic": _least_ms(lambda: bayer_gray(fmt, raws[0], h, w, 2), n, reps),
            "pyramid": _least_ms(lambda: build_pyramid(grays[0], lk), n, reps),
            "forward_backward": _least_ms(lambda: forward_backward(p0, p1, pts, lk), n, reps),
            "opencv_forward_backward": _least_ms(opencv_pair, n, reps),
        },
    }  # fmt: skip


def _detector_parts(detector: OnnxPoseDetector, raw: NDArray[np.uint8], w: int, h: int, reps: int) -> dict[str, float]:
    """Thread CPU (ms) of each stage of one whole-frame detection of a ``w`` x ``h`` BayerRG8 frame."""
    fmt = pixel_format("BayerRG8")
    rgb = np.empty((h, w, 3), np.uint8)
    convert_into(fmt, raw, h, w, rgb)
    bgr = np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), np.uint8)
    fitted = detector.fit_to(w, h)
    iw, ih, session = fitted if fitted is not None else (*detector.input_size, detector.session)
    lb = letterbox_geometry(w, h, iw, ih)
    canvas = letterbox_image(bgr, lb, iw, ih, detector.spec.pad_value)
    x = detector.to_batch([canvas], (iw, ih))
    out = detector._infer(session, x)
    return {
        "demosaic": _least_ms(lambda: convert_into(fmt, raw, h, w, rgb), 20, reps),
        "copy_out_of_ring": _least_ms(rgb.copy, 20, reps),
        "rgb_to_bgr": _least_ms(lambda: cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), 20, reps),
        "letterbox": _least_ms(lambda: letterbox_image(bgr, lb, iw, ih, detector.spec.pad_value), 20, reps),
        "input_tensor": _least_ms(lambda: detector.to_batch([canvas], (iw, ih)), 20, reps),
        # onnxruntime's own threads run most of it: the process's CPU
        "inference_process": _least_ms(lambda: detector._infer(session, x), 2, reps, time.process_time_ns),
        "decode": _least_ms(lambda: detector._decode(out), 20, reps),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cameras", type=int, default=2)
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--seconds", type=float, default=6.6, help="frames replayed per camera (at 60 fps)")
    ap.add_argument("--interval", type=int, default=12, help="frames between two detections of a camera")
    ap.add_argument("--delay", type=int, default=6, help="frames between a detected frame and its detections")
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args()
    load0 = os.getloadavg()
    cfg = load_config().detector.options()
    options = cfg.tracking
    w, h = round(1088 * args.scale), round(1920 * args.scale)
    detector = OnnxPoseDetector.from_config(cfg, [(w, h)])
    lk = LKOptions(options.window_px, options.levels, 30, 0.01)
    cameras = [_measure(name, args, detector, options, lk) for name in CAMERAS[: args.cameras]]
    fmt = pixel_format("BayerRG8")
    first = load_video_rgb(demo_video("Demo_MultiPerson", CAMERAS[0]), 1, (w, h))[0]
    detector_ms = _detector_parts(detector, from_rgb(first, fmt), w, h, args.reps)
    print(json.dumps({
        "machine": machine(), "opencv": cv2.__version__, "opencv_threads": cv2.getNumThreads(),
        "image": [w, h], "tracking_image": [w // 2, h // 2], "window_px": lk.window_px, "levels": lk.levels,
        "interval_frames": args.interval, "delay_frames": args.delay, "cameras": cameras,
        "detector_ms": detector_ms, "detector": detector.describe(),
        "loadavg": {"start": [round(x, 2) for x in load0], "end": [round(x, 2) for x in os.getloadavg()]},
    }, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()

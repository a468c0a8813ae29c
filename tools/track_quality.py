"""Keypoints between detections, how good: the live tracker replayed on real footage and on rendered synthetic
frames under live detection schedules, against a reference on every frame (:mod:`mocapd.eval.keypoint_tracking`).

``--source demo``: the Pose2Sim demo videos at the camera demo's size (``--scale`` of 1088x1920, default 544x960),
each frame mosaicked as the fake cameras send it (BayerRG8) and read as the daemon reads it: the detector sees the
demosaicked frame, the tracker the mosaic's 2x2-cell gray image. The reference is the shipped detector on every
frame; its output on every ``interval``-th frame is the live schedule's detections. With ``--held-out``
(Demo_SinglePerson: one subject), each method's subject keypoints are also triangulated from the other cameras and
reprojected into each camera against its detection there (the held-out-view error).

``--source synthetic``: the synthetic rig (4 HD cameras in a ring, two people on recorded motion) rendered with
textured bodies at ``--scale`` (default 960x540); the reference is the truth, the detections the truth plus
``--noise-px`` Gaussian noise.

The clips play forwards then backwards (``--seconds`` of them) at 60 fps. Prints one JSON object: per schedule
(``--intervals-ms``, ``--delay-ms``), per method (tracked, interpolated, held) the error median/p90 (px), by joint
group, coverage and latency, pooled over the cameras; the tracker's own error against each next detection and its
CPU per frame and per person; and ``people_sorted``: the daemon's people sorting and enrolment run on the tracked
keypoint stream (at a 5-frame latency) and on the detections alone (at their interval + delay + a frame), people
per 60 Hz tick and identities (:func:`~mocapd.eval.keypoint_tracking.people_replay`).

    .venv/bin/python tools/track_quality.py --source demo --demo Demo_MultiPerson
    .venv/bin/python tools/track_quality.py --source demo --demo Demo_SinglePerson --held-out
    .venv/bin/python tools/track_quality.py --source synthetic
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.keypoints import keypoint_format
from mocapd.core.sorting import Detections2D
from mocapd.eval.keypoint_tracking import (
    CONFIDENT,
    METHODS,
    Comparison,
    Estimate,
    Reference,
    Schedule,
    compare,
    detection_baselines,
    detection_stream,
    group_indices,
    held_out_view,
    match_people,
    people_replay,
    replay_tracker,
    summary,
    tracked_stream,
)
from mocapd.io.calibration_files import core_cameras, read_qca, scale_calibration
from mocapd.io.pixels import bayer_gray, convert_into, from_rgb, pixel_format
from mocapd.io.pose2sim_demo import CAMERAS, demo_calibration, demo_video
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import TrackingConfig
from mocapd.pipeline.frame_ring import block_mean
from mocapd.service.config import load_config
from mocapd.sim.fake_gige import load_video_rgb
from mocapd.sim.textured_frames import TexturedWorldFrames
from mocapd.sim.world import SyntheticWorld

FloatArray = NDArray[np.float64]
FPS = 60.0
TRACKED_LATENCY_FRAMES = 5  # the scheduler's latency with tracked keypoints (live auto latency: ~70-120 ms)


@dataclass
class CameraRun:
    """One camera's replay: gray frames at the tracking resolution, the reference and the detections by frame."""

    grays: list[NDArray[np.uint8]]
    reference: dict[int, Reference]
    detections: dict[int, Detections2D]  # the detector's output on every frame (demo) or the noisy truth (synthetic)


def bounce(n_unique: int, n_frames: int) -> list[int]:
    """Frame indices of a clip played forwards then backwards, ``n_frames`` of them."""
    lap = list(range(n_unique)) + list(range(n_unique - 2, 0, -1))
    return [lap[k % len(lap)] for k in range(n_frames)]


def demo_runs(args: argparse.Namespace, options: TrackingConfig) -> tuple[list[CameraRun], list[Camera], int]:
    """The demo's cameras: frames as the daemon reads them, the shipped detector on every frame."""
    cfg = load_config().detector.options()
    size = (round(1088 * args.scale), round(1920 * args.scale))
    fmt = pixel_format("BayerRG8")
    w, h = size
    factor = options.factor_for(w, h)
    detector = OnnxPoseDetector.from_config(cfg, [size])
    runs = []
    for cam in CAMERAS[: args.cameras]:
        rgb = load_video_rgb(demo_video(args.demo, cam), 100, size)
        grays, dets = [], []
        for frame in rgb:
            raw = from_rgb(frame, fmt)
            grays.append(bayer_gray(fmt, raw, h, w, factor))
            image = np.empty((h, w, 3), np.uint8)
            convert_into(fmt, raw, h, w, image)
            found = detector.detect(np.asarray(cv2.cvtColor(image, cv2.COLOR_RGB2BGR), np.uint8))
            dets.append(Detections2D(found.keypoints[..., :2].astype(np.float64),
                                     found.keypoints[..., 2].astype(np.float64)))  # fmt: skip
        seq = bounce(len(rgb), round(args.seconds * FPS))
        runs.append(CameraRun(
            grays=[grays[i] for i in seq],
            reference={f: Reference(dets[i].keypoints, dets[i].confidences >= CONFIDENT) for f, i in enumerate(seq)},
            detections={f: dets[i] for f, i in enumerate(seq)},
        ))  # fmt: skip
    calib = scale_calibration(read_qca(demo_calibration(args.demo)), args.scale)
    return runs, core_cameras(calib), factor


def synthetic_runs(args: argparse.Namespace, options: TrackingConfig) -> tuple[list[CameraRun], list[Camera], int]:
    """The synthetic rig rendered: the truth as reference, the truth plus noise as the detections."""
    world = SyntheticWorld(args.cameras, 2, 0, seed=args.seed)
    frames = TexturedWorldFrames(world, args.scale, seed=args.seed)
    rng = np.random.default_rng(args.seed)
    n = round(args.seconds * FPS)
    runs = []
    factor = 1
    for cam in range(args.cameras):
        w, h = frames.size(cam)
        factor = options.factor_for(w, h)
        grays, reference, dets = [], {}, {}
        for f in range(n):
            t = f / FPS
            grays.append(block_mean(frames.render(cam, t), factor))
            kp, inside = frames.keypoints(cam, t)
            reference[f] = Reference(kp, inside)
            noisy = kp + rng.normal(scale=args.noise_px, size=kp.shape)
            keep = inside.sum(axis=1) >= 5  # a person mostly out of the image is not detected
            dets[f] = Detections2D(np.where(inside[keep][..., None], noisy[keep], 0.0), inside[keep] * 0.9)
        runs.append(CameraRun(grays, reference, dets))
    return runs, [scaled(c, args.scale) for c in world.cameras], factor


def scaled(camera: Camera, scale: float) -> Camera:
    """``camera`` at ``scale`` of its image size (intrinsics scaled)."""
    K = np.asarray(camera.K, np.float64).copy()
    K[:2] *= scale
    return dataclasses.replace(camera, K=K, width=round(camera.width * scale), height=round(camera.height * scale))


def evaluate(
    runs: list[CameraRun],
    schedule: Schedule,
    options: TrackingConfig,
    factor: int,
    names: list[str],
    cameras: list[Camera],
) -> tuple[dict[str, Any], list[dict[str, dict[int, Estimate]]]]:
    """Every method on every camera under ``schedule``; pooled summaries and the estimates per camera."""
    groups = group_indices(names)
    pooled = {m: Comparison.empty() for m in METHODS}
    jitter = Comparison.empty()  # the detections themselves, two frames (33 ms) apart: their noise
    trackers = []
    per_camera = []
    tracked_streams, detection_streams = [], []
    for run in runs:
        n = len(run.grays)
        seeds = {f: d for f, d in run.detections.items() if f % schedule.interval_frames == 0}
        tracked, tracker = replay_tracker(run.grays, seeds, schedule, options, factor, names)
        interpolated, held = detection_baselines(seeds, schedule, n)
        start = schedule.interval_frames + schedule.delay_frames  # every method has its first estimate
        frames = [f for f in tracked if f >= start and f in interpolated and f in held]
        methods = {"tracked": tracked, "interpolated": interpolated, "held": held}
        for m, est in methods.items():
            pooled[m].add(compare(est, run.reference, groups, frames))
        apart = {f: Estimate(run.detections[f - 2], 2, 0) for f in frames if f - 2 in run.detections}
        jitter.add(compare(apart, run.reference, groups, frames))
        trackers.append(tracker.status())
        per_camera.append(methods)
        tracked_streams.append(tracked_stream(tracked))
        detection_streams.append(detection_stream(seeds, schedule))
    n = len(runs[0].grays)
    # Downstream: the daemon's people sorting on the keypoint streams, each at the latency it needs (tracked: ~5
    # frames, what the live auto latency found; detections: a detection interval + delay + a frame).
    need = schedule.interval_frames + schedule.delay_frames + 1
    people = {"tracked": people_replay(cameras, tracked_streams, TRACKED_LATENCY_FRAMES, n),
              "detections": people_replay(cameras, detection_streams, need, n)}  # fmt: skip
    out: dict[str, Any] = {
        "interval_ms": round(schedule.seconds(schedule.interval_frames) * 1e3, 1),
        "delay_ms": round(schedule.seconds(schedule.delay_frames) * 1e3, 1),
        "tracking_hz": round(schedule.fps / schedule.track_every, 1),
        "methods": {m: summary(c, schedule) for m, c in pooled.items()},
        "detections_two_frames_apart": summary(jitter, schedule),
        "tracker_vs_next_detection_px": {
            "median_by_camera": [t["error_vs_detection_px"]["all"]["median"] for t in trackers],
            "by_joint_group_camera_0": {g: v["median"] for g, v in
                                        trackers[0]["error_vs_detection_px"]["by_joint_group"].items()},
        },
        "tracker_cpu_ms_per_step": [t["cpu_ms_per_step"] for t in trackers],
        "tracker_cpu_ms_per_person_step": [t["cpu_ms_per_person_step"] for t in trackers],
        "people_dropped": sum(t["people_dropped_keypoints"] + t["people_dropped_age"] for t in trackers),
        "people_sorted": people,
    }  # fmt: skip
    return out, per_camera


def held_out(
    runs: list[CameraRun],
    methods: list[dict[str, dict[int, Estimate]]],
    cameras: list[Camera],
    options: TrackingConfig,
    schedule: Schedule,
) -> dict[str, Any]:
    """Held-out-view error of the subject (the tallest reference person of each camera) for every method and for the
    detector on every frame itself. A tracked keypoint votes with its detected confidence (its decay undone)."""
    frames = sorted(set.intersection(*(set(m["tracked"]) for m in methods)))
    subject_ref: dict[int, list[FloatArray | None]] = {}
    for f in frames:
        views: list[FloatArray | None] = []
        for run in runs:
            ref = run.detections[f]
            if len(ref) == 0:
                views.append(None)
                continue
            sure = ref.confidences >= CONFIDENT
            extent = [float(np.ptp(ref.keypoints[p][sure[p], 1])) if sure[p].any() else 0.0 for p in range(len(ref))]
            p = int(np.argmax(extent))
            views.append(np.concatenate([ref.keypoints[p], ref.confidences[p][:, None]], axis=1))
        subject_ref[f] = views
    out: dict[str, Any] = {"detected_every_frame": held_out_view(cameras, subject_ref, subject_ref)}
    for m in METHODS:
        subject: dict[int, list[FloatArray | None]] = {}
        for f in frames:
            views = []
            for cam, per in enumerate(methods):
                est, subject_view = per[m].get(f), subject_ref[f][cam]
                if est is None or subject_view is None:
                    views.append(None)
                    continue
                target = Reference(subject_view[None, :, :2], (subject_view[:, 2] >= CONFIDENT)[None])
                pairs = match_people(est.people, target)
                if not pairs:
                    views.append(None)
                    continue
                i = pairs[0][0]
                conf = est.people.confidences[i]
                if m == "tracked":  # undo the decay: vote with the detector's confidence, like the other methods
                    conf = conf / 0.5 ** (schedule.seconds(est.age_frames) / options.half_life_s)
                views.append(np.concatenate([est.people.keypoints[i], conf[:, None]], axis=1))
            subject[f] = views
        out[m] = held_out_view(cameras, subject, subject_ref)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", choices=["demo", "synthetic"], default="demo")
    ap.add_argument("--demo", default="Demo_MultiPerson", choices=["Demo_SinglePerson", "Demo_MultiPerson"])
    ap.add_argument("--scale", type=float, default=None, help="demo: of 1088x1920 (0.5); synthetic: of 1920x1080")
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=10.0, help="frames replayed per camera (at 60 fps)")
    ap.add_argument("--intervals-ms", type=float, nargs="+", default=[100.0, 150.0, 250.0, 400.0])
    ap.add_argument("--delay-ms", type=float, default=100.0)
    ap.add_argument("--tracking-hz", type=float, default=None, help="default: [detector.tracking] rate_hz")
    ap.add_argument("--noise-px", type=float, default=2.0, help="synthetic: detection noise (sigma, px)")
    ap.add_argument("--held-out", action="store_true", help="demo: held-out-view error of the subject")
    ap.add_argument(
        "--downsample",
        type=int,
        choices=[1, 2, 4],
        default=None,
        help="tracking image downsampling (default: [detector.tracking] downsample)",
    )
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    args.scale = args.scale if args.scale is not None else 0.5
    options = load_config().detector.options().tracking
    if args.downsample is not None:
        options = dataclasses.replace(options, downsample=args.downsample)
    load0 = os.getloadavg()
    if args.source == "demo":
        runs, cameras, factor = demo_runs(args, options)
    else:
        runs, cameras, factor = synthetic_runs(args, options)
    names = list(keypoint_format("coco17").keypoints)
    every = max(1, round(FPS / (args.tracking_hz or options.rate_hz)))
    results = []
    for interval in args.intervals_ms:
        schedule = Schedule(FPS, max(1, round(interval / 1e3 * FPS)), round(args.delay_ms / 1e3 * FPS), every)
        out, per_camera = evaluate(runs, schedule, options, factor, names, cameras)
        if args.held_out:
            out["held_out_view_px"] = held_out(runs, per_camera, cameras, options, schedule)
        results.append(out)
    report = {
        "source": args.source if args.source == "synthetic" else f"demo {args.demo}",
        "image": [int(runs[0].grays[0].shape[1] * factor), int(runs[0].grays[0].shape[0] * factor)],
        "tracking_downsample": factor, "cameras": len(runs), "frames_per_camera": len(runs[0].grays),
        "noise_px": args.noise_px if args.source == "synthetic" else None,
        "tracking": {k: getattr(options, k) for k in ("rate_hz", "window_px", "levels", "max_fb_px", "lost_confidence",
                                                        "half_life_s", "max_age_s", "min_keypoints")},
        "schedules": results,
        "loadavg": {"start": [round(x, 2) for x in load0], "end": [round(x, 2) for x in os.getloadavg()]},
    }  # fmt: skip
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()

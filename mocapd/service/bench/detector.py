"""``mocapd bench detector``: naive per-camera detection against ROI packing on the Pose2Sim 4-camera demo videos.

Prints one JSON object. Both paths run in the same process, interleaved frame pair by frame pair (their
order alternating), and every figure is a median over pairs, so that the other work on this shared 2-core
machine hits both alike. ``naive`` letterboxes each camera frame alone into the model's input;
``packed`` packs the ROIs of 4 cameras x 2 consecutive frames (N_o = 2) into as few model-sized canvases as
keep every tile at least at the naive scale. ``disagreement_px`` is the distance between the keypoints that
both paths found with confidence >= 0.5 on the same person in the same camera frame, in source pixels.

    mocapd bench detector --pairs 30 --threads 2
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import cv2
import numpy as np

from mocapd.core.pose2d import PoseDetections
from mocapd.core.roi_packing import match_people
from mocapd.errors import InputError
from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.pipeline.detector import Image, OnnxPoseDetector
from mocapd.pipeline.detector_config import ModelSpec, PackingConfig
from mocapd.pipeline.packing import PackedDetector


def _disagreements(a: PoseDetections, b: PoseDetections, conf: float) -> list[float]:
    out: list[float] = []
    for i, j in match_people(a, b):
        ka, kb = a.keypoints[i], b.keypoints[j]
        ok = (ka[:, 2] >= conf) & (kb[:, 2] >= conf)
        out.extend(np.linalg.norm(ka[ok, :2] - kb[ok, :2], axis=1).tolist())
    return out


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Time both paths on ``args.pairs`` frame pairs of the demo videos (the options of ``mocapd bench detector``:
    :func:`mocapd.service.cli.bench.detector_arguments`)."""

    det = OnnxPoseDetector(ModelSpec(), intra_op_threads=args.threads, inter_op_threads=1)
    caps = [cv2.VideoCapture(str(demo_video(args.demo, c))) for c in CAMERAS]

    def read() -> list[Image] | None:
        imgs = []
        for cap in caps:
            ok, img = cap.read()
            if not ok:
                return None
            imgs.append(np.asarray(img, dtype=np.uint8))
        return imgs

    first = read()
    if first is None:
        raise InputError(f"cannot read the Pose2Sim {args.demo} videos (run the set-up: make demo)")
    sizes = [(im.shape[1], im.shape[0]) for im in first]
    canvas_det = None
    if args.canvas:
        cw, ch = (int(v) for v in args.canvas.split("x"))
        canvas_det = OnnxPoseDetector(
            ModelSpec(input_width=cw, input_height=ch), intra_op_threads=args.threads, inter_op_threads=1
        )
        canvas_det.run_canvas(np.full((ch, cw, 3), 114, dtype=np.uint8))  # warm-up
    packer = PackedDetector(
        det,
        sizes,
        PackingConfig(
            roi_margin=args.margin,
            gap=args.gap,
            align_stride=args.align_stride,
            min_scale_ratio=args.min_scale_ratio,
            max_scale_ratio=args.max_scale_ratio,
            max_tile_height=args.max_tile_height,
            refresh_every=args.refresh_every,
            refresh_scale_ratio=args.refresh_scale_ratio,
            n_o=2,
            n_p=2,
        ),
        canvas_detector=canvas_det,
    )
    det.detect(first[0])  # warm-up: first run allocates
    t_naive: list[float] = []
    t_packed: list[float] = []
    canvases: list[int] = []
    scales: list[float] = []
    dis: list[float] = []
    people_naive = people_packed = 0
    frame: list[Image] | None = first
    for k in range(args.pairs):
        nxt = read()
        if frame is None or nxt is None:
            break
        pair = [frame, nxt]

        def run_naive(pair: list[list[Image]] = pair) -> tuple[float, list[list[PoseDetections]]]:
            t0 = time.perf_counter()
            res = [[det.detect(img) for img in cams] for cams in pair]
            return time.perf_counter() - t0, res

        def run_packed(pair: list[list[Image]] = pair) -> tuple[float, list[list[PoseDetections]]]:
            t0 = time.perf_counter()
            res = packer.detect(pair)
            return time.perf_counter() - t0, res

        if k % 2 == 0:
            tn, rn = run_naive()
            tp, rp = run_packed()
        else:
            tp, rp = run_packed()
            tn, rn = run_naive()
        t_naive.append(tn)
        t_packed.append(tp)
        canvases.append(len(packer.last_packings))
        scales.extend(p.scale for p in packer.last_packings)
        for s in range(2):
            for c in range(len(CAMERAS)):
                dis.extend(_disagreements(rn[s][c], rp[s][c], 0.5))
                people_naive += len(rn[s][c])
                people_packed += len(rp[s][c])
        frame = read()
    n_cf = 2 * len(CAMERAS)
    tn_a, tp_a = np.array(t_naive), np.array(t_packed)
    result = {
        "demo": args.demo,
        "frame_pairs": len(t_naive),
        "camera_frames_per_pair": n_cf,
        "image_size": sizes[0],
        "model_input": list(det.input_size),
        "packed_canvas": list(packer.canvas_detector.input_size),
        "providers": det.providers,
        "intra_op_threads": args.threads,
        "roi_margin": args.margin,
        "gap": args.gap,
        "align_stride": args.align_stride,
        "min_scale_ratio": args.min_scale_ratio,
        "max_scale_ratio": args.max_scale_ratio,
        "max_tile_height": args.max_tile_height,
        "refresh_every": args.refresh_every,
        "refresh_scale_ratio": args.refresh_scale_ratio,
        "naive_camera_frames_per_s_median": round(float(np.median(n_cf / tn_a)), 2),
        "packed_camera_frames_per_s_median": round(float(np.median(n_cf / tp_a)), 2),
        "speedup_median": round(float(np.median(tn_a / tp_a)), 2),
        "packed_canvases_per_pair_median": float(np.median(canvases)),
        "packed_canvases_per_pair_mean": round(float(np.mean(canvases)), 2),
        "refresh_tiles": packer.stats.refresh_tiles,
        "packed_scale_median": round(float(np.median(scales)), 3),
        "naive_scale": round(min(det.input_size[0] / sizes[0][0], det.input_size[1] / sizes[0][1]), 3),
        "disagreement_px_median": round(float(np.median(dis)), 2) if dis else None,
        "disagreement_px_p90": round(float(np.percentile(dis, 90)), 2) if dis else None,
        "keypoint_pairs_compared": len(dis),
        "people_naive": people_naive,
        "people_packed": people_packed,
    }
    return result

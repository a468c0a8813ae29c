"""Benchmark: naive per-camera detection against ROI packing on the Pose2Sim 4-camera demo videos.

Prints one JSON object. Both paths run in the same process, interleaved frame pair by frame pair (their
order alternating), and every figure is a median over pairs, so that the other work on this shared 2-core
machine hits both alike. ``naive`` letterboxes each camera frame alone into the model's input;
``packed`` packs the ROIs of 4 cameras x 2 consecutive frames (N_o = 2) into as few model-sized canvases as
keep every tile at least at the naive scale. ``disagreement_px`` is the distance between the keypoints that
both paths found with confidence >= 0.5 on the same person in the same camera frame, in source pixels.

    .venv/bin/python tools/bench_detect.py --pairs 30 --threads 2
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import cv2
import numpy as np

from mocapd.core.pose2d import PoseDetections
from mocapd.core.roi_packing import match_people
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--demo", default="Demo_MultiPerson", help="Demo_SinglePerson or Demo_MultiPerson")
    ap.add_argument("--pairs", type=int, default=30, help="frame pairs to time (each: 8 camera frames)")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    defaults = PackingConfig()
    ap.add_argument("--margin", type=float, default=defaults.roi_margin, help="ROI margin (fraction of box side)")
    ap.add_argument("--gap", type=int, default=defaults.gap, help="canvas pixels between tiles")
    ap.add_argument("--min-scale-ratio", type=float, default=1.0, help="packed tile scale / naive scale, minimum")
    ap.add_argument("--max-scale-ratio", type=float, default=1.0, help="packed tile scale / naive scale, maximum")
    ap.add_argument("--align-stride", type=int, default=32, help="0: common-scale packing; >0: aligned tiles")
    ap.add_argument(
        "--max-tile-height", type=float, default=defaults.max_tile_height, help="tallest tile / canvas height (0: off)"
    )
    ap.add_argument("--refresh-every", type=int, default=defaults.refresh_every, help="whole-frame refresh period")
    ap.add_argument("--refresh-scale-ratio", type=float, default=defaults.refresh_scale_ratio, help="refresh scale")
    ap.add_argument("--canvas", default="", help="packed canvas size WxH (default: the model's 640x640)")
    args = ap.parse_args(argv)

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
        raise SystemExit("cannot read the demo videos")
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
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())

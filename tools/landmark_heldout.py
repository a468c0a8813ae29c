"""Held-out-view error of YOLO11n-pose against BlazePose landmarks (full, heavy) on a Pose2Sim demo (issue 40).

The issue's outside check, made with mocapd's own parts: per frame, the subject (the tallest person of each view)
as YOLO sees it and as the landmark models see it on crops YOLO placed (:mod:`mocapd.pipeline.landmarks`). For each
camera held out, every keypoint is triangulated from the other views (confidence-weighted DLT,
``core.camera.triangulate_projections``, views with confidence >= 0.5 only), projected into the held-out camera with
its distortion, and compared with that camera's own confident keypoint. Each front end is judged against its own
held-out detections, on the joints both have (nose, shoulders, elbows, wrists, hips, knees, ankles); the landmarks'
feet and hand points are reported apart. No association, no left/right repair, no solve: the detector alone.

    PYTHONPATH=$PWD nice -n 19 .venv/bin/python tools/landmark_heldout.py --frames 100 \
        --out docs/detection/landmark_heldout.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mocapd.core.camera import Camera, triangulate_projections
from mocapd.core.keypoints import BLAZEPOSE33_FORMAT as BLAZEPOSE33
from mocapd.core.keypoints import COCO17_FORMAT as COCO17
from mocapd.eval.video_input import pose2sim_take
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import ModelSpec
from mocapd.pipeline.landmarks import LandmarkRunner

SHARED = ("nose", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
          "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle")  # fmt: skip
GROUPS = {
    "shoulders": ("left_shoulder", "right_shoulder"),
    "wrists": ("left_wrist", "right_wrist"),
    "hips": ("left_hip", "right_hip"),
    "ankles": ("left_ankle", "right_ankle"),
    "feet (heel, foot index)": ("left_heel", "right_heel", "left_foot_index", "right_foot_index"),
    "hands (pinky, index, thumb)": ("left_pinky", "right_pinky", "left_index", "right_index", "left_thumb",
                                    "right_thumb"),
}  # fmt: skip
MIN_CONFIDENCE = 0.5


def detect(demo: str, frames: int, variants: list[str]) -> tuple[list[Camera], dict[str, np.ndarray]]:
    """The subject's keypoints per front end: name -> (frames, cameras, K, 3)."""
    take = pose2sim_take(demo)
    n = min(frames, take.n_frames)
    det = OnnxPoseDetector(ModelSpec(), intra_op_threads=2)
    runners = {v: LandmarkRunner(v) for v in variants}
    caps = [cv2.VideoCapture(str(v)) for v in take.videos]
    out: dict[str, list[np.ndarray]] = {"yolo": [], **{v: [] for v in variants}}
    for f in range(n):
        images: list[np.ndarray[Any, np.dtype[np.uint8]]] = []
        people: list[np.ndarray] = []
        for cap in caps:
            ok, frame = cap.read()
            if not ok:
                raise SystemExit(f"frame {f} unreadable")
            img: np.ndarray[Any, np.dtype[np.uint8]] = np.ascontiguousarray(frame, np.uint8)
            found = det.detect(img)
            kp = np.zeros((1, 17, 3))
            if len(found):
                kp = found.keypoints[[int(np.argmax(found.boxes[:, 3] - found.boxes[:, 1]))]]
            images.append(img)
            people.append(kp)
        out["yolo"].append(np.concatenate(people))
        for v, runner in runners.items():
            out[v].append(np.concatenate([p.keypoints for p in runner.run(images, people)]))
        print(f"frame {f + 1}/{n}", end="\r", flush=True)
    print()
    return take.cameras, {k: np.stack(v) for k, v in out.items()}


def held_out(cameras: list[Camera], kp: np.ndarray) -> np.ndarray:
    """Per (frame, held-out camera, keypoint) the held-out error in px (NaN where not compared), shape (F, C, K)."""
    n_f, n_c, n_k, _ = kp.shape
    und = np.stack([cam.undistort_points(kp[:, c, :, :2]) for c, cam in enumerate(cameras)], axis=1)
    w = np.where(kp[..., 2] >= MIN_CONFIDENCE, kp[..., 2], 0.0)
    P = np.stack([c.projection_matrix for c in cameras])
    err = np.full((n_f, n_c, n_k), np.nan)
    for f in range(n_f):
        for k in range(n_c):
            keep = [c for c in range(n_c) if c != k]
            X, ok = triangulate_projections(P[keep], und[f, keep], w[f, keep])
            uv = cameras[k].project(X)
            e = np.linalg.norm(uv - kp[f, k, :, :2], axis=1)
            err[f, k] = np.where(ok & (w[f, k] > 0), e, np.nan)
    return err


def summary(err: np.ndarray, names: tuple[str, ...], fmt_names: tuple[str, ...]) -> dict[str, Any]:
    cols = [fmt_names.index(n) for n in names if n in fmt_names]
    e = err[:, :, cols]
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"n": 0}
    return {"n": int(e.size), "median": round(float(np.median(e)), 1), "p90": round(float(np.percentile(e, 90)), 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--demo", default="Demo_SinglePerson")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--variants", nargs="*", default=["full", "heavy"])
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    cameras, kps = detect(args.demo, args.frames, args.variants)
    result: dict[str, Any] = {"demo": args.demo, "frames": int(kps["yolo"].shape[0]), "front_ends": {}}
    for name, kp in kps.items():
        fmt = COCO17 if name == "yolo" else BLAZEPOSE33
        err = held_out(cameras, kp)
        row: dict[str, Any] = {"shared joints": summary(err, SHARED, fmt.keypoints)}
        row.update({g: summary(err, names, fmt.keypoints) for g, names in GROUPS.items()})
        row["per held-out camera (shared, median)"] = [
            summary(err[:, [c]], SHARED, fmt.keypoints).get("median") for c in range(len(cameras))
        ]
        result["front_ends"][name] = row
        print(name, json.dumps(row))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

"""Multi-person tracking on real video: the Pose2Sim multi-person demo (4 cameras, two subjects, a bystander).

Runs the real detector (whole frames) on every camera frame, sorts the detections into subjects with mocapd's
tracker (Algorithm 1 + the changes of docs/tracking.md) on the demo's own calibration, and reports per subject the
frames it was tracked in, its views per frame and the track continuity; saves annotated frames (one colour per
subject, grey for people no subject took) to look at.

    .venv/bin/python -m tools.track_video --out results/tracking_video
"""

from __future__ import annotations

import argparse
import json
from itertools import pairwise
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mocapd.core.camera import Camera
from mocapd.core.sorting import Detections2D, DetectionSorter
from mocapd.core.tracking import SubjectTracker, TrackingOptions
from mocapd.io.calibration_files import core_cameras, read_qca
from mocapd.io.pose2sim_demo import CAMERAS, demo_calibration, demo_video
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.service.config import load_config

COLOURS = ((0, 200, 255), (255, 80, 0), (0, 220, 0), (200, 0, 200))


def cameras(demo: str) -> list[Camera]:
    return core_cameras(read_qca(demo_calibration(demo)))


def detect_all(demo: str, max_frames: int) -> tuple[list[list[Detections2D]], list[list[np.ndarray]]]:
    """Per frame and camera, the detector's 2D people (and the images, for annotation)."""
    det = OnnxPoseDetector.from_config(load_config().detector.options())
    caps = [cv2.VideoCapture(str(demo_video(demo, c))) for c in CAMERAS]
    frames: list[list[Detections2D]] = []
    images: list[list[np.ndarray]] = []
    for _ in range(max_frames):
        row, imgs = [], []
        for cap in caps:
            ok, img = cap.read()
            if not ok:
                return frames, images
            people = det.detect(np.asarray(img, dtype=np.uint8))
            kp = people.keypoints
            row.append(Detections2D(kp[..., :2], kp[..., 2]))
            imgs.append(img)
        frames.append(row)
        images.append(imgs)
    return frames, images


def annotate(img: np.ndarray, det: Detections2D, owner: dict[int, int]) -> np.ndarray:
    out = img.copy()
    for i in range(len(det)):
        colour = COLOURS[(owner[i] - 1) % len(COLOURS)] if i in owner else (160, 160, 160)
        for (x, y), c in zip(det.keypoints[i], det.confidences[i], strict=True):
            if c >= 0.3:
                cv2.circle(out, (int(x), int(y)), 9, colour, -1)
        if i in owner:
            x, y = det.keypoints[i][det.confidences[i] >= 0.3].min(axis=0).astype(int)
            cv2.putText(out, f"S{owner[i]}", (x, max(40, y - 20)), cv2.FONT_HERSHEY_SIMPLEX, 2.0, colour, 5)
    return out


def run(demo: str, out: Path, max_frames: int) -> dict[str, Any]:
    cams = cameras(demo)
    frames, images = detect_all(demo, max_frames)
    fps = 60.0
    tracker = SubjectTracker(
        DetectionSorter(cams),
        TrackingOptions(max_subjects=2, enrol_after_s=0.1, volume_min=(-2.0, -2.0), volume_max=(2.0, 2.0)),
    )
    seen: dict[int, list[int]] = {}
    views: dict[int, list[int]] = {}
    bystanders = []
    owners_per_frame = []
    centres: dict[int, list[list[float]]] = {}
    for f, row in enumerate(frames):
        res = tracker.update(int(f * 1e9 / fps), row)
        bystanders.append(res.bystanders)
        owners: list[dict[int, int]] = [{} for _ in cams]
        for s in res.subjects:
            if s.seen:
                seen.setdefault(s.id, []).append(f)
                views.setdefault(s.id, []).append(len(s.detections))
                centres.setdefault(s.id, []).append(np.nanmean(s.last_points, axis=0).round(3).tolist())
                for cam, i in s.detections.items():
                    owners[cam][i] = s.id
        owners_per_frame.append(owners)
    out.mkdir(parents=True, exist_ok=True)
    for f in sorted({0, len(frames) // 2, len(frames) - 1}):
        tiles = [cv2.resize(annotate(images[f][c], frames[f][c], owners_per_frame[f][c]), (544, 960)) for c in range(4)]
        cv2.imwrite(str(out / f"frame{f:03d}.jpg"), np.hstack(tiles))
    steps = {sid: float(np.max(np.linalg.norm(np.diff(np.array(c), axis=0), axis=1))) if len(c) > 1 else 0.0
             for sid, c in centres.items()}  # fmt: skip
    report = {
        "demo": demo,
        "frames": len(frames),
        "subjects": {
            str(sid): {
                "frames_tracked": len(fs),
                "first_frame": fs[0],
                "gaps": int(sum(1 for a, b in pairwise(fs) if b != a + 1)),
                "median_views": float(np.median(views[sid])),
                "largest_step_m": round(steps[sid], 3),
                "start_centre": centres[sid][0],
                "end_centre": centres[sid][-1],
            }
            for sid, fs in seen.items()
        },
        "people_per_frame_not_subjects_median": float(np.median(bystanders)),
        "annotated": str(out),
    }
    (out / "report.json").write_text(json.dumps(report, indent=2))
    return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--demo", default="Demo_MultiPerson")
    p.add_argument("--out", type=Path, default=Path("results/tracking_video"))
    p.add_argument("--max-frames", type=int, default=100)
    args = p.parse_args(argv)
    print(json.dumps(run(args.demo, args.out, args.max_frames), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Cost of one hand crop on this machine (issue 44): the hand landmark model (full, lite) on LiteRT, per crop, at
batch 1 and 4, on real hand crops of the Pose2Sim single-person demo (frame 0, all cameras, both hands, placed from
BlazePose full's landmarks), and the crop itself (``cv2.warpAffine`` to 224 x 224, RGB in [0, 1]); beside them, in
the same rounds, the body landmark models (full, heavy) per person crop, which ``[detector] hands = "auto"`` weighs
them against.

    PYTHONPATH=$PWD nice -n 19 .venv/bin/python tools/hand_cost.py --rounds 3
"""

from __future__ import annotations

import argparse
import json
import time

import cv2
import numpy as np

from mocapd.core.hand_roi import hand_rois
from mocapd.core.keypoints import BLAZEPOSE33_FORMAT as BLAZEPOSE33
from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import ModelSpec
from mocapd.pipeline.hand_landmarks import HandRunner, crop_hand
from mocapd.pipeline.landmarks import LandmarkRunner
from mocapd.pipeline.landmarks import crop as landmark_crop


def crops() -> tuple[list[np.ndarray], list[float], np.ndarray]:
    """The hand crops of frame 0, the time of making each (s), and the people's body crops (n, 256, 256, 3)."""
    det = OnnxPoseDetector(ModelSpec(), intra_op_threads=2)
    body = LandmarkRunner("full")
    out, times, bodies = [], [], []
    for cam in CAMERAS:
        ok, frame = cv2.VideoCapture(str(demo_video("Demo_SinglePerson", cam))).read()
        assert ok
        img = np.ascontiguousarray(frame, np.uint8)
        people = det.detect(img)
        (marks,) = body.run([img], [people.keypoints])
        bodies += [landmark_crop(img, r) for r in marks.rois if r is not None]
        for lm in marks.keypoints:
            for roi in hand_rois(lm, BLAZEPOSE33.keypoints):
                if roi is not None:
                    t0 = time.perf_counter()
                    out.append(crop_hand(img, roi))
                    times.append(time.perf_counter() - t0)
    return out, times, np.stack(bodies)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=6)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    batch, crop_s, body_crops = crops()
    stack = np.stack(batch)
    result: dict[str, object] = {"crops": len(batch), "crop ms (median)": round(1000 * float(np.median(crop_s)), 2)}
    for r in range(args.rounds):
        for variant in ("full", "lite"):
            for size in (1, 4):
                runner = HandRunner(BLAZEPOSE33.keypoints, variant, threads=args.threads, batch=size)
                runner.infer(stack[:size])  # warm-up
                runner.infer(stack[:size])
                per = []
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    runner.infer(stack)
                    per.append((time.perf_counter() - t0) / len(stack))
                key = f"{variant} batch {size} ms per crop"
                prev = result.setdefault(key, [])
                assert isinstance(prev, list)
                prev.append(round(1000 * float(np.median(per)), 1))
        for variant in ("full", "heavy"):  # the body landmark crop the hands ride on, interleaved
            body = LandmarkRunner(variant, threads=args.threads)
            body.infer(body_crops[:1])
            per = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                body.infer(body_crops)
                per.append((time.perf_counter() - t0) / len(body_crops))
            prev = result.setdefault(f"body {variant} ms per crop", [])
            assert isinstance(prev, list)
            prev.append(round(1000 * float(np.median(per)), 1))
        print(f"round {r + 1}/{args.rounds}", flush=True)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

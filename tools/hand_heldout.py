"""Held-out-view error of the hand keypoints (``[detector] hands``, issue 44) on a Pose2Sim demo.

Per frame and camera: YOLO11n-pose's people, BlazePose's 33 landmarks on crops YOLO placed (``--body``; heavy by
default, as the issue-40 front end), and each person's two hand crops placed from the landmarks' wrist, index and
pinky (:mod:`mocapd.core.hand_roi`) through the hand landmark model (:mod:`mocapd.pipeline.hand_landmarks`). The
people of the four views are matched by the symmetric epipolar distance of their confident body landmarks (Hungarian
assignment against the view with the most people; a pair farther than ``MATCH_PX`` apart is not matched). For each
camera held out, every hand keypoint is triangulated from the other views (confidence-weighted DLT,
``core.camera.triangulate_projections``, views whose hand confidence is >= 0.5 only), projected into the held-out
camera with its distortion, and compared with that camera's own hand keypoint. Reported per finger (median, p90 px)
over hands >= ``--min-span`` px long in the held-out view (as the body sees it: MediaPipe's pose-derived hand box,
twice the wrist → middle-knuckle distance, so a wrong, sprawling detection does not pick itself in), and the share
of hands found per camera (of the hand crops the body placed there). The detector alone: no tracking, no solve.

    PYTHONPATH=$PWD nice -n 19 .venv/bin/python tools/hand_heldout.py --demo Demo_SinglePerson \\
        --out docs/detection/hand_heldout_single.json

The body landmarks of a demo are cached (``--cache``, an .npz per demo, body model and frame count) so that the
crop placement can be compared (``--scales``, ``--shifts``) without running BlazePose again.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from mocapd.core.camera import Camera, triangulate_projections
from mocapd.core.hand_roi import hand_roi_from_blazepose, hand_roi_from_hand
from mocapd.core.keypoints import BLAZEPOSE33_FORMAT as BLAZEPOSE33
from mocapd.core.keypoints import FINGERS, HAND21, HAND_SIDES
from mocapd.core.landmark_roi import LandmarkRoi
from mocapd.eval.heldout import camera_offsets
from mocapd.eval.video_input import pose2sim_take, with_calibration
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import ModelSpec
from mocapd.pipeline.hand_landmarks import HandRunner, Image
from mocapd.pipeline.landmarks import LandmarkRunner

MIN_CONFIDENCE = 0.5
MATCH_PX = 40.0
MAX_PEOPLE = 4
GROUPS = {"wrist": ("wrist",), **FINGERS}
PALM = ("wrist", "thumb_cmc", "index_finger_mcp", "middle_finger_mcp", "ring_finger_mcp", "pinky_mcp")
"""The points of the palm (the wrist and the five first joints), against the fingertips (the hardest to place)."""
TIPS = ("thumb_tip", "index_finger_tip", "middle_finger_tip", "ring_finger_tip", "pinky_tip")
_BODY_JOINTS = [BLAZEPOSE33.index(n) for n in ("left_shoulder", "right_shoulder", "left_hip", "right_hip",
                                               "left_elbow", "right_elbow", "left_knee", "right_knee")]  # fmt: skip
_HAND_POINTS = {s: [BLAZEPOSE33.index(f"{s}_{n}") for n in ("wrist", "index", "pinky")] for s in HAND_SIDES}


def bodies(demo: str, frames: int, variant: str, cache: Path | None) -> np.ndarray:
    """Each view's people as BlazePose landmarks, shape (F, C, MAX_PEOPLE, 33, 3) (zeros: nobody)."""
    path = None if cache is None else cache / f"{demo}-{variant}-{frames}.npz"
    if path is not None and path.is_file():
        return np.asarray(np.load(path)["bodies"])
    take = pose2sim_take(demo)
    det = OnnxPoseDetector(ModelSpec(), intra_op_threads=2)
    runner = LandmarkRunner(variant)
    caps = [cv2.VideoCapture(str(v)) for v in take.videos]
    out = np.zeros((frames, len(caps), MAX_PEOPLE, 33, 3))
    for f in range(frames):
        for c, cap in enumerate(caps):
            ok, read = cap.read()
            if not ok:
                raise SystemExit(f"{demo}: frame {f} of camera {c} unreadable")
            frame: Image = np.ascontiguousarray(read, np.uint8)
            found = det.detect(frame)
            keep = np.argsort(-(found.boxes[:, 3] - found.boxes[:, 1]))[:MAX_PEOPLE]
            if len(keep):
                lm = runner.run([frame], [found.keypoints[keep]])[0].keypoints
                out[f, c, : len(keep)] = lm
        print(f"bodies {f + 1}/{frames}", end="\r", flush=True)
    print()
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, bodies=out)
    return out


def _fundamental(a: Camera, b: Camera) -> np.ndarray:
    """F with x_b^T F x_a = 0 for undistorted pixels of cameras a and b."""
    pa, pb = a.projection_matrix, b.projection_matrix
    centre = np.linalg.svd(pa)[2][-1]
    e = pb @ centre
    ex = np.array([[0, -e[2], e[1]], [e[2], 0, -e[0]], [-e[1], e[0], 0]])
    return np.asarray(ex @ pb @ np.linalg.pinv(pa))


def _epipolar(f_ab: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> float:
    """Median symmetric point-to-epipolar-line distance (px) of matched undistorted points (n, 2) of a and b."""
    ha, hb = np.hstack([xa, np.ones((len(xa), 1))]), np.hstack([xb, np.ones((len(xb), 1))])
    lb, la = ha @ f_ab.T, hb @ f_ab
    db = np.abs(np.sum(lb * hb, axis=1)) / np.hypot(lb[:, 0], lb[:, 1])
    da = np.abs(np.sum(la * ha, axis=1)) / np.hypot(la[:, 0], la[:, 1])
    return float(np.median((da + db) / 2.0))


def associate(cameras: list[Camera], frame: np.ndarray, und: np.ndarray) -> list[np.ndarray]:
    """The people of one frame across views: a list of (C,) person indices (-1: not in that view).

    ``frame`` is (C, MAX_PEOPLE, 33, 3) landmarks, ``und`` their undistorted pixels (C, MAX_PEOPLE, 33, 2)."""
    n_c = len(cameras)
    present = frame[:, :, _BODY_JOINTS, 2].max(axis=2) > 0
    ref = int(np.argmax(present.sum(axis=1)))
    seeds = np.flatnonzero(present[ref])
    clusters = [np.full(n_c, -1) for _ in seeds]
    for k, s in enumerate(seeds):
        clusters[k][ref] = s
    for c in range(n_c):
        if c == ref:
            continue
        f_rc = _fundamental(cameras[ref], cameras[c])
        cand = np.flatnonzero(present[c])
        cost = np.full((len(seeds), len(cand)), 1e6)
        for i, s in enumerate(seeds):
            for j, p in enumerate(cand):
                ok = (frame[ref, s, _BODY_JOINTS, 2] >= MIN_CONFIDENCE) & (
                    frame[c, p, _BODY_JOINTS, 2] >= MIN_CONFIDENCE
                )
                if ok.sum() >= 3:
                    idx = np.array(_BODY_JOINTS)[ok]
                    cost[i, j] = _epipolar(f_rc, und[ref, s, idx], und[c, p, idx])
        for i, j in zip(*linear_sum_assignment(cost), strict=True):
            if cost[i, j] <= MATCH_PX:
                clusters[i][c] = cand[j]
    return clusters


def _rois(body: np.ndarray, scale: float, shift: float) -> list[LandmarkRoi | None]:
    out: list[LandmarkRoi | None] = []
    for s in HAND_SIDES:
        pts = body[_HAND_POINTS[s]]
        ok = bool(np.all(pts[:, 2] >= 0.3))
        out.append(
            hand_roi_from_blazepose(pts[0, :2], pts[1, :2], pts[2, :2], scale=scale, shift=shift) if ok else None
        )
    return out


def hands(
    demo: str,
    body: np.ndarray,
    placements: list[tuple[float, float]],
    variant: str,
    side_check: bool,
    refine: bool,
    given: dict[tuple[int, int, int, int], LandmarkRoi] | None = None,
) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """Hands per placement, shape (P, F, C, MAX_PEOPLE, 2, 21, 3), whether a crop was placed (F, C, MAX_PEOPLE, 2),
    and the model's time per crop (s) of each call. With ``given`` (crops by frame, camera, person and side) those
    crops instead of the body's, as one placement."""
    take = pose2sim_take(demo)
    runner = HandRunner(BLAZEPOSE33.keypoints, variant, side_check=side_check, refine=refine)
    caps = [cv2.VideoCapture(str(v)) for v in take.videos]
    n_f, n_c = body.shape[:2]
    out = np.zeros((len(placements), n_f, n_c, MAX_PEOPLE, 2, 21, 3))
    placed = np.zeros((n_f, n_c, MAX_PEOPLE, 2), dtype=bool)
    per_crop: list[float] = []
    for f in range(n_f):
        images: list[Image] = []
        for cap in caps:
            ok, read = cap.read()
            if not ok:
                raise SystemExit(f"{demo}: frame {f} unreadable")
            images.append(np.ascontiguousarray(read, np.uint8))
        for k, (scale, shift) in enumerate(placements):
            spots = [(c, p, s, r) for c in range(n_c) for p in range(MAX_PEOPLE) if body[f, c, p, :, 2].any()
                     for s, r in enumerate(_rois(body[f, c, p], scale, shift)) if r]  # fmt: skip
            if given is not None:
                spots = [(c, p, s, given[(f, c, p, s)]) for c, p, s, _ in spots if (f, c, p, s) in given]
            if not spots:
                continue
            t0 = time.perf_counter()
            found = runner.run_rois([images[c] for c, *_ in spots], [r for *_, r in spots], [s for _, _, s, _ in spots])
            per_crop.append((time.perf_counter() - t0) / len(spots))
            for (c, p, s, _), hand in zip(spots, found, strict=True):
                out[k, f, c, p, s] = hand
                placed[f, c, p, s] = True
        print(f"hands {f + 1}/{n_f}", end="\r", flush=True)
    print()
    return out, placed, per_crop


def consensus_rois(
    cameras: list[Camera], body: np.ndarray, hand: np.ndarray
) -> dict[tuple[int, int, int, int], LandmarkRoi]:
    """The crops all views agree on: each matched hand triangulated from every view that found it (>= 2), projected
    into each view of that person and cropped there as MediaPipe's tracking places a crop from a hand's own points
    (:func:`~mocapd.core.hand_roi.hand_roi_from_hand`). The best a crop placed from the body could do, short of the
    rig's own error: how much of the held-out error the crop placement explains."""
    n_f, n_c = body.shape[:2]
    P = np.stack([c.projection_matrix for c in cameras])
    out: dict[tuple[int, int, int, int], LandmarkRoi] = {}
    for f in range(n_f):
        und_body = np.stack([cam.undistort_points(body[f, c, :, :, :2]) for c, cam in enumerate(cameras)])
        for cl in associate(cameras, body[f], und_body):
            for s in range(2):
                kp = np.stack([hand[f, c, cl[c], s] if cl[c] >= 0 else np.zeros((21, 3)) for c in range(n_c)])
                w = np.where(kp[..., 2] >= MIN_CONFIDENCE, kp[..., 2], 0.0)
                if np.count_nonzero(w[:, 0]) < 2:
                    continue
                und = np.stack([cam.undistort_points(kp[c, :, :2]) for c, cam in enumerate(cameras)])
                X, ok = triangulate_projections(P, und, w)
                if not ok.all():
                    continue
                for c in range(n_c):
                    roi = hand_roi_from_hand(cameras[c].project(X)) if cl[c] >= 0 else None
                    if roi is not None:
                        out[(f, c, int(cl[c]), s)] = roi
    return out


def _hand_length(body: np.ndarray, side: int) -> float:
    """The hand's length in one view as the body sees it: MediaPipe's pose-derived hand box, twice the wrist →
    middle-knuckle distance (``(2 index + pinky) / 3``), independent of the hand model's own points."""
    wrist, index, pinky = body[_HAND_POINTS[HAND_SIDES[side]], :2]
    return float(2.0 * np.linalg.norm((2.0 * index + pinky) / 3.0 - wrist))


def held_out(cameras: list[Camera], body: np.ndarray, hand: np.ndarray, min_span: float) -> tuple[
    np.ndarray, np.ndarray, np.ndarray
]:  # fmt: skip
    """Signed held-out errors (n, 21, 2) (detected - predicted px, NaN where not compared), each row's held-out
    hand length (n,) and held-out camera (n,), over every frame, matched person, side and held-out camera."""
    n_f, n_c = body.shape[:2]
    P = np.stack([c.projection_matrix for c in cameras])
    rows, spans, held = [], [], []
    for f in range(n_f):
        und_body = np.stack([cam.undistort_points(body[f, c, :, :, :2]) for c, cam in enumerate(cameras)])
        for cl in associate(cameras, body[f], und_body):
            for s in range(2):
                kp = np.zeros((n_c, 21, 3))
                for c in range(n_c):
                    if cl[c] >= 0:
                        kp[c] = hand[f, c, cl[c], s]
                und = np.stack([cam.undistort_points(kp[c, :, :2]) for c, cam in enumerate(cameras)])
                w = np.where(kp[..., 2] >= MIN_CONFIDENCE, kp[..., 2], 0.0)
                for k in range(n_c):
                    if w[k, 0] == 0:
                        continue
                    span = _hand_length(body[f, k, cl[k]], s)
                    if span < min_span:
                        continue
                    keep = [c for c in range(n_c) if c != k]
                    X, ok = triangulate_projections(P[keep], und[keep], w[keep])
                    e = kp[k, :, :2] - cameras[k].project(X)
                    rows.append(np.where(ok[:, None], e, np.nan))
                    spans.append(span)
                    held.append(k)
    return np.array(rows).reshape(-1, 21, 2), np.array(spans), np.array(held, dtype=np.int64)


def body_reference(cameras: list[Camera], body: np.ndarray, min_span: float) -> dict[str, Any]:
    """The same held-out error of BlazePose's own wrist, pinky, index and thumb points (the body model, the same
    frames, people and size cut): the floor the footage sets for any hand keypoint."""
    names = ("wrist", "pinky", "index", "thumb")
    n_f, n_c = body.shape[:2]
    P = np.stack([c.projection_matrix for c in cameras])
    rows: list[np.ndarray] = []
    held: list[int] = []
    for f in range(n_f):
        und_body = np.stack([cam.undistort_points(body[f, c, :, :, :2]) for c, cam in enumerate(cameras)])
        for cl in associate(cameras, body[f], und_body):
            for s, side in enumerate(HAND_SIDES):
                cols = [BLAZEPOSE33.index(f"{side}_{n}") for n in names]
                kp = np.zeros((n_c, len(cols), 3))
                for c in range(n_c):
                    if cl[c] >= 0:
                        kp[c] = body[f, c, cl[c], cols]
                und = np.stack([cam.undistort_points(kp[c, :, :2]) for c, cam in enumerate(cameras)])
                w = np.where(kp[..., 2] >= MIN_CONFIDENCE, kp[..., 2], 0.0)
                for k in range(n_c):
                    if cl[k] < 0 or _hand_length(body[f, k, cl[k]], s) < min_span:
                        continue
                    keep = [c for c in range(n_c) if c != k]
                    X, ok = triangulate_projections(P[keep], und[keep], w[keep])
                    e = kp[k, :, :2] - cameras[k].project(X)
                    rows.append(np.where((ok & (w[k] > 0))[:, None], e, np.nan))
                    held.append(k)
    signed = np.array(rows).reshape(-1, len(names), 2)
    err = np.linalg.norm(signed, axis=-1)
    out: dict[str, Any] = {"per camera": _offsets(signed, np.array(held, dtype=np.int64), n_c)}
    for j, n in (*enumerate(names), (-1, "all")):
        e = err if j < 0 else err[:, j]
        e = e[np.isfinite(e)]
        out[n] = {"n": int(e.size)} if e.size == 0 else {
            "n": int(e.size), "median": round(float(np.median(e)), 1), "p90": round(float(np.percentile(e, 90)), 1)
        }  # fmt: skip
    return out


def _offsets(signed: np.ndarray, held: np.ndarray, n_cameras: int) -> dict[str, Any]:
    """Per held-out camera: the median error, the mean signed error (the camera's constant shift) and the median
    with that shift taken out (:func:`mocapd.eval.heldout.camera_offsets`)."""
    off = camera_offsets(signed, held, n_cameras)
    return {
        "median px": [round(float(v), 1) for v in off.median],
        "mean signed px (x, y)": [[round(float(v), 1) for v in m] for m in off.mean],
        "median px less the camera's mean": [round(float(v), 1) for v in off.median_less_mean],
    }


def summary(err: np.ndarray) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for g, names in (("all", HAND21), *GROUPS.items(), ("palm", PALM), ("fingertips", TIPS)):
        e = err[:, [HAND21.index(n) for n in names]]
        e = e[np.isfinite(e)]
        out[g] = {"n": int(e.size)} if e.size == 0 else {
            "n": int(e.size), "median": round(float(np.median(e)), 1), "p90": round(float(np.percentile(e, 90)), 1)
        }  # fmt: skip
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--demo", default="Demo_SinglePerson")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--body", default="heavy", help="BlazePose landmark model that places the hand crops")
    ap.add_argument("--hand", default="full", help="hand landmark model (full, lite)")
    ap.add_argument("--scales", type=float, nargs="*", default=None, help="crop sizes to compare (default: shipped)")
    ap.add_argument("--shifts", type=float, nargs="*", default=None, help="crop shifts to compare (default: shipped)")
    ap.add_argument("--min-span", type=float, default=60.0, help="hands at least this many px long (held-out view)")
    ap.add_argument("--side-check", action="store_true", help="confidence x the model's agreement with the side")
    ap.add_argument("--refine", action="store_true", help="a second pass on the crop each found hand's points place")
    ap.add_argument("--reference-only", action="store_true", help="only BlazePose's own hand points (no hand model)")
    ap.add_argument("--consensus", action="store_true", help="also a second pass on the crops all views agree on")
    ap.add_argument("--calibration", type=Path, help="score with this calibration file's cameras (default: the demo's)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/mocapd-hand-heldout"))
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    from mocapd.core.hand_roi import BLAZEPOSE_SCALE, BLAZEPOSE_SHIFT

    take = pose2sim_take(args.demo)
    if args.calibration is not None:
        take = with_calibration(take, args.calibration)
    n = min(args.frames, take.n_frames)
    body = bodies(args.demo, n, args.body, args.cache)
    reference = body_reference(take.cameras, body, args.min_span)
    print("BlazePose's own hand points:", json.dumps(reference))
    if args.reference_only:
        if args.out is not None:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps({"demo": args.demo, "frames": n, "body": args.body,
                                            "min_span_px": args.min_span, "blazepose hand points held-out px":
                                            reference}, indent=2) + "\n", encoding="utf-8")  # fmt: skip
        return
    placements = [(a, b) for a in (args.scales or [BLAZEPOSE_SCALE]) for b in (args.shifts or [BLAZEPOSE_SHIFT])]
    found, placed, per_crop = hands(args.demo, body, placements, args.hand, args.side_check, args.refine)
    labels = [f"scale {a}, shift {b}" for a, b in placements]
    if args.consensus:
        # A second pass on the crops every view's hands agree on, from the first placement's hands.
        given = consensus_rois(take.cameras, body, found[0])
        again, _, _ = hands(args.demo, body, placements[:1], args.hand, args.side_check, False, given)
        found = np.concatenate([found, again])
        placements.append(placements[0])
        labels.append("consensus crop")
    result: dict[str, Any] = {"demo": args.demo, "frames": n, "calibration": str(take.calibration),
                              "body": args.body, "hand": args.hand,
                              "side_check": args.side_check, "refine": args.refine, "min_span_px": args.min_span,
                              "blazepose hand points held-out px": reference, "placements": []}  # fmt: skip
    for k, (scale, shift) in enumerate(placements):
        all_signed, all_spans, all_held = held_out(take.cameras, body, found[k], 0.0)
        all_err = np.linalg.norm(all_signed, axis=-1)
        big = all_spans >= args.min_span
        err, spans = all_err[big], all_spans[big]
        hit = found[k][..., 0, 2] >= MIN_CONFIDENCE
        offsets = camera_offsets(all_signed[big], all_held[big], len(take.cameras))
        row: dict[str, Any] = {
            "crop": labels[k],
            "scale": scale,
            "shift": shift,
            "hands compared": len(spans),
            "hands compared, any size": len(all_spans),
            "held-out px": summary(err),
            "per held-out camera": _offsets(all_signed[big], all_held[big], len(take.cameras)),
            "held-out px less each camera's mean": summary(offsets.less_mean(all_signed[big], all_held[big])),
            "hands found per camera (of crops placed)": [
                round(float(hit[:, c].sum() / max(1, placed[:, c].sum())), 3) for c in range(placed.shape[1])
            ],
            "frames with a hand found per camera": [
                round(float(hit[:, c].any(axis=(1, 2)).mean()), 3) for c in range(placed.shape[1])
            ],
            "held-out hand length px (median)": round(float(np.median(all_spans)), 1) if len(all_spans) else None,
            "held-out px by hand length (median, p90, n points)": {
                f"{lo}-{hi} px": summary(all_err[(all_spans >= lo) & (all_spans < hi)])["all"]
                for lo, hi in ((0, 40), (40, 60), (60, 80), (80, 1000))
            },
        }
        result["placements"].append(row)
        print(json.dumps(row))
    result["ms per hand crop (median, p90)"] = [
        round(1000 * float(np.median(per_crop)), 1),
        round(1000 * float(np.percentile(per_crop, 90)), 1),
    ]
    print("ms per hand crop", result["ms per hand crop (median, p90)"])
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

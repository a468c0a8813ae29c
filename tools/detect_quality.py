"""Detection quality on the real Pose2Sim demo videos; prints one JSON object, saves annotated frames.

For each demo and camera: the fraction of frames in which each subject is detected with >= 12 keypoints of
confidence >= 0.5, and the bystanders (everyone else). People are followed per camera by box overlap; the
subjects are the ``n`` tracks with the largest (frames seen x median box height), ``n`` = 1 for the
single-person demo and 2 for the multi-person one. For the single-person demo the subject is triangulated
per frame from all cameras with the demo's own calibration (``Calib.qca.txt``, read here minimally the way
Pose2Sim converts it) and the median reprojection error is reported.

    .venv/bin/python tools/detect_quality.py --mode packed --out results/detection
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import triangulate_projections
from mocapd.core.keypoints import COCO17_FORMAT
from mocapd.core.pose2d import PoseDetections, box_iou
from mocapd.io.pose2sim_demo import CAMERAS, demo_calibration, demo_video
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.packing import packed_detector_from_config, render_canvas

CONF = 0.5
MIN_KP = 12
F64 = NDArray[np.float64]


@dataclass
class QcaCamera:
    name: str
    K: F64
    dist: F64
    R: F64  # world -> camera
    t: F64  # world -> camera, metres

    @property
    def projection(self) -> F64:
        return self.K @ np.hstack([self.R, self.t[:, None]])


def read_qca(path: Path) -> list[QcaCamera]:
    """Qualisys ``.qca.txt`` → OpenCV cameras, following Pose2Sim's ``calib_qca_fun`` (binning 1).

    Intrinsics are stored in 1/64 sub-pixels; the transform is the camera pose in the world (mm), which is
    inverted, then rotated by pi about the camera x axis (Qualisys cameras look along -z with y up).
    """
    root = ET.parse(path).getroot()
    cams = []
    for cam in root.findall("cameras/camera"):
        fov = cam.find("fov_video")
        intr = cam.find("intrinsic")
        tr = cam.find("transform")
        assert fov is not None and intr is not None and tr is not None
        g = intr.attrib
        fu, fv = float(g["focalLengthU"]) / 64, float(g["focalLengthV"]) / 64
        cu = float(g["centerPointU"]) / 64 - float(fov.attrib["left"])
        cv = float(g["centerPointV"]) / 64 - float(fov.attrib["top"])
        K = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
        dist = np.array(
            [
                float(g[k]) / 64
                for k in ("radialDistortion1", "radialDistortion2", "tangentalDistortion1", "tangentalDistortion2")
            ]
        )
        a = tr.attrib
        M = np.array([[float(a[f"r{i}{j}"]) for j in (1, 2, 3)] for i in (1, 2, 3)])
        C = np.array([float(a["x"]), float(a["y"]), float(a["z"])]) / 1000.0
        R = M  # Pose2Sim reads M.T (camera→world), and world_to_camera transposes it back: R = M, t = -R @ C
        t = -R @ C
        flip = np.diag([1.0, -1.0, -1.0])  # rotation by pi about x
        cams.append(QcaCamera(cam.attrib["serial"], K, dist, flip @ R, flip @ t))
    return sorted(cams, key=lambda c: c.name)


@dataclass
class Track:
    box: F64
    frames: list[int] = field(default_factory=list)
    heights: list[float] = field(default_factory=list)
    good: list[bool] = field(default_factory=list)
    dets: dict[int, int] = field(default_factory=dict)  # frame -> detection index


def track_camera(per_frame: list[PoseDetections]) -> list[Track]:
    """Greedy IoU tracking of one camera's detections over frames."""
    tracks: list[Track] = []
    for f, det in enumerate(per_frame):
        live = [t for t in tracks if t.frames and f - t.frames[-1] <= 10]
        used: set[int] = set()
        if len(det) and live:
            iou = box_iou(det.boxes, np.array([t.box for t in live]))
            for flat in np.argsort(-iou, axis=None):
                i, j = divmod(int(flat), len(live))
                if iou[i, j] < 0.3:
                    break
                if i in used or live[j].frames[-1] == f:
                    continue
                _add(live[j], f, i, det)
                used.add(i)
        for i in range(len(det)):
            if i not in used:
                t = Track(det.boxes[i])
                _add(t, f, i, det)
                tracks.append(t)
    return tracks


def _add(t: Track, f: int, i: int, det: PoseDetections) -> None:
    t.box = det.boxes[i]
    t.frames.append(f)
    t.heights.append(float(det.boxes[i, 3] - det.boxes[i, 1]))
    t.good.append(int((det.keypoints[i, :, 2] >= CONF).sum()) >= MIN_KP)
    t.dets[f] = i


def run_demo(
    demo: str, det: OnnxPoseDetector, cfg: DetectorConfig, mode: str, n_frames: int
) -> tuple[list[list[PoseDetections]], list[list[np.ndarray]], Any]:
    caps = [cv2.VideoCapture(str(demo_video(demo, c))) for c in CAMERAS]
    frames: list[list[np.ndarray]] = []
    for _ in range(n_frames):
        imgs = []
        for cap in caps:
            ok, img = cap.read()
            if not ok:
                break
            imgs.append(img)
        if len(imgs) != len(caps):
            break
        frames.append(imgs)
    sizes = [(im.shape[1], im.shape[0]) for im in frames[0]]
    results: list[list[PoseDetections]] = []  # [frame][camera]
    packer = packed_detector_from_config(cfg, sizes)
    sample_canvas = None
    for f in range(0, len(frames), 2):
        group = frames[f : f + 2]
        if mode == "naive":
            results.extend([det.detect(im) for im in cams] for cams in group)
        else:
            results.extend(packer.detect(group))
            if f == 50 and len(group) == 2:
                sample_canvas = (packer.last_packings, packer.last_tile_images)
    return results, frames, sample_canvas


def _triangulate(P: F64, uv: F64, w: F64) -> F64:
    """One keypoint from its views: P (n_cams, 3, 4), undistorted uv (n_cams, 2), weights (n_cams,)."""
    X, _ = triangulate_projections(P, uv[:, None], w[:, None])
    point: F64 = X[0]
    return point


def _errors(cams: list[QcaCamera], X: F64, raw: F64, views: NDArray[np.bool_]) -> F64:
    out = np.full(len(cams), np.nan)
    for c, cam in enumerate(cams):
        if views[c]:
            rvec = cv2.Rodrigues(cam.R)[0]
            proj = cv2.projectPoints(X[None], rvec, cam.t, cam.K, cam.dist)[0][0, 0]
            out[c] = float(np.linalg.norm(proj - raw[c]))
    return out


def reprojection(
    cams: list[QcaCamera], results: list[list[PoseDetections]], subject: list[dict[int, int]], reject_px: float = 20.0
) -> dict[str, Any]:
    """Reprojection error (px) of the subject triangulated per frame and keypoint from its confident views.

    ``all_views``: one confidence-weighted DLT over every confident view. ``robust``: while the worst view's
    error exceeds ``reject_px`` and more than 2 views remain, that view is dropped and the point
    re-triangulated (as Pose2Sim does); the share of views dropped is reported.
    """
    P = np.stack([c.projection for c in cams])
    errs: list[float] = []
    robust: list[float] = []
    n_points = dropped = 0
    for f in range(len(results)):
        uv = np.full((len(cams), 17, 2), np.nan)
        w = np.zeros((len(cams), 17))
        raw = np.full((len(cams), 17, 2), np.nan)
        for c, cam in enumerate(cams):
            i = subject[c].get(f)
            if i is None:
                continue
            kp = results[f][c].keypoints[i]
            und = cv2.undistortPoints(kp[:, None, :2].astype(np.float64), cam.K, cam.dist, P=cam.K)[:, 0]
            uv[c] = und
            raw[c] = kp[:, :2]
            w[c] = np.where(kp[:, 2] >= CONF, kp[:, 2], 0.0)
        for k in range(17):
            views = w[:, k] > 0
            if views.sum() < 2:
                continue
            X = _triangulate(P, uv[:, k], w[:, k])
            if not np.all(np.isfinite(X)):
                continue
            n_points += 1
            e = _errors(cams, X, raw[:, k], views)
            errs.extend(e[views].tolist())
            while views.sum() > 2 and np.nanmax(e) > reject_px:
                views[int(np.nanargmax(e))] = False
                dropped += 1
                X = _triangulate(P, uv[:, k], np.where(views, w[:, k], 0.0))
                e = _errors(cams, X, raw[:, k], views)
            robust.extend(e[views].tolist())
    a, r = np.array(errs), np.array(robust)
    if not a.size:
        return {"triangulated_points": 0}
    return {
        "reprojection_px_median_all_views": round(float(np.median(a)), 2),
        "reprojection_px_p90_all_views": round(float(np.percentile(a, 90)), 2),
        "reprojection_px_median_robust": round(float(np.median(r)), 2),
        "reprojection_px_p90_robust": round(float(np.percentile(r, 90)), 2),
        "robust_views_dropped_fraction": round(dropped / a.size, 3),
        "triangulated_points": n_points,
        "views": int(a.size),
    }


def draw(img: np.ndarray, det: PoseDetections, subjects: set[int]) -> np.ndarray:
    out = img.copy()
    for i in range(len(det)):
        color = (0, 200, 0) if i in subjects else (0, 140, 255)
        x0, y0, x1, y1 = det.boxes[i].astype(int)
        cv2.rectangle(out, (x0, y0), (x1, y1), color, 3)
        kp = det.keypoints[i]
        for a, b in COCO17_FORMAT.edges:
            if kp[a, 2] >= CONF and kp[b, 2] >= CONF:
                cv2.line(out, tuple(kp[a, :2].astype(int)), tuple(kp[b, :2].astype(int)), color, 4)
        for x, y, c in kp:
            if c >= CONF:
                cv2.circle(out, (int(x), int(y)), 7, (255, 255, 255), -1)
                cv2.circle(out, (int(x), int(y)), 7, color, 2)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mode", choices=("naive", "packed"), default="packed")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("results/detection"))
    ap.add_argument("--demo", choices=("both", "Demo_SinglePerson", "Demo_MultiPerson"), default="both")
    packing = DetectorConfig().packing
    ap.add_argument("--refresh-every", type=int, default=packing.refresh_every, help="0: no whole-frame refresh")
    ap.add_argument("--max-tile-height", type=float, default=packing.max_tile_height, help="0: no tile cap")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    packing = dataclasses.replace(packing, refresh_every=args.refresh_every, max_tile_height=args.max_tile_height)
    # The shipped defaults (config.toml) unless overridden above.
    cfg = DetectorConfig(intra_op_threads=args.threads, packing=packing)
    det = OnnxPoseDetector.from_config(cfg)
    report: dict[str, Any] = {"mode": args.mode, "confident": CONF, "min_keypoints": MIN_KP}
    if args.mode == "packed":
        report["packing"] = dataclasses.asdict(cfg.packing)
    for demo, n_subjects in (("Demo_SinglePerson", 1), ("Demo_MultiPerson", 2)):
        if args.demo not in ("both", demo):
            continue
        results, frames, sample = run_demo(demo, det, cfg, args.mode, args.frames)
        n = len(results)
        per_cam: dict[str, Any] = {}
        subject_maps: list[dict[int, int]] = []
        for c, cam in enumerate(CAMERAS):
            tracks = track_camera([results[f][c] for f in range(n)])
            ranked = sorted(tracks, key=lambda t: -len(t.frames) * float(np.median(t.heights)))
            subs, others = ranked[:n_subjects], ranked[n_subjects:]
            subject_maps.append(subs[0].dets if subs else {})
            per_cam[cam] = {
                "subjects_detected_fraction": [round(sum(t.good) / n, 3) for t in subs],
                "subject_median_height_px": [round(float(np.median(t.heights))) for t in subs],
                "bystanders_tracked": sum(1 for t in others if len(t.frames) >= 5),
                "bystander_detections_per_frame": round(sum(len(t.frames) for t in others) / n, 2),
            }
            # Annotated frame 50 of this camera.
            f = min(50, n - 1)
            sub_idx = {t.dets[f] for t in subs if f in t.dets}
            img = draw(frames[f][c], results[f][c], sub_idx)
            cv2.imwrite(str(args.out / f"{demo}_{cam}_f{f:03d}_{args.mode}.png"), cv2.resize(img, None, fx=0.5, fy=0.5))
        entry: dict[str, Any] = {"frames": n, "cameras": per_cam}
        if n_subjects == 1:
            entry.update(reprojection(read_qca(demo_calibration(demo)), results, subject_maps))
        report[demo] = entry
        if sample is not None:
            packings, items = sample
            for k, p in enumerate(packings):
                cv2.imwrite(str(args.out / f"{demo}_packed_canvas{k}.png"), render_canvas(p, items, 114))
    json.dump(report, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())

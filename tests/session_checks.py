"""Checks of a recorded camera session against its own images' detections, computed here with OpenCV and numpy
from the session's calibration, not with mocapd's camera, kinematics or body-size code.

The 12 COCO-17 limb keypoints (shoulders, elbows, wrists, hips, knees, ankles) are track targets at joints with a
zero offset, so a published person's joint positions are where those keypoints must reproject. Each camera frame
the detector saw (a keypoint record) is compared with the pose published for the same instant: the detected
person nearest the subject's reprojection is that subject in that camera.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.io.session import Session
from mocapd.protocols.session_format import KeypointRecord, PersonRecord, PoseRecord

FloatArray = NDArray[np.float64]

LIMB_KEYPOINTS = slice(5, 17)
"""COCO-17 left/right shoulder, elbow, wrist, hip, knee, ankle."""
LIMB_JOINTS = [7, 10, 8, 11, 9, 12, 13, 17, 14, 18, 15, 19]
"""The joints (bone origins) those keypoints sit on: upper arms, lower arms, hands, upper legs, lower legs, feet."""
SEGMENTS = {"upper arm": ((0, 2), (1, 3)), "forearm": ((2, 4), (3, 5)), "thigh": ((6, 8), (7, 9)),
            "shank": ((8, 10), (9, 11))}  # fmt: skip
"""Limb segments as pairs of indices into the 12 limb keypoints, left and right."""
MIRROR = [1, 0, 3, 2, 5, 4, 7, 6, 9, 8, 11, 10]
"""The 12 limb keypoints with left and right exchanged."""
MIN_CONFIDENCE = 0.5
MIN_KEYPOINTS = 6


@dataclass
class SubjectFit:
    """How one published subject fits the detections."""

    errors_px: dict[int, list[float]] = field(default_factory=lambda: defaultdict(list))
    """Per camera: for each compared camera frame, the median distance (px) between the subject's reprojected
    limb joints and the matched detection's confident limb keypoints."""
    detections: dict[int, dict[int, FloatArray]] = field(default_factory=lambda: defaultdict(dict))
    """Per camera frame (capture ns): per camera, the matched detection's 12 limb keypoints, (12, 3) = x, y, conf."""


def project(camera: dict[str, Any], points: FloatArray) -> FloatArray:
    """World points (n, 3) to distorted pixels (n, 2) through a manifest camera (OpenCV's model)."""
    rvec, _ = cv2.Rodrigues(np.asarray(camera["R"], np.float64))
    uv, _ = cv2.projectPoints(np.asarray(points, np.float64).reshape(-1, 1, 3), rvec,
                              np.asarray(camera["t"], np.float64), np.asarray(camera["K"], np.float64),
                              np.asarray(camera["dist"], np.float64))  # fmt: skip
    return np.asarray(uv, np.float64).reshape(-1, 2)


def check_limb_targets(manifest: dict[str, Any]) -> None:
    """The session's keypoints 5..16 are the limb joints themselves (zero offsets), as this module assumes."""
    bones = manifest["targets"]["bones"][LIMB_KEYPOINTS]
    offsets = np.asarray(manifest["targets"]["offsets"])[LIMB_KEYPOINTS]
    assert bones == LIMB_JOINTS and not offsets.any(), (bones, offsets)


def _pose_at(poses: list[PoseRecord], t_solve: NDArray[np.int64], t_ns: int, tolerance_ns: int) -> PoseRecord | None:
    i = int(np.searchsorted(t_solve, t_ns))
    best = min((j for j in (i - 1, i) if 0 <= j < len(poses)), key=lambda j: abs(int(t_solve[j]) - t_ns), default=None)
    return poses[best] if best is not None and abs(int(t_solve[best]) - t_ns) <= tolerance_ns else None


def _match(person: PersonRecord, camera: dict[str, Any], record: KeypointRecord) -> tuple[float, FloatArray] | None:
    """The detection of ``record`` that best fits ``person``: its median limb-keypoint error (px) and keypoints.

    A detector mirrors a person now and then (left and right limbs swapped, docs/detection.md), and the solve
    rightly leaves such a view out; each detection is taken as detected or mirrored, whichever fits."""
    uv = project(camera, np.asarray(person.joints, np.float64)[LIMB_JOINTS])
    best: tuple[float, FloatArray] | None = None
    for kp, conf in zip(record.keypoints, record.confidences, strict=True):
        limbs = np.column_stack([kp[LIMB_KEYPOINTS], conf[LIMB_KEYPOINTS]])
        for candidate in (limbs, limbs[MIRROR]):
            ok = candidate[:, 2] >= MIN_CONFIDENCE
            if ok.sum() < MIN_KEYPOINTS:
                continue
            err = float(np.median(np.linalg.norm(candidate[ok, :2] - uv[ok], axis=1)))
            if best is None or err < best[0]:
                best = (err, candidate)
    return best


def subject_fits(session: Session, tolerance_ns: int | None = None) -> dict[str, SubjectFit]:
    """Every published subject against every detected camera frame, with the pose published nearest its capture
    time (at most ``tolerance_ns`` away; default half an output tick)."""
    manifest = session.manifest
    check_limb_targets(manifest)
    cameras = manifest["cameras"]
    offsets = manifest["scheduler"]["camera_offsets_ns"]
    half_tick = int(0.5e9 / manifest["scheduler"]["rate_hz"]) if tolerance_ns is None else tolerance_ns
    poses = [f for f in session.poses() if f.people]
    t_solve = np.array([f.t_solve_ns for f in poses], dtype=np.int64)
    fits: dict[str, SubjectFit] = defaultdict(SubjectFit)
    for record in session.keypoints():
        t = record.capture_ns + offsets[record.camera]
        frame = _pose_at(poses, t_solve, t, half_tick)
        if frame is None:
            continue
        for person in frame.people:
            found = _match(person, cameras[record.camera], record)
            if found is not None:
                fits[person.identity].errors_px[record.camera].append(found[0])
                fits[person.identity].detections[t][record.camera] = found[1]
    return dict(fits)


def triangulate(cameras: list[dict[str, Any]], views: dict[int, FloatArray]) -> FloatArray:
    """Linear (DLT) triangulation of the 12 limb keypoints from their confident detections in two or more
    cameras (undistorted with OpenCV); NaN where fewer than two cameras are confident. Returns (12, 3)."""
    out = np.full((12, 3), np.nan)
    rows: list[list[FloatArray]] = [[] for _ in range(12)]
    for cam, kp in views.items():
        c = cameras[cam]
        K, R, t = (np.asarray(c[k], np.float64) for k in ("K", "R", "t"))
        P = K @ np.hstack([R, t[:, None]])
        uv = cv2.undistortPoints(kp[:, None, :2].astype(np.float64), K, np.asarray(c["dist"], np.float64), P=K)
        for j, (u, v) in enumerate(uv.reshape(-1, 2)):
            if kp[j, 2] >= MIN_CONFIDENCE:
                rows[j] += [u * P[2] - P[0], v * P[2] - P[1]]
    for j, a in enumerate(rows):
        if len(a) >= 4:
            _, _, vt = np.linalg.svd(np.array(a))
            out[j] = vt[-1, :3] / vt[-1, 3]
    return out


def segment_lengths(points: FloatArray) -> dict[str, float]:
    """Left/right mean length of each limb segment from 12 limb points (NaN when neither side is known)."""
    out = {}
    for name, sides in SEGMENTS.items():
        lengths = [float(np.linalg.norm(points[a] - points[b])) for a, b in sides]
        out[name] = float(np.nanmean(lengths)) if not all(np.isnan(lengths)) else np.nan
    return out


def triangulated_segments(session: Session, fit: SubjectFit, window_ns: int) -> dict[str, float]:
    """Median over instants of each limb segment's length triangulated from the subject's matched detections in
    three or more cameras whose frames were captured within ``window_ns`` of each other."""
    cameras = session.manifest["cameras"]
    times = sorted(fit.detections)
    samples: dict[str, list[float]] = defaultdict(list)
    for i, t in enumerate(times):
        views = dict(fit.detections[t])
        for u in times[i + 1 :]:
            if u - t > window_ns:
                break
            views.update({c: kp for c, kp in fit.detections[u].items() if c not in views})
        if len(views) >= 3:
            for name, value in segment_lengths(triangulate(cameras, views)).items():
                if np.isfinite(value):
                    samples[name].append(value)
    return {name: float(np.median(v)) for name, v in samples.items()}


def published_segments(frames: list[PoseRecord], identity: str) -> list[dict[str, float]]:
    """The limb segment lengths (from its joints) of each pose published for one subject on its own body-sized
    skeleton."""
    return [segment_lengths(np.asarray(p.joints, np.float64)[LIMB_JOINTS])
            for f in frames for p in f.people if p.identity == identity and p.skeleton is not None]  # fmt: skip

"""Held-out-view reprojection error of the learned stream and of the LM solver on real footage (issue 30).

The Pose2Sim single-person demo (4 real 60 fps portrait cameras, BSD-3, ``mocapd.io.pose2sim_demo``) has no 3D
ground truth. Issue 29's held-out-view metric stands in for one: for each camera k, every method sees the other
cameras only, its 3D result is projected into k and compared with k's own confident detections (the 12 limb
keypoints, which sit on the skeleton's joints: shoulders, elbows, wrists, hips, knees, ankles; median and 90th
percentile in pixels). Issue 29's ``mocapd eval video`` was not on main when this was written: this module
computes the same metric itself (:func:`held_out_errors`).

Inputs: the detector on every frame of every camera (the subject is each view's largest detection: the demo's
bystander stands far behind), and foreground mattes. A live rig's MOG2 subtractor
(:class:`~mocapd.pipeline.mattes.BackgroundMatte`) learns the background over minutes; the demo is 1.7 s with the
subject in every frame, and MOG2 run over it absorbs the subject's inside into the background (hollow outlines).
:func:`clean_plate_mattes` does what seed 001 does, against a clean plate estimated from the take itself: each
pixel's median over the frames where the detected subject is not near it.

Methods: the naive confidence-weighted DLT, the LM solver (no IMUs: the demo has none), the learned stream's joints
(PVH network + vision LSTM on every 3rd frame, as the daemon), the skeleton fitted to them (``mode = "learned"``)
and the LM solve with them as E_J (``mode = "both"``).
"""

from __future__ import annotations

import hashlib
import json
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.body_size import estimate_skeleton
from mocapd.core.camera import Camera, project_points, triangulate
from mocapd.core.fusion_features import N_JOINTS
from mocapd.core.keypoints import COCO17, COCO17_FORMAT, coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.prior import PcaPrior
from mocapd.core.pvh import carve, joint_map, joint_sigma, log_channels, person_centre, scaled_pixels
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.core.solver import Observations, PoseSolver
from mocapd.core.terms import CostOptions
from mocapd.errors import InputError
from mocapd.io.calibration_files import core_cameras, read_qca
from mocapd.io.model_cache import cache_dir
from mocapd.io.pose2sim_demo import CAMERAS, demo_calibration, demo_video
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.fusion import FusionModels, PersonFusion
from mocapd.pipeline.scheduler import initial_pose

FloatArray = NDArray[np.float64]
F32 = NDArray[np.float32]

LIMB_KEYPOINTS = tuple(i for i, (_, _, off) in enumerate(COCO17) if i >= 5 and not any(off))
"""COCO-17 keypoints with a zero offset on their bone (shoulders … ankles): both the skeleton's and the learned
joints project onto them."""
LIMB_BONES = tuple(BONE_INDEX[COCO17[i][1]] for i in LIMB_KEYPOINTS)
MIN_CONFIDENCE = 0.5
"""Held-out detections below this confidence are not compared against."""


@dataclass
class VideoInputs:
    """One demo's detections and mattes (cached on disk: the detector over 400 frames takes minutes here)."""

    cameras: list[Camera]
    uv: FloatArray  # (f, n_cams, 17, 2) the subject's keypoints, NaN where none
    conf: FloatArray  # (f, n_cams, 17)
    mattes: list[F32]  # per camera (f, h, w) (the cameras' sizes differ)


def _cache_key(demo: str, frames: int, scale: int) -> str:
    h = hashlib.sha256()
    for c in CAMERAS:
        h.update(demo_video(demo, c).read_bytes()[: 1 << 20])
    return f"{demo}-{frames}-{scale}-{h.hexdigest()[:12]}"


def video_inputs(
    detector: DetectorConfig, demo: str = "Demo_SinglePerson", max_frames: int = 100, scale: int = 8
) -> VideoInputs:
    """Detect the subject in every frame of the demo's cameras with the ``[detector]`` of ``detector`` (cached: the
    detector over 400 frames takes minutes here) and compute their mattes."""
    cams = core_cameras(read_qca(demo_calibration(demo)))
    cache = cache_dir() / "fusion-video" / f"{_cache_key(demo, max_frames, scale)}.npz"
    small = _small_frames(demo, max_frames, scale)
    if cache.is_file():
        d = np.load(cache)
        uv_a, conf_a = d["uv"], d["conf"]
    else:
        uv_a, conf_a = _detect(detector, demo, len(small[0]))
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(cache, uv=uv_a, conf=conf_a)
    f = min(len(uv_a), len(small[0]))
    mattes = [clean_plate_mattes(np.stack(small[c][:f]), uv_a[:f, c], conf_a[:f, c], scale) for c in range(len(cams))]
    return VideoInputs(cams, uv_a[:f], conf_a[:f], mattes)


def _small_frames(demo: str, max_frames: int, scale: int) -> list[list[NDArray[np.uint8]]]:
    """Every camera's frames at ``1/scale`` (BGR)."""
    out: list[list[NDArray[np.uint8]]] = []
    for c in CAMERAS:
        cap = cv2.VideoCapture(str(demo_video(demo, c)))
        frames: list[NDArray[np.uint8]] = []
        while len(frames) < max_frames:
            ok, img = cap.read()
            if not ok:
                break
            h, w = img.shape[:2]
            frames.append(
                np.asarray(cv2.resize(img, (-(-w // scale), -(-h // scale)), interpolation=cv2.INTER_AREA), np.uint8)
            )
        out.append(frames)
    n = min(len(x) for x in out)
    if n == 0:
        raise InputError(f"{demo}: no frames could be read")
    return [x[:n] for x in out]


def _detect(detector: DetectorConfig, demo: str, n: int) -> tuple[FloatArray, FloatArray]:
    """The subject's keypoints (n, n_cams, 17, 2) and confidences in every frame: each view's largest detection."""
    from mocapd.pipeline.detector import OnnxPoseDetector

    det = OnnxPoseDetector.from_config(detector)
    caps = [cv2.VideoCapture(str(demo_video(demo, c))) for c in CAMERAS]
    uv = np.full((n, len(caps), 17, 2), np.nan)
    conf = np.zeros((n, len(caps), 17))
    for t in range(n):
        for c, cap in enumerate(caps):
            ok, img = cap.read()
            if not ok:
                raise InputError(f"{demo}: camera {CAMERAS[c]} ended at frame {t}")
            people = det.detect(np.asarray(img, dtype=np.uint8)).keypoints  # (n, 17, 3)
            if not len(people):
                continue
            xy, cf = people[..., :2], people[..., 2]
            seen = np.where(cf[..., None] > 0.3, xy, np.nan)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # a detection with no confident keypoint
                span = np.nan_to_num(np.nanmax(seen, axis=1) - np.nanmin(seen, axis=1), nan=0.0)
            k = int(np.argmax(span[:, 0] * span[:, 1]))  # the largest person: the subject
            uv[t, c] = xy[k]
            conf[t, c] = np.clip(cf[k], 0.0, 1.0)
    return uv, conf


PLATE_THRESHOLD = 30.0
"""Colour distance (Lab units) from the clean plate at which a pixel is half foreground; ±15 spans 0 to 1."""


def clean_plate_mattes(frames: NDArray[np.uint8], uv: FloatArray, conf: FloatArray, scale: int) -> F32:
    """Seed 001's occupancy channel on a take without a clean plate: the plate is each pixel's median colour over
    the frames where the detected subject is not near it (thick limbs between the confident keypoints, masked);
    a frame's matte is the soft-thresholded Lab distance to it, blurred by a pixel.

    Parameters
    ----------
    frames : (f, h, w, 3) BGR at the PVH's scale; uv : (f, 17, 2) the subject's keypoints (full-resolution
    pixels); conf : (f, 17).

    Returns
    -------
    (f, h, w) float32 in [0, 1].
    """
    f, h, w = frames.shape[:3]
    masked = np.zeros((f, h, w), dtype=bool)
    for t in range(f):
        ok = conf[t] > 0.3
        if ok.sum() < 2:
            continue
        pts = (uv[t] + 0.5) / scale - 0.5
        size = float(np.max(np.ptp(pts[ok], axis=0)))
        m = np.zeros((h, w), np.uint8)
        thick = max(2, round(0.2 * size))
        for a, b in COCO17_FORMAT.edges:
            if ok[a] and ok[b]:
                cv2.line(m, tuple(int(v) for v in pts[a]), tuple(int(v) for v in pts[b]), 1, thick)
        for k in np.flatnonzero(ok):
            cv2.circle(m, tuple(int(v) for v in pts[k]), thick, 1, -1)
        masked[t] = m > 0
    lab = np.stack([cv2.cvtColor(fr, cv2.COLOR_BGR2LAB) for fr in frames]).astype(np.float32)
    free = np.where(masked[..., None], np.nan, lab)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # pixels the subject covers in every frame
        plate = np.nanmedian(free, axis=0)
    plate = np.where(np.isnan(plate), np.median(lab, axis=0), plate)
    d = np.linalg.norm(lab - plate, axis=-1)
    p = np.clip((d - PLATE_THRESHOLD) / 30.0 + 0.5, 0.0, 1.0).astype(np.float32)
    return np.stack([np.asarray(cv2.GaussianBlur(x, (0, 0), 0.8), np.float32) for x in p])


def held_out_errors(points: FloatArray, camera: Camera, uv: FloatArray, conf: FloatArray) -> FloatArray:
    """Pixel distances between 3D points projected into ``camera`` and its confident detections.

    Parameters
    ----------
    points : (f, 12, 3) the limb joints (NaN rows skipped); uv : (f, 17, 2); conf : (f, 17) of that camera.

    Returns
    -------
    flat array of the distances (px) where the detection is confident and the point finite.
    """
    idx = list(LIMB_KEYPOINTS)
    proj, _, vis = project_points(camera.K, camera.dist, camera.R, camera.t, np.nan_to_num(points).reshape(-1, 3),
                                  jacobian=False)  # fmt: skip
    proj = proj.reshape(points.shape[0], len(idx), 2)
    ok = (conf[:, idx] >= MIN_CONFIDENCE) & np.all(np.isfinite(points), axis=-1) & vis.reshape(points.shape[:2])
    d = np.linalg.norm(proj - np.nan_to_num(uv[:, idx]), axis=-1)
    return np.asarray(d[ok])


def _skeleton(cams: list[Camera], uv: FloatArray, conf: FloatArray) -> Skeleton:
    kp = np.stack([triangulate(cams, np.nan_to_num(uv[t]), conf[t])[0] for t in range(uv.shape[0])])
    try:
        return estimate_skeleton(kp)
    except InputError:
        return Skeleton.from_height(1.75)


def run(
    models: FusionModels, prior: PcaPrior | None, cost: CostOptions, inputs: VideoInputs, weight: float
) -> dict[str, Any]:
    """Every method's held-out-view errors, per held-out camera and pooled."""
    n_cams = len(inputs.cameras)
    f = inputs.uv.shape[0]
    stride = models.stride
    results: dict[str, dict[str, list[float]]] = {}
    per_camera: dict[str, dict[str, Any]] = {}
    g = models.grid
    for k in range(n_cams):
        views = [c for c in range(n_cams) if c != k]
        cams = [inputs.cameras[c] for c in views]
        uv, conf = inputs.uv[:, views], inputs.conf[:, views]
        sk = _skeleton(cams, uv, conf)
        targets = coco17_targets(sk)
        kin = Kinematics(sk)
        limbs = list(LIMB_BONES)
        # naive DLT
        dlt = np.stack([triangulate(cams, np.nan_to_num(uv[t]), conf[t])[0][list(LIMB_KEYPOINTS)] for t in range(f)])
        # learned stream (vision only: no IMUs in the demo) on every stride-th frame
        pf = PersonFusion(models)
        learned: dict[int, FloatArray] = {}
        centre = None
        for t in range(0, f, stride):
            centre = person_centre(cams, uv[t], conf[t], fallback=centre)
            if centre is None:
                continue
            imgs = []
            valid = np.ones((len(cams), 2), dtype=bool)
            for i, cam in enumerate(cams):
                m = inputs.mattes[views[i]][t]
                seen = bool(np.any(conf[t, i] > 0))
                valid[i, 1] = seen
                jm = (
                    joint_map(scaled_pixels(np.nan_to_num(uv[t, i]), g.scale), conf[t, i], m.shape,
                              joint_sigma(cam, centre, g.scale))
                    if seen
                    else np.ones_like(m)
                )  # fmt: skip
                imgs.append(log_channels(np.stack((m, jm))))
            pvh = carve(g, centre, cams, imgs, valid)
            learned[t] = pf.step(pvh, centre, int(valid[:, 1].sum()), None).vision
        learned_frames = sorted(learned)
        stream = np.full((f, N_JOINTS, 3), np.nan)
        for t in learned_frames:
            stream[t] = learned[t]
        between: dict[int, FloatArray] = {}
        for i, t in enumerate(learned_frames):
            step = (learned[t] - learned[learned_frames[i - 1]]) / stride if i > 0 else np.zeros((N_JOINTS, 3))
            for d in range(stride):
                if t + d < f:
                    between[t + d] = learned[t] + d * step
        start = np.stack([triangulate(cams, np.nan_to_num(uv[0]), conf[0])[0]])[0]
        theta0 = initial_pose(sk, start)
        solves: dict[str, FloatArray] = {}
        for name, solver_cams, joints in (
            ("LM solver", cams, None),
            ("learned (skeleton fit)", [], between),
            ("both", cams, learned),
        ):
            solver = PoseSolver(sk, solver_cams, targets, (), prior, replace(cost, lambda_learned=weight))
            solver.reset(theta0)
            out = np.zeros((f, N_JOINTS, 3))
            for t in range(f):
                obs = Observations(
                    keypoints=np.nan_to_num(uv[t]) if solver_cams else None,
                    confidences=conf[t] if solver_cams else None,
                    joint_positions=None if joints is None else joints.get(t),
                    dt=1.0 / 60.0,
                )
                out[t] = kin.forward(solver.solve(obs).theta).positions
            solves[name] = out[:, limbs]
        methods = {
            "naive DLT": dlt,
            **solves,
            "learned stream (joints)": stream[:, limbs],
        }
        cam_name = inputs.cameras[k].name
        per_camera[cam_name] = {}
        for name, pts in methods.items():
            e = held_out_errors(pts, inputs.cameras[k], inputs.uv[:, k], inputs.conf[:, k])
            results.setdefault(name, {"errors": []})["errors"].extend(e.tolist())
            per_camera[cam_name][name] = _summary(e)
    return {
        "pooled": {name: _summary(np.asarray(r["errors"])) for name, r in results.items()},
        "per_held_out_camera": per_camera,
        "frames": f,
        "learned_frames_every": stride,
    }


def _summary(e: FloatArray) -> dict[str, float]:
    if e.size == 0:
        return {"median_px": float("nan"), "p90_px": float("nan"), "n": 0}
    return {"median_px": round(float(np.median(e)), 2), "p90_px": round(float(np.percentile(e, 90)), 2),
            "n": int(e.size)}  # fmt: skip


def markdown(res: dict[str, Any], demo: str) -> str:
    lines = [
        f"### Held-out-view reprojection error on real footage ({demo}, {res['frames']} frames, 4 cameras)",
        "",
        "Each camera in turn held out; every method sees the other three; pixels between its limb joints projected"
        f" into the held-out camera and that camera's detections of confidence ≥ {MIN_CONFIDENCE}. The learned"
        f" stream runs on every {res['learned_frames_every']}rd frame (its row counts those frames only).",
        "",
        "| method | median px | p90 px | comparisons |",
        "|---|---|---|---|",
    ]
    for name, s in res["pooled"].items():
        lines.append(f"| {name} | {s['median_px']:.1f} | {s['p90_px']:.1f} | {s['n']} |")
    lines += ["", "Per held-out camera, median px:", ""]
    cams = list(res["per_held_out_camera"])
    names = list(res["pooled"])
    lines += ["| method | " + " | ".join(cams) + " |", "|---|" + "---|" * len(cams)]
    for name in names:
        cells = [f"{res['per_held_out_camera'][c][name]['median_px']:.1f}" for c in cams]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append("")
    return "\n".join(lines)


def save(res: dict[str, Any], out: Path, demo: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "video.json").write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
    (out / "video.md").write_text(markdown(res, demo), encoding="utf-8")

"""Held-out-view reprojection error of the learned stream and of the LM solver on real footage (issue 30).

The Pose2Sim single-person demo (4 real 60 fps portrait cameras, BSD-3, ``mocapd.io.pose2sim_demo``) has no 3D
ground truth. Issue 29's held-out-view metric stands in for one: for each camera k, every method sees the other
cameras only, its 3D result is projected into k and compared with k's own confident detections by issue 29's
:func:`mocapd.eval.heldout.held_out_errors`, the function ``mocapd eval video`` scores with (docs/accuracy-video.md):
the projected person matched to one of k's detections (Hungarian on the median distance, gated at half the
detection's height), the error at every keypoint k detected with confidence >= 0.5. The keypoints compared are the
12 limb keypoints, which sit on the skeleton's joints (shoulders, elbows, wrists, hips, knees, ankles): the learned
stream gives joints, and issue 29's 13th keypoint, the nose, is not one. *Common*: only the (held-out camera,
frame, detection, keypoint) that every method was compared on.

Inputs: ``mocapd eval video``'s own detections of the take (:func:`mocapd.eval.video_input.detect_take`: the
evaluation's FP32 detector, cached in ``<cache>/eval-video/``), the subject being each view's largest detection
(the demo's bystander stands far behind), and foreground mattes. A live rig's MOG2 subtractor
(:class:`~mocapd.pipeline.mattes.BackgroundMatte`) learns the background over minutes; the demo is 1.7 s with the
subject in every frame, and MOG2 run over it absorbs the subject's inside into the background (hollow outlines).
:func:`clean_plate_mattes` does what seed 001 does, against a clean plate estimated from the take itself: each
pixel's median over the frames where the detected subject is not near it.

Methods: the naive confidence-weighted DLT, the LM solver (no IMUs: the demo has none), the learned stream's joints
(PVH network + vision LSTM on every 3rd frame, as the daemon), the skeleton fitted to them (``mode = "learned"``)
and the LM solve with them as E_J (``mode = "both"``).
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.body_size import estimate_skeleton
from mocapd.core.camera import Camera, triangulate
from mocapd.core.fusion_features import N_JOINTS
from mocapd.core.keypoints import COCO17, COCO17_FORMAT, coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.prior import PcaPrior
from mocapd.core.pvh import carve, joint_map, joint_sigma, log_channels, person_centre, scaled_pixels
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.core.solver import Observations, PoseSolver
from mocapd.core.sorting import Detections2D
from mocapd.core.terms import CostOptions
from mocapd.core.warm_start import initial_pose
from mocapd.errors import InputError
from mocapd.eval.heldout import held_out_errors, summarize
from mocapd.eval.video_input import detect_take, eval_detector_config, pose2sim_take
from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.fusion import FusionModels, PersonFusion

FloatArray = NDArray[np.float64]
F32 = NDArray[np.float32]

LIMB_KEYPOINTS = tuple(i for i, (_, _, off) in enumerate(COCO17) if i >= 5 and not any(off))
"""COCO-17 keypoints with a zero offset on their bone (shoulders … ankles): both the skeleton's and the learned
joints project onto them."""
LIMB_BONES = tuple(BONE_INDEX[COCO17[i][1]] for i in LIMB_KEYPOINTS)
MIN_CONFIDENCE = 0.5
"""Held-out detections below this confidence are not compared against (issue 29's default)."""


@dataclass
class VideoInputs:
    """One demo's detections and mattes."""

    cameras: list[Camera]
    uv: FloatArray  # (f, n_cams, 17, 2) the subject's keypoints, NaN where none
    conf: FloatArray  # (f, n_cams, 17)
    mattes: list[F32]  # per camera (f, h, w) (the cameras' sizes differ)
    detections: list[list[Detections2D]]  # [f][camera]: every detection, what a held-out camera is compared with


def video_inputs(
    detector: DetectorConfig, demo: str = "Demo_SinglePerson", max_frames: int = 100, scale: int = 8
) -> VideoInputs:
    """The demo's detections as ``mocapd eval video`` makes them (its FP32 detector from the ``[detector]`` of
    ``detector``, cached: the same file that command reads), the subject in each view, and the mattes."""
    from mocapd.pipeline.detector import OnnxPoseDetector

    take = pose2sim_take(demo)
    if take.subjects != 1:
        raise InputError(
            f"{demo}: {take.subjects} performers; this evaluation takes each view's largest person as its one subject"
            " (it has no cross-view association): only Demo_SinglePerson"
        )
    dets = detect_take(
        take, lambda: OnnxPoseDetector.from_config(eval_detector_config(detector)), min(max_frames, take.n_frames)
    )
    small = _small_frames(demo, max_frames, scale)
    f = min(dets.n_frames, len(small[0]))
    uv_a, conf_a = subject_keypoints(dets.frames[:f])
    mattes = [clean_plate_mattes(np.stack(small[c][:f]), uv_a[:, c], conf_a[:, c], scale) for c in range(len(CAMERAS))]
    return VideoInputs(take.cameras, uv_a, conf_a, mattes, dets.frames[:f])


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


def subject_keypoints(frames: list[list[Detections2D]]) -> tuple[FloatArray, FloatArray]:
    """The subject's keypoints (f, n_cams, 17, 2), NaN where none, and confidences (f, n_cams, 17): each view's
    largest detection (the box of its keypoints of confidence > 0.3)."""
    n, n_cams = len(frames), len(frames[0]) if frames else 0
    uv = np.full((n, n_cams, 17, 2), np.nan)
    conf = np.zeros((n, n_cams, 17))
    for t, row in enumerate(frames):
        for c, det in enumerate(row):
            if not len(det):
                continue
            xy, cf = det.keypoints, det.confidences
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


def held_out_grid(limbs: FloatArray, camera: Camera, detections: list[Detections2D], max_det: int) -> FloatArray:
    """Issue 29's held-out-view errors of one method in one held-out camera, placed by (frame, detection, keypoint).

    Parameters
    ----------
    limbs : (f, 12, 3) the method's limb joints in world (rows of NaN: no estimate that frame); camera : the held-out
    camera; detections : its f frames of detections; max_det : detections per frame to make room for.

    Returns
    -------
    (f, max_det, 17) pixel errors, NaN where not compared (so that methods can be intersected).
    """
    f = limbs.shape[0]
    pts = np.full((f, 1, 17, 3), np.nan)
    pts[:, 0, list(LIMB_KEYPOINTS)] = limbs
    res = held_out_errors(camera, detections, pts, min_confidence=MIN_CONFIDENCE)
    grid = np.full((f, max_det, 17), np.nan)
    for t in np.flatnonzero(res.matched[:, 0] >= 0):
        grid[t, res.matched[t, 0]] = res.errors[t, 0]
    return grid


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
    max_det = max((len(d) for row in inputs.detections for d in row), default=0)
    grids: dict[str, FloatArray] = {}  # method -> (n_cams, f, max_det, 17)
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
            STREAM: stream[:, limbs],
        }
        held_out = [row[k] for row in inputs.detections]
        for name, pts in methods.items():
            grids.setdefault(name, np.full((n_cams, f, max_det, 17), np.nan))[k] = held_out_grid(
                pts, inputs.cameras[k], held_out, max_det
            )
    every_frame = [n for n in grids if n != STREAM]
    common = np.logical_and.reduce([np.isfinite(grids[n]) for n in every_frame])
    common_stream = common & np.isfinite(grids[STREAM])
    names = [c.name for c in inputs.cameras]
    return {
        "metric": "mocapd.eval.heldout.held_out_errors (issue 29), 12 limb keypoints, confidence >= 0.5",
        "pooled": {n: _summary(gr) for n, gr in grids.items()},
        "common": {n: _summary(np.where(common, gr, np.nan)) for n, gr in grids.items() if n != STREAM},
        "common_with_stream": {n: _summary(np.where(common_stream, gr, np.nan)) for n, gr in grids.items()},
        "per_held_out_camera": {c: {n: _summary(gr[k]) for n, gr in grids.items()} for k, c in enumerate(names)},
        "frames": f,
        "learned_frames_every": stride,
    }


STREAM = "learned stream (joints)"
"""The one method evaluated on the learned frames only (every ``stride``-th)."""


def _summary(errors: FloatArray) -> dict[str, float]:
    s = summarize(errors, keypoints=LIMB_KEYPOINTS)["all"]
    return {"median_px": round(s["median"], 2), "p90_px": round(s["p90"], 2), "n": int(s["n"])}


def markdown(res: dict[str, Any], demo: str) -> str:
    every = res["learned_frames_every"]
    lines = [
        f"### Held-out-view error on real footage ({demo}, {res['frames']} frames, 4 cameras)",
        "",
        "Each camera in turn held out; every method sees the other three; issue 29's held-out-view error"
        f" (`mocapd/eval/heldout.py`) over the 12 limb keypoints, detections of confidence ≥ {MIN_CONFIDENCE}."
        " *Own*: every keypoint the method was compared on; *common*: those every method on every frame was compared"
        f" on; *with the stream*: those the learned stream (every {every}rd frame) was compared on too.",
        "",
        "| method | median px (own) | p90 (own) | compared (own) | median (common) | p90 (common) | compared"
        " (common) | median (with the stream) | compared (with the stream) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in res["pooled"].items():
        c = res["common"].get(name)
        cs = res["common_with_stream"][name]
        common = f"{c['median_px']:.1f} | {c['p90_px']:.1f} | {c['n']}" if c else "– | – | –"
        lines.append(
            f"| {name} | {s['median_px']:.1f} | {s['p90_px']:.1f} | {s['n']} | {common} | {cs['median_px']:.1f} |"
            f" {cs['n']} |"
        )
    lines += ["", "Per held-out camera, median px (own):", ""]
    cams = list(res["per_held_out_camera"])
    lines += ["| method | " + " | ".join(cams) + " |", "|---|" + "---|" * len(cams)]
    for name in res["pooled"]:
        cells = [f"{res['per_held_out_camera'][c][name]['median_px']:.1f}" for c in cams]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append("")
    return "\n".join(lines)


def save(res: dict[str, Any], out: Path, demo: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "video.json").write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
    (out / "video.md").write_text(markdown(res, demo), encoding="utf-8")

"""Real multi-view footage for ``mocapd eval video``: takes (videos + calibration) and their detections, cached.

A :class:`Take` is a set of synchronised videos, one per calibrated camera. Its detections — mocapd's detector run
once on every frame of every camera (whole frames, at the camera's aspect where the export exists) — are the one
input every evaluated system sees (:class:`TakeDetections`). They are cached in ``<cache>/eval-video/`` in a file
named by a key over the videos' and the model's SHA-256 and the detector settings that change its output, so a
rerun skips the detector entirely and any change of video, model or setting detects again.

Cache file (numpy ``.npz``, no pickles): ``counts`` (n_frames, n_cams) people per frame and camera, ``keypoints``
(sum(counts), n_kp, 2) pixels of the source image and ``confidences`` (sum(counts), n_kp), people in frame-major,
camera-minor order, plus ``key`` (the cache key) and ``meta`` (JSON: what was detected with what).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from tokenize import TokenError  # numpy's header parser raises it for a damaged .npy header
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.keypoints import BLAZEPOSE33_FORMAT, COCO17_FORMAT
from mocapd.core.sorting import Detections2D
from mocapd.errors import CalibrationError, InputError
from mocapd.io.calibration_files import core_cameras, read_any, read_qca
from mocapd.io.media_files import open_video
from mocapd.io.model_cache import cache_dir
from mocapd.io.model_quant import model_path
from mocapd.io.pose2sim_demo import CAMERAS, DEMOS, demo_calibration, demo_root, demo_video
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.keypoint_timeline import interpolate_people
from mocapd.pipeline.landmarks import LandmarkRunner, with_landmarks
from mocapd.pipeline.scheduler import SchedulerOptions

FloatArray = NDArray[np.float64]

#: The COCO-17 keypoints' columns among BlazePose's 33 landmarks.
_COCO17_IN_BLAZEPOSE33 = np.array([BLAZEPOSE33_FORMAT.index(n) for n in COCO17_FORMAT.keypoints], dtype=np.intp)

MATCH_PX: float = SchedulerOptions.match_px
"""Largest mean keypoint distance (px) at which a person of one frame is the same as one of the next, blending a
camera's frames to its time offset: the daemon's (``SchedulerOptions.match_px``)."""

CACHE_VERSION = 1
"""Bumped when the cache layout or what is stored changes."""


@dataclass(frozen=True)
class Take:
    """Synchronised videos of a calibrated rig.

    Attributes
    ----------
    name : str
    cameras : list of Camera
        In the order of ``videos``.
    videos : list of Path
    fps : float
        Frame rate of the videos (all equal).
    n_frames : int
        Frames every video has.
    subjects : int
        How many performers the take has (the rest are bystanders): the reference the people metrics use.
    calibration : Path
        The calibration file the cameras came from (Pose2Sim converts the same file itself).
    sizes : list of (int, int)
        (width, height) of each video's frames (may differ from the calibration's by a few pixels).
    source : str
        Where the footage comes from, with its licence.
    time_offsets_s : tuple of float
        Per camera, how late its frames run (s, the ``[daemon.offsets] cameras`` convention: frame ``f`` shows the
        scene the others show at ``f - offset * fps``), from the calibration file's ``time_offset_s``; empty: none
        given. :func:`time_aligned` takes them out of the detections.
    """

    name: str
    cameras: list[Camera]
    videos: list[Path]
    fps: float
    n_frames: int
    subjects: int
    calibration: Path
    sizes: list[tuple[int, int]]
    source: str = ""
    time_offsets_s: tuple[float, ...] = ()

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.cameras]


def pose2sim_take(demo: str) -> Take:
    """One of the Pose2Sim demos (``Demo_SinglePerson``: one performer; ``Demo_MultiPerson``: two), as the set-up
    unpacked them (:mod:`mocapd.io.pose2sim_demo`), with the demo's own Qualisys calibration."""
    if demo not in DEMOS:
        raise InputError(f"unknown Pose2Sim demo {demo!r}; known: {', '.join(DEMOS)}")
    calib = demo_calibration(demo)
    cams = core_cameras(read_qca(calib))
    videos = [demo_video(demo, c) for c in CAMERAS]
    if [c.name for c in cams] != list(CAMERAS):
        raise InputError(f"{calib}: cameras {[c.name for c in cams]}, expected {list(CAMERAS)}")
    fps, n, sizes = _video_info(videos)
    return Take(
        name=demo, cameras=cams, videos=videos, fps=fps, n_frames=n, subjects=1 if "Single" in demo else 2,
        calibration=calib, sizes=sizes, source=f"Pose2Sim {demo} (pose2sim wheel, BSD-3-Clause; {demo_root()})",
    )  # fmt: skip


def with_calibration(take: Take, path: Path) -> Take:
    """``take`` with the cameras of another calibration file (any format ``mocapd calibrate convert`` reads), matched
    by name: e.g. one ``mocapd calibrate cameras --from-people`` made, to score it against the take's own.

    Raises
    ------
    InputError
        The file cannot be read, or lacks one of the take's cameras.
    """
    try:
        calib = read_any(path)
    except CalibrationError as exc:
        raise InputError(f"cannot read the calibration {path}: {exc}") from None
    given = {c.name: c for c in core_cameras(calib)}
    missing = [n for n in take.camera_names if n not in given]
    if missing:
        raise InputError(f"{path}: camera(s) {missing} of {take.name} are not in it (it has {sorted(given)})")
    # `--from-people` writes each camera's time offset beside it (issue 43); a camera without one is on time.
    offsets = {c.name: c.time_offset_s or 0.0 for c in calib.cameras}
    names = take.camera_names
    times = tuple(offsets[n] for n in names) if any(offsets[n] for n in names) else ()
    return replace(take, cameras=[given[n] for n in names], calibration=path, time_offsets_s=times)


def time_aligned(take: Take, dets: TakeDetections) -> TakeDetections:
    """``dets`` with each camera's time offset (``take.time_offsets_s``) taken out: frame ``f`` of a camera whose
    frames run ``d`` s late becomes its people at ``f + d * fps``, blended between the two frames around it as the
    daemon's timelines blend them (:func:`~mocapd.pipeline.keypoint_timeline.interpolate_people`: people matched
    by keypoint distance, the nearer frame's unmatched ones passed through), so that every camera's frame ``f``
    shows one moment. Where ``f + d * fps`` falls outside the camera's frames it sees nobody (never held or
    extrapolated). The evaluated systems match the cameras' frames by index; the offsets go nowhere else."""
    if not any(take.time_offsets_s):
        return dets
    n = dets.n_frames
    n_kp = next((d.keypoints.shape[1] for row in dets.frames for d in row), 17)
    frames = [list(row) for row in dets.frames]
    for c, offset_s in enumerate(take.time_offsets_s):
        if offset_s == 0.0:
            continue
        for f in range(n):
            frames[f][c] = _camera_at(dets.frames, c, f + offset_s * take.fps, n_kp)
    meta = {**dets.meta, "time_offsets_s": dict(zip(take.camera_names, take.time_offsets_s, strict=True))}
    return TakeDetections(frames, dets.key, meta, dets.from_cache)


def _camera_at(frames: list[list[Detections2D]], camera: int, x: float, n_kp: int) -> Detections2D:
    """Camera ``camera``'s people at fractional frame ``x`` (nobody outside its frames)."""
    k = math.floor(x + 1e-9)  # a whole frame given as 1.9999999999 is that frame
    alpha = max(0.0, x - k)
    if k < 0 or k >= len(frames) or (alpha > 1e-9 and k + 1 >= len(frames)):
        return Detections2D.empty(n_kp)
    if alpha <= 1e-9:
        return frames[k][camera]
    return interpolate_people(frames[k][camera], frames[k + 1][camera], alpha, MATCH_PX)


def _video_info(videos: list[Path]) -> tuple[float, int, list[tuple[int, int]]]:
    fps, frames, sizes = [], [], []
    for v in videos:
        cap = open_video(v)
        fps.append(float(cap.get(cv2.CAP_PROP_FPS)))
        frames.append(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        sizes.append((int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))))
        cap.release()
    if max(fps) - min(fps) > 1e-3:
        raise InputError(f"videos have different frame rates {fps}: {[str(v) for v in videos]}")
    return fps[0], min(frames), sizes


@dataclass
class TakeDetections:
    """Every frame's detections of a take: ``frames[f][c]`` is camera ``c``'s :class:`Detections2D` of frame ``f``."""

    frames: list[list[Detections2D]]
    key: str
    meta: dict[str, Any] = field(default_factory=dict)
    from_cache: bool = False

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    def head(self, n: int) -> TakeDetections:
        """The first ``n`` frames."""
        return TakeDetections(self.frames[:n], self.key, self.meta, self.from_cache)

    def without(self, camera: int) -> list[list[Detections2D]]:
        """Every frame's detections with camera ``camera`` left out."""
        return [[d for c, d in enumerate(row) if c != camera] for row in self.frames]

    def most_confident(self, n_kp: int = 17) -> list[tuple[FloatArray, FloatArray]]:
        """Per frame, each camera's most confident person (the largest sum of keypoint confidences): pixels
        (n_cams, n_kp, 2), NaN where a camera saw nobody, and confidences (n_cams, n_kp), 0 there."""
        out = []
        for row in self.frames:
            kp = np.full((len(row), n_kp, 2), np.nan)
            cf = np.zeros((len(row), n_kp))
            for c, d in enumerate(row):
                if len(d.keypoints):
                    i = int(np.argmax(d.confidences.sum(axis=1)))
                    kp[c], cf[c] = d.keypoints[i], d.confidences[i]
            out.append((kp, cf))
        return out


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def detector_fingerprint(det: OnnxPoseDetector, image_sizes: list[tuple[int, int]]) -> dict[str, Any]:
    """What about the detector changes its output on images of ``image_sizes`` (width, height): the model files'
    hashes (the square model and each fitted export whole frames run on), precision, decoding thresholds."""
    spec = det.spec
    files = {str(det.path)}
    inputs = {}
    for w, h in dict.fromkeys(image_sizes):
        fitted = det.fit_to(w, h)
        inputs[f"{w}x{h}"] = "x".join(map(str, fitted[:2] if fitted is not None else det.input_size))
        if fitted is not None:
            files.add(str(model_path(fitted[0], fitted[1], det.precision)))
    return {
        "model_sha256": {Path(f).name: _sha256(Path(f)) for f in sorted(files)},
        "whole_frame_inputs": inputs,
        "precision": det.precision,
        "providers": list(det.session.get_providers()),
        "decoder": spec.decoder,
        "keypoint_format": spec.keypoint_format,
        "score_threshold": spec.score_threshold,
        "iou_threshold": spec.iou_threshold,
        "max_people": spec.max_people,
    }


def cache_key(take: Take, n_frames: int, fingerprint: dict[str, Any]) -> str:
    """Key of a take's detections: the videos' SHA-256, the frame count, the detector and the cache version."""
    payload = {
        "version": CACHE_VERSION,
        "videos": [_sha256(v) for v in take.videos],
        "frames": n_frames,
        "detector": fingerprint,
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:24]


def cache_path(take: Take, key: str) -> Path:
    return cache_dir() / "eval-video" / f"{take.name}-{key}.npz"


def eval_detector_config(base: DetectorConfig, precision: str = "fp32") -> DetectorConfig:
    """The detector the evaluation runs: the config's, whole frames, at ``precision`` (FP32 by default: the same
    keypoints on every machine, where "auto" picks INT8 or BF16 by CPU)."""
    return replace(base, precision=precision, workers=1)


def detect_take(
    take: Take,
    detector: Callable[[], OnnxPoseDetector],
    n_frames: int | None = None,
    progress: Callable[[int], None] | None = None,
    use_cache: bool = True,
    landmarks: LandmarkRunner | None = None,
) -> TakeDetections:
    """The detections of every frame and camera of ``take`` (the first ``n_frames``), from the cache when there.

    ``detector`` makes the detector (only called when something must be detected or fingerprinted); ``progress``
    is called with 1 per camera frame detected. With ``landmarks`` (``[detector] landmarks``) the people's COCO-17
    keypoints are BlazePose's landmarks of the same names (every COCO-17 point is one of the 33): the evaluated
    systems, Pose2Sim's COCO_17 model included, and the held-out metric see the two front ends in one layout.
    """
    n = take.n_frames if n_frames is None else min(n_frames, take.n_frames)
    det = detector()
    fp = detector_fingerprint(det, take.sizes)
    if landmarks is not None:
        fp["landmarks"] = {"model": landmarks.variant, "sha256": _sha256(landmarks.path), "as": "coco17"}
    key = cache_key(take, n, fp)
    path = cache_path(take, key)
    if use_cache and path.is_file():
        loaded = load_detections(path, len(take.cameras))
        if loaded is not None and loaded.key == key:
            return loaded
    caps = [open_video(v) for v in take.videos]
    frames: list[list[Detections2D]] = []
    try:
        for f in range(n):
            row = []
            for cap, video in zip(caps, take.videos, strict=True):
                ok, img = cap.read()
                if not ok:
                    raise InputError(f"{video}: frame {f} could not be read (the video has {take.n_frames})")
                image = np.ascontiguousarray(img, dtype=np.uint8)
                (people,) = with_landmarks(landmarks, [image], [det.detect(image)])
                kp = people.keypoints if landmarks is None else people.keypoints[:, _COCO17_IN_BLAZEPOSE33]
                row.append(Detections2D(kp[..., :2], kp[..., 2]))
                if progress is not None:
                    progress(1)
            frames.append(row)
    finally:
        for cap in caps:
            cap.release()
    meta = {"take": take.name, "frames": n, "cameras": take.camera_names, "detector": fp}
    out = TakeDetections(frames, key, meta)
    save_detections(path, out)
    return out


def save_detections(path: Path, dets: TakeDetections) -> None:
    """Write ``dets`` to ``path`` (atomically: a temporary file renamed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    counts = np.array([[len(d) for d in row] for row in dets.frames], dtype=np.int64)
    n_kp = next((d.keypoints.shape[1] for row in dets.frames for d in row), 17)
    kp = [d.keypoints for row in dets.frames for d in row]
    cf = [d.confidences for row in dets.frames for d in row]
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(
        tmp,
        counts=counts,
        keypoints=np.concatenate(kp) if kp else np.zeros((0, n_kp, 2)),
        confidences=np.concatenate(cf) if cf else np.zeros((0, n_kp)),
        key=np.array(dets.key),
        meta=np.array(json.dumps(dets.meta)),
    )
    tmp.replace(path)


def load_detections(path: Path, n_cams: int) -> TakeDetections | None:
    """Read a cache file; None when it is damaged or does not fit ``n_cams`` cameras (it is then detected again)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            counts, kp, cf = z["counts"], z["keypoints"], z["confidences"]
            key, meta = str(z["key"]), json.loads(str(z["meta"]))
    except (OSError, ValueError, KeyError, json.JSONDecodeError, TokenError):
        return None
    if counts.ndim != 2 or counts.shape[1] != n_cams or int(counts.sum()) != kp.shape[0] or kp.shape[:2] != cf.shape:
        return None
    frames: list[list[Detections2D]] = []
    i = 0
    for row in counts:
        out = []
        for k in row:
            out.append(Detections2D(kp[i : i + k], cf[i : i + k]))
            i += int(k)
        frames.append(out)
    return TakeDetections(frames, key, meta, from_cache=True)

"""What each camera sees, for the viewer's camera panels: the newest frame (downscaled), the 2D detections of
that moment, every solved subject reprojected through the camera's calibration, and per-camera health.

:class:`CameraViews` observes the daemon without ever holding it up: the detection tap and the pose sink only
append references to short deques (no copies, no computation). Everything else — copying and downscaling a
frame, forward kinematics, projections, the reprojection error — happens in :meth:`CameraViews.views`, which the
WebSocket server calls a few times a second, off the solver's tick, and only while a viewer asks for camera views.

Timing. A frame captured at ``t`` is solved ``latency`` later, so the overlay of a frame must wait for the pose
of its capture time: :meth:`views` keeps each camera's newest frame pending until a pose frame with
``t_solve >= t`` has been published, then draws the pose nearest ``t`` and the detection set captured nearest
``t`` (the detector's own result for that frame when it detected it). A camera without frames (the synthetic
rig's simulated detections) is drawn at the newest solve time. Both histories span :attr:`CameraViewOptions.
history_s`, which must exceed the daemon's latency.

Reprojection error (per camera, pixels): for each detected person of the drawn detection set, the mean distance
between its confident keypoints and the same keypoints (the rig's track targets) on the nearest solved subject,
projected; the camera's value is the mean over the detected persons matched within ``match_px``. Detection
rate: detection sets delivered per second over the last two seconds.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.keypoints import TrackTargets
from mocapd.core.kinematics import Kinematics
from mocapd.core.per_skeleton import PerSkeleton
from mocapd.core.skeleton import Skeleton
from mocapd.core.sorting import Detections2D
from mocapd.errors import ConfigError
from mocapd.pipeline.frame_ring import FrameRef, FrameRing
from mocapd.pipeline.scheduler import PoseFrame

FloatArray = NDArray[np.float64]
RATE_WINDOW_NS = 2_000_000_000


@dataclass(frozen=True)
class CameraViewOptions:
    """How camera views are made.

    Attributes
    ----------
    max_width : int
        Width (pixels) a frame is downscaled to (never upscaled); the height keeps the aspect ratio.
    rate_hz : float
        Camera messages per second per camera while a viewer asks (at most).
    jpeg_quality : int
        JPEG quality of the panels' images (1..100).
    history_s : float
        How long poses and detections are kept to match a frame's capture time (must exceed the latency).
    min_confidence : float
        Keypoints below this detector confidence are neither drawn as confident nor counted in the error.
    match_px : float
        A detected person farther than this (mean keypoint distance) from every solved subject is unmatched.
    """

    max_width: int = 320
    rate_hz: float = 4.0
    jpeg_quality: int = 70
    history_s: float = 3.0
    min_confidence: float = 0.3
    match_px: float = 80.0

    def __post_init__(self) -> None:
        if not 16 <= self.max_width <= 4096:
            raise ConfigError(f"camera views: max_width = {self.max_width}; allowed: 16 .. 4096")
        if not 0.1 <= self.rate_hz <= 30.0:
            raise ConfigError(f"camera views: rate_hz = {self.rate_hz}; allowed: 0.1 .. 30")
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"camera views: jpeg_quality = {self.jpeg_quality}; allowed: 1 .. 100")
        if not 0.2 <= self.history_s <= 30.0:
            raise ConfigError(f"camera views: history_s = {self.history_s}; allowed: 0.2 .. 30")


@dataclass(frozen=True)
class Snapshot:
    """One frame of a camera, downscaled: ``image`` (h, w, 3) RGB uint8, or already-encoded ``jpeg`` bytes
    (a recorded session's frames); ``capture_ns`` on the host clock."""

    capture_ns: int
    image: NDArray[np.uint8] | None = None
    jpeg: bytes | None = None


class SnapshotSource(Protocol):
    """Where a camera's newest frame comes from (a live ring, a replayed session)."""

    def snapshot(self, max_width: int) -> Snapshot | None:
        """The newest frame, downscaled to at most ``max_width`` pixels wide (None: no frame yet)."""
        ...


def downscale(image: NDArray[np.uint8], max_width: int) -> NDArray[np.uint8]:
    """RGB/mono image (h, w[, c]) → at most ``max_width`` wide, RGB (area averaging, the aspect ratio kept)."""
    h, w = image.shape[:2]
    if w > max_width:
        size = (max_width, max(1, round(h * max_width / w)))
        image = np.asarray(cv2.resize(image, size, interpolation=cv2.INTER_AREA), dtype=np.uint8)
    if image.ndim == 2 or image.shape[2] == 1:
        image = np.asarray(cv2.cvtColor(image.reshape(image.shape[:2]), cv2.COLOR_GRAY2RGB), dtype=np.uint8)
    return image


def encode_jpeg(image: NDArray[np.uint8], quality: int) -> bytes:
    """An RGB image (h, w, 3) as baseline JPEG bytes."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [int(cv2.IMWRITE_JPEG_QUALITY), quality])
    if not ok:
        raise ValueError(f"JPEG encoding failed for an image of shape {image.shape}")
    return bytes(np.asarray(buf).tobytes())


class RingSnapshots:
    """The newest frame of a capture ring (:class:`~mocapd.pipeline.frame_ring.FrameRing`), copied when asked.

    ``stamp`` maps a frame reference to its capture time on the host clock (the keypoint source's
    ``capture_ns``, so frames and detections share one time base).
    """

    def __init__(self, ring: FrameRing, stamp: Callable[[FrameRef], int] | None = None) -> None:
        self.ring = ring
        self.stamp = stamp if stamp is not None else (lambda ref: ref.host_ns)

    def snapshot(self, max_width: int) -> Snapshot | None:
        ref = self.ring.latest()
        if ref is None:
            return None
        image = self.ring.read(ref.seq)  # None: the writer overtook the copy; the next call takes a newer one
        return None if image is None else Snapshot(self.stamp(ref), downscale(image, max_width))


class LatestSnapshot:
    """A snapshot source fed from outside (a replayed session's recorded frames)."""

    def __init__(self) -> None:
        self.latest: Snapshot | None = None

    def put(self, snapshot: Snapshot) -> None:
        self.latest = snapshot

    def snapshot(self, max_width: int) -> Snapshot | None:
        return self.latest


@dataclass(frozen=True)
class SubjectOverlay:
    """One solved subject drawn on a camera: ``joints`` (21, 2) full-resolution pixels (NaN: behind it)."""

    id: str
    joints: FloatArray


@dataclass(frozen=True)
class CameraView:
    """One camera panel's content.

    Attributes
    ----------
    camera : int
        Index in the rig.
    name : str
    width, height : int
        The camera's full resolution: every pixel coordinate below is in it.
    capture_ns : int
        When the frame (or, without frames, the drawn pose) was taken.
    snapshot : Snapshot or None
        The downscaled frame (None: the camera has no frame source).
    frame : int
        Counter of the pose frame drawn (-1: none).
    t_solve_ns : int
        Its solve time.
    detections : array, shape (n_people, n_kp, 3)
        x, y (pixels), confidence of the detection set drawn.
    subjects : list of SubjectOverlay
    reprojection_px : float or None
        See the module doc; None when no detected person matched a subject.
    detection_hz : float
        Detection sets per second over the last two seconds.
    """

    camera: int
    name: str
    width: int
    height: int
    capture_ns: int
    snapshot: Snapshot | None
    frame: int
    t_solve_ns: int
    detections: FloatArray
    subjects: list[SubjectOverlay]
    reprojection_px: float | None
    detection_hz: float


class CameraViews:
    """Taps on the daemon (detections, poses) and the camera panels assembled from them on request.

    Parameters
    ----------
    cameras : list of Camera
        The rig's calibrated cameras (index = camera number of the detection tap).
    targets : TrackTargets
        The detector's keypoints on the skeleton (for the reprojection error).
    skeleton : Skeleton
        The rig's skeleton (subjects without their own).
    sources : list of SnapshotSource or None
        Per camera, where its frames come from (None: no frames).
    options : CameraViewOptions
    now : callable
        Host monotonic ns now, in the time base of the stamps (for the detection rate's window).
    """

    def __init__(
        self,
        cameras: Sequence[Camera],
        targets: TrackTargets,
        skeleton: Skeleton,
        sources: Sequence[SnapshotSource | None],
        options: CameraViewOptions | None = None,
        now: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if len(sources) != len(cameras):
            raise ConfigError(f"camera views: {len(cameras)} cameras but {len(sources)} frame sources")
        self.cameras = list(cameras)
        self.targets = targets
        self.skeleton = skeleton
        self.sources = list(sources)
        self.options = options or CameraViewOptions()
        self._poses: deque[PoseFrame] = deque()
        self._dets: list[deque[tuple[int, Detections2D]]] = [deque() for _ in cameras]
        self._arrivals: list[deque[int]] = [deque() for _ in cameras]
        keep = int(self.options.history_s * self.options.rate_hz) + 2
        self._pending: list[deque[Snapshot]] = [deque(maxlen=keep) for _ in cameras]
        self._newest = [-1] * len(cameras)  # capture time of the newest frame queued per camera
        self._kin: PerSkeleton[Kinematics] = PerSkeleton(Kinematics(skeleton), Kinematics)
        self.name = "camera-views"
        self.now = now
        """The time base of the taps' time stamps, now (a replay sets the recorded clock's)."""

    def set_camera(self, index: int, camera: Camera) -> None:
        """Camera ``index`` recalibrated while running: the subjects are projected through ``camera`` from now on."""
        self.cameras[index] = camera

    # ------------------------------------------------------------------------------------------ taps
    def on_detections(self, camera: int, capture_ns: int, dets: Detections2D, arrival_ns: int) -> None:
        """Detection tap (the daemon's ``detection_taps``): keeps a reference, nothing else."""
        if not 0 <= camera < len(self._dets):
            return
        self._dets[camera].append((capture_ns, dets))
        self._arrivals[camera].append(arrival_ns)
        self._trim(self._dets[camera], capture_ns)
        arrivals = self._arrivals[camera]
        while arrivals and arrivals[0] < arrival_ns - RATE_WINDOW_NS:
            arrivals.popleft()

    def publish(self, frame: PoseFrame) -> None:
        """Pose sink: keeps a reference to the frame."""
        self._poses.append(frame)
        self._trim(self._poses, frame.t_solve_ns)

    async def start(self) -> None:
        return None

    async def aclose(self) -> None:
        return None

    def _trim(self, history: deque[PoseFrame] | deque[tuple[int, Detections2D]], now_ns: int) -> None:
        horizon = now_ns - int(self.options.history_s * 1e9)
        while len(history) > 1 and _time(history[0]) < horizon:
            history.popleft()

    # ------------------------------------------------------------------------------------------ assembly
    def views(self, now_ns: int) -> list[CameraView]:
        """The camera panels ready now (off the tick: copies, projections, errors). Call it at ``rate_hz``: each
        call queues every camera's newest frame and draws the newest queued frame whose capture time is solved
        (none for a camera whose frames are all newer than the latest solve time)."""
        # Copies of the histories first: the taps append on the event loop while this may run in a worker
        # thread (list() of a deque is one C call under the GIL, so the copy is consistent).
        poses = list(self._poses)
        dets = [list(d) for d in self._dets]
        arrivals = [list(a) for a in self._arrivals]
        out = []
        latest = poses[-1] if poses else None
        for i, cam in enumerate(self.cameras):
            src = self.sources[i]
            if src is not None:
                pending = self._solvable(i, src, latest)
                if pending is None:
                    continue
                t = pending.capture_ns
            else:
                pending = None
                if latest is None:
                    continue
                t = latest.t_solve_ns
            out.append(self._view(i, cam, t, pending, poses, dets[i], arrivals[i], now_ns))
        return out

    def _solvable(self, i: int, src: SnapshotSource, latest: PoseFrame | None) -> Snapshot | None:
        """Queue camera ``i``'s newest frame; return (and drop from the queue) the newest queued frame whose
        capture time is solved already, with the older ones."""
        queue = self._pending[i]
        snap = src.snapshot(self.options.max_width)
        if snap is not None and snap.capture_ns > self._newest[i]:
            queue.append(snap)
            self._newest[i] = snap.capture_ns
        if latest is None:
            return None
        ready = None
        while queue and queue[0].capture_ns <= latest.t_solve_ns:
            ready = queue.popleft()
        return ready

    def _view(
        self,
        i: int,
        cam: Camera,
        t: int,
        snap: Snapshot | None,
        poses: list[PoseFrame],
        dets_history: list[tuple[int, Detections2D]],
        arrivals: list[int],
        now_ns: int,
    ) -> CameraView:
        pose = _nearest(poses, t)
        subjects: list[SubjectOverlay] = []
        keypoints: list[FloatArray] = []
        for p in pose.people if pose is not None else []:
            subjects.append(SubjectOverlay(p.identity, cam.project(np.asarray(p.joints, dtype=np.float64))))
            keypoints.append(cam.project(self._target_positions(p.theta, p.skeleton)))
        period_ns = 1e9 / self.options.rate_hz
        found = _nearest(dets_history, t)
        dets = np.zeros((0, len(self.targets), 3))
        if found is not None and abs(found[0] - t) <= max(period_ns, 0.1e9):
            d = found[1]
            dets = np.concatenate([d.keypoints, d.confidences[..., None]], axis=-1)
        recent = sum(1 for a in arrivals if a >= now_ns - RATE_WINDOW_NS)
        return CameraView(
            i, cam.name, cam.width, cam.height, t, snap,
            pose.frame if pose is not None else -1, pose.t_solve_ns if pose is not None else 0,
            dets, subjects, self._reprojection(dets, keypoints), recent / (RATE_WINDOW_NS / 1e9),
        )  # fmt: skip

    def _target_positions(self, theta: FloatArray, skeleton: Skeleton | None) -> FloatArray:
        """World positions of the track targets (the detector's keypoints) on a posed subject, shape (n_kp, 3)."""
        fk = self._kin.get(skeleton).forward(np.asarray(theta, dtype=np.float64))
        b = self.targets.bones
        return np.asarray(fk.positions[b] + np.einsum("kij,kj->ki", fk.rotations[b], self.targets.offsets))

    def _reprojection(self, dets: FloatArray, keypoints: list[FloatArray]) -> float | None:
        if not len(dets) or not keypoints:
            return None
        errors = []
        for person in dets:
            ok = person[:, 2] >= self.options.min_confidence
            if not ok.any():
                continue
            best = min(float(np.nanmean(np.linalg.norm(kp[ok] - person[ok, :2], axis=-1))) for kp in keypoints)
            if np.isfinite(best) and best <= self.options.match_px:
                errors.append(best)
        return float(np.mean(errors)) if errors else None


def _time(item: PoseFrame | tuple[int, Detections2D]) -> int:
    return item.t_solve_ns if isinstance(item, PoseFrame) else item[0]


_Timed = TypeVar("_Timed", PoseFrame, tuple[int, Detections2D])


def _nearest(history: list[_Timed], t: int) -> _Timed | None:
    """The item of ``history`` (in time order) whose time is nearest ``t``."""
    if not history:
        return None
    return min(history, key=lambda item: abs(_time(item) - t))


__all__ = [
    "CameraView",
    "CameraViewOptions",
    "CameraViews",
    "LatestSnapshot",
    "RingSnapshots",
    "Snapshot",
    "SnapshotSource",
    "SubjectOverlay",
    "downscale",
    "encode_jpeg",
]

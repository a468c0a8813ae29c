"""mocapd's systems in ``mocapd eval video``: the live path, ``mocapd resolve`` and a naive DLT beside them (the
daemon's own parts, hence the service layer; the metrics are :mod:`mocapd.eval.video`).

**Live** (:func:`run_live`): a :class:`~mocapd.service.daemon.Daemon` is built from the config and the take's
calibrated cameras exactly as ``mocapd run`` builds it (its tracker, its :class:`FixedLatencyScheduler`, its
solvers), and fed the take's detections in lockstep instead of through capture and the detector threads: frame
``f`` is captured at ``t_f = f / fps``, its detections arrive ``detection_delay_ns`` later, and the daemon's tick
for ``t_f + latency`` (its own :meth:`~FixedLatencyScheduler.tick`) solves ``t_f`` with every detection that would
have arrived by then. A session recorder (the daemon's own, :func:`attach_recorder`) records the run, so that

**resolve** (:func:`run_resolve`) is ``mocapd resolve`` on that recorded session: the offline re-solve with the
larger LM budget, then the RTS smoother (:func:`mocapd.service.session.solve.resolve`).

**Naive DLT** (:func:`dlt_from_live`): each subject the live tracker assigned, its keypoints triangulated per
frame by confidence-weighted DLT from every view it was assigned (keypoints of confidence >= 0.3), nothing
rejected; the same association as the live path, so the difference is the solve alone.

Every system gives per identity the 3D positions of the detector's keypoints (COCO-17) per frame: for mocapd, the
solver's keypoint targets on the solved skeleton; NaN where the identity was not solved.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera, triangulate
from mocapd.core.keypoints import TrackTargets, keypoint_format
from mocapd.core.kinematics import Kinematics
from mocapd.core.per_skeleton import PerSkeleton
from mocapd.core.skeleton import Skeleton
from mocapd.core.sorting import Detections2D
from mocapd.errors import InputError
from mocapd.io.prior import resolve_prior
from mocapd.io.session import Session
from mocapd.service.config import Config
from mocapd.service.daemon import Daemon, Rig
from mocapd.service.outputs.recorder import FrameRecordOptions, attach_recorder
from mocapd.service.session.solve import ResolveOptions, manifest_skeleton, resolve

FloatArray = NDArray[np.float64]

DLT_MIN_CONFIDENCE = 0.3
"""Keypoints below this confidence take no part in the naive DLT (Pose2Sim's likelihood threshold, the sorter's)."""


@dataclass
class Trajectories:
    """One system's output on a take.

    Attributes
    ----------
    points : dict identity -> array, shape (n_frames, n_kp, 3)
        The detector's keypoints in 3D (world metres), NaN where the identity was not solved.
    skeletons : dict identity -> Skeleton
        The skeleton each identity was solved on last (mocapd's systems only).
    views : dict identity -> list of dict camera -> person index
        Per frame, the 2D detections the system assigned to the identity (camera indices of the cameras it was
        given; empty where it was not seen). mocapd's systems and the DLT only.
    """

    points: dict[str, FloatArray]
    skeletons: dict[str, Skeleton] = field(default_factory=dict)
    views: dict[str, list[dict[int, int]]] = field(default_factory=dict)


def live_config(config: Config, fps: float) -> Config:
    """The config the live replay runs: ``config`` with the output rate at the videos' frame rate (one solve per
    frame) and a fixed latency (``"auto"`` follows a detector that does not run here)."""
    daemon = config.daemon.model_copy(
        update={
            "output_rate_hz": fps,
            "latency_s": 0.15 if config.daemon.latency_s == "auto" else config.daemon.latency_s,
        }
    )
    return config.model_copy(update={"daemon": daemon})


def _keypoints(
    kins: PerSkeleton[Kinematics], targets: TrackTargets, theta: FloatArray, sk: Skeleton | None
) -> FloatArray:
    kin = kins.get(sk)
    points: FloatArray = kin.targets(kin.forward(theta), targets.bones, targets.offsets)
    return points


@dataclass
class LiveRun:
    """The live replay's output, the tracker's assignments and the recorded session."""

    live: Trajectories
    session: Path
    enrolled: list[str]
    detections_used: dict[str, int]


def run_live(
    config: Config,
    cameras: list[Camera],
    frames: list[list[Detections2D]],
    fps: float,
    session_dir: Path,
    detection_delay_ns: int = 50_000_000,
    progress: Callable[[int], None] | None = None,
) -> LiveRun:
    """The daemon's per-frame solve of ``frames`` (per frame, one :class:`Detections2D` per camera of ``cameras``),
    recorded into ``session_dir`` (a new directory)."""
    if any(len(row) != len(cameras) for row in frames):
        raise InputError(f"every frame needs detections for the {len(cameras)} cameras")
    config = live_config(config, fps)
    skeleton = Skeleton.from_height(1.75)
    # The evaluation's detections are COCO-17 whatever the front end (eval.video_input.detect_take).
    targets = keypoint_format(config.detector.model.keypoint_format).track_targets(skeleton)
    rig = Rig(cameras, [], skeleton, targets, resolve_prior(config.solver.prior))
    daemon = Daemon(config, rig)
    recorder = attach_recorder(config, daemon, session_dir, frames=FrameRecordOptions(enabled=False))
    assert recorder is not None
    recorder.writer.open()
    sched = daemon.scheduler
    period = sched.options.period_ns
    t0 = 1_000_000_000  # the first frame's capture time (host clock of the replay)
    capture = [t0 + round(f * 1e9 / fps) for f in range(len(frames))]
    kins = PerSkeleton(Kinematics(skeleton), Kinematics)
    n, n_kp = len(frames), len(targets)
    points: dict[str, FloatArray] = {}
    views: dict[str, list[dict[int, int]]] = {}
    skeletons: dict[str, Skeleton] = {}
    fed = 0
    try:
        for f, t in enumerate(capture):
            now = t + sched.latency_ns
            while fed < n and capture[fed] + detection_delay_ns <= now:
                for c, det in enumerate(frames[fed]):
                    arrival = capture[fed] + detection_delay_ns
                    sched.add_detections(c, capture[fed], det, arrival)
                    recorder.on_detections(c, capture[fed], det, arrival)
                fed += 1
            frame = sched.tick(now, predict=False)
            if frame.t_solve_ns != t:
                raise InputError(f"tick solved {frame.t_solve_ns}, not frame {f} at {t} (period {period})")
            recorder.publish(frame)
            assigned = {f"track:{s.id}": dict(s.detections) for s in sched.people.tracker.subjects if s.seen}
            for p in frame.people:
                arr = points.setdefault(p.identity, np.full((n, n_kp, 3), np.nan))
                arr[f] = _keypoints(kins, targets, p.theta, p.skeleton)
                skeletons[p.identity] = p.skeleton if p.skeleton is not None else skeleton
                views.setdefault(p.identity, [{} for _ in range(n)])[f] = assigned.get(p.identity, {})
            if progress is not None:
                progress(1)
    finally:
        recorder.writer.close({"source": "mocapd eval video (lockstep replay of cached detections)"})
    statuses = [dict(s) for s in sched.keypoint_status]
    inexact = sum(v for st in statuses for k, v in st.items() if k != "exact")
    if inexact:
        raise InputError(f"the replay sampled detections other than exactly at their frames: {statuses}")
    enrolled = sorted(points)
    used = {k: sum(len(v) for v in vs) for k, vs in views.items()}
    return LiveRun(Trajectories(points, skeletons, views), session_dir, enrolled, used)


def run_resolve(
    session_dir: Path, n_frames: int, fps: float, progress: Callable[[int], None] | None = None
) -> Trajectories:
    """``mocapd resolve`` of a session :func:`run_live` recorded: per identity, keypoints per frame."""
    session = Session(session_dir)
    frames, _ = resolve(session, ResolveOptions(), progress)
    skeleton, targets = manifest_skeleton(session.manifest)
    kins = PerSkeleton(Kinematics(skeleton), Kinematics)
    t0 = min(fr.t_solve_ns for fr in frames) if frames else 0
    points: dict[str, FloatArray] = {}
    skeletons: dict[str, Skeleton] = {}
    for fr in frames:
        f = round((fr.t_solve_ns - t0) * fps / 1e9)
        if not 0 <= f < n_frames:
            continue
        for p in fr.people:
            arr = points.setdefault(p.identity, np.full((n_frames, len(targets), 3), np.nan))
            arr[f] = _keypoints(kins, targets, p.theta, p.skeleton)
            skeletons[p.identity] = p.skeleton if p.skeleton is not None else skeleton
    return Trajectories(points, skeletons)


def dlt_from_live(live: Trajectories, cameras: list[Camera], frames: list[list[Detections2D]]) -> Trajectories:
    """The naive DLT on the live tracker's assignments (see the module docstring)."""
    points: dict[str, FloatArray] = {}
    for identity, per_frame in live.views.items():
        n_kp = frames[0][0].keypoints.shape[1] if frames and frames[0] else 17
        arr = np.full((len(frames), n_kp, 3), np.nan)
        for f, assigned in enumerate(per_frame):
            if len(assigned) < 2:
                continue
            uv = np.zeros((len(cameras), n_kp, 2))
            w = np.zeros((len(cameras), n_kp))
            for c, i in assigned.items():
                uv[c] = frames[f][c].keypoints[i]
                conf = frames[f][c].confidences[i]
                w[c] = np.where(conf >= DLT_MIN_CONFIDENCE, conf, 0.0)
            X, ok = triangulate(cameras, uv, w)
            arr[f, ok] = X[ok]
        points[identity] = arr
    return Trajectories(points, views=live.views)

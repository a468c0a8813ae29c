"""The session recorder: a :class:`~mocapd.service.daemon.PoseSink` that also taps the daemon's raw inputs.

:func:`attach_recorder` (config, daemon) builds one, registers it on the daemon's detection and IMU taps and
adds it to the daemon's sinks. Everything it is given on the event loop (published frames, detected camera frames,
IMU samples) goes into the bounded queue of a :class:`~mocapd.io.session.SessionWriter` as is; encoding, writing
and fsync happen on the writer's thread. When the queue is full a record is dropped and counted, never waited for.

The manifest describes everything :mod:`mocapd.service.session.solve` needs to re-solve the session offline: the
parsed config, the cameras, the skeleton and keypoint targets, the suits' calibrations, the scheduler's timing and
the pose prior (``prior.npz`` beside it).

Camera frames (optional, :class:`FrameRecordOptions`): a few times a second each camera's newest frame is copied,
downscaled and JPEG-encoded in a worker thread and queued as a ``T_FRAME`` record of the ``frames`` stream, so
``mocapd replay`` can show the camera panels of the session.

What happens to the rig while recording goes into the ``events`` stream: a camera recalibrated live
(:class:`~mocapd.pipeline.camera_watch.CameraChange`, :func:`camera_event`), which ``mocapd resolve`` follows.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import platform
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

import mocapd
from mocapd.core.camera import Camera
from mocapd.core.plausibility import PlausibilityMonitor
from mocapd.core.sorting import Detections2D
from mocapd.errors import ConfigError
from mocapd.io.session import EVENTS, FRAMES, STREAMS, SessionWriter
from mocapd.io.xsens_serial import ImuSample
from mocapd.pipeline.camera_views import SnapshotSource, encode_jpeg
from mocapd.pipeline.camera_watch import CameraChange
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.protocols.session_format import (
    T_EVENT,
    T_FRAME,
    T_IMU,
    T_KEYPOINTS,
    T_POSE,
    FrameRecord,
    ImuRecord,
    PersonRecord,
    PoseRecord,
    encode_event,
    encode_frame,
    encode_imu,
    encode_keypoints,
    encode_pose,
)
from mocapd.service.config import config_document
from mocapd.service.config.cameras import SyntheticConfig
from mocapd.service.config.record import RecordConfig
from mocapd.service.outputs.camera_views import snapshot_source

if TYPE_CHECKING:
    from mocapd.service.config import Config
    from mocapd.service.daemon import Daemon


def pose_record(frame: PoseFrame) -> PoseRecord:
    """A published frame as a recorded one (same fields, and the instant each pose is for)."""
    people = tuple(
        PersonRecord(p.identity, p.suit, p.track, p.views, p.imus, p.iterations, p.converged, p.confidence,
                     p.theta, p.joints, p.skeleton, frame.pose_time_ns(p), p.hands)
        for p in frame.people
    )  # fmt: skip
    return PoseRecord(frame.frame, frame.t_solve_ns, frame.tick_ns, frame.missing_cameras, people, frame.output)


def _encode_frame(frame: PoseFrame) -> bytes:
    return encode_pose(pose_record(frame))


def _encode_detections(camera: int, capture_ns: int, arrival_ns: int, dets: Detections2D) -> bytes:
    return encode_keypoints(camera, capture_ns, arrival_ns, dets.keypoints, dets.confidences)


def _encode_sample(s: ImuSample, quat: tuple[float, ...], acc: tuple[float, ...], t: int | None) -> bytes:
    q = (float(quat[0]), float(quat[1]), float(quat[2]), float(quat[3]))
    a = (float(acc[0]), float(acc[1]), float(acc[2]))
    return encode_imu(ImuRecord(s.sensor, -1 if t is None else t, s.host_ns, s.device_ticks, s.packet_counter, q, a))


@dataclass(frozen=True)
class FrameRecordOptions:
    """Recording of downscaled camera frames into the session's ``frames`` stream."""

    enabled: bool = False
    """Record camera frames (for the camera panels of ``mocapd replay``)."""
    rate_hz: float = 2.0
    """Frames per second per camera."""
    max_width: int = 320
    """Width the frames are downscaled to (pixels; the aspect ratio is kept, never upscaled)."""
    jpeg_quality: int = 70
    """JPEG quality, 1..100."""

    def __post_init__(self) -> None:
        if not 0.1 <= self.rate_hz <= 30.0:
            raise ConfigError(f"record.frames_hz = {self.rate_hz!r}; allowed: 0.1 .. 30")
        if not 16 <= self.max_width <= 4096:
            raise ConfigError(f"record.frames_width = {self.max_width!r}; allowed: 16 .. 4096")
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"record.frames_quality = {self.jpeg_quality!r}; allowed: 1 .. 100")


class SessionRecorder:
    """Records one session (see the module docstring); a pose sink plus two input taps, and optionally a task
    recording each camera's frames from ``frame_sources``. Its counters are ``/status`` → ``sinks.recorder``."""

    name = "recorder"

    def __init__(
        self,
        writer: SessionWriter,
        frame_sources: Sequence[SnapshotSource | None] = (),
        frames: FrameRecordOptions | None = None,
    ) -> None:
        self.writer = writer
        self.frames = 0
        self.frame_sources = list(frame_sources)
        self.frame_options = frames or FrameRecordOptions()
        self.frames_recorded = 0
        self._newest = [-1] * len(self.frame_sources)
        self._frame_task: asyncio.Task[None] | None = None
        # Anatomically impossible stretches of the recorded poses, per identity: the manifest's notes at the end.
        self.plausibility: dict[str, PlausibilityMonitor] = {}

    # ------------------------------------------------------------------------------------------ PoseSink
    async def start(self) -> None:
        await asyncio.get_running_loop().run_in_executor(None, self.writer.open)
        if self.frame_options.enabled and any(s is not None for s in self.frame_sources):
            self._frame_task = asyncio.create_task(self._frame_loop())

    async def _frame_loop(self) -> None:
        period = 1.0 / self.frame_options.rate_hz
        while True:
            for record in await asyncio.to_thread(self._grab_frames):
                if self.writer.put(FRAMES, T_FRAME, encode_frame, record):
                    self.frames_recorded += 1
            await asyncio.sleep(period)

    def _grab_frames(self) -> list[FrameRecord]:
        """In a worker thread: each camera's newest frame not recorded yet, downscaled, as JPEG."""
        o = self.frame_options
        out = []
        for i, src in enumerate(self.frame_sources):
            snap = src.snapshot(o.max_width) if src is not None else None
            if snap is None or snap.capture_ns <= self._newest[i]:
                continue
            self._newest[i] = snap.capture_ns
            if snap.image is not None:
                h, w = snap.image.shape[:2]
                out.append(FrameRecord(i, snap.capture_ns, w, h, encode_jpeg(snap.image, o.jpeg_quality)))
        return out

    def publish(self, frame: PoseFrame) -> None:
        self.writer.put("poses", T_POSE, _encode_frame, frame)
        self.frames += 1
        for p in frame.people:
            self.plausibility.setdefault(p.identity, PlausibilityMonitor()).step(frame.t_solve_ns / 1e9, p.theta)

    async def aclose(self, update: dict[str, Any] | None = None) -> None:
        if self._frame_task is not None:
            self._frame_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._frame_task
            self._frame_task = None
        info: dict[str, Any] = {"ended_utc": dt.datetime.now(dt.UTC).isoformat(),
                                "ended_monotonic_ns": time.monotonic_ns()}  # fmt: skip
        monitors = sorted(self.plausibility.items())
        info["plausibility"] = {k: m.status() for k, m in monitors}
        info["notes"] = [f"{k}: {line}" for k, m in monitors for line in m.summary_lines()]
        await asyncio.get_running_loop().run_in_executor(None, self.writer.close, {**info, **(update or {})})

    # ------------------------------------------------------------------------------------------ taps
    def on_detections(self, camera: int, capture_ns: int, dets: Detections2D, arrival_ns: int) -> None:
        self.writer.put("keypoints", T_KEYPOINTS, _encode_detections, camera, capture_ns, arrival_ns, dets)

    def on_camera_change(self, change: CameraChange) -> None:
        """A camera recalibrated while running (a tap of the daemon's): an event of the session."""
        self.writer.put(EVENTS, T_EVENT, encode_event, camera_event(change))

    def on_imu(self, s: ImuSample, quat: tuple[float, ...] | None, t: int | None) -> None:
        if quat is None or s.acc is None:
            return  # incomplete samples are counted by the ingest and carry nothing to re-solve with
        self.writer.put("imu", T_IMU, _encode_sample, s, quat, s.acc, t)

    def status(self) -> dict[str, Any]:
        """``recording`` false and ``stopped`` (errno and message) once a write error stopped the recording."""
        c = self.writer.counters
        cut = self.writer.cut
        return {"directory": str(self.writer.directory), "recording": cut is None,
                "stopped": None if cut is None else f"{cut['errno']}: {cut['error']}", "queued": c.queued,
                "written": c.written, "dropped": c.dropped, "not_recorded": c.not_recorded, "bytes": c.bytes,
                "write_errors": c.write_errors, "camera_frames": self.frames_recorded}  # fmt: skip


# ---------------------------------------------------------------------------------------------- manifest
def camera_dict(c: Camera) -> dict[str, Any]:
    return {"name": c.name, "width": c.width, "height": c.height, "K": c.K.tolist(), "R": c.R.tolist(),
            "t": c.t.tolist(), "dist": c.dist.tolist()}  # fmt: skip


def camera_from_dict(d: dict[str, Any]) -> Camera:
    return Camera(str(d["name"]), int(d["width"]), int(d["height"]), np.array(d["K"]), np.array(d["R"]),
                  np.array(d["t"]), np.array(d["dist"]))  # fmt: skip


def camera_event(change: CameraChange) -> dict[str, Any]:
    """The ``events`` stream's record of a camera recalibrated while running (``kind = "camera"``)."""
    return {"t_ns": change.t_ns, "kind": "camera", "index": change.index, "camera": camera_dict(change.camera),
            "source": change.source, "rotation_deg": change.rotation_deg, **change.details}  # fmt: skip


def session_manifest(config: Config, daemon: Daemon, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """What a session records about the run it comes from (see ``docs/sessions.md``)."""
    rig = daemon.rig
    o = daemon.scheduler.options
    return {
        "format": "mocapd-session",
        "version": 1,
        "software": {"mocapd": mocapd.__version__, "python": platform.python_version(), "numpy": np.__version__},
        "started_utc": dt.datetime.now(dt.UTC).isoformat(),
        "started_monotonic_ns": time.monotonic_ns(),
        "host": platform.node(),
        "streams": list(STREAMS),
        "config": config_document(config),
        "scheduler": {
            "rate_hz": o.rate_hz, "latency_ns": o.latency_ns, "keypoint_max_age_ns": o.keypoint_max_age_ns,
            "keypoint_max_gap_ns": o.keypoint_max_gap_ns, "match_px": o.match_px,
            "camera_offsets_ns": list(o.camera_offsets_ns), "imu_offsets_ns": dict(o.imu_offsets_ns),
            "body_size_frames": o.body_size_frames, "body_size_first_frames": o.body_size_first_frames,
            "lr_flips": o.flips.enabled, "output": o.prediction.output,
            "heading_correction": o.heading.enabled,
        },
        "cameras": [camera_dict(c) for c in rig.cameras],
        "skeleton": {"offsets": rig.skeleton.offsets.tolist(), "root_height": rig.skeleton.root_height,
                     "height": rig.skeleton.height, "from": _skeleton_source(config)},
        "targets": {"names": list(rig.targets.names), "bones": rig.targets.bones.tolist(),
                    "offsets": rig.targets.offsets.tolist()},
        # The detections' columns when they go beyond the targets' (both hands' keypoints: `resolve` solves fingers)
        **({"keypoint_columns": list(rig.keypoint_names)} if rig.keypoint_names else {}),
        "prior": "prior.npz" if rig.prior is not None else None,
        "suits": [{"id": s.id, "sensors": list(s.sensors), "calibration": s.calibration.to_json_dict()}
                  for s in rig.suits],
        "devices": {"imu": [{"path": d.config.path} for d in daemon.imu.devices],
                    "keypoint_sources": [src.name for src in rig.sources]},
        **({"extra": extra} if extra else {}),
    }  # fmt: skip


def _skeleton_source(config: Config) -> dict[str, Any]:
    """How the rig's skeleton was sized: the synthetic world's, or ``[imu.body]`` (a height, and segment lengths if
    given). People the cameras measure get their own (``[daemon] body_size_s``; recorded with their poses)."""
    if any(c.source == "synthetic" for c in config.cameras):
        return {"source": "synthetic world"}
    return config.imu.body.spec().describe()


def synthetic_extra(syn: SyntheticConfig, cameras: list[str], epoch_ns: int) -> dict[str, Any]:
    """The manifest's description of a synthetic world (rebuilt by the resolve measurement to score against
    the truth): its cameras, size, seed and the host time of its t = 0."""
    return {"epoch_ns": epoch_ns, "cameras": len(cameras), "camera_names": cameras, "people": syn.people,
            "suits": syn.suits, "seed": syn.seed, "motion": syn.motion}  # fmt: skip


def session_directory(cfg: RecordConfig, directory: str | Path | None) -> Path:
    """The explicit directory, else a new ``session-YYYYmmdd-HHMMSS[-n]`` under ``cfg.directory``."""
    if directory is not None:
        return Path(directory)
    base = Path(cfg.directory) / dt.datetime.now(dt.UTC).strftime("session-%Y%m%d-%H%M%S")
    path, n = base, 1
    while path.exists():
        n += 1
        path = base.with_name(f"{base.name}-{n}")
    return path


def attach_recorder(
    config: Config,
    daemon: Daemon,
    directory: str | Path | None = None,
    extra: dict[str, Any] | None = None,
    frames: FrameRecordOptions | None = None,
) -> SessionRecorder | None:
    """Record ``daemon``'s session when ``config.record.enabled`` or a ``directory`` is given (else None).

    The recorder is appended to ``daemon.sinks`` and to its detection and IMU taps; its files are created when
    the daemon starts its sinks. With ``frames`` enabled (default: ``[record] frames``) it also records
    downscaled camera frames from the rig's frame sources.
    """
    rc = config.record
    if directory is None and not rc.enabled:
        return None
    if frames is None:
        frames = FrameRecordOptions(rc.frames, rc.frames_hz, rc.frames_width, rc.frames_quality)
    path = session_directory(rc, directory)
    manifest = session_manifest(config, daemon, extra)
    streams = (*STREAMS, EVENTS, FRAMES) if frames.enabled else (*STREAMS, EVENTS)
    manifest["streams"] = list(streams)
    writer = SessionWriter(path, manifest, streams=streams, flush_interval_s=rc.flush_interval_s, fsync=rc.fsync,
                           queue_size=rc.queue_size)  # fmt: skip
    sources = [snapshot_source(s) for s in daemon.rig.sources] if frames.enabled else []
    rec = SessionRecorder(writer, sources, frames)
    prior = daemon.rig.prior
    if prior is not None:
        path.mkdir(parents=True, exist_ok=True)
        np.savez(path / "prior.npz", M=prior.M, mu=prior.mu, sigma=prior.sigma)
    daemon.sinks.append(rec)
    daemon.detection_taps.append(rec.on_detections)
    daemon.imu.taps.append(rec.on_imu)
    daemon.camera_taps.append(rec.on_camera_change)
    return rec

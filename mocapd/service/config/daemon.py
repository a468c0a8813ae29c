"""The ``[daemon]`` section of config.toml: output rate, latency, late-data limits, HTTP, time offsets,
supervision, device opening."""

from __future__ import annotations

import re
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import AfterValidator, Field

from mocapd.errors import ConfigError
from mocapd.service.config.cameras import Name
from mocapd.service.config.schema import Allowed, Section

if TYPE_CHECKING:  # the scheduler's modules (the solver's, NumBa's): imported when its options are built
    from mocapd.pipeline.scheduler import SchedulerOptions

_SENSOR_ID = re.compile(r"[0-9A-Fa-f]{8}")


def _sensor_id(value: str) -> str:
    if not _SENSOR_ID.fullmatch(value):
        raise ValueError("must be the 8 hex digits printed on the sensor")
    return value.upper()


SensorId = Annotated[str, AfterValidator(_sensor_id), Allowed("a sensor id: 8 hex digits, e.g. 00B421E6")]
IMU_ONLY_LATENCY_S = 0.06
"""``latency_s = "auto"`` on a rig without cameras (s): nothing to follow but the IMUs, whose samples arrive within
a few ms of being measured: a 100 Hz sensor's interval, the SlimeVR server's 20 ms holding and Wi-Fi jitter."""
#: how far a device's time stamps run ahead of the host clock (s)
Offset = Annotated[float, Field(ge=-1.0, le=1.0)]


class OffsetsConfig(Section):
    """``[daemon.offsets]``: per-device time offsets (s), cameras by name, IMUs by sensor id."""

    cameras: Annotated[dict[Name, Offset], Field(max_length=256)] = Field(default_factory=dict)
    imus: Annotated[dict[SensorId, Offset], Field(max_length=256)] = Field(default_factory=dict)


class DaemonConfig(Section):
    """``[daemon]``."""

    ordered = (("restart_min_s", "<=", "restart_max_s"),)

    output_rate_hz: float = Field(60.0, ge=1.0, le=500.0)
    latency_s: Annotated[float, Field(ge=0.0, le=2.0)] | Literal["auto"] = "auto"
    """Delay between wall time and solve time (s), or "auto": the smallest that covers what the detector
    delivers (measured p95 of detection delay + detection interval), adapted slowly (docs/daemon.md)."""
    output: Literal["delayed", "predicted"] = "delayed"
    """Publish the solve of ``now - latency_s`` ("delayed"), or carry suit wearers forward to the newest IMU
    samples ("predicted", docs/daemon.md "Predicted output")."""
    heading_correction: bool = True
    """Correct each IMU's heading from the cameras while at least two see its wearer."""
    mounting_from_cameras: bool = False
    """Refine each suit sensor's mounting once from the cameras' first seconds of its wearer
    (:mod:`mocapd.core.camera_mounting`)."""
    max_catch_up_s: float = Field(0.05, ge=0.0, le=1.0)
    capture_nice: int = Field(5, ge=0, le=19)
    """How much nicer than the event loop (whose output tick has a deadline every period) the cameras' capture
    threads, which run the keypoint tracking, run (Linux nice, per thread)."""
    detector_nice: int = Field(10, ge=0, le=19)
    """... and the detector's threads: throughput work, after the tick and the tracking that sets the latency."""
    solve_threads: Annotated[int, Field(ge=1, le=64)] | Literal["auto"] = "auto"
    """Threads that solve the people of a tick in parallel, beside the tick's own thread ("auto": one per core
    beyond the first, at most 4; 1: people one after another on the tick's thread)."""
    tick_thread: bool = False
    """Solve each tick on the daemon's tick thread, off the event loop (issue 39); off: on the loop, as before."""
    governor: bool = True
    """Shed work (the detector's duty, then the keypoint tracking rate) when the tick does not fit its
    period, in the order of docs/daemon.md "Real time on a slow machine"; never the output tick itself."""
    governor_pin_step: int = Field(-1, ge=-1, le=10)
    """A developer's key: hold the governor at this step of the rig's ladder (``/status`` ``governor.ladder``) to
    measure what the step saves; -1: the governor decides. Ignored with ``governor = false``."""
    switch_interval_ms: float = Field(1.0, ge=0.1, le=50.0)
    """The interpreter's thread switch interval (``sys.setswitchinterval``): the longest a thread that wants the
    interpreter lock waits for the one that holds it."""
    opencv_threads: int = Field(1, ge=0, le=64)
    """OpenCV's own worker threads (``cv2.setNumThreads``; 0 and 1: none, each call runs on its caller's thread).
    The daemon calls OpenCV from many threads at once already (every camera's capture thread tracks, the detector
    converts frames); a pool beside them spun waiting for work between calls (``sched_yield``) and cost ~0.03 s of
    CPU a second on the 4-camera demo (docs/daemon.md "OpenCV's worker threads")."""
    body_size_s: float = Field(2.0, ge=0.0, le=60.0)
    body_size_first_s: float = Field(0.25, ge=0.0, le=60.0)
    """A provisional body size from this much of a person's keypoints, before ``body_size_s`` (0: none)."""
    lr_flips: bool = True
    """Undo each view's left/right confusions before the solve (:mod:`mocapd.core.lr_flips`), and leave a pair out of
    a view that put both of its keypoints on one limb (:mod:`mocapd.core.lr_collapse`)."""
    keypoint_max_age_s: float = Field(0.1, ge=0.0, le=2.0)
    keypoint_max_gap_s: float = Field(0.25, ge=0.0, le=5.0)
    match_px: float = Field(80.0, ge=1.0, le=10000.0)
    http_host: Literal["127.0.0.1", "::1", "localhost"] = "127.0.0.1"
    """/status and /metrics listen on loopback only."""
    http_port: int = Field(8765, ge=0, le=65535)
    heading_reset_burst: int = Field(3, ge=1, le=100)
    """Heading resets allowed at once (every source together: HTTP, WebSocket, ``mocapd reset-heading``,
    trackers' gestures); more are refused (HTTP 429) until the rate below allows one."""
    heading_resets_per_s: float = Field(1.0, ge=0.01, le=100.0)
    """... and one more every ``1 / heading_resets_per_s`` seconds."""
    restart_min_s: float = Field(0.5, ge=0.01, le=60.0)
    restart_max_s: float = Field(10.0, ge=0.01, le=600.0)
    shutdown_timeout_s: float = Field(1.5, ge=0.1, le=10.0)
    open_timeout_s: float = Field(30.0, ge=1.0, le=600.0)
    """Every camera and IMU port must open within this long at start-up (s)."""
    offsets: OffsetsConfig = Field(default_factory=OffsetsConfig)

    @property
    def camera_offsets_s(self) -> dict[str, float]:
        return dict(self.offsets.cameras)

    @property
    def imu_offsets_s(self) -> dict[str, float]:
        """By upper-case sensor id."""
        return dict(self.offsets.imus)

    def solve_thread_count(self, cores: int | None) -> int:
        """Person-solve threads for a machine with ``cores`` CPUs (``solve_threads``, "auto" decided here)."""
        if self.solve_threads != "auto":
            return self.solve_threads
        return max(1, min(4, (cores or 1) - 1))

    def check_offsets(self, camera_names: list[str]) -> None:
        """Refuse ``[daemon.offsets] cameras`` that name no camera of a rig whose cameras have these names."""
        unknown = sorted(set(self.offsets.cameras) - set(camera_names))
        if unknown:
            raise ConfigError(f"daemon.offsets.cameras: unknown camera(s) {unknown}; the rig has {camera_names}")

    def scheduler_options(self, camera_names: list[str]) -> SchedulerOptions:
        """Scheduler options for a rig whose cameras have these names (offsets looked up by name)."""
        from mocapd.core.camera_mounting import MountingOptions
        from mocapd.core.heading import HeadingOptions
        from mocapd.core.lr_flips import FlipOptions
        from mocapd.pipeline.latency import AutoLatencyOptions
        from mocapd.pipeline.prediction import PredictionOptions
        from mocapd.pipeline.scheduler import SchedulerOptions

        self.check_offsets(camera_names)
        # "auto" follows the detector; a rig without cameras has none: its IMUs need a short fixed delay.
        auto = self.latency_s == "auto" and bool(camera_names)
        fixed = IMU_ONLY_LATENCY_S if self.latency_s == "auto" else self.latency_s
        return SchedulerOptions(
            rate_hz=self.output_rate_hz,
            latency_ns=AutoLatencyOptions.start_ns if auto else round(fixed * 1e9),
            # a tick runs up to one period late: the delay covers that too
            auto_latency=AutoLatencyOptions(margin_ns=round(1e9 / self.output_rate_hz)) if auto else None,
            keypoint_max_age_ns=round(self.keypoint_max_age_s * 1e9),
            keypoint_max_gap_ns=round(self.keypoint_max_gap_s * 1e9),
            match_px=self.match_px,
            camera_offsets_ns=tuple(round(self.offsets.cameras.get(n, 0.0) * 1e9) for n in camera_names),
            imu_offsets_ns={k: round(v * 1e9) for k, v in self.offsets.imus.items()},
            body_size_frames=round(self.body_size_s * self.output_rate_hz),
            body_size_first_frames=round(self.body_size_first_s * self.output_rate_hz),
            flips=FlipOptions(enabled=self.lr_flips),
            prediction=PredictionOptions(output=self.output),
            heading=HeadingOptions(enabled=self.heading_correction),
            mounting=MountingOptions(enabled=self.mounting_from_cameras),
        )

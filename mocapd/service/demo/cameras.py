"""``mocapd demo``: the daemon on four fake GigE Vision cameras streaming the Pose2Sim multi-person demo videos,
through the one assembly path, with a generated config.

The demo is data plus fakes fed to :func:`mocapd.service.assembly.run`: a config whose ``[[cameras]]`` are four
``aravis`` cameras opened by IP (the fake cameras of :mod:`mocapd.sim.fake_cameras`, one per loopback alias) and
whose ``[calibration]`` is the demo's Qualisys calibration scaled to the served image size (written as a mocapd
calibration file next to the run). The user's config (``--config``) supplies everything else: detector, solver,
streams, recording.

Why two processes. Aravis and the fake cameras need loopback aliases and GigE Vision traffic that must never
reach a real network, so the cameras and the daemon live in a private network namespace (``unshare -rn``). But
the status page, the viewer and the streams must be reachable from the user's host. A socket belongs to the
namespace it was created in, whatever process later uses it, so:

1. the parent (``mocapd demo``, host namespace) binds the status, WebSocket and UDP sockets;
2. it starts ``unshare -rn python -m mocapd.io.lifecycle mocapd.service.demo.cameras:child_main --http-fd N ...``
   with them inherited (``pass_fds``) and closes its copies;
3. the child (new namespace) brings ``lo`` up with aliases 127.0.0.2-5, starts the fake cameras there, and runs
   the daemon on the generated config with those sockets.

The parent forwards stop signals (SIGINT, SIGTERM, SIGHUP) to the child and returns its exit status; the child
ends with the parent even when the parent is killed (:func:`mocapd.io.lifecycle.die_with_parent`), and so do the
fake cameras with the child. The fake camera servers run in their own session, so the terminal's Ctrl-C reaches
the daemon only: the cameras stay up while the daemon stops (as real cameras would), and are stopped after it.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import cv2

from mocapd.errors import ConfigError, MocapdError
from mocapd.io import cpu_budget, lifecycle, ports
from mocapd.io.calibration_files import read_qca, scale_calibration, write_mocapd_toml
from mocapd.io.pose2sim_demo import CAMERAS, demo_calibration, demo_video
from mocapd.io.ws_server import listen_error
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.service import assembly
from mocapd.service.assembly import Monitor, RunOptions, Sockets
from mocapd.service.config import Config, load_config
from mocapd.service.config.cameras import CalibrationConfig, parse_cameras
from mocapd.service.config.schema import validate
from mocapd.service.daemon import Daemon
from mocapd.sim.fake_cameras import FakeCameraFleet, FakeCameraSpec
from mocapd.sim.fake_gige import add_loopback_aliases

AUTO_MAX_AGE_S = 0.5  # keypoint hold with latency "auto" (s): what the old fixed 1.0 s default gave
AUTO_MAX_GAP_S = 2.0  # keypoint interpolation gap with latency "auto" (s): ditto
SOURCE_SIZE = (1088, 1920)  # the Pose2Sim demo videos: 1088 wide, 1920 tall (portrait)


@dataclass(frozen=True)
class CameraDemoOptions:
    """What the camera demo serves and how (``mocapd demo`` flags).

    Attributes
    ----------
    demo : str
        Pose2Sim demo folder (``Demo_MultiPerson``: two people walking, four 60 fps portrait cameras).
    scale : float
        Served image size as a fraction of the videos' 1088 x 1920 (0.5: 544 x 960).
    pixel_format : str
        What the cameras send (``BayerRG8``: what a colour machine-vision camera sends; mocapd demosaics).
    max_frames : int
        Frames of each video served, looped (the demo videos have 100).
    replug_after_s : float
        A fake camera whose process ends is started again after this long.
    lost_after_s : float
        A camera silent this long is declared lost and reopened with back-off.
    speed : float
        Playback speed of the videos: 1 serves them at their own pace (60 fps), 0.05 in slow motion (3 fps, each
        frame shown 20 times as long). The cameras send at the slowed rate. For a detector far slower than the
        motion (a loaded CPU): the people then move little between two detections of a camera, so they can be
        tracked and solved as on a rig whose detector keeps up. The keypoint tracker's times (``[detector.tracking]``
        ``half_life_s``, ``max_age_s``, ``history_s``) stretch by ``1 / speed`` with the motion.
    packed : bool or "auto"
        Detect the newest frames of all cameras together, their people's regions packed onto shared canvases
        (``[detector.packing] enabled``); False: one whole-frame inference per camera frame, the cameras taking
        turns on ``[detector] workers`` (docs/daemon.md, Numbers); "auto" (the default): each pass packed or a
        whole frame, whichever costs less detector time per camera frame (measured while the demo runs).
    latency_s : float or "auto"
        The daemon's delay between solve time and wall time. A CPU detector shared by four cameras
        delivers each camera's detections late and far apart, and the scheduler interpolates only between
        detections it already has: the latency must cover the detection delay plus the interval between two
        detections of a camera. "auto" (the default) measures both and follows them (``[daemon] latency_s``);
        a fixed value sets the keypoint hold and gap limits after it (``latency/2``, ``2 × latency``).
    """

    demo: str = "Demo_MultiPerson"
    scale: float = 0.5
    pixel_format: str = "BayerRG8"
    max_frames: int = 100
    replug_after_s: float = 3.0
    lost_after_s: float = 2.0
    latency_s: float | Literal["auto"] = "auto"
    speed: float = 1.0
    packed: bool | Literal["auto"] = "auto"
    cpu_budget: float | None = None
    """The daemon's process held to this many CPUs (:mod:`mocapd.io.cpu_budget`; the fake cameras exempt)."""

    def __post_init__(self) -> None:
        if not 0.05 <= self.scale <= 1.0:
            raise ConfigError(f"camera demo scale = {self.scale}; allowed: 0.05 .. 1.0")
        if self.max_frames < 1 or self.replug_after_s < 0 or self.lost_after_s <= 0:
            raise ConfigError("camera demo: max_frames >= 1, replug_after_s >= 0 and lost_after_s > 0 are required")
        if self.latency_s != "auto" and not 0.0 < self.latency_s <= 2.0:
            raise ConfigError(f"camera demo latency = {self.latency_s} s; allowed: (0, 2]")
        if not 0.01 <= self.speed <= 1.0:
            raise ConfigError(f"camera demo speed = {self.speed}; allowed: 0.01 .. 1.0")

    @property
    def size(self) -> tuple[int, int]:
        """Served image size (width, height)."""
        return round(SOURCE_SIZE[0] * self.scale), round(SOURCE_SIZE[1] * self.scale)


def video_fps(path: Path) -> float:
    """Frame rate of a video file (30 if the container does not say)."""
    cap = cv2.VideoCapture(str(path))
    try:
        return float(cap.get(cv2.CAP_PROP_FPS)) or 30.0
    finally:
        cap.release()


def write_scaled_calibration(opts: CameraDemoOptions, path: Path) -> list[str]:
    """The demo's Qualisys calibration scaled to the served image size, as a mocapd calibration file; returns
    the camera names."""
    calib = scale_calibration(read_qca(demo_calibration(opts.demo)), opts.scale)
    write_mocapd_toml(calib, path)
    return calib.names


def fake_camera_specs(opts: CameraDemoOptions, names: list[str], addresses: list[str]) -> list[FakeCameraSpec]:
    """One fake camera per calibrated camera, serving that camera's video at its own pace (times ``opts.speed``)."""
    if len(addresses) < len(names):
        raise ConfigError(f"{len(names)} cameras need as many addresses, got {addresses}")
    specs = []
    for name, video_name, address in zip(names, CAMERAS, addresses, strict=False):
        video = demo_video(opts.demo, video_name)
        specs.append(FakeCameraSpec(name, video, address, opts.size, video_fps(video) * opts.speed,
                                    opts.pixel_format, opts.max_frames))  # fmt: skip
    return specs


def demo_config(base: Config, opts: CameraDemoOptions, specs: list[FakeCameraSpec], calibration: Path) -> Config:
    """``base`` (the user's config) with the demo's cameras, calibration, detection mode and timing: the tables a
    user would write, checked by the same rules."""
    w, h = opts.size
    tables = [
        {"name": s.name, "source": "aravis", "address": s.address, "pixel_format": opts.pixel_format,
         "region": [0, 0, w, h], "frame_rate": s.video_fps, "packet_size": 8192, "ring_slots": 8,
         "lost_after_s": opts.lost_after_s}
        for s in specs
    ]  # fmt: skip
    lat = opts.latency_s
    # With "auto" the limits cannot follow the latency (it moves): a hold of a few detection intervals at most,
    # and interpolation across any interval a shared CPU detector leaves between two frames of a camera.
    age, gap = (AUTO_MAX_AGE_S, AUTO_MAX_GAP_S) if lat == "auto" else (lat / 2, 2 * lat)
    daemon = base.daemon.model_copy(update={"latency_s": lat, "keypoint_max_age_s": age,
                                            "keypoint_max_gap_s": gap})  # fmt: skip
    packing = base.detector.packing.model_copy(update={"enabled": opts.packed})
    # Slow motion stands for a rig whose detector keeps up with the people: the tracker's times (in seconds of
    # motion) stretch with it, as the videos do.
    tr = base.detector.tracking
    tracking = tr.model_copy(update={k: min(60.0, getattr(tr, k) / opts.speed)
                                     for k in ("half_life_s", "max_age_s", "history_s")})  # fmt: skip
    return base.model_copy(update={
        "cameras": parse_cameras(tables), "daemon": daemon,
        "calibration": validate(CalibrationConfig, {"file": str(calibration)}, "calibration"),
        "detector": base.detector.model_copy(update={"packing": packing, "tracking": tracking}),
    })  # fmt: skip


async def run_camera_demo(
    base: Config,
    opts: CameraDemoOptions,
    options: RunOptions,
    *,
    monitor: Monitor | None = None,
    seconds: float | None = None,
    stop: asyncio.Event | None = None,
    on_ready: Callable[[assembly.Assembly], None] | None = None,
) -> int:
    """Inside a private network namespace: start the fake cameras, then run the daemon of the generated config
    until ``stop``, ``seconds`` or ``monitor``; the cameras stop after the daemon."""
    stop = stop if stop is not None else asyncio.Event()
    with cpu_budget.held(opts.cpu_budget if cpu_budget.active() is None else None):
        return await _run_camera_demo(base, opts, options, monitor, seconds, stop, on_ready)


async def _run_camera_demo(
    base: Config,
    opts: CameraDemoOptions,
    options: RunOptions,
    monitor: Monitor | None,
    seconds: float | None,
    stop: asyncio.Event,
    on_ready: Callable[[assembly.Assembly], None] | None,
) -> int:
    lifecycle.enter_phase("starting the fake cameras")
    addresses = add_loopback_aliases(4)
    with tempfile.TemporaryDirectory(prefix="mocapd-demo-") as tmp:
        work = Path(tmp)
        names = write_scaled_calibration(opts, work / "calibration.toml")
        specs = fake_camera_specs(opts, names, addresses)
        config = demo_config(base, opts, specs, work / "calibration.toml")
        fleet = FakeCameraFleet(specs, time.monotonic_ns(), opts.replug_after_s)
        started = asyncio.Event()
        fleet_task = asyncio.create_task(fleet.run(started), name="fake cameras")
        try:
            waits = {asyncio.create_task(started.wait()), asyncio.create_task(stop.wait()), fleet_task}
            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
            for w in waits - {fleet_task}:
                w.cancel()
            if fleet_task.done():
                fleet_task.result()  # a camera did not start: raise its error
            if stop.is_set():
                return 0
            options = RunOptions(
                record=options.record, sockets=options.sockets, status_line=options.status_line, sinks=options.sinks,
                manifest_extra={**options.manifest_extra, "camera_demo": asdict(opts)},
                status_extras={**options.status_extras, "fake_cameras": fleet.status, "cpu_budget": _budget_status},
            )  # fmt: skip
            return await assembly.run(config, options, monitor=monitor, seconds=seconds, stop=stop,
                                      on_ready=on_ready)  # fmt: skip
        finally:
            await fleet.stop()
            fleet_task.cancel()
            await asyncio.gather(fleet_task, return_exceptions=True)


def _budget_status() -> dict[str, object] | None:
    """/status ``cpu_budget``: the budget the daemon is held to (``--cpu-budget``) and how often it bit."""
    budget = cpu_budget.active()
    return None if budget is None else budget.describe()


class PeopleCount:
    """A pose sink counting what was solved: frames with people, the most people in a frame, identities, and the
    seconds from the first published frame to the last (``clock``: monotonic seconds)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.frames = 0
        self.frames_with_people = 0
        self.max_people = 0
        self.identities: set[str] = set()
        self.clock = clock
        self.first_s: float | None = None
        self.last_s: float | None = None

    def seconds(self) -> float:
        """Seconds from the first published frame to the last (0 before two frames)."""
        return 0.0 if self.first_s is None or self.last_s is None else self.last_s - self.first_s

    def publish(self, frame: PoseFrame) -> None:
        now = self.clock()
        self.first_s = now if self.first_s is None else self.first_s
        self.last_s = now
        self.frames += 1
        if frame.people:
            self.frames_with_people += 1
            self.max_people = max(self.max_people, len(frame.people))
            self.identities.update(p.identity for p in frame.people)

    async def start(self) -> None:
        return None

    async def aclose(self) -> None:
        return None


def _summary(daemon: Daemon | None, people: PeopleCount) -> dict[str, Any]:
    out: dict[str, Any] = {
        "frames": people.frames, "frames_with_people": people.frames_with_people, "max_people": people.max_people,
        "identities": sorted(people.identities),
    }  # fmt: skip
    if daemon is not None:
        st = daemon.status()
        out["missed_ticks"] = st["output"]["missed_ticks"]
        out["detected"] = {c["name"]: c["detected"] for c in st["cameras"]}
        out["end_to_end_ms"] = st["latency_ms"]["end_to_end"]
        # The rates' seconds: the output's, from its first frame to its last. The daemon's uptime also counts its
        # start-up (models loaded, kernels compiled: 35 s on a fresh checkout), when no camera detects or tracks,
        # and a closing line that divided by it said 32 Hz of keypoints where the cameras gave 55.
        out["seconds"] = round(people.seconds(), 3) or st["uptime_s"]
        out["uptime_s"] = st["uptime_s"]
        tracked = {c["name"]: c for c in st["cameras"] if c.get("tracking")}
        if tracked:
            # Keypoint sets per camera (tracked frames), and per person in view: people in keypoint sets per
            # second over the people per detection, over the whole run.
            out["keypoint_sets"] = {n: c["tracking"]["keypoint_sets"] for n, c in tracked.items()}
            out["keypoint_hz_per_person"] = {n: _per_person_hz(c, out["seconds"]) for n, c in tracked.items()}
            # Detections that went out as they are, tracking having stepped back (later than it can carry).
            out["detections_untracked"] = {n: c["tracking"]["detections_delivered"] for n, c in tracked.items()}
    return out


def _per_person_hz(camera: dict[str, Any], seconds: float) -> float | None:
    """A camera's keypoints per second for each person in view: people in its keypoint sets per second over the
    people in its detections (on average)."""
    if not camera["detected_people"] or not seconds:
        return None
    in_view = float(camera["detected_people"]) / float(camera["detected"])
    return round(float(camera["tracking"]["person_keypoint_sets"]) / seconds / in_view, 1)


def summary_line(summary: dict[str, Any]) -> str:
    """The closing line of ``mocapd demo``: what was solved, how often each camera gave keypoints, how late."""
    who = ", ".join(summary["identities"]) or "nobody"
    line = (f"done: {summary['frames']} frames, {summary['frames_with_people']} with people solved "
            f"(at most {summary['max_people']} at once: {who})")  # fmt: skip
    seconds = summary.get("seconds")
    if seconds and summary.get("detected"):
        det = sum(summary["detected"].values()) / len(summary["detected"]) / seconds
        line += f"; detections {det:.1f} Hz per camera"
        rates = [v for v in (summary.get("keypoint_hz_per_person") or {}).values() if v is not None]
        if rates:
            line += f", keypoints {min(rates):.0f}-{max(rates):.0f} Hz per camera and person"
    e2e = summary.get("end_to_end_ms") or {}
    if e2e.get("p50") is not None:
        line += f"; end to end p50 {e2e['p50']:.0f} ms, p95 {e2e['p95']:.0f} ms"
    return line


def announce(a: assembly.Assembly) -> None:
    """Print where the running daemon can be seen (the line scripts and tests wait for)."""
    url = a.daemon.http.url
    print(f"ready: status {url}/status  metrics {url}/metrics  (Ctrl-C stops)", flush=True)


def child_main(argv: list[str] | None = None) -> int:
    """Entry point inside the private network namespace (``python -m mocapd.service.demo.cameras``)."""
    p = argparse.ArgumentParser(description="mocapd camera demo (inside a private network namespace)")
    p.add_argument("--config", type=Path, default=None)
    p.add_argument("--seconds", type=float, default=0.0)
    p.add_argument("--http-fd", type=int, default=None, help="inherited listening socket for /status")
    p.add_argument("--record", type=Path, default=None, help="record the run as a session into this directory")
    p.add_argument("--ws-fd", type=int, default=None, help="inherited listening socket for the WebSocket stream")
    p.add_argument("--udp-fd", type=int, default=None, help="inherited UDP socket for the MVN / VMC streams")
    p.add_argument("--options", default="{}", help="CameraDemoOptions fields as JSON")
    args = p.parse_args(argv)
    lifecycle.install_stop_signals("mocapd demo (in its network namespace)")  # names the stop line
    people = PeopleCount()
    holder: list[Daemon] = []

    def ready(a: assembly.Assembly) -> None:
        holder.append(a.daemon)
        announce(a)

    async def main(stop: asyncio.Event) -> int:
        opts = CameraDemoOptions(**json.loads(args.options))
        sockets = Sockets(
            http=socket.socket(fileno=args.http_fd) if args.http_fd is not None else None,
            websocket=socket.socket(fileno=args.ws_fd) if args.ws_fd is not None else None,
            udp_fileno=args.udp_fd,
        )
        options = RunOptions(record=args.record, sockets=sockets, status_line=lambda s: print(s, flush=True),
                             sinks=[people])  # fmt: skip
        return await run_camera_demo(load_config(args.config), opts, options, stop=stop, on_ready=ready,
                                     seconds=None if args.seconds <= 0 else args.seconds)  # fmt: skip

    try:
        code = lifecycle.run_until_stopped(main)
    except MocapdError as exc:  # missing model or demo data, a camera that never opened: say what, no traceback
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 2
    summary = _summary(holder[0] if holder else None, people)
    print(summary_line(summary), flush=True)
    print(json.dumps({"summary": summary}), flush=True)
    return code


def in_private_netns(
    target: str,
    args: list[str],
    *,
    inherited: dict[str, socket.socket] | None = None,
) -> int:
    """Run ``target`` (``module:function``, see :func:`mocapd.io.lifecycle.child_command`) under ``unshare -rn``
    with each socket of ``inherited`` passed as ``--<name> FD``, forwarding stop signals to it; returns its exit
    status (128 + N when a signal N ended it).

    The child ends with this process, however it ends (SIGTERM from the kernel if this one is killed: it then
    stops as cleanly as on Ctrl-C, its recording closed, its fake cameras stopped; see
    :func:`~mocapd.io.lifecycle.child_command`).
    """
    cmd = ["unshare", "-rn", *lifecycle.child_command(target, *args)]
    passed = dict(inherited or {})
    for flag, sock in passed.items():
        cmd += [f"--{flag}", str(sock.fileno())]
    with lifecycle.deferred():  # from here a stop signal is forwarded to the child, never raised
        if lifecycle.requested() is not None:
            for sock in passed.values():
                sock.close()
            return 0
        # Its own session: the terminal's Ctrl-C reaches us only, and we forward it once (twice would hurry the
        # child's clean stop).
        proc = subprocess.Popen(cmd, pass_fds=tuple(sock.fileno() for sock in passed.values()), start_new_session=True)
        for sock in passed.values():
            sock.close()  # the child holds them now

        def forward(signum: int) -> None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signum)

        with lifecycle.on_stop(forward, quiet=True):  # the child names the phase it stops in
            code = proc.wait()
    return 128 - code if code < 0 else code


def host_sockets(config: Config) -> dict[str, socket.socket]:
    """The sockets the daemon serves and sends through, made here in the host's namespace so that what the
    daemon does from its private namespace reaches the host: status listener, WebSocket listener, UDP socket."""
    out: dict[str, socket.socket] = {}
    d = config.daemon
    try:
        out["http-fd"] = socket.create_server((d.http_host, d.http_port))
    except OSError as exc:
        raise ports.listen_error("[daemon] http_port", d.http_host, d.http_port, exc) from None
    ws = config.websocket
    if ws.enabled:
        try:
            out["ws-fd"] = socket.create_server((ws.host, ws.port))
        except OSError as exc:
            out.pop("http-fd").close()
            raise listen_error(ws.host, ws.port, exc) from exc
    if config.udp.mvn.enabled or config.udp.vmc.enabled:
        out["udp-fd"] = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    return out


def _detection_text(opts: CameraDemoOptions, config: Config) -> str:
    if opts.packed == "auto":
        return "packed or whole-frame passes, whichever costs less per camera frame (measured)"
    return "packed (all cameras per pass)" if opts.packed else f"{config.detector.workers} worker(s)"


def run(
    config_path: Path | None,
    config: Config,
    seconds: float | None,
    *,
    opts: CameraDemoOptions,
    record: Path | None = None,
) -> int:
    """``mocapd demo``: bind the host sockets here, run the demo in a private network namespace."""
    inherited = host_sockets(config)
    d = config.daemon
    pace = "at their own 60 fps pace" if opts.speed == 1.0 else f"in slow motion ({60 * opts.speed:g} fps)"
    print(
        f"mocapd demo: 4 fake GigE Vision cameras ({opts.pixel_format}, {opts.size[0]}x{opts.size[1]}) streaming "
        f"the Pose2Sim {opts.demo} videos {pace}, in a private network namespace; detector "
        f"{config.detector.model.input_width}x{config.detector.model.input_height}, precision "
        f"{config.detector.precision} (/status detector says what runs), on {_detection_text(opts, config)}",
        flush=True,
    )
    port = inherited["http-fd"].getsockname()[1]
    print(f"status: http://{d.http_host}:{port}/status  (starting cameras and models ...)", flush=True)
    if "ws-fd" in inherited:
        ws_port = inherited["ws-fd"].getsockname()[1]
        ws = config.websocket
        print(f"viewer: http://{ws.host}:{ws_port}/  pose stream ws://{ws.host}:{ws_port}/", flush=True)
    args = ["--seconds", str(seconds or 0.0), "--options", json.dumps(asdict(opts))]
    if config_path is not None:
        args += ["--config", str(config_path)]
    if record is not None:
        args += ["--record", str(record)]
    return in_private_netns("mocapd.service.demo.cameras:child_main", args, inherited=inherited)


if __name__ == "__main__":
    lifecycle.child_main(["mocapd.service.demo.cameras:child_main", *sys.argv[1:]])

"""``mocapd demo --synthetic``: the full daemon on a rig built from synthetic motion, no hardware needed.

- keypoints: one :class:`~mocapd.sim.world.SyntheticKeypointSource` per camera of a ring rig
  (unsynchronised cameras at the camera rate, detections arriving after a detection delay, stamped with the
  capture time), as the detector will deliver them;
- IMUs: every suit sensor is a simulated Xsens device (``mocapd/sim/xsens.py``) on its own pseudo-terminal,
  speaking real Xbus/MTData2 that mocapd's real serial path opens, brings up, parses, clock-maps and buffers;
  the suit calibration is the one that matches the simulated mounting, so IMU fusion runs end to end;
- the truth is known, so a sink measures the published poses' keypoint error (3D, the 17 observed sites) and
  the status line shows it.

The simulators run from the source tree (``tools/`` is not installed): this command is for a checkout, which is
what ``make demo`` runs.
"""

from __future__ import annotations

import asyncio
import contextlib
import shutil
import tempfile
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.io.prior import resolve_prior
from mocapd.io.xsens_serial import XsensPortConfig
from mocapd.pipeline.scheduler import PoseFrame, Suit
from mocapd.service.config import Config
from mocapd.service.daemon import Daemon, PoseSink, Rig
from mocapd.service.outputs.recorder import attach_recorder, synthetic_extra
from mocapd.service.outputs.udp import build_udp_sinks
from mocapd.service.outputs.websocket import build_websocket_sinks
from mocapd.sim import xsens as sim
from mocapd.sim.world import SyntheticKeypointSource, SyntheticWorld

FloatArray = NDArray[np.float64]
SCORE_EVERY = 4  # the truth sink scores every n-th published frame


class TruthError:
    """A pose sink that scores each published person against the nearest true person: the mean distance of the 17
    keypoint sites (:meth:`SyntheticWorld.nearest_site_error`)."""

    def __init__(self, world: SyntheticWorld, epoch_ns: int) -> None:
        self.world = world
        self.epoch_ns = epoch_ns
        self.errors: deque[float] = deque(maxlen=54_000)  # the last hour of scored frames at 60 Hz
        self.frames = 0

    def publish(self, frame: PoseFrame) -> None:
        self.frames += 1
        if self.frames % SCORE_EVERY:
            return  # a sample of frames is plenty for a median, and scoring every one costs the tick ~1 ms
        for person in frame.people:  # each pose against the truth at its own instant (later when predicted)
            t = (frame.pose_time_ns(person) - self.epoch_ns) / 1e9
            self.errors.append(self.world.nearest_site_error(person.theta, person.skeleton, t)[0])

    def recent_mm(self, n: int = 30) -> float | None:
        return 1e3 * float(np.median(list(self.errors)[-n:])) if self.errors else None

    async def start(self) -> None:
        return None

    async def aclose(self) -> None:
        return None


@dataclass
class SyntheticDemo:
    """Everything the synthetic demo runs: the daemon, its world, the simulators and their loop."""

    daemon: Daemon
    world: SyntheticWorld
    simulators: list[Any]  # mocapd.sim.xsens.XsensSimulator
    truth: TruthError
    workdir: Path
    _loop: Any

    def close(self) -> None:
        self._loop.stop()
        shutil.rmtree(self.workdir, ignore_errors=True)


def build_demo(
    config: Config,
    *,
    sinks: list[PoseSink] | None = None,
    status_line: Callable[[str], None] | None = None,
    clock: Callable[[], int] = time.monotonic_ns,
    record: str | Path | None = None,
) -> SyntheticDemo:
    """Start the simulated IMUs and build (not run) the daemon of ``config.daemon.synthetic``."""
    syn = config.daemon.synthetic
    world = SyntheticWorld(syn.cameras, syn.people, syn.suits, seed=syn.seed, motion=syn.motion)
    epoch = clock()
    workdir = Path(tempfile.mkdtemp(prefix="mocapd-demo-"))

    class TimedDevice(sim.SimDevice):
        """A simulated device whose motion sample is the world's at the emission time (shared host clock)."""

        _next_ns: int | None
        write_times: dict[int, int]
        index: int
        measuring: bool
        rate_hz: int

        def due_ns(self, now_ns: int) -> int | None:
            if self.measuring and self._next_ns is None:
                period = round(1e9 / self.rate_hz)
                self._next_ns = epoch + -(-(now_ns - epoch) // period) * period  # the next grid point
            result: int | None = super().due_ns(now_ns)
            return result

        def next_message(self, now_ns: int) -> bytes:
            assert self._next_ns is not None
            if len(self.write_times) > 1024:
                # The simulator keeps a write time per packet counter for its own benchmark; a demo that runs
                # for hours must not (65536 counters x 13 devices would be ~85 MB).
                self.write_times.clear()
            self.index = round((self._next_ns - epoch) * self.rate_hz / 1e9)
            data: bytes = super().next_message(now_ns)
            return data

    simulators = []
    for suit in world.suits:
        quats, accs = world.imu_motion(suit, float(syn.imu_rate_hz))
        for k, device_id in enumerate(suit.sensor_ids):
            motion = sim.Motion(quats[k], accs[k], float(syn.imu_rate_hz), device_id)
            simulators.append(sim.XsensSimulator(workdir / f"imu-{device_id:08X}", TimedDevice(motion)))
    loop = sim.SimulatorLoop(simulators).start() if simulators else _NoLoop()
    ports = tuple(
        XsensPortConfig(path=str(s.link), rate_hz=syn.imu_rate_hz, reconnect_min_s=0.2, reconnect_max_s=1.0,
                        stall_timeout_s=1.0)
        for s in simulators
    )  # fmt: skip
    config = replace(config, imu=replace(config.imu, ports=ports))
    suits = [Suit.from_calibration(s.id, world.calibration(s), world.skeleton) for s in world.suits]
    sources = [
        SyntheticKeypointSource(world, c, epoch_ns=epoch, rate_hz=syn.camera_rate_hz, delay_s=syn.detection_delay_s,
                                noise_px=syn.noise_px, seed=syn.seed, clock=clock)
        for c in range(len(world.cameras))
    ]  # fmt: skip
    truth = TruthError(world, epoch)
    rig = Rig(world.cameras, list(sources), world.skeleton, world.targets, resolve_prior(config.solver.prior), suits)
    daemon = Daemon(config, rig, sinks=[truth, *(sinks or [])], clock=clock, status_line=status_line)
    daemon.sinks.extend(build_udp_sinks(config, daemon))
    attach_recorder(config, daemon, record, extra={"synthetic": synthetic_extra(syn, epoch)})
    return SyntheticDemo(daemon, world, simulators, truth, workdir, loop)


class _NoLoop:
    def stop(self) -> None:
        return None


@contextlib.contextmanager
def running_demo(config: Config, **kw: Any) -> Iterator[SyntheticDemo]:
    demo = build_demo(config, **kw)
    try:
        yield demo
    finally:
        demo.close()


async def _run_for(demo: SyntheticDemo, seconds: float | None) -> int:
    task = asyncio.create_task(demo.daemon.run())
    if seconds is not None:
        stop_at = asyncio.get_running_loop().time() + seconds
        while not task.done() and asyncio.get_running_loop().time() < stop_at:
            await asyncio.wait({task}, timeout=0.1)
        demo.daemon.request_stop()
    return await task


def run(
    config: Config, seconds: float | None, sinks: list[PoseSink] | None = None, record: str | Path | None = None
) -> int:
    """Run the synthetic demo for ``seconds`` (None: until SIGINT/SIGTERM), printing a status line per second."""
    syn = config.daemon.synthetic
    print(
        f"mocapd demo --synthetic: {syn.people} people in a {syn.cameras}-camera ring "
        f"({syn.camera_rate_hz:g} Hz, detections {1e3 * syn.detection_delay_s:g} ms late), "
        f"{syn.suits} wearing 13 simulated Xsens IMUs on pseudo-terminals",
        flush=True,
    )
    print("starting: solver kernel (compiled once per machine, up to a minute the first time), inputs ...", flush=True)
    holder: dict[str, SyntheticDemo] = {}

    def line(text: str) -> None:
        err = holder["demo"].truth.recent_mm() if "demo" in holder else None
        print(f"{text}  keypoint error {'-' if err is None else f'{err:.1f}'} mm", flush=True)

    with running_demo(config, sinks=sinks, status_line=line, record=record) as demo:
        holder["demo"] = demo
        streams = build_websocket_sinks(config, demo.daemon)
        demo.daemon.sinks.extend(streams)

        async def main() -> int:
            task = asyncio.create_task(_run_for(demo, seconds))
            ready = asyncio.create_task(demo.daemon.ready.wait())
            await asyncio.wait({task, ready}, return_when=asyncio.FIRST_COMPLETED)
            if ready.done():
                url = demo.daemon.http.url
                print(f"ready: status {url}/status  metrics {url}/metrics  (Ctrl-C stops)", flush=True)
                for ws in streams:
                    print(f"viewer {ws.viewer_url}  pose stream {ws.url}", flush=True)
            else:
                ready.cancel()
            return await task

        code = asyncio.run(main())
        err = demo.truth.recent_mm(10**9)
        st = demo.daemon.status()["output"]
        print(
            f"done: {st['frames']} frames, {st['missed_ticks']} missed ticks, "
            f"median keypoint error {'-' if err is None else f'{err:.1f}'} mm",
            flush=True,
        )
    return code

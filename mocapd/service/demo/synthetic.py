"""``mocapd demo --synthetic``: the daemon on the simulated rig, through the one assembly path, no hardware needed.

The demo is a generated config: the user's config (``--config``, default the shipped one) with four ``synthetic``
cameras, i.e. the rig of ``[synthetic]``:

- keypoints: one :class:`~mocapd.sim.world.SyntheticKeypointSource` per camera of a ring rig (unsynchronised
  cameras at the camera rate, detections arriving after a detection delay, stamped with the capture time), as
  the detector would deliver them, from people moving with recorded motion (CMU clips);
- IMUs: every suit sensor is a simulated Xsens device (:mod:`mocapd.sim.suits`) on its own pseudo-terminal,
  speaking real Xbus/MTData2 that mocapd's real serial path opens, brings up, parses, clock-maps and buffers;
  the suit calibration is the one that matches the simulated mounting, so IMU fusion runs end to end;
- the truth is known, so a sink measures the published poses' keypoint error (3D, the 17 observed sites) and the
  status line shows it.

The same rig runs from a file with ``mocapd run --config F`` where F has ``[[cameras]] source = "synthetic"``
tables (see :func:`synthetic_config`).
"""

from __future__ import annotations

import asyncio
from pathlib import Path

from mocapd.io import lifecycle
from mocapd.service import assembly
from mocapd.service.assembly import Monitor, RunOptions
from mocapd.service.config import Config
from mocapd.service.config.cameras import CalibrationConfig, parse_cameras

DEFAULT_CAMERAS = 4


def synthetic_config(base: Config, cameras: int = DEFAULT_CAMERAS) -> Config:
    """``base`` with ``cameras`` synthetic cameras (``cam0``, ``cam1``, ...) in place of its own cameras and
    calibration: the tables a user would write, checked by the same rules."""
    tables = [{"name": f"cam{i}", "source": "synthetic"} for i in range(cameras)]
    return base.model_copy(update={"cameras": parse_cameras(tables), "calibration": CalibrationConfig()})


async def run_synthetic(
    config: Config,
    options: RunOptions,
    *,
    monitor: Monitor | None = None,
    seconds: float | None = None,
    stop: asyncio.Event | None = None,
) -> tuple[int, assembly.Assembly | None]:
    """Run the synthetic rig of ``config``; returns the exit status and the assembly (for its truth score)."""
    holder: list[assembly.Assembly] = []

    def ready(a: assembly.Assembly) -> None:
        holder.append(a)
        url = a.daemon.http.url
        print(f"ready: status {url}/status  metrics {url}/metrics  (Ctrl-C stops)", flush=True)
        for line in assembly.ready_lines(a):
            print(line, flush=True)

    code = await assembly.run(config, options, monitor=monitor, seconds=seconds, stop=stop, on_ready=ready)
    return code, holder[0] if holder else None


def run(config: Config, seconds: float | None, record: str | Path | None = None, cameras: int = DEFAULT_CAMERAS) -> int:
    """``mocapd demo --synthetic``: run for ``seconds`` (None: until SIGINT/SIGTERM), a status line per second."""
    config = synthetic_config(config, cameras)
    syn = config.synthetic
    print(
        f"mocapd demo --synthetic: {syn.people} people in a {cameras}-camera ring "
        f"({syn.camera_rate_hz:g} Hz, detections {1e3 * syn.detection_delay_s:g} ms late), "
        f"{syn.suits} wearing 13 simulated Xsens IMUs on pseudo-terminals",
        flush=True,
    )
    print("starting: solver kernel (compiled once per machine, up to a minute the first time), inputs ...", flush=True)

    async def main(stop: asyncio.Event) -> tuple[int, assembly.Assembly | None]:
        options = RunOptions(record=None if record is None else Path(record),
                             status_line=lambda s: print(s, flush=True))  # fmt: skip
        return await run_synthetic(config, options, seconds=seconds, stop=stop)

    code, done = lifecycle.run_until_stopped(main)
    if done is not None:
        err = done.truth.recent_mm(10**9) if done.truth is not None else None
        st = done.daemon.status()["output"]
        print(
            f"done: {st['frames']} frames, {st['missed_ticks']} missed ticks, "
            f"median keypoint error {'-' if err is None else f'{err:.1f}'} mm",
            flush=True,
        )
    return code

"""``mocapd demo --imu-only``: a suit alone drives the avatar — no camera, no hardware.

One person walks recorded motion (the synthetic rig's CMU clips); the 13 sensors of their suit are simulated Xsens
devices on pseudo-terminals (:mod:`mocapd.sim.suits`), speaking real Xbus/MTData2 through mocapd's real serial
path. The demo is a generated config, the one a suit owner writes for a real suit: ``[imu] ports`` naming the
devices, ``[imu.assignment]`` saying which sensor sits on which bone, and a calibration directory holding the
suit's ``<person>.imu.json`` (here the one that matches the simulated mounting, where a real suit has
``mocapd calibrate imu``'s); no ``[[cameras]]``. It runs through the one assembly path like ``mocapd run``.

Output goes wherever the config sends it: the WebSocket stream and viewer by default, and VRChat OSC, MVN, VMC
when enabled (``--config`` with ``[udp.vrchat] enabled = true``). The truth is known, so a sink measures the
solved joints against it after putting both roots at the origin (without cameras nothing fixes where the body is
in the room; ``mocapd eval ground`` measures that drift) and the status line shows it.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

from mocapd.core.body_dims import segment_lengths
from mocapd.service import assembly
from mocapd.service.assembly import RunOptions
from mocapd.service.config import Config
from mocapd.service.config.cameras import CalibrationConfig
from mocapd.sim.suits import SimulatedSuits
from mocapd.sim.truth import RootRelativeError
from mocapd.sim.world import SyntheticWorld

IMU_RATE_HZ = 100


@dataclass
class SimulatedSuitRig:
    """A simulated suit running on pseudo-terminals and the config of an IMU-only rig that reads it."""

    config: Config
    world: SyntheticWorld
    epoch_ns: int
    suits: SimulatedSuits
    workdir: Path

    def close(self) -> None:
        self.suits.close()
        shutil.rmtree(self.workdir, ignore_errors=True)


def suit_rig_config(base: Config, ports: tuple[str, ...], bones: dict[str, str], calibration_dir: Path) -> Config:
    """``base`` as an IMU-only rig: no cameras; ``[imu]`` with these serial ports, this assignment and calibration
    directory (what a suit owner's config.toml says)."""
    imu = base.imu.model_copy(update={
        "ports": ports, "assignment": bones, "imu_set": "13" if len(bones) == 13 else "",
        "calibration_dir": str(calibration_dir), "rate_hz": IMU_RATE_HZ,
        # simulated devices restart in milliseconds: reconnect and stall-detect faster than real ones need
        "reconnect_min_s": 0.2, "reconnect_max_s": 1.0, "stall_timeout_s": 1.0,
    })  # fmt: skip
    return base.model_copy(update={"cameras": (), "calibration": CalibrationConfig(), "imu": imu})


def start_simulated_suit(
    base: Config, *, seed: int = 0, motion: str = "recorded", person: str = "suit0"
) -> SimulatedSuitRig:
    """Start one simulated 13-sensor Xsens suit on pseudo-terminals and write its calibration (as ``person``)."""
    world = SyntheticWorld(0, 1, 1, seed=seed, motion=motion)
    suit = world.suits[0]
    workdir = Path(tempfile.mkdtemp(prefix="mocapd-imu-only-"))
    try:
        calibration = replace(world.calibration(suit), person=person)
        folder = workdir / "calibration"
        folder.mkdir()
        (folder / f"{person}.imu.json").write_text(json.dumps(calibration.to_json_dict(), indent=2), encoding="utf-8")
        epoch = time.monotonic_ns()
        sims = SimulatedSuits.start(world, IMU_RATE_HZ, epoch)
    except BaseException:
        shutil.rmtree(workdir, ignore_errors=True)
        raise
    config = suit_rig_config(base, sims.ports, dict(calibration.bones), folder)
    # The wearer measured with a tape, as a suit owner would: [imu.body] from the simulated person's segments.
    body = {f"{k}_m": round(v, 3) for k, v in segment_lengths(world.skeleton).items()}
    config = config.model_copy(update={"imu": config.imu.model_copy(update={
        "body": config.imu.body.model_copy(update={"height_m": world.skeleton.height, **body})})})  # fmt: skip
    return SimulatedSuitRig(config, world, epoch, sims, workdir)


@contextlib.contextmanager
def simulated_suit(base: Config, **kw: object) -> Iterator[SimulatedSuitRig]:
    """:func:`start_simulated_suit`, stopped and removed on exit."""
    rig = start_simulated_suit(base, **kw)  # type: ignore[arg-type]
    try:
        yield rig
    finally:
        rig.close()


def run(config: Config, seconds: float | None, record: str | Path | None = None) -> int:
    """``mocapd demo --imu-only``: run for ``seconds`` (None: until SIGINT/SIGTERM), a status line per second."""
    with simulated_suit(config) as rig:
        print(
            f"mocapd demo --imu-only: one person walking recorded motion, wearing 13 simulated Xsens IMUs on "
            f"pseudo-terminals ({', '.join(rig.suits.ports[:2])}, ...); no camera",
            flush=True,
        )
        print("starting: solver kernel (compiled once per machine, up to a minute the first time), inputs ...",
              flush=True)  # fmt: skip
        truth = RootRelativeError(rig.world, rig.epoch_ns)

        def ready(a: assembly.Assembly) -> None:
            url = a.daemon.http.url
            a.daemon.status_line_extras.append(truth.status_field)
            print(f"ready: status {url}/status  metrics {url}/metrics  (Ctrl-C stops)", flush=True)
            for line in assembly.ready_lines(a):
                print(line, flush=True)

        async def main() -> int:
            stop = asyncio.Event()
            with assembly.stop_on_signals(stop):
                options = RunOptions(record=None if record is None else Path(record), sinks=[truth],
                                     status_line=lambda s: print(s, flush=True))  # fmt: skip
                return await assembly.run(rig.config, options, seconds=seconds, stop=stop, on_ready=ready)

        code = asyncio.run(main())
        err = truth.recent_mm(10**9)
        median = "-" if err is None else f"{err:.1f}"
        print(f"done: {truth.frames} frames, root-relative joint error median {median} mm", flush=True)
    return code

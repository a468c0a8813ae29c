"""The synthetic rig with SlimeVR trackers: the daemon's SlimeVR server fed by the PyPI ``slimevr-tracker-emulator``
(a dev dependency, hence here and not in the package), one emulated tracker carrying one sensor per suit bone.

The rig is a config (:func:`slimevr_rig_config`: ``[imu.slimevr]`` with the suit's sensors assigned, its
calibration file in a calibration directory, synthetic cameras or none) built by the one assembly path
(:func:`mocapd.service.assembly.assemble`), as ``mocapd run`` builds a user's.

The emulated sensors report what the synthetic world's suit sensors would (:meth:`SyntheticWorld.imu_motion`,
ENU taken as the trackers' +Z-up frame), optionally with a yaw drift of their own (degrees per minute about the
vertical, as gyroscope bias makes 6-axis trackers drift). The emulator sends at most about ten updates a second
(its loop sleeps 0.1 s twice per received packet), so the daemon sees steps that the SlimeVR server's holding
bridges. Used by ``tests/test_slimevr_daemon.py`` and ``tools/bench_vr_drift.py``.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import math
import multiprocessing
import multiprocessing.process
import shutil
import tempfile
import time
import types
from collections.abc import AsyncIterator, Coroutine
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from slimevr_tracker_emulator.async_tracker_emulator import SlimeVRTrackerEmulatorAsync
from slimevr_tracker_emulator.tracker_types import (
    ImuType,
    SensorAcceleration,
    SensorData,
    SensorPosition,
    SensorRotationQuat,
    SensorState,
)

from mocapd.core.imu_calibration import ImuCalibration
from mocapd.core.rotations import quat_conjugate, quat_from_rotvec, quat_multiply, quat_rotate
from mocapd.service.assembly import Assembly, RunOptions, assemble
from mocapd.service.config import Config
from mocapd.service.config.cameras import CalibrationConfig, parse_cameras
from mocapd.service.daemon import Daemon, PoseSink
from mocapd.sim.world import SuitTruth, SyntheticWorld

#: The MAC a SlimeVR server reads from the emulator's handshake (its firmware string carries a NUL the length byte
#: does not count, so the six 0x78 bytes are read one byte early).
EMULATOR_MAC = "00:78:78:78:78:78"
RATE_HZ = 100.0
GRAVITY = 9.81  # the synthetic world's


def sensor_ids(suit: SuitTruth) -> list[str]:
    return [f"{EMULATOR_MAC}/{k}" for k in range(len(suit.sensor_ids))]


def slimevr_calibration(world: SyntheticWorld, suit: SuitTruth) -> ImuCalibration:
    """The suit's calibration with the emulated trackers' sensor ids."""
    c = world.calibration(suit)
    old = [f"{s:08X}" for s in suit.sensor_ids]
    new = sensor_ids(suit)
    rename = dict(zip(old, new, strict=True))
    return replace(c, bones={rename[k]: v for k, v in c.bones.items()}, q_ib={rename[k]: v for k, v in c.q_ib.items()},
                   spread_deg={rename[k]: v for k, v in c.spread_deg.items()})  # fmt: skip


@dataclass
class SlimeVrRig:
    """The rig as a config (what a user of SlimeVR trackers writes: ``[imu.slimevr]`` with the assignment, a
    calibration directory, the synthetic cameras or none), the daemon assembled from it, and the world its
    emulated trackers follow. :meth:`close` after the daemon stopped."""

    config: Config
    assembly: Assembly
    world: SyntheticWorld
    epoch_ns: int
    drift_deg_per_min: np.ndarray  # (n_sensors,)
    workdir: Path
    sent: list[dict[int, tuple[float, float, float, float]]] = field(default_factory=list)

    @property
    def daemon(self) -> Daemon:
        return self.assembly.daemon

    def close(self) -> None:
        self.assembly.close()
        shutil.rmtree(self.workdir, ignore_errors=True)


def slimevr_rig_config(base: Config, calibration: ImuCalibration, calibration_dir: Path, *, cameras: int,
                       motion: str, seed: int) -> Config:  # fmt: skip
    """``base`` as the rig of one person wearing the emulated SlimeVR suit: ``[imu.slimevr]`` on a free loopback
    port with the suit's sensors assigned, its calibration in ``calibration_dir``, and ``cameras`` synthetic
    cameras seeing the same person (``[synthetic]``: one person, no simulated Xsens suit), or none (IMU only)."""
    folder = Path(calibration_dir)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{calibration.person}.imu.json").write_text(json.dumps(calibration.to_json_dict()), encoding="utf-8")
    slimevr = base.imu.slimevr.model_copy(update={"enabled": True, "port": 0, "assignment": dict(calibration.bones)})
    imu = base.imu.model_copy(update={"slimevr": slimevr, "ports": (), "assignment": {}, "imu_set": "",
                                      "calibration_dir": str(folder)})  # fmt: skip
    tables = [{"name": f"cam{i}", "source": "synthetic"} for i in range(cameras)]
    synthetic = base.synthetic.model_copy(update={"people": 1, "suits": 0, "motion": motion, "seed": seed})
    return base.model_copy(update={"imu": imu, "cameras": parse_cameras(tables), "calibration": CalibrationConfig(),
                                   "synthetic": synthetic})  # fmt: skip


def build_slimevr_daemon(
    config: Config,
    *,
    cameras: int = 2,
    motion: str = "procedural",
    drift_deg_per_min: np.ndarray | None = None,
    sinks: list[PoseSink] | None = None,
    seed: int = 0,
) -> SlimeVrRig:
    """One person wearing a 13-sensor SlimeVR suit, in a ring of ``cameras`` synthetic cameras (0: none), assembled
    from its config by the one assembly path (built, not run)."""
    world = SyntheticWorld(cameras, 1, 1, seed=seed, motion=motion)
    suit = world.suits[0]
    workdir = Path(tempfile.mkdtemp(prefix="mocapd-slimevr-rig-"))
    try:
        cfg = slimevr_rig_config(config, slimevr_calibration(world, suit), workdir / "calibration", cameras=cameras,
                                 motion=motion, seed=seed)  # fmt: skip
        built = assemble(cfg, RunOptions(sinks=list(sinks or [])))
    except BaseException:
        shutil.rmtree(workdir, ignore_errors=True)
        raise
    # The synthetic cameras' world starts at the assembly's epoch; without cameras the trackers start now.
    epoch = built.built.epoch_ns if built.built.world is not None else time.monotonic_ns()
    drift = np.zeros(len(suit.sensor_ids)) if drift_deg_per_min is None else np.asarray(drift_deg_per_min, float)
    return SlimeVrRig(cfg, built, world, epoch, drift, workdir)


def _sensor(k: int) -> SensorData:
    return SensorData(k, SensorState.SENSOR_OK, ImuType.BNO080, SensorRotationQuat(0.0, 0.0, 0.0, 1.0),
                      SensorAcceleration(0.0, 0.0, 0.0), SensorPosition(0.0, 0.0, 0.0))  # fmt: skip


#: The emulator announces protocol version 17; servers turn such trackers' acceleration by -90° about +Z (a fix
#: for old firmware), so an emulated tracker reports it turned by +90°.
_OLD_FIRMWARE_ACC = np.array([math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)])


@contextlib.asynccontextmanager
async def emulated_suit(rig: SlimeVrRig, port: int, period_s: float = 0.02) -> AsyncIterator[None]:
    """Run the emulator against ``port`` with every suit sensor following the world (and its drift) until exit."""
    async with emulated_trackers(rig.world, rig.epoch_ns, port, rig.drift_deg_per_min, rig.sent, period_s):
        yield


@contextlib.asynccontextmanager
async def emulated_trackers(
    world: SyntheticWorld,
    epoch_ns: int,
    port: int,
    drift_deg_per_min: np.ndarray | None = None,
    sent_log: list[dict[int, tuple[float, float, float, float]]] | None = None,
    period_s: float = 0.02,
) -> AsyncIterator[None]:
    """The emulator against the SlimeVR server on loopback ``port``, one tracker sensor per sensor of ``world``'s
    first suit following its motion (world time 0 at ``epoch_ns``), until exit."""
    suit = world.suits[0]
    drift_deg_per_min = np.zeros(len(suit.sensor_ids)) if drift_deg_per_min is None else drift_deg_per_min
    sent_log = [] if sent_log is None else sent_log
    quats, accs = world.imu_motion(suit, RATE_HZ)  # (n, m, 4), (n, m, 3): ENU orientation, specific force
    emu = SlimeVRTrackerEmulatorAsync()
    for k in range(len(suit.sensor_ids)):
        await emu.set_tracker(_sensor(k))
    up = np.array([0.0, 0.0, GRAVITY])

    async def drive() -> None:
        while True:
            t = (time.monotonic_ns() - epoch_ns) / 1e9
            i = round(t * RATE_HZ) % quats.shape[1]
            sent = {}
            for k in range(quats.shape[0]):
                yaw = quat_from_rotvec(np.array([0.0, 0.0, math.radians(drift_deg_per_min[k] * t / 60.0)]))
                q = quat_multiply(yaw, quats[k, i])  # drift: the tracker's heading reference turns
                lin = accs[k, i] - quat_rotate(quat_conjugate(quats[k, i]), up)  # the firmware sends it gravity-free
                a = quat_rotate(_OLD_FIRMWARE_ACC, lin)
                w, x, y, z = (float(v) for v in q)
                await emu.set_tracker_rotation(k, SensorRotationQuat(x, y, z, w))
                await emu.set_tracker_acceleration(k, SensorAcceleration(float(a[0]), float(a[1]), float(a[2])))
                sent[k] = (w, x, y, z)
            sent_log.append(sent)
            del sent_log[:-500]
            await asyncio.sleep(period_s)

    runner = asyncio.create_task(emu.run(("127.0.0.1", port)))
    driver = asyncio.create_task(drive())
    try:
        yield
    finally:
        for task in (driver, runner):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        if emu.sock is not None:
            emu.sock.close()


def _child(port: int, epoch_ns: int, cameras: int, motion: str, seed: int, drift: list[float], seconds: float,
           pace: float) -> None:  # fmt: skip
    world = SyntheticWorld(cameras, 1, 1, seed=seed, motion=motion)  # the same world: same seed, same motion
    if pace != 1.0:
        # The emulator paces itself with two 0.1 s sleeps per received packet (about 10 updates a second); scale
        # them so that sensors update at a real tracker's rate. Only its module's view of asyncio changes.
        import slimevr_tracker_emulator.async_tracker_emulator as emulator_module

        def sleep(delay: float) -> Coroutine[Any, Any, None]:
            return asyncio.sleep(delay * pace)

        emulator_module.asyncio = types.SimpleNamespace(**{**vars(asyncio), "sleep": sleep})

    async def main() -> None:
        async with emulated_trackers(world, epoch_ns, port, np.array(drift), [], 0.01):
            await asyncio.sleep(seconds)

    with contextlib.redirect_stdout(io.StringIO()):  # the emulator prints every packet it does not expect
        asyncio.run(main())


def emulator_process(rig: SlimeVrRig, port: int, seconds: float, *, cameras: int, motion: str, seed: int,
                     pace: float = 1.0) -> multiprocessing.process.BaseProcess:  # fmt: skip
    """The emulated suit in a process of its own (as trackers are devices of their own): started, runs ``seconds``.

    ``pace`` scales the emulator's own sleeps (0.1: about ten times as many updates, a real tracker's rate).
    """
    ctx = multiprocessing.get_context("spawn")
    drift = [float(v) for v in rig.drift_deg_per_min]
    proc = ctx.Process(target=_child, args=(port, rig.epoch_ns, cameras, motion, seed, drift, seconds, pace),
                       daemon=True)  # fmt: skip
    proc.start()
    return proc

"""The synthetic world's IMU suits as real serial devices: one simulated Xsens device per sensor on its own
pseudo-terminal, speaking Xbus/MTData2, streaming what that sensor measures of the world's motion.

Each device samples the world at the emission time on the shared host clock (world time 0 at ``epoch_ns``), on
a grid of ``1 / imu_rate_hz`` from that epoch, so every simulated sensor and every simulated camera see the same
instant of the same truth. The daemon opens them through its real serial path (``[imu] ports``), exactly as it
opens a docked MTw: bring-up, MTData2 parsing, clock mapping, buffering.
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from mocapd.io import lifecycle
from mocapd.sim import xsens as sim
from mocapd.sim.world import SyntheticWorld

#: a simulator keeps a write time per packet counter for its own benchmark; a daemon that runs for hours must not
#: (65536 counters x 13 devices would be ~85 MB)
MAX_WRITE_TIMES = 1024


class _WorldClockedDevice(sim.SimDevice):
    """A simulated device whose sample ``k`` is the world's at ``epoch + k / rate`` (shared host clock)."""

    def __init__(self, motion: sim.Motion, epoch_ns: int) -> None:
        super().__init__(motion)
        self.epoch_ns = epoch_ns

    def due_ns(self, now_ns: int) -> int | None:
        if self.measuring and self._next_ns is None:
            period = round(1e9 / self.rate_hz)
            self._next_ns = self.epoch_ns + -(-(now_ns - self.epoch_ns) // period) * period  # the next grid point
        return super().due_ns(now_ns)

    def next_message(self, now_ns: int) -> bytes:
        assert self._next_ns is not None
        if len(self.write_times) > MAX_WRITE_TIMES:
            self.write_times.clear()
        self.index = round((self._next_ns - self.epoch_ns) * self.rate_hz / 1e9)
        return super().next_message(now_ns)


@dataclass
class SimulatedSuits:
    """Running simulated Xsens devices for every suit of a world; :meth:`close` stops them and removes their
    pseudo-terminal links."""

    simulators: list[sim.XsensSimulator]
    ports: tuple[str, ...]
    """The devices' paths (symlinks to their pseudo-terminals), for ``[imu] ports``."""
    workdir: Path
    _loop: sim.SimulatorLoop | None = field(default=None, repr=False)

    @classmethod
    def start(cls, world: SyntheticWorld, rate_hz: int, epoch_ns: int) -> SimulatedSuits:
        """Create a pty per sensor of every suit of ``world`` and start streaming (one thread for all)."""
        workdir = Path(tempfile.mkdtemp(prefix="mocapd-imu-sim-"))
        # Removed at exit even if the build that started them is abandoned by a stop during start-up.
        lifecycle.remove_at_exit(workdir)
        simulators = []
        for suit in world.suits:
            quats, accs = world.imu_motion(suit, float(rate_hz))
            for k, device_id in enumerate(suit.sensor_ids):
                motion = sim.Motion(quats[k], accs[k], float(rate_hz), device_id)
                device = _WorldClockedDevice(motion, epoch_ns)
                simulators.append(sim.XsensSimulator(workdir / f"imu-{device_id:08X}", device))
        loop = sim.SimulatorLoop(simulators).start() if simulators else None
        return cls(simulators, tuple(str(s.link) for s in simulators), workdir, loop)

    def close(self) -> None:
        if self._loop is not None:
            self._loop.stop()
            self._loop = None
        shutil.rmtree(self.workdir, ignore_errors=True)
        lifecycle.forget_at_exit(self.workdir)

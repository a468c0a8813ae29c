"""IMU samples → per-sensor clock mapping → per-sensor ring buffers (pure: no clock reads here).

Each sensor gets a :class:`~mocapd.pipeline.clocksync.ClockSync` (device counter → host ns) and a
:class:`~mocapd.pipeline.ringbuffer.RingBuffer` with :data:`~mocapd.pipeline.ringbuffer.IMU_FIELDS`. A
sample's buffer time is its device time mapped to the host clock when the device sends SampleTimeFine,
otherwise its host arrival time. Buffer times are kept strictly increasing: when a refit of the clock map
steps back (a new least-delayed sample lowers the envelope), the sample is placed 1 ns after the previous
one and counted. Samples without an orientation or acceleration are counted and dropped.

The table of sensors is bounded: every sample names its sensor, and a sender on the bridge or the SlimeVR port
can name a new one in every datagram (each costs a buffer, ~100 KiB, and a /status entry). Sensors the
configuration names (:meth:`ImuIngest.keep`: the suits' sensors, the assignment) are kept for good; at most
``max_other_sensors`` others are held, and a new one beyond that evicts the one silent longest (counted in
:attr:`ImuIngest.evicted`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from mocapd.pipeline.clocksync import ClockSync
from mocapd.pipeline.ringbuffer import IMU_FIELDS, RingBuffer

TICK_HZ = 10_000.0
MAX_OTHER_SENSORS = 64
"""Sensors held that the configuration does not name (a site discovering its sensors, a tracker not yet assigned)."""


@dataclass(slots=True)
class SensorStream:
    """Clock map and buffer of one sensor."""

    clock: ClockSync
    buffer: RingBuffer
    incomplete: int = 0
    counter_gaps: int = 0
    last_counter: int | None = None
    #: samples whose mapped time was moved just after the previous one because a refit of the clock map
    #: stepped backwards (a new least-delayed sample lowered the envelope)
    clock_steps_back: int = 0
    #: host arrival time of the latest sample (which unconfigured sensor has been silent longest)
    last_host_ns: int = 0


class ImuIngest:
    """Routes samples into per-sensor ring buffers.

    Parameters
    ----------
    capacity : int
        Samples kept per sensor (e.g. 4 s at 120 Hz = 480).
    max_gap_ns : int
        Look-ups do not interpolate across a larger hole (dropouts).
    max_other_sensors : int
        Sensors held besides the kept ones (:meth:`keep`); a new one beyond this evicts the one silent longest.
    """

    def __init__(
        self, *, capacity: int = 512, max_gap_ns: int = 100_000_000, max_other_sensors: int = MAX_OTHER_SENSORS
    ) -> None:
        self.capacity = capacity
        self.max_gap_ns = max_gap_ns
        self.max_other_sensors = max_other_sensors
        self.streams: dict[str, SensorStream] = {}
        self.kept: frozenset[str] = frozenset()
        self.evicted = 0
        """Streams of unconfigured sensors dropped to make room for a new one."""
        self._others = 0  # streams of sensors not kept
        self._row = np.empty(sum(f.width for f in IMU_FIELDS))

    def keep(self, sensors: Iterable[str]) -> None:
        """Never evict these sensors (the configured ones), whatever else arrives; adds to earlier calls."""
        self.kept = self.kept | frozenset(sensors)
        self._others = sum(1 for sid in self.streams if sid not in self.kept)

    def stream(self, sensor: str) -> SensorStream:
        """The stream of a sensor, created on first use (evicting the longest silent unconfigured one if the
        table of unconfigured sensors is full)."""
        s = self.streams.get(sensor)
        if s is None:
            if sensor not in self.kept:
                if self._others >= self.max_other_sensors:
                    self._evict_one()
                self._others += 1
            buffer = RingBuffer(self.capacity, IMU_FIELDS, max_gap_ns=self.max_gap_ns)
            s = SensorStream(ClockSync(tick_hz=TICK_HZ), buffer)
            self.streams[sensor] = s
        return s

    def _evict_one(self) -> None:
        others = [(s.last_host_ns, sid) for sid, s in self.streams.items() if sid not in self.kept]
        if others:
            del self.streams[min(others)[1]]
            self._others -= 1
            self.evicted += 1

    def add(
        self,
        sensor: str,
        host_ns: int,
        *,
        device_ticks: int | None,
        packet_counter: int | None,
        quat: tuple[float, ...] | None,
        acc: tuple[float, ...] | None,
    ) -> int | None:
        """Buffer one sample; returns its buffer time (ns) or None if it was dropped."""
        s = self.stream(sensor)
        s.last_host_ns = host_ns
        if quat is None or acc is None:
            s.incomplete += 1
            return None
        if packet_counter is not None:
            if s.last_counter is not None and packet_counter != (s.last_counter + 1) & 0xFFFF:
                s.counter_gaps += 1
            s.last_counter = packet_counter
        t = host_ns
        device_s = np.nan
        if device_ticks is not None:
            s.clock.update(device_ticks, host_ns)
            mapped = s.clock.to_host_ns(device_ticks)
            t = mapped if mapped is not None else host_ns
            device_s = device_ticks / TICK_HZ
        newest = s.buffer.newest_ns()
        if newest is not None and t <= newest:
            # Keep the buffer time monotonic: a refit may step the map back by a fraction of a sample period.
            s.clock_steps_back += 1
            t = newest + 1
        row = self._row
        counter = np.nan if packet_counter is None else packet_counter
        if len(quat) == 4 and len(acc) == 3:
            row[:] = (*quat, *acc, device_s, counter)  # one numpy write per sample, not four
        else:  # refused as before, by the field's width
            row[0:4] = quat
            row[4:7] = acc
        if not s.buffer.push(t, row):
            return None
        return t

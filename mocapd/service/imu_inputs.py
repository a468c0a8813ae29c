"""All configured IMU inputs feeding one :class:`~mocapd.pipeline.imu_ingest.ImuIngest`, for the asyncio app.

``ImuInputs.run()`` supervises every serial device, the experimental Awinda station, the bridge listener and the
SlimeVR server in one ``asyncio.TaskGroup``; each sample is re-expressed in ENU and buffered. ``status()`` is what
the HTTP status page shows per input; ``bone_orientations(t_ns, calibration)`` turns buffered sensor orientations into
world bone orientations with a person's calibration (``R_gb = R_ig · R_i · R_ib⁻¹``).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from mocapd.core.imu_calibration import ImuCalibration, bone_orientation, quat_to_enu
from mocapd.core.rotations import quat_multiply, quat_multiply_floats
from mocapd.core.taps import TapDetector, TapOptions, linear_norm
from mocapd.io.imu_bridge import ImuBridgeListener
from mocapd.io.slimevr import SlimeVrListener
from mocapd.io.xsens_serial import ImuSample, XsensPortConfig, XsensSerialDevice
from mocapd.pipeline.imu_ingest import ImuIngest
from mocapd.pipeline.ringbuffer import LookupStatus
from mocapd.service.config.imu import ImuConfig


@dataclass(frozen=True, slots=True)
class BoneSample:
    """A bone's world orientation at the requested time, or why there is none."""

    bone: str
    sensor: str
    status: LookupStatus
    quat: np.ndarray | None  # (4,) R_gb, (w, x, y, z)


class ImuInputs:
    """Runs the IMU inputs of an :class:`ImuConfig` until :meth:`stop`."""

    def __init__(self, config: ImuConfig, ingest: ImuIngest | None = None) -> None:
        self.config = config
        self.ingest = ingest or ImuIngest(capacity=config.buffer_capacity)
        self.ingest.keep(config.sensors)  # the assigned sensors are never evicted by unknown ones
        self.devices = [XsensSerialDevice(p, self.on_sample) for p in config.port_configs()]
        if config.awinda.experimental:
            station_port = XsensPortConfig(path=config.awinda.path)
            self.devices.append(XsensSerialDevice(station_port, self.on_sample, awinda=config.awinda.options()))
        self.bridge = (
            ImuBridgeListener(self.on_sample, host=config.bridge.host, port=config.bridge.port)
            if config.bridge.enabled
            else None
        )
        sv = config.slimevr
        self.slimevr = SlimeVrListener(self.on_sample, host=sv.host, port=sv.port) if sv.enabled else None
        #: per-sensor device headings (``Rz(δ)`` as (w, x, y, z) floats, from the suits' calibrations) applied to
        #: each sample before it is buffered: sensors without a shared heading reference (SlimeVR trackers)
        self.device_headings: dict[str, tuple[float, ...]] = {}
        #: observers of every sample (the sample, its quaternion in ENU, its buffer time or None when it was
        #: dropped), e.g. the session recorder; called where samples arrive, so they must not block
        self.taps: list[Callable[[ImuSample, tuple[float, ...] | None, int | None], None]] = []
        self._stop = asyncio.Event()
        # Tap gestures: per watched sensor its detector, the sensors whose motion cancels its taps, and what to call.
        self._tap_watch: dict[str, tuple[TapDetector, tuple[str, ...], Callable[[str], None]]] = {}
        self._tap_norms: dict[str, tuple[int, float]] = {}  # sensor -> (time, linear acceleration norm)
        self._bound = False

    def on_sample(self, s: ImuSample) -> None:
        """Buffer one sample (re-expressed in ENU)."""
        quat = s.quat
        if quat is not None and s.frame is not None and s.frame.name != "ENU":
            quat = tuple(quat_to_enu(np.array(quat), s.frame.name))
        heading = self.device_headings.get(s.sensor)
        if quat is not None and heading is not None:
            # Plain floats, not numpy: one quaternion per sample, 1300 a second for a suit (bit-identical).
            quat = quat_multiply_floats(heading, quat)
        if s.sensor in self._tap_norms and quat is not None and s.acc is not None:
            self._tap_sample(s.sensor, s.host_ns, quat, s.acc)
        t = self.ingest.add(
            s.sensor,
            s.host_ns,
            device_ticks=s.device_ticks,
            packet_counter=s.packet_counter,
            quat=quat,
            acc=s.acc,
        )
        for tap in self.taps:
            tap(s, quat, t)

    def use_calibrations(self, calibrations: list[ImuCalibration]) -> None:
        """Apply the device headings of these calibrations to their sensors' samples from now on."""
        self.device_headings = {sid: _floats(q) for c in calibrations for sid, q in c.device_heading_quats().items()}

    def turn_headings(self, turns: dict[str, np.ndarray]) -> None:
        """Turn these sensors' device headings by ``turns[sensor]`` (a quaternion about the device frame's up, from
        now on and for every sample already buffered, so that the solve sees no step): a heading reset."""
        for sid, turn in turns.items():
            old = self.device_headings.get(sid)
            self.device_headings[sid] = _floats(turn if old is None else quat_multiply(turn, np.asarray(old)))
            stream = self.ingest.streams.get(sid)
            if stream is not None:
                stream.buffer.transform("quat", _turned_by(turn))

    def watch_taps(self, sensor: str, body: Iterable[str], options: TapOptions, on_taps: Callable[[str], None]) -> None:
        """Count taps on ``sensor`` (its linear acceleration) while the ``body`` sensors stay calm; ``on_taps(sensor)``
        when the gesture is complete (:mod:`mocapd.core.taps`)."""
        others = tuple(b for b in body if b != sensor)
        self._tap_watch[sensor] = (TapDetector(options), others, on_taps)
        for sid in (sensor, *others):
            self._tap_norms.setdefault(sid, (0, 0.0))

    def _tap_sample(self, sensor: str, t_ns: int, quat: tuple[float, ...], acc: tuple[float, ...]) -> None:
        norm = linear_norm(quat, acc)
        self._tap_norms[sensor] = (t_ns, norm)
        watched = self._tap_watch.get(sensor)
        if watched is None:
            return
        detector, others, on_taps = watched
        calm = detector.options.calm
        recent = t_ns - 200_000_000
        moving = any(n > calm for t, n in (self._tap_norms[o] for o in others) if t >= recent)
        if detector.update(t_ns, norm, moving):
            on_taps(sensor)

    def keep_sensors(self, sensors: Iterable[str]) -> None:
        """Never evict these sensors' buffers (the suits' sensors), however many unknown sensor ids arrive."""
        self.ingest.keep(sensors)

    async def bind(self) -> None:
        """Bind the bridge's and the SlimeVR server's ports now (the daemon does before it starts its tasks, so a
        port in use stops the start-up with one line naming it, rather than failing a supervised task)."""
        if self._bound:
            return
        if self.bridge is not None:
            await self.bridge.start()
        try:
            if self.slimevr is not None:
                await self.slimevr.start()
        except BaseException:
            if self.bridge is not None:
                self.bridge.close()
            raise
        self._bound = True

    async def run(self) -> None:
        """Run every input until :meth:`stop`; device failures are retried inside each device's own loop."""
        await self.bind()
        try:
            async with asyncio.TaskGroup() as tg:
                for device in self.devices:
                    tg.create_task(device.run())
                if self.slimevr is not None:
                    tg.create_task(self.slimevr.run())
                await self._stop.wait()
                for device in self.devices:
                    device.stop()
                if self.slimevr is not None:
                    self.slimevr.stop()
        finally:
            self.close()

    def close(self) -> None:
        """Close the bridge's and the SlimeVR server's sockets (again: nothing)."""
        self._bound = False
        if self.bridge is not None:
            self.bridge.close()
        if self.slimevr is not None:
            self.slimevr.close()

    def stop(self) -> None:
        self._stop.set()

    def status(self) -> dict[str, object]:
        """Per-input health for the status page and metrics."""
        devices = []
        for d in self.devices:
            counters = d.session.parser.counters if d.session is not None else None
            devices.append(
                {
                    "path": d.config.path,
                    "serial": d.info.serial if d.info else None,
                    "product": d.info.product_code if d.info else None,
                    "firmware": d.info.firmware if d.info else None,
                    "awinda_experimental": d.awinda is not None,
                    "streaming": d.streaming.is_set(),
                    "samples": d.stats.samples,
                    "connects": d.stats.connects,
                    "disconnects": d.stats.disconnects,
                    "stalls": d.stats.stalls,
                    "checksum_errors": counters.checksum_errors if counters else 0,
                    "discarded_bytes": counters.discarded_bytes if counters else 0,
                    "last_error": d.last_error,
                }
            )
        streams = {
            sid: {
                "buffered": len(s.buffer),
                "counter_gaps": s.counter_gaps,
                "incomplete": s.incomplete,
                "clock_skew_ppm": round(s.clock.skew_ppm, 1),
                "clock_steps_back": s.clock_steps_back,
            }
            for sid, s in self.ingest.streams.items()
        }
        bridge = None
        if self.bridge is not None:
            st = self.bridge.stats
            bridge = {
                "port": self.bridge.port,
                "datagrams": st.datagrams,
                "records": st.records,
                "rejected": st.rejected,
                "rejected_reasons": st.rejections.as_dict(),
            }
        slimevr = self.slimevr.status() if self.slimevr is not None else None
        return {"devices": devices, "bridge": bridge, "slimevr": slimevr, "sensors": streams,
                "sensors_evicted": self.ingest.evicted}  # fmt: skip

    def bone_orientations(self, t_ns: int, calibration: ImuCalibration) -> list[BoneSample]:
        """World orientation of every calibrated bone at ``t_ns`` (slerped between samples)."""
        out = []
        for sid, bone in calibration.bones.items():
            stream = self.ingest.streams.get(sid)
            if stream is None:
                out.append(BoneSample(bone, sid, LookupStatus.EMPTY, None))
                continue
            r = stream.buffer.sample(t_ns)
            if r.status is not LookupStatus.OK:
                out.append(BoneSample(bone, sid, r.status, None))
                continue
            q_i = stream.buffer.field(r.row, "quat")
            out.append(BoneSample(bone, sid, r.status, bone_orientation(calibration.q_ig, q_i, calibration.q_ib[sid])))
        return out


def _floats(q: np.ndarray) -> tuple[float, ...]:
    """A quaternion as plain Python floats (exact: each float64 as it is)."""
    return tuple(float(v) for v in q)


def _turned_by(turn: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    def turned(q: np.ndarray) -> np.ndarray:
        out: np.ndarray = quat_multiply(turn[None], q)
        return out

    return turned

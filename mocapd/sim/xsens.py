#!/usr/bin/env python3
"""Xsens device simulator on a pseudo-terminal: answers Xbus configuration messages and streams MTData2.

It behaves like an MTi / MTw on a USB-serial link, byte for byte: a host opens the pty's slave end (through a
stable symlink, like ``/dev/serial/by-id/...``) and talks Xbus to it. The simulator

- answers GoToConfig, ReqDID, ReqProductCode, ReqFWRev, SetOutputConfiguration, GoToMeasurement, Reset and
  WakeUpAck with the acknowledgements a real device sends (unknown requests get Error 0x04),
- streams MTData2 at the configured rate with the requested outputs (packet counter, SampleTimeFine,
  SampleTimeCoarse, quaternion / rotation matrix / Euler angles in any precision and frame, acceleration)
  taken from a motion file: a real Xsens MTw export (``../shared/data/imu/opensense_mtw/*.txt``) or a
  synthetic motion,
- injects faults on request: random garbage between messages, corrupted checksums, dropped samples, an unplug
  (pty closed, symlink removed) followed by a replug (new pty, symlink recreated, WakeUp sent), and a heading
  error (:class:`HeadingFault`: a constant offset plus a drift about the vertical, as a magnetically disturbed
  or magnetometer-free sensor reports).

Run several at once: ``python -m mocapd.sim.xsens --link /tmp/imu0 --link /tmp/imu1 --motion FILE ...``.
``XsensSimulator`` (one device on one pty, in a thread) is what the integration tests and the benchmark use.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import selectors
import signal
import sys
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mocapd.core.rotations import (
    matrix_from_quat,
    quat_conjugate,
    quat_from_matrix,
    quat_multiply,
    quat_normalize,
)
from mocapd.io.mt_export import read_mt_export
from mocapd.protocols import xbus
from mocapd.protocols.mtdata2 import TYPE_MASK, AwindaSnapshot, CoordFrame, DataId, encode_packet
from mocapd.protocols.xbus import MID, OutputSetting

TICK_HZ = 10_000
FloatArray = NDArray[np.float64]


# ------------------------------------------------------------------------------------------------ motion


@dataclass(frozen=True)
class Motion:
    """Sensor orientation (ENU, w x y z) and sensor-frame acceleration (m/s², with gravity) per sample."""

    quat: NDArray[np.float64]  # (n, 4)
    acc: NDArray[np.float64]  # (n, 3)
    rate_hz: float
    device_id: int


def load_opensense(path: Path) -> Motion:
    """Read an Xsens MT Manager text export (OpenSense example data) with :func:`mocapd.io.mt_export.read_mt_export`:
    its orientation in ENU and its sensor-frame acceleration."""
    e = read_mt_export(path)
    return Motion(e.quat, e.acc, e.rate_hz, int(e.sensor, 16))


def synthetic_motion(n: int = 2400, rate_hz: float = 100.0, device_id: int = 0x00B40001) -> Motion:
    """A sensor turning about a tilted axis at ~1 rad/s, sitting still (gravity only) in its sensor frame."""
    t = np.arange(n) / rate_hz
    axis = np.array([0.3, 0.2, 0.93])
    axis /= np.linalg.norm(axis)
    angle = np.sin(t) * 1.2
    quat = np.concatenate([np.cos(angle / 2)[:, None], np.sin(angle / 2)[:, None] * axis], axis=1)
    world_g = np.array([0.0, 0.0, 9.81])  # specific force of a still sensor in ENU
    acc = np.einsum("nji,j->ni", matrix_from_quat(quat), world_g)
    return Motion(quat, acc, rate_hz, device_id)


def still_motion(
    quat: NDArray[np.float64], n: int = 600, rate_hz: float = 100.0, device_id: int = 0x00B40001
) -> Motion:
    """A sensor held still at orientation ``quat`` (w, x, y, z; ENU), measuring only gravity."""
    q = np.broadcast_to(quat_normalize(np.asarray(quat, dtype=np.float64)), (n, 4)).copy()
    acc = np.einsum("nji,j->ni", matrix_from_quat(q), np.array([0.0, 0.0, 9.81]))
    return Motion(q, acc, rate_hz, device_id)


# ENU coordinates → other device frames (rows: target axes in ENU).
_FRAME_FROM_ENU = {
    CoordFrame.ENU: np.eye(3),
    CoordFrame.NED: np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]]),
    CoordFrame.NWU: np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]]),
}


@dataclass(frozen=True)
class HeadingFault:
    """A sensor whose heading is wrong: its reported orientation is turned about the vertical (ENU +z) by
    ``offset_deg + drift_deg_per_min · t / 60`` at sample time ``t`` (seconds since the device's first sample).

    A magnetic disturbance bends the field a magnetometer-aided filter takes as north (an offset); a filter
    without magnetometer integrates gyro bias into its heading (a drift). Gravity still gives the vertical, so
    only the rotation about it is wrong, and the accelerometer (sensor frame) is unaffected.
    """

    offset_deg: float = 0.0
    drift_deg_per_min: float = 0.0

    def angle_rad(self, t_s: FloatArray | float) -> FloatArray:
        """The heading error at ``t_s`` (radians)."""
        return np.radians(self.offset_deg + self.drift_deg_per_min * np.asarray(t_s, dtype=np.float64) / 60.0)

    def apply(self, quat: FloatArray, t_s: FloatArray | float) -> FloatArray:
        """Sensor orientations (ENU, (..., 4)) at ``t_s`` as the faulty sensor reports them."""
        half = 0.5 * self.angle_rad(t_s)
        turn = np.zeros((*np.shape(half), 4))
        turn[..., 0], turn[..., 3] = np.cos(half), np.sin(half)
        return quat_normalize(quat_multiply(turn, np.asarray(quat, dtype=np.float64)))


# ------------------------------------------------------------------------------------------ device logic


@dataclass
class Faults:
    """Fault injection rates (probability per streamed message) and an RNG seed."""

    garbage: float = 0.0
    bad_checksum: float = 0.0
    dropout: float = 0.0
    seed: int = 0


@dataclass
class SimStats:
    """What the simulated device did."""

    sent: int = 0
    dropped: int = 0
    garbage: int = 0
    bad_checksums: int = 0
    overflowed: int = 0
    requests: dict[str, int] = field(default_factory=dict)


class SimDevice:
    """Sans-I/O device side: bytes from the host in, bytes to the host out; time as an argument."""

    def __init__(
        self,
        motion: Motion,
        *,
        product_code: str = "MTw2-3A7G6",
        firmware: tuple[int, int, int] = (4, 6, 0),
        faults: Faults | None = None,
        heading: HeadingFault | None = None,
    ) -> None:
        self.motion = motion
        #: a heading error of the reported orientation (None: the motion's orientation as is)
        self.heading = heading
        self.product_code = product_code
        self.firmware = firmware
        self.faults = faults or Faults()
        self.rng = np.random.default_rng(self.faults.seed)
        self.parser = xbus.XbusParser()
        self.settings: list[OutputSetting] = [
            OutputSetting(DataId.PACKET_COUNTER, xbus.RATE_MAX),
            OutputSetting(DataId.SAMPLE_TIME_FINE, xbus.RATE_MAX),
            OutputSetting(DataId.QUATERNION, 100),
            OutputSetting(DataId.ACCELERATION, 100),
        ]
        self.measuring = True  # a powered device streams its stored configuration
        self.stats = SimStats()
        self.counter = 0
        self.index = 0
        self._next_ns: int | None = None
        self._ticks0 = int(self.rng.integers(0, 1 << 31))
        self._start_ns = 0
        #: monotonic time just before the write, per packet counter (the benchmark reads it)
        self.write_times: dict[int, int] = {}
        self._packet_cache: dict[tuple[int, int], bytes] = {}
        self._frames: dict[CoordFrame, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}

    @property
    def rate_hz(self) -> int:
        rates = [s.rate_hz for s in self.settings if s.rate_hz != xbus.RATE_MAX]
        return min(rates) if rates else 100

    def receive(self, data: bytes, now_ns: int) -> bytes:
        """Answer every complete request in ``data``."""
        self.parser.receive_data(data)
        out = b""
        for msg in self.parser.events_received():
            name = MID(msg.mid).name if msg.mid in MID._value2member_map_ else f"0x{msg.mid:02X}"
            self.stats.requests[name] = self.stats.requests.get(name, 0) + 1
            out += self._answer(msg, now_ns)
        return out

    def _answer(self, msg: xbus.XbusMessage, now_ns: int) -> bytes:
        mid, payload = msg.mid, msg.payload
        if mid in (MID.GOTO_CONFIG, MID.WAKE_UP_ACK):
            self.measuring = False
            return xbus.encode(MID.GOTO_CONFIG_ACK) if mid == MID.GOTO_CONFIG else b""
        if mid in (MID.GOTO_MEASUREMENT, MID.RESET):
            self.measuring = True
            self._next_ns = None
            if mid == MID.RESET:
                return xbus.encode(MID.RESET_ACK) + xbus.encode(MID.WAKE_UP)
            return xbus.encode(MID.GOTO_MEASUREMENT_ACK)
        if mid == MID.SET_OUTPUT_CONFIGURATION:
            return self._set_outputs(payload)
        replies: dict[int, tuple[int, bytes]] = {
            MID.REQ_DID: (MID.DEVICE_ID, self.motion.device_id.to_bytes(4, "big")),
            MID.REQ_PRODUCT_CODE: (MID.PRODUCT_CODE, self.product_code.encode().ljust(20, b" ")),
            MID.REQ_FW_REV: (MID.FIRMWARE_REV, bytes(self.firmware) + bytes(8)),
        }
        reply_mid, reply = replies.get(mid, (MID.ERROR, bytes((0x04,))))  # 0x04: message invalid
        return xbus.encode(reply_mid, reply)

    def _set_outputs(self, payload: bytes) -> bytes:
        settings = xbus.decode_output_configuration(payload)
        supported = {
            DataId.PACKET_COUNTER,
            DataId.SAMPLE_TIME_FINE,
            DataId.SAMPLE_TIME_COARSE,
            DataId.QUATERNION,
            DataId.ROTATION_MATRIX,
            DataId.EULER_ANGLES,
            DataId.ACCELERATION,
        }
        if (
            not settings
            or any(s.data_id & TYPE_MASK not in supported for s in settings)
            or any(s.rate_hz == 0 or (s.rate_hz > 400 and s.rate_hz != xbus.RATE_MAX) for s in settings)
        ):
            return xbus.encode(MID.ERROR, bytes((0x21,)))  # parameter invalid, as a real device answers
        self.settings = settings
        return xbus.encode(MID.SET_OUTPUT_CONFIGURATION_ACK, payload)

    def due_ns(self, now_ns: int) -> int | None:
        """When the next sample is due (None when not measuring)."""
        if not self.measuring:
            return None
        if self._next_ns is None:
            self._next_ns = now_ns
            self._start_ns = now_ns
        return self._next_ns

    def next_message(self, now_ns: int) -> bytes:
        """The bytes of the sample due now (possibly with injected faults); advances the motion."""
        # The rate once a message (a scan of the settings): the simulator thread streams 13 devices at 100 Hz
        # beside the daemon's event loop, and holds the interpreter lock while it builds a message.
        rate = self.rate_hz
        period_ns = round(1e9 / rate)
        assert self._next_ns is not None
        self._next_ns += period_ns
        i = self.index % len(self.motion.quat)
        self.index += 1
        self.counter = (self.counter + 1) & 0xFFFF
        ticks = (self._ticks0 + (self.index * TICK_HZ) // rate) & 0xFFFFFFFF
        frame = self._build_frame(i, ticks)
        f = self.faults
        if f.dropout and self.rng.random() < f.dropout:
            self.stats.dropped += 1
            return b""
        out = b""
        if f.garbage and self.rng.random() < f.garbage:
            junk = self.rng.integers(0, 256, size=int(self.rng.integers(1, 24)), dtype=np.uint8).tobytes()
            out += junk
            self.stats.garbage += 1
        if f.bad_checksum and self.rng.random() < f.bad_checksum:
            frame = frame[:-1] + bytes(((frame[-1] + 1) & 0xFF,))
            self.stats.bad_checksums += 1
        self.stats.sent += 1
        return out + frame

    def _build_frame(self, i: int, ticks: int) -> bytes:
        """The MTData2 message(s) of motion sample ``i``."""
        payload = b"".join(self._packet(s.data_id, i, ticks) for s in self.settings)
        return xbus.encode(MID.MTDATA2, payload)

    def _packet(self, data_id: int, i: int, ticks: int) -> bytes:
        kind = data_id & TYPE_MASK
        if self.heading is not None and kind in (DataId.QUATERNION, DataId.ROTATION_MATRIX, DataId.EULER_ANGLES):
            # Sample index = samples since the device started: the error keeps drifting over motion loops.
            return self._faulty_packet(data_id, kind, i, float(self.heading.angle_rad((self.index - 1) / self.rate_hz)))
        if kind == DataId.PACKET_COUNTER:
            return encode_packet(data_id, self.counter)
        if kind == DataId.SAMPLE_TIME_FINE:
            return encode_packet(data_id, ticks)
        if kind == DataId.SAMPLE_TIME_COARSE:
            return encode_packet(data_id, ticks // TICK_HZ)
        # Motion packets depend only on (output, row): encode each once, the motion repeats in a loop.
        key = (data_id, i)
        cached = self._packet_cache.get(key)
        if cached is None:
            cached = self._packet_cache[key] = self._motion_packet(data_id, kind, i)
        return cached

    def _motion_packet(self, data_id: int, kind: int, i: int) -> bytes:
        if kind == DataId.ACCELERATION:
            return encode_packet(data_id, tuple(self.motion.acc[i].tolist()))
        quats, mats = self._in_frame(CoordFrame(data_id & 0x0C))
        return _orientation_packet(data_id, kind, quats[i], mats[i])

    def _faulty_packet(self, data_id: int, kind: int, i: int, angle: float) -> bytes:
        """An orientation output of sample ``i`` turned about the vertical by ``angle`` (radians, about ENU +z).

        The cached sample in the output's frame is turned about that frame's vertical (+z for ENU and NWU, -z for
        NED) on plain floats: the simulator thread streams 13 devices at 100 Hz, and per-sample numpy conversions
        cost ten times more than the rest of a message.
        """
        frame = CoordFrame(data_id & 0x0C)
        quats, mats = self._in_frame(frame)
        phi = angle if frame is not CoordFrame.NED else -angle
        c, s = math.cos(0.5 * phi), math.sin(0.5 * phi)
        w, x, y, z = (float(v) for v in quats[i])
        quat = np.array([c * w - s * z, c * x - s * y, c * y + s * x, c * z + s * w])
        cz, sz = math.cos(phi), math.sin(phi)
        turn = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
        return _orientation_packet(data_id, kind, quat, turn @ mats[i])

    def _in_frame(self, frame: CoordFrame) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The whole motion's orientations in a device frame, as quaternions (n, 4) and matrices (n, 3, 3).

        Computed once per frame, vectorised: per-sample conversions cost more than the rest of the simulator.
        """
        cached = self._frames.get(frame)
        if cached is None:
            mats = _FRAME_FROM_ENU[frame] @ matrix_from_quat(self.motion.quat)
            cached = self._frames[frame] = (quat_normalize(quat_from_matrix(mats)), mats)
        return cached


def _orientation_packet(data_id: int, kind: int, quat: FloatArray, mat: FloatArray) -> bytes:
    """An orientation output of one sample, from its quaternion (4,) and matrix (3, 3) in the output's frame."""
    if kind == DataId.QUATERNION:
        value = tuple(quat.tolist())
    elif kind == DataId.ROTATION_MATRIX:
        value = tuple(mat.T.reshape(-1).tolist())  # Xsens sends the matrix column-major
    else:
        value = tuple(np.degrees(_euler_xyz(mat)).tolist())
    return encode_packet(data_id, value)


def _euler_xyz(rot: NDArray[np.float64]) -> NDArray[np.float64]:
    """Xsens Euler angles (roll, pitch, yaw; Z-Y-X order) of a rotation matrix."""
    roll = np.arctan2(rot[2, 1], rot[2, 2])
    pitch = -np.arcsin(np.clip(rot[2, 0], -1.0, 1.0))
    yaw = np.arctan2(rot[1, 0], rot[0, 0])
    return np.array([roll, pitch, yaw])


class SimStation(SimDevice):
    """An Awinda station with wireless MTws, as mocapd's EXPERIMENTAL station path assumes it to be.

    It answers the station steps of :func:`mocapd.protocols.awinda.station_steps` (update rate at message id
    ``update_rate_mid``, EnableMaster) and streams, per frame, one MTData2 message per MTw carrying an Awinda
    snapshot whose SDI increments are the motion's orientation and velocity changes divided by the given
    scale factors. The real station's payloads and scales are not public: this checks mocapd's plumbing
    against its own assumptions, not against a real station.
    """

    def __init__(
        self,
        children: list[Motion],
        *,
        station_id: int = 0x12300001,
        delta_q_scale: float = 1e-9,
        delta_v_scale: float = 1e-6,
        update_rate_mid: int = 0x04,
        faults: Faults | None = None,
    ) -> None:
        super().__init__(Motion(children[0].quat, children[0].acc, 60.0, station_id), faults=faults)
        self.children = children
        self.delta_q_scale = delta_q_scale
        self.delta_v_scale = delta_v_scale
        self.update_rate_mid = update_rate_mid
        self.station_rate = 60
        self.radio_channel: int | None = None
        self.measuring = False

    @property
    def rate_hz(self) -> int:
        return self.station_rate

    def _answer(self, msg: xbus.XbusMessage, now_ns: int) -> bytes:
        if msg.mid == self.update_rate_mid and len(msg.payload) == 2:
            self.station_rate = int.from_bytes(msg.payload, "big")
            return xbus.encode(self.update_rate_mid + 1)
        if msg.mid == MID.ENABLE_MASTER and len(msg.payload) == 2:
            self.radio_channel = int.from_bytes(msg.payload, "big")
            return xbus.encode(MID.ENABLE_MASTER_ACK)
        return super()._answer(msg, now_ns)

    def _build_frame(self, i: int, ticks: int) -> bytes:
        out = b""
        for motion in self.children:
            k = i % len(motion.quat)
            prev = motion.quat[k - 1] if k > 0 else motion.quat[k]
            dq = quat_multiply(quat_conjugate(prev), motion.quat[k])
            dq = dq if dq[0] >= 0 else -dq
            dv = motion.acc[k] / self.station_rate
            snap = AwindaSnapshot(
                motion.device_id,
                self.index,
                tuple(round(v / self.delta_q_scale) for v in dq[1:]),
                tuple(round(v / self.delta_v_scale) for v in dv),
                (0, 0, 0),
                101325,
                0,
                0,
                0,
                False,
            )
            out += xbus.encode(MID.MTDATA2, encode_packet(0xC810, snap))
        return out


# ----------------------------------------------------------------------------------------- pty plumbing


class XsensSimulator:
    """One simulated device on a pty, reachable at ``link`` (a symlink to the slave end).

    ``start()`` runs it in its own :class:`SimulatorLoop`; several simulators can share one loop (one thread,
    one selector), which is what the command line does.
    """

    def __init__(self, link: Path, device: SimDevice) -> None:
        self.link = Path(link)
        self.device = device
        self._master = -1
        self._slave = -1
        self.generation = 0  # incremented on every plug: a new pty may reuse the old descriptor numbers
        self._lock = threading.Lock()
        self._loop: SimulatorLoop | None = None
        self._own_loop = False
        self.plugged = False

    # -- plug / unplug
    def plug(self) -> None:
        """Create a fresh pty and point the link at it (a device appearing on the bus)."""
        with self._lock:
            master, slave = os.openpty()
            tty.setraw(slave)  # no echo, no line discipline: bytes pass unchanged
            os.set_blocking(master, False)
            tmp = self.link.with_name(self.link.name + ".tmp")
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            tmp.symlink_to(os.ttyname(slave))
            tmp.replace(self.link)
            self._master, self._slave = master, slave
            self.generation += 1
            self.plugged = True
        self._wake()

    def unplug(self) -> None:
        """Remove the link and close the pty: the host's reads fail like on a USB unplug."""
        with self._lock:
            if not self.plugged:
                return
            with contextlib.suppress(FileNotFoundError):
                self.link.unlink()
            os.close(self._master)
            os.close(self._slave)
            self._master = self._slave = -1
            self.plugged = False
            # A re-powered device comes back streaming its stored configuration.
            self.device.measuring = True
            self.device._next_ns = None
        self._wake()

    def replug(self) -> None:
        """Plug in again and announce power-up with WakeUp, like a device after a USB re-plug."""
        self.plug()
        with self._lock:
            self._write(xbus.encode(MID.WAKE_UP))

    def _wake(self) -> None:
        if self._loop is not None:
            self._loop.wake()

    # -- running
    def start(self) -> XsensSimulator:
        """Plug in and run in a loop of its own (a thread)."""
        self._own_loop = True
        SimulatorLoop([self]).start()
        return self

    def stop(self) -> None:
        """Stop its own loop (if :meth:`start` made one) and unplug."""
        if self._own_loop and self._loop is not None:
            self._loop.stop()
        self.unplug()

    def poll_fd(self) -> tuple[int, int]:
        """(master descriptor or -1, plug generation) for the loop's selector."""
        with self._lock:
            return self._master, self.generation

    def due_ns(self, now_ns: int) -> int | None:
        with self._lock:
            return self.device.due_ns(now_ns) if self._master >= 0 else None

    def emit_due(self, now_ns: int) -> None:
        """Write every sample that is due (several if the loop fell behind, like a device's UART buffer)."""
        with self._lock:
            due = self.device.due_ns(now_ns) if self._master >= 0 else None
            while due is not None and due <= now_ns:
                counter = (self.device.counter + 1) & 0xFFFF
                data = self.device.next_message(now_ns)
                self.device.write_times[counter] = time.monotonic_ns()
                self._write(data)
                due = self.device.due_ns(now_ns)

    def read_host(self, fd: int) -> None:
        """Answer what the host wrote (called by the loop when the master end is readable)."""
        with self._lock:
            if fd != self._master:
                return
            try:
                data = os.read(fd, 4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                # EIO: no process has the slave open any more (we keep it open, so this is rare).
                return
            self._write(self.device.receive(data, time.monotonic_ns()))

    def _write(self, data: bytes) -> None:
        if not data or self._master < 0:
            return
        try:
            os.write(self._master, data)
        except OSError:
            # Full pty buffer (nobody reading, like a real UART) or a closing pty: the bytes are lost.
            self.device.stats.overflowed += 1


class SimulatorLoop:
    """Runs several simulators in one thread: one selector over their pty masters, one sample scheduler."""

    def __init__(self, sims: list[XsensSimulator]) -> None:
        self.sims = sims
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        for sim in sims:
            sim._loop = self

    def start(self) -> SimulatorLoop:
        for sim in self.sims:
            if not sim.plugged:
                sim.plug()
        self._thread = threading.Thread(target=self._run, name="xsens-sim", daemon=True)
        self._thread.start()
        return self

    def wake(self) -> None:
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"w")

    def stop(self) -> None:
        self._stop.set()
        self.wake()
        if self._thread is not None:
            self._thread.join(timeout=5)
        for sim in self.sims:
            sim._loop = None
        os.close(self._wake_r)
        os.close(self._wake_w)

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._wake_r, selectors.EVENT_READ, None)
        registered: dict[int, tuple[int, int]] = {}  # sim index -> (fd, generation)
        while not self._stop.is_set():
            for k, sim in enumerate(self.sims):
                fd, gen = sim.poll_fd()
                old = registered.get(k, (-1, -1))
                if (fd, gen) != old:
                    if old[0] >= 0:
                        with contextlib.suppress(KeyError, ValueError, OSError):
                            sel.unregister(old[0])
                    if fd >= 0:
                        sel.register(fd, selectors.EVENT_READ, sim)
                    registered[k] = (fd, gen)
            now = time.monotonic_ns()
            dues = [d for sim in self.sims if (d := sim.due_ns(now)) is not None]
            timeout = 0.05 if not dues else max(0.0, (min(dues) - now) / 1e9)
            for key, _ in sel.select(timeout):
                if key.data is None:
                    with contextlib.suppress(BlockingIOError):
                        os.read(self._wake_r, 4096)
                else:
                    key.data.read_host(key.fd)
            now = time.monotonic_ns()
            for sim in self.sims:
                sim.emit_due(now)
        sel.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--link", action="append", required=True, type=Path, help="symlink path per device")
    ap.add_argument("--motion", action="append", type=Path, default=[], help="MT Manager export per device")
    ap.add_argument("--garbage", type=float, default=0.0, help="probability of junk before a message")
    ap.add_argument("--bad-checksum", type=float, default=0.0, help="probability of a corrupted checksum")
    ap.add_argument("--dropout", type=float, default=0.0, help="probability of a dropped sample")
    ap.add_argument("--unplug-every", type=float, default=0.0, help="seconds between unplug/replug cycles")
    ap.add_argument("--heading-error", type=float, default=0.0, help="heading offset of every device, degrees")
    ap.add_argument("--heading-drift", type=float, default=0.0, help="heading drift of every device, degrees/min")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--write-log", type=Path, help="on exit, write {device id: {counter: write ns}} as JSON")
    args = ap.parse_args(argv)
    sims = []
    for k, link in enumerate(args.link):
        motion = load_opensense(args.motion[k]) if k < len(args.motion) else synthetic_motion(device_id=0xB40000 + k)
        faults = Faults(args.garbage, args.bad_checksum, args.dropout, args.seed + k)
        heading = HeadingFault(args.heading_error, args.heading_drift)
        device = SimDevice(motion, faults=faults, heading=heading if heading != HeadingFault() else None)
        sims.append(XsensSimulator(link, device))
    loop = SimulatorLoop(sims).start()
    for sim in sims:
        print(f"{sim.link} -> {os.readlink(sim.link)} (device {sim.device.motion.device_id:08X})", flush=True)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        while not stop.wait(args.unplug_every or 3600.0):
            if args.unplug_every:
                for sim in sims:
                    sim.unplug()
                time.sleep(1.0)
                for sim in sims:
                    sim.replug()
    except KeyboardInterrupt:
        pass
    loop.stop()
    for sim in sims:
        sim.unplug()
    if args.write_log:
        log = {f"{s.device.motion.device_id:08X}": s.device.write_times for s in sims}
        args.write_log.write_text(json.dumps(log))
    return 0


if __name__ == "__main__":
    sys.exit(main())

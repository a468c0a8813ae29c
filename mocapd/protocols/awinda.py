"""EXPERIMENTAL: Xsens Awinda station (wireless master) bring-up and snapshot integration.

What is public and implemented:

- the wireless-master message ids (:class:`mocapd.protocols.xbus.MID`, 0xB0..0xCF, Xsens SDK headers),
- the Awinda snapshot record layout (0xC810 / 0xC811, :class:`mocapd.protocols.mtdata2.AwindaSnapshot`).

What is NOT publicly specified, and therefore comes from :class:`AwindaConfig` (config.toml
``[imu.awinda]``) and is unverified against a real station:

- the message id and payload that set the station's update rate (default: id 0x04 with a uint16 rate),
- the payload of EnableMaster (default: uint16 radio channel),
- the scale factors turning the snapshot's integer SDI increments into radians (delta-q) and m/s
  (delta-v): there are no defaults; the session refuses to start until both are configured.

The integration here is plain strapdown integration of the delta-q increments (orientation relative to the
first snapshot, no inclination or heading correction). The vendor's sensor-fusion filter, which corrects
drift with gravity and the magnetometer, is not reproduced. Prefer the IMU bridge input
(``tools/xsens_sdk_bridge.py``) for production; this path exists so that a station can be brought up and
its byte stream inspected and decoded.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

from mocapd.core.rotations import quat_multiply_floats
from mocapd.errors import ConfigError
from mocapd.protocols.mtdata2 import AwindaSnapshot
from mocapd.protocols.xbus import MID
from mocapd.protocols.xsens_session import Step

_U16 = struct.Struct(">H")


@dataclass(frozen=True, slots=True)
class AwindaConfig:
    """``[imu.awinda]``: the station path plus the constants that are not publicly documented."""

    experimental: bool = False
    path: str = ""
    radio_channel: int = 19
    update_rate_hz: int = 60
    update_rate_mid: int = 0x04  # unverified
    delta_q_scale: float | None = None  # radians per SDI delta-q unit: unknown, must be configured
    delta_v_scale: float | None = None  # m/s per SDI delta-v unit: unknown, must be configured

    def check(self) -> None:
        """Raise ConfigError unless the experimental path is enabled and fully configured."""
        if not self.experimental:
            raise ConfigError("imu.awinda is experimental: set imu.awinda.experimental = true to use it")
        if not 11 <= self.radio_channel <= 25:
            raise ConfigError(f"imu.awinda.radio_channel={self.radio_channel}: use 11..25")
        if self.delta_q_scale is None or self.delta_v_scale is None:
            raise ConfigError(
                "imu.awinda.delta_q_scale and delta_v_scale are not publicly documented by Xsens and have no "
                "default; set both (see docs/imu.md) or use the IMU bridge input instead"
            )


def station_steps(config: AwindaConfig) -> list[Step]:
    """Bring-up requests for a station (unverified payloads, see the module docstring)."""
    return [
        Step("GoToConfig", MID.GOTO_CONFIG, b"", MID.GOTO_CONFIG_ACK),
        Step("ReqDID", MID.REQ_DID, b"", MID.DEVICE_ID),
        Step(
            "SetUpdateRate",
            config.update_rate_mid,
            _U16.pack(config.update_rate_hz),
            config.update_rate_mid + 1,
        ),
        Step("EnableMaster", MID.ENABLE_MASTER, _U16.pack(config.radio_channel), MID.ENABLE_MASTER_ACK),
        Step("GoToMeasurement", MID.GOTO_MEASUREMENT, b"", MID.GOTO_MEASUREMENT_ACK),
    ]


@dataclass(slots=True)
class _Track:
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    last_frame: int | None = None


@dataclass(frozen=True, slots=True)
class IntegratedSample:
    """Orientation (relative to the first snapshot) and mean acceleration over the snapshot interval."""

    sensor: str
    frame_number: int
    device_ticks: int
    quat: tuple[float, float, float, float]
    acc: tuple[float, float, float]


@dataclass
class SnapshotIntegrator:
    """Integrates Awinda snapshots per MTw (pure). Retransmitted or repeated frames are skipped, counted."""

    delta_q_scale: float
    delta_v_scale: float
    rate_hz: float
    tracks: dict[int, _Track] = field(default_factory=dict)
    duplicates: int = 0

    def add(self, snap: AwindaSnapshot) -> IntegratedSample | None:
        track = self.tracks.setdefault(snap.device_id, _Track())
        if track.last_frame is not None and snap.frame_number <= track.last_frame:
            self.duplicates += 1
            return None
        frames = 1 if track.last_frame is None else snap.frame_number - track.last_frame
        track.last_frame = snap.frame_number
        vx, vy, vz = (v * self.delta_q_scale for v in snap.delta_q)
        w = math.sqrt(max(0.0, 1.0 - (vx * vx + vy * vy + vz * vz)))
        track.quat = _normalize(quat_multiply_floats(track.quat, (w, vx, vy, vz)))
        dt = frames / self.rate_hz
        ax, ay, az = (v * self.delta_v_scale / dt for v in snap.delta_v)
        ticks = round(snap.frame_number * 10_000 / self.rate_hz) & 0xFFFFFFFF
        return IntegratedSample(f"{snap.device_id:08X}", snap.frame_number, ticks, track.quat, (ax, ay, az))


def _normalize(q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    n = math.sqrt(sum(v * v for v in q))
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)

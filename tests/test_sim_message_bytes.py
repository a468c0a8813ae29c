"""The simulated Xsens device builds a message with less Python (issue 45's soak: its thread streams the 13 devices
of the synthetic suit, 1300 messages a second, beside the daemon's event loop and under the same interpreter
lock): the output rate is read once a message, not three times (each a scan of the settings), and the counter
packets are chosen without a dictionary built per packet. The bytes it writes are the old code's, byte for byte:
the old methods are kept here, verbatim, in a subclass, and both devices stream side by side."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.protocols import xbus
from mocapd.protocols.mtdata2 import TYPE_MASK, DataId, encode_packet
from mocapd.sim import xsens as sim
from mocapd.sim.xsens import TICK_HZ


class _OldDevice(sim.SimDevice):
    def next_message(self, now_ns: int) -> bytes:
        period_ns = round(1e9 / self.rate_hz)
        assert self._next_ns is not None
        self._next_ns += period_ns
        i = self.index % len(self.motion.quat)
        self.index += 1
        self.counter = (self.counter + 1) & 0xFFFF
        ticks = (self._ticks0 + (self.index * TICK_HZ) // self.rate_hz) & 0xFFFFFFFF
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

    def _packet(self, data_id: int, i: int, ticks: int) -> bytes:
        kind = data_id & TYPE_MASK
        if self.heading is not None and kind in (DataId.QUATERNION, DataId.ROTATION_MATRIX, DataId.EULER_ANGLES):
            return self._faulty_packet(data_id, kind, i, float(self.heading.angle_rad((self.index - 1) / self.rate_hz)))
        counters: dict[int, int] = {
            DataId.PACKET_COUNTER: self.counter,
            DataId.SAMPLE_TIME_FINE: ticks,
            DataId.SAMPLE_TIME_COARSE: ticks // TICK_HZ,
        }
        if kind in counters:
            return encode_packet(data_id, counters[kind])
        key = (data_id, i)
        cached = self._packet_cache.get(key)
        if cached is None:
            cached = self._packet_cache[key] = self._motion_packet(data_id, kind, i)
        return cached


_EVERY = xbus.RATE_MAX
OUTPUTS = {
    "stored": None,  # the device's own configuration: counter, fine time, quaternion and acceleration at 100 Hz
    "mixed": [
        xbus.OutputSetting(DataId.PACKET_COUNTER, _EVERY),
        xbus.OutputSetting(DataId.SAMPLE_TIME_COARSE, _EVERY),
        xbus.OutputSetting(DataId.SAMPLE_TIME_FINE, _EVERY),
        xbus.OutputSetting(DataId.QUATERNION | 0x04, 60),  # NED
        xbus.OutputSetting(DataId.ROTATION_MATRIX, 120),
        xbus.OutputSetting(DataId.EULER_ANGLES | 0x08, 120),  # NWU
        xbus.OutputSetting(DataId.ACCELERATION, 60),
    ],
}
FAULTS = {
    "none": {},
    "faults": {"faults": sim.Faults(garbage=0.1, bad_checksum=0.1, dropout=0.1, seed=4)},
    "heading": {"heading": sim.HeadingFault(12.0, 3.0)},
}


@pytest.mark.parametrize("outputs", list(OUTPUTS))
@pytest.mark.parametrize("faults", list(FAULTS))
def test_the_device_streams_the_old_codes_bytes(outputs: str, faults: str) -> None:
    devices: list[sim.SimDevice] = []
    for cls in (_OldDevice, sim.SimDevice):
        d = cls(sim.synthetic_motion(n=300, device_id=0x00B40007), **FAULTS[faults])  # type: ignore[arg-type]
        if OUTPUTS[outputs] is not None:
            d.settings = list(OUTPUTS[outputs] or [])
        d.due_ns(1_000_000)
        devices.append(d)
    old, new = devices
    for k in range(700):  # past the motion's 300 samples: the cached packets are reused
        assert old._next_ns == new._next_ns
        assert new.next_message(new._next_ns or 0) == old.next_message(old._next_ns or 0), f"message {k}"
        assert (new.counter, new.index, new.stats) == (old.counter, old.index, old.stats)
    assert new.stats.sent > 500

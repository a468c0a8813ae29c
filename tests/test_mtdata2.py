"""MTData2 decoding against real MTi bytes (einride captures, MIT) and encode/decode round trips."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mocapd.protocols.mtdata2 import (
    AwindaSnapshot,
    CoordFrame,
    DataId,
    GnssSatInfo,
    Precision,
    UtcTime,
    decode_mtdata2,
    encode_packet,
)
from mocapd.protocols.xbus import MID, XbusParser, decode_output_configuration

DATA = Path(__file__).parent / "data" / "xbus_einride"
CAPTURES = [DATA / str(i) for i in range(1, 6)]

NAMES = {
    "PacketCounter": DataId.PACKET_COUNTER,
    "SampleTimeFine": DataId.SAMPLE_TIME_FINE,
    "SampleTimeCoarse": DataId.SAMPLE_TIME_COARSE,
    "UTCTime": DataId.UTC_TIME,
    "StatusWord": DataId.STATUS_WORD,
    "StatusByte": DataId.STATUS_BYTE,
    "EulerAngles": DataId.EULER_ANGLES,
    "Acceleration": DataId.ACCELERATION,
    "DeltaV": DataId.DELTA_V,
    "RateOfTurn": DataId.RATE_OF_TURN,
    "DeltaQ": DataId.DELTA_Q,
    "LatLon": DataId.LAT_LON,
    "AltitudeEllipsoid": DataId.ALTITUDE_ELLIPSOID,
    "VelocityXYZ": DataId.VELOCITY_XYZ,
    "GNSSPVTData": DataId.GNSS_PVT_DATA,
    "GNSSSatInfo": DataId.GNSS_SAT_INFO,
    "RotationMatrix": DataId.ROTATION_MATRIX,
    "FreeAcceleration": DataId.FREE_ACCELERATION,
    "Quaternion": DataId.QUATERNION,
    "Temperature": DataId.TEMPERATURE,
    "PositionECEF": DataId.POSITION_ECEF,
    "MagneticField": DataId.MAGNETIC_FIELD,
    "BaroPressure": DataId.BARO_PRESSURE,
}
PRECISIONS = {
    "Float32": Precision.FLOAT32,
    "FP1220": Precision.FP1220,
    "FP1632": Precision.FP1632,
    "Float64": Precision.FLOAT64,
}
FRAMES = {"EastNorthUp": CoordFrame.ENU, "NorthEastDown": CoordFrame.NED, "NorthWestUp": CoordFrame.NWU}
KEY = re.compile(r"^(\w+)(?:\((?:(\w+),)?(\w+)\))?:$")

GoldenEntry = tuple[str, str | None, str | None, list[str]]


def parse_golden(path: Path) -> list[list[GoldenEntry]]:
    """einride's text dump: blank-line separated messages of ``Name(Frame,Precision):`` + indented values."""
    messages: list[list[GoldenEntry]] = []
    current: list[GoldenEntry] = []
    for line in path.read_text().splitlines():
        if not line.strip():
            if current:
                messages.append(current)
            current = []
        elif line.startswith("  "):
            current[-1][3].append(line.strip())
        else:
            m = KEY.match(line)
            assert m, line
            current.append((m.group(1), m.group(2), m.group(3), []))
    if current:
        messages.append(current)
    return messages


def _read_capture(capture: Path) -> list[bytes]:
    parser = XbusParser()
    parser.receive_data(capture.joinpath("output.bin").read_bytes())
    messages = parser.events_received()
    assert parser.counters.checksum_errors == 0
    assert parser.counters.discarded_bytes == 0
    assert all(m.mid == MID.MTDATA2 and m.bid == 0xFF for m in messages)
    return [m.payload for m in messages]


def _check_value(name: str, value: object, lines: list[str]) -> None:
    if name in ("PacketCounter", "SampleTimeFine", "SampleTimeCoarse", "BaroPressure"):
        assert value == int(lines[0])
    elif name == "StatusWord":
        assert f"{value:032b}" == lines[0]
    elif name == "StatusByte":
        assert f"{value:08b}" == lines[0]
    elif name == "UTCTime":
        assert isinstance(value, UtcTime)
        assert value.isoformat() == lines[0]
    elif name == "GNSSPVTData":
        assert isinstance(value, dict)
        assert {k: int(v) for k, v in (s.split(":") for s in lines)} == value
    elif name == "GNSSSatInfo":
        assert isinstance(value, GnssSatInfo)
        assert {k: int(v) for k, v in (s.split(":") for s in lines)} == value.header
        assert len(value.satellites) == value.header["NumSVS"]
    else:
        assert isinstance(value, tuple)
        golden = [float(s.split(":")[-1]) for s in lines]
        # Exact: the golden decimal strings are shortest round-trip representations of the same doubles.
        assert list(value) == golden, (name, value, golden)


@pytest.mark.parametrize("capture", CAPTURES, ids=lambda p: p.name)
def test_every_message_decodes_to_golden_values(capture: Path) -> None:
    payloads = _read_capture(capture)
    golden = parse_golden(capture / "output.golden")
    assert len(payloads) == len(golden) == 100
    for payload, expected in zip(payloads, golden, strict=True):
        packet = decode_mtdata2(payload)
        assert packet.unknown == 0
        assert packet.malformed == 0
        assert [NAMES[name] for name, *_ in expected] == list(packet.items)
        for name, frame, precision, lines in expected:
            item = packet.items[NAMES[name]]
            if precision is not None:
                assert item.precision == PRECISIONS[precision]
            if frame is not None:
                assert item.frame == FRAMES[frame]
            _check_value(name, item.value, lines)


@pytest.mark.parametrize("capture", CAPTURES, ids=lambda p: p.name)
def test_output_configuration_matches_golden(capture: Path) -> None:
    settings = decode_output_configuration(capture.joinpath("outputconfig.bin").read_bytes())
    assert settings is not None
    lines = capture.joinpath("outputconfig.golden").read_text().splitlines()
    names = [KEY.match(line).group(1) for line in lines[0::2]]  # type: ignore[union-attr]
    rates = [line.strip() for line in lines[1::2]]
    assert len(settings) == len(names)
    for s, name, rate in zip(settings, names, rates, strict=True):
        if name in NAMES:
            assert s.data_id & 0xF8F0 == NAMES[name]
        assert s.rate_hz == (0xFFFF if rate == "Max" else int(rate.split()[0]))


def test_reencoding_real_messages_is_byte_exact() -> None:
    """Decoding then encoding every packet of every capture reproduces the device's bytes."""
    for capture in CAPTURES:
        for payload in _read_capture(capture):
            packet = decode_mtdata2(payload)
            rebuilt = b"".join(
                encode_packet(item.data_id, item.value)
                for item in packet.items.values()
                if item.data_id & 0xFF00 != 0x7000  # GNSS records are decoded, not re-encoded
            )
            gnss_free = _strip_gnss(payload)
            assert rebuilt == gnss_free


def _strip_gnss(payload: bytes) -> bytes:
    out = b""
    pos = 0
    while pos < len(payload):
        size = payload[pos + 2]
        if payload[pos] != 0x70:
            out += payload[pos : pos + 3 + size]
        pos += 3 + size
    return out


def test_unknown_and_malformed_packets_are_counted_and_skipped() -> None:
    good = encode_packet(DataId.PACKET_COUNTER, 7)
    unknown = bytes((0x66, 0x60, 2, 1, 2))
    wrong_size = bytes((0x20, 0x10, 3, 1, 2, 3))  # quaternion float32 must be 16 bytes
    truncated = bytes((0x10, 0x60, 4, 1))
    packet = decode_mtdata2(unknown + good + wrong_size + truncated)
    assert packet.unknown == 1
    assert packet.malformed == 2
    assert packet.packet_counter == 7
    assert decode_mtdata2(b"\x10").malformed == 1


def test_awinda_snapshot_round_trip_and_retransmission_flag() -> None:
    snap = AwindaSnapshot(0x00B421E6, 1234, (1, -2, 3), (-4, 5, -6), (7, -8, 9), 101325, 0x0003, 1, 2, False)
    packet = decode_mtdata2(encode_packet(0xC810, snap))
    item = packet.items[DataId.AWINDA_SNAPSHOT]
    assert item.value == snap
    again = decode_mtdata2(encode_packet(0xC811, snap)).items[DataId.AWINDA_SNAPSHOT].value
    assert isinstance(again, AwindaSnapshot)
    assert again.retransmitted
    assert len(encode_packet(0xC810, snap)) == 3 + 46


@pytest.mark.parametrize("precision", list(Precision))
@pytest.mark.parametrize("frame", list(CoordFrame))
def test_float_outputs_round_trip_in_every_precision_and_frame(precision: Precision, frame: CoordFrame) -> None:
    rng = np.random.default_rng(int(precision) * 16 + int(frame))
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    data_id = DataId.QUATERNION | frame | precision
    item = decode_mtdata2(encode_packet(data_id, list(q))).items[DataId.QUATERNION]
    tol = {Precision.FLOAT32: 1e-7, Precision.FP1220: 1e-6, Precision.FP1632: 1e-9, Precision.FLOAT64: 0.0}
    assert np.allclose(item.value, q, atol=tol[precision], rtol=0)  # type: ignore[arg-type]
    assert item.frame == frame
    assert item.precision == precision


def test_negative_fixed_point_values() -> None:
    for precision in (Precision.FP1220, Precision.FP1632):
        values = (-1.5, -0.0009765625, -2047.25)
        item = decode_mtdata2(encode_packet(DataId.ACCELERATION | precision, values)).items[DataId.ACCELERATION]
        assert item.value == values


@settings(deadline=None)  # the machine is shared: no per-example wall-clock limit
@given(st.binary(max_size=300))
def test_decode_never_raises_on_arbitrary_payloads(payload: bytes) -> None:
    packet = decode_mtdata2(payload)
    assert packet.unknown + packet.malformed + len(packet.items) >= (1 if payload else 0)

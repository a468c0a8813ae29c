"""SlimeVR tracker datagrams (pure): golden bytes written from the firmware's packets.h / connection.cpp layouts,
round trips, truncation at every offset, and arbitrary bytes."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mocapd.protocols.slimevr import (
    HANDSHAKE_REPLY,
    Acceleration,
    Battery,
    Decoded,
    FeatureFlags,
    Handshake,
    Heartbeat,
    Ignored,
    Packet,
    PingPong,
    Rotation,
    SensorInfo,
    ServerFeature,
    SignalStrength,
    Tap,
    Temperature,
    TrackerError,
    Tx,
    UserAction,
    decode_datagram,
    encode_bundle,
    encode_feature_flags,
    encode_heartbeat,
    encode_packet,
    encode_ping,
    encode_sensor_info_ack,
)

# Header: u32 type, u64 packet number (here 5), big-endian.
N5 = "0000000000000005"
GOLDEN: dict[str, tuple[str, Packet]] = {
    "heartbeat": ("00000000" + N5, Heartbeat()),
    # sensor 1, data type 1, x y z w = 0 0 0 1, accuracy 0
    "rotation data": ("00000011" + N5 + "0101" + "00000000" * 3 + "3f800000" + "00",
                      Rotation(1, (1.0, 0.0, 0.0, 0.0))),
    # legacy rotation (sensor 0): x y z w = 0 0 -1 0 → (w, x, y, z) = (0, 0, 0, -1)
    "rotation legacy": ("00000001" + N5 + "00000000" * 2 + "bf800000" + "00000000", Rotation(0, (0.0, 0.0, 0.0, -1.0))),
    "rotation 2 legacy": ("00000010" + N5 + "3f800000" + "00000000" * 3, Rotation(1, (0.0, 1.0, 0.0, 0.0))),
    # x y z = 1.0 -2.0 0.5 m/s², sensor 2
    "acceleration": ("00000004" + N5 + "3f800000" + "c0000000" + "3f000000" + "02", Acceleration(2, (1.0, -2.0, 0.5))),
    "ping echo": ("0000000a" + "0000000000000000" + "0000002a", PingPong(42)),
    "battery": ("0000000c" + N5 + "40800000" + "3f000000", Battery(4.0, 0.5)),
    "battery level only": ("0000000c" + N5 + "3f400000", Battery(None, 0.75)),
    # sensor 0, status 1 (ok), IMU type 3 (BNO080), then the optional fields a newer firmware adds
    "sensor info": ("0000000f" + N5 + "000103" + "0000" + "01" + "00" + "01" + "00000000" * 2, SensorInfo(0, 1, 3)),
    "signal strength": ("00000013" + N5 + "ff" + "c4", SignalStrength(255, -60)),
    "temperature": ("00000014" + N5 + "00" + "41c80000", Temperature(0, 25.0)),
    "error": ("0000000e" + N5 + "0103", TrackerError(1, 3)),
    "feature flags": ("00000016" + N5 + "05", FeatureFlags(b"\x05")),
    # sensor 0, Q15 quaternion x y z w = 0 0 0 0x7fff, Q7 acceleration 128 -64 0 → 1.0 -0.5 0.0 m/s²
    "rotation + acceleration": ("00000017" + N5 + "00" + "0000" * 3 + "7fff" + "0080" + "ffc0" + "0000",
                                Rotation(0, (1.0, 0.0, 0.0, 0.0), acc=(1.0, -0.5, 0.0))),
    # sensor 1, flags 0x41: the firmware's tap detector saw a double tap (bit 6)
    "tap": ("0000000d" + N5 + "0141", Tap(1, 0x41)),
    "user action": ("00000015" + N5 + "03", UserAction(3)),  # a yaw reset asked on the tracker
    "serial (ignored)": ("0000000b" + N5 + "00000002" + "6869", Ignored(Tx.SERIAL)),
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_golden_packets(name: str) -> None:
    hexdata, packet = GOLDEN[name]
    data = bytes.fromhex(hexdata)
    decoded = decode_datagram(data)
    assert decoded.error is None
    assert decoded.packets == (packet,)
    assert decoded.number == (0 if name == "ping echo" else 5)


def test_handshake_as_the_firmware_sends_it() -> None:
    # board 2, IMU 3, MCU 2, three unused ints, protocol 22, "0.6.3", MAC, then tracker type and vendor strings.
    data = bytes.fromhex(
        "00000003" + "0000000000000000" + "00000002" + "00000003" + "00000002" + "00000000" * 3 + "00000016"
        + "05" + b"0.6.3".hex() + "a1b2c3d4e5f6" + "01" + "07" + b"SlimeVR".hex()
    )  # fmt: skip
    decoded = decode_datagram(data)
    assert decoded.error is None
    assert decoded.packets == (Handshake(2, 3, 2, 22, "0.6.3", "A1:B2:C3:D4:E5:F6"),)


def test_handshake_fields_are_optional_from_the_end() -> None:
    assert decode_datagram(bytes.fromhex("00000003" + "00" * 8)).packets == (Handshake(0, 0, 0, 0, "", None),)
    short = bytes.fromhex("00000003" + "00" * 8 + "00000001" + "00000002")
    assert decode_datagram(short).packets == (Handshake(1, 2, 0, 0, "", None),)
    zeros_mac = bytes.fromhex("00000003" + "00" * 8 + "00000001" * 7 + "00" + "000000000000")
    assert decode_datagram(zeros_mac).packets[0] == Handshake(1, 1, 1, 1, "", None)


def test_firmware_string_read_through_its_nul_as_the_server_does() -> None:
    # A sender that writes the length and then the string *with* a NUL (the PyPI tracker emulator does): the server
    # reads `length` bytes, the NUL stays, and the MAC starts one byte early. We read the same MAC the server would.
    body = struct.pack(">7I", 2, 250, 250, 0, 0, 0, 17) + b"\x05" + b"0.4.0\x00" + bytes([120] * 6)
    decoded = decode_datagram(struct.pack(">IQ", 3, 0) + body)
    assert decoded.packets == (Handshake(2, 250, 250, 17, "0.4.0", "00:78:78:78:78:78"),)


def test_bundles() -> None:
    packets: list[Packet] = [Rotation(0, (1.0, 0.0, 0.0, 0.0)), Acceleration(0, (0.0, 0.0, 1.0)), Heartbeat()]
    # A bundle by hand: u16 length, then u32 type + payload (no packet number inside).
    inner = bytes.fromhex("00000011" + "0001" + "00000000" * 3 + "3f800000" + "00")
    data = bytes.fromhex("00000064" + N5) + struct.pack(">H", len(inner)) + inner
    assert decode_datagram(data) == Decoded(100, 5, (packets[0],))
    for compact in (False, True):
        decoded = decode_datagram(encode_bundle(packets, 9, compact=compact))
        assert decoded == Decoded(101 if compact else 100, 9, tuple(packets))
    # Zero-length entries are skipped; an entry longer than what is left stops the bundle with an error.
    assert decode_datagram(bytes.fromhex("00000064" + N5 + "0000")).packets == ()
    bad = decode_datagram(bytes.fromhex("00000064" + N5) + struct.pack(">H", 200) + inner)
    assert bad.error is not None and bad.packets == ()
    nested = decode_datagram(bytes.fromhex("00000065" + N5 + "0164"))
    assert nested.error == "packet type 100 inside a bundle"


def test_round_trip_of_every_tracker_packet() -> None:
    packets: list[Packet] = [
        Heartbeat(),
        Handshake(4, 10, 3, 22, "0.6.3", "01:02:03:04:05:06"),
        Rotation(3, (0.5, 0.5, -0.5, 0.5)),
        Rotation(1, (1.0, 0.0, 0.0, 0.0), acc=(2.0, -3.0, 0.25)),
        Acceleration(1, (0.5, 0.25, -9.5)),
        PingPong(0xDEADBEEF),
        Battery(3.75, 0.8125),
        Battery(None, 0.5),
        SignalStrength(255, -71),
        SensorInfo(2, 1, 11),
        Temperature(0, 31.5),
        TrackerError(0, 4),
        FeatureFlags(b"\x01\x02"),
    ]
    for p in packets:
        decoded = decode_datagram(encode_packet(p, 77))
        assert decoded.error is None, p
        assert decoded.packets == (p,)
        assert decoded.number == (0 if isinstance(p, Handshake) else 77)


def test_truncation_at_every_offset_never_raises_and_is_reported() -> None:
    # Bytes a packet cannot do without (the acceleration's sensor byte is optional: owoTrack omits it).
    required = {"rotation data": 31, "rotation legacy": 28, "acceleration": 24, "rotation + acceleration": 27,
                "ping echo": 16, "temperature": 17, "error": 14, "signal strength": 14}  # fmt: skip
    for name, (hexdata, _) in GOLDEN.items():
        data = bytes.fromhex(hexdata)
        for cut in range(len(data)):
            decoded = decode_datagram(data[:cut])
            if cut < 12:
                assert decoded.packet_type == -1 and decoded.error is not None
            elif cut < required.get(name, 0):
                assert decoded.error is not None and decoded.packets == (), (name, cut)


def test_non_rotations_and_non_finite_values_are_refused() -> None:
    zero = bytes.fromhex("00000011" + N5 + "0001" + "00000000" * 4 + "00")
    assert "not a rotation" in str(decode_datagram(zero).error)
    nan = bytes.fromhex("00000011" + N5 + "0001" + "7fc00000" + "00000000" * 3 + "00")
    assert decode_datagram(nan).error == "non-finite quaternion"
    inf_acc = bytes.fromhex("00000004" + N5 + "7f800000" + "00000000" * 2 + "00")
    assert decode_datagram(inf_acc).error == "non-finite vector"
    assert decode_datagram(bytes.fromhex("00000063" + N5)).error == "unknown packet type 99"


def test_server_datagrams() -> None:
    assert bytes(51) + HANDSHAKE_REPLY[:13] == bytes(51) + b"\x03Hey OVR =D 5"
    assert not any(HANDSHAKE_REPLY[13:])
    assert len(HANDSHAKE_REPLY) == 64
    assert encode_heartbeat() == bytes.fromhex("00000001" + "00" * 8)
    assert encode_ping(42) == bytes.fromhex("0000000a" + "00" * 8 + "0000002a")
    assert encode_sensor_info_ack(1, 1) == bytes.fromhex("0000000f0101")
    assert encode_feature_flags(ServerFeature.BUNDLE | ServerFeature.BUNDLE_COMPACT) == bytes.fromhex(
        "00000016" + "00" * 8 + "03"
    )


@settings(deadline=None, max_examples=300)
@given(st.binary(max_size=120))
def test_arbitrary_bytes_never_raise(data: bytes) -> None:
    decoded = decode_datagram(data)
    assert isinstance(decoded, Decoded)


@settings(deadline=None, max_examples=300)
@given(st.sampled_from(sorted(GOLDEN)), st.data())
def test_mutated_golden_packets_never_raise(name: str, data: st.DataObject) -> None:
    raw = bytearray(bytes.fromhex(GOLDEN[name][0]))
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i] = data.draw(st.integers(0, 255))
    decoded = decode_datagram(bytes(raw))
    assert decoded.error is not None or len(decoded.packets) <= 1

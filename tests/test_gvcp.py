"""GVCP discovery (GigE Vision 2.0 Part 2): DISCOVERY_CMD bytes, DISCOVERY_ACK from a real Aravis fake camera and
from bytes laid out by hand, truncation at every length, garbage, foreign acks and duplicates counted."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mocapd.protocols.gvcp import (
    DISCOVERY_ACK_SIZE,
    DeviceClass,
    DiscoveryAck,
    DiscoveryCollector,
    IpConfig,
    Rejected,
    encode_discovery_ack,
    encode_discovery_cmd,
    parse_discovery_ack,
)

ARAVIS_FAKE_ACK = (Path(__file__).parent / "data" / "gvcp" / "aravis_fake_discovery_ack.bin").read_bytes()


def _hand_made_ack(ack_id: int = 0x2A2A) -> bytes:
    """A DISCOVERY_ACK written field by field from the specification's layout (not with the encoder)."""
    return (
        bytes.fromhex("0000 0003 00f8") + ack_id.to_bytes(2, "big")
        + bytes.fromhex("0002 0001")  # version 2.1
        + bytes.fromhex("80000001")  # big-endian registers, device class 0 (transmitter), UTF-8
        + bytes.fromhex("0000") + bytes.fromhex("00305311abcd")  # reserved, MAC
        + bytes.fromhex("00000007") + bytes.fromhex("00000005")  # supported: all; current: persistent + LLA
        + bytes(12) + bytes((192, 168, 10, 11))
        + bytes(12) + bytes((255, 255, 255, 0))
        + bytes(12) + bytes((192, 168, 10, 1))
        + b"Basler".ljust(32, b"\0")
        + b"acA1920-155um".ljust(32, b"\0")
        + b"106755-11".ljust(32, b"\0")
        + b"none".ljust(48, b"\0")
        + b"40012345".ljust(16, b"\0")
        + b"left-cam".ljust(16, b"\0")
    )  # fmt: skip


def test_discovery_cmd_bytes() -> None:
    # key 0x42, flags: acknowledge required, command 0x0002, length 0, req_id.
    assert encode_discovery_cmd(1) == bytes.fromhex("4201 0002 0000 0001")
    assert encode_discovery_cmd(0xFFFF, allow_broadcast_ack=True) == bytes.fromhex("4211 0002 0000 ffff")
    for bad in (0, 0x10000, -1):
        with pytest.raises(ValueError, match="req_id"):
            encode_discovery_cmd(bad)


def test_ack_of_a_real_aravis_fake_camera() -> None:
    assert len(ARAVIS_FAKE_ACK) == 8 + DISCOVERY_ACK_SIZE
    ack = parse_discovery_ack(ARAVIS_FAKE_ACK)
    assert isinstance(ack, DiscoveryAck)
    assert ack.ack_id == 7
    assert (ack.manufacturer, ack.model, ack.serial, ack.user_name) == ("Aravis", "Fake", "MOCAPD-FAKE", "")
    assert ack.device_version.startswith("0.8.") and ack.manufacturer_info == "none"
    assert ack.ip == "127.0.0.1" and ack.mac == "00:00:00:00:00:00"
    assert encode_discovery_ack(ack) == ARAVIS_FAKE_ACK


def test_ack_laid_out_by_hand() -> None:
    data = _hand_made_ack()
    ack = parse_discovery_ack(data)
    assert isinstance(ack, DiscoveryAck)
    assert ack.ack_id == 0x2A2A and ack.spec_version == (2, 1)
    assert ack.big_endian and ack.device_class == DeviceClass.TRANSMITTER and ack.character_set == 1
    assert ack.mac == "00:30:53:11:ab:cd"
    assert ack.ip_config_supported == IpConfig.PERSISTENT | IpConfig.DHCP | IpConfig.LLA
    assert ack.ip_config_current == IpConfig.PERSISTENT | IpConfig.LLA
    assert (ack.ip, ack.subnet, ack.gateway) == ("192.168.10.11", "255.255.255.0", "192.168.10.1")
    assert (ack.manufacturer, ack.model, ack.device_version) == ("Basler", "acA1920-155um", "106755-11")
    assert (ack.manufacturer_info, ack.serial, ack.user_name) == ("none", "40012345", "left-cam")
    assert encode_discovery_ack(ack) == data


def test_full_width_strings_and_bad_utf8_are_kept() -> None:
    data = bytearray(_hand_made_ack())
    data[8 + 0xD8 : 8 + 0xE8] = b"0123456789ABCDEF"  # serial fills its 16 bytes: no NUL
    data[8 + 0xE8 : 8 + 0xEC] = b"\xe9t\xe9\0"  # Latin-1, not UTF-8
    ack = parse_discovery_ack(bytes(data))
    assert isinstance(ack, DiscoveryAck)
    assert ack.serial == "0123456789ABCDEF"
    assert ack.user_name == "\ufffdt\ufffd"


def test_device_mode_fields() -> None:
    ack = parse_discovery_ack(_hand_made_ack())
    assert isinstance(ack, DiscoveryAck)
    peripheral = replace(ack, device_mode=(3 << 28) | 2)
    assert not peripheral.big_endian and peripheral.device_class == DeviceClass.PERIPHERAL
    assert peripheral.character_set == 2


def test_truncated_at_every_length_is_rejected() -> None:
    data = _hand_made_ack()
    for n in range(len(data)):
        assert parse_discovery_ack(data[:n]) is Rejected.TRUNCATED, n
    # The length field says less than a discovery payload.
    short_length = data[:4] + (0x20).to_bytes(2, "big") + data[6:]
    assert parse_discovery_ack(short_length) is Rejected.TRUNCATED
    # Trailing bytes beyond the 248 are ignored (a later specification may add fields).
    assert isinstance(parse_discovery_ack(data + b"\0" * 8), DiscoveryAck)


def test_other_packets_are_rejected_not_raised() -> None:
    assert parse_discovery_ack(encode_discovery_cmd(5)) is Rejected.MALFORMED  # our own command looped back
    read_ack = bytes.fromhex("0000 0081 0004 0001 00000001")  # READREG_ACK
    assert parse_discovery_ack(read_ack) is Rejected.MALFORMED
    error = bytes.fromhex("8001 0003 0000 0001")  # DISCOVERY_ACK with status "not implemented"
    assert parse_discovery_ack(error) is Rejected.ERROR_STATUS


@given(st.binary(max_size=400))
def test_random_bytes_never_raise(data: bytes) -> None:
    result = parse_discovery_ack(data)
    assert isinstance(result, DiscoveryAck | Rejected)


def test_collector_counts_every_datagram() -> None:
    collector = DiscoveryCollector(first_req_id=0xFFFF)
    first, second = collector.command(), collector.command()
    assert first[6:8] == b"\xff\xff" and second[6:8] == b"\x00\x01"  # wraps past 65535 to 1, never 0
    camera = _hand_made_ack(ack_id=0xFFFF)
    collector.receive_datagram(camera, "192.168.10.11")
    collector.receive_datagram(_hand_made_ack(ack_id=1), "192.168.10.11")  # same camera, second command
    assert [d.ack.serial for d in collector.events_received()] == ["40012345"]
    other = parse_discovery_ack(ARAVIS_FAKE_ACK)
    assert isinstance(other, DiscoveryAck)
    collector.receive_datagram(encode_discovery_ack(replace(other, ack_id=1)), "127.0.0.1")
    collector.receive_datagram(_hand_made_ack(ack_id=99), "192.168.10.12")  # another application's discovery
    collector.receive_datagram(camera[:40], "192.168.10.13")
    collector.receive_datagram(b"\x42\x01garbage", "192.168.10.14")
    collector.receive_datagram(bytes.fromhex("8001 0003 0000 0001"), "192.168.10.15")
    c = collector.counters
    assert (c.acks, c.duplicates, c.unknown_id, c.truncated, c.malformed, c.error_status) == (2, 1, 1, 1, 1, 1)
    assert c.rejected() == 4
    assert [(d.ack.serial, d.source) for d in collector.devices] == [
        ("40012345", "192.168.10.11"),
        ("MOCAPD-FAKE", "127.0.0.1"),
    ]
    assert collector.events_received()[0].ack.serial == "MOCAPD-FAKE"
    assert collector.events_received() == []
    assert c.as_dict()["acks"] == 2


def test_two_unconfigured_cameras_with_the_same_mac_are_two_devices() -> None:
    collector = DiscoveryCollector()
    collector.command()
    ack = parse_discovery_ack(ARAVIS_FAKE_ACK)
    assert isinstance(ack, DiscoveryAck)
    for ip, serial in (("10.0.0.2", "A"), ("10.0.0.3", "B")):
        collector.receive_datagram(encode_discovery_ack(replace(ack, ack_id=1, ip=ip, serial=serial)), ip)
    assert len(collector.devices) == 2


def test_encoder_refuses_what_does_not_fit() -> None:
    ack = parse_discovery_ack(ARAVIS_FAKE_ACK)
    assert isinstance(ack, DiscoveryAck)
    with pytest.raises(ValueError, match="serial"):
        encode_discovery_ack(replace(ack, serial="x" * 17))
    with pytest.raises(ValueError, match="MAC"):
        encode_discovery_ack(replace(ack, mac="00:11"))
    with pytest.raises(ValueError, match="req_id"):
        DiscoveryCollector(first_req_id=0)

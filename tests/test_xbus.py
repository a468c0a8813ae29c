"""Xbus framing: real captures, every split offset, garbage, corrupted checksums, truncation."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mocapd.protocols.xbus import (
    MAX_PAYLOAD,
    MID,
    OutputSetting,
    XbusMessage,
    XbusParser,
    checksum,
    decode_device_id,
    decode_error,
    decode_firmware_revision,
    decode_output_configuration,
    decode_product_code,
    encode,
    encode_output_configuration,
)

CAPTURE = Path(__file__).parent / "data" / "xbus_einride" / "1" / "output.bin"


def _parse(*chunks: bytes) -> tuple[list[XbusMessage], XbusParser]:
    parser = XbusParser()
    out: list[XbusMessage] = []
    for chunk in chunks:
        parser.receive_data(chunk)
        out += parser.events_received()
    return out, parser


def test_known_frames() -> None:
    # GoToConfig as in the Xsens manual: FA FF 30 00 D1.
    assert encode(MID.GOTO_CONFIG) == bytes.fromhex("faff3000d1")
    assert encode(MID.GOTO_MEASUREMENT) == bytes.fromhex("faff1000f1")
    assert encode(MID.REQ_DID) == bytes.fromhex("faff000001")
    assert checksum(b"\xff\x30\x00") == 0xD1


def test_extended_length_round_trip() -> None:
    payload = bytes(range(256)) * 4  # 1024 bytes: extended form
    frame = encode(MID.MTDATA2, payload)
    assert frame[3] == 0xFF and frame[4:6] == (1024).to_bytes(2, "big")
    (msg,), _ = _parse(frame)
    assert msg == XbusMessage(0xFF, MID.MTDATA2, payload)
    # Exactly 254 bytes is still the short form, 255 needs the extended form.
    assert encode(0x36, bytes(254))[3] == 254
    assert encode(0x36, bytes(255))[3:6] == b"\xff\x00\xff"
    with pytest.raises(ValueError, match="exceeds"):
        encode(0x36, bytes(MAX_PAYLOAD + 1))


def test_real_capture_split_at_every_offset() -> None:
    stream = CAPTURE.read_bytes()
    whole, _ = _parse(stream)
    assert len(whole) == 100
    first_two = stream[: sum(len(encode(m.mid, m.payload)) for m in whole[:2])]
    for cut in range(len(first_two) + 1):
        parts, parser = _parse(first_two[:cut], first_two[cut:])
        assert parts == whole[:2], cut
        assert parser.counters.checksum_errors == 0 and parser.buffered == 0


def test_every_real_message_split_at_every_offset() -> None:
    """All 500 messages of the five captures, each cut in two at every byte offset, decode unchanged."""
    captures = sorted(CAPTURE.parent.parent.glob("*/output.bin"))
    assert len(captures) == 5, captures  # an empty glob must not pass
    n = 0
    for capture in captures:
        whole, _ = _parse(capture.read_bytes())
        n += len(whole)
        for msg in whole:
            frame = encode(msg.mid, msg.payload)
            for cut in range(len(frame) + 1):
                parser = XbusParser()
                parser.receive_data(frame[:cut])
                first = parser.events_received()
                parser.receive_data(frame[cut:])
                assert first + parser.events_received() == [msg]
                assert parser.buffered == 0
    assert n == 500


def test_byte_by_byte() -> None:
    stream = CAPTURE.read_bytes()
    msgs, parser = _parse(*(stream[i : i + 1] for i in range(len(stream))))
    assert len(msgs) == 100
    assert parser.counters.messages == 100


def test_corrupted_checksum_is_counted_and_the_next_message_survives() -> None:
    a = bytearray(encode(MID.DEVICE_ID, b"\x00\xb4\x21\xe6"))
    a[-1] ^= 0x01
    b = encode(MID.PRODUCT_CODE, b"MTw2-3A7G6")
    msgs, parser = _parse(bytes(a) + b)
    assert msgs == [XbusMessage(0xFF, MID.PRODUCT_CODE, b"MTw2-3A7G6")]
    assert parser.counters.checksum_errors == 1


def test_oversize_length_is_counted() -> None:
    fake = bytes((0xFA, 0xFF, 0x36, 0xFF, 0xFF, 0xFF))  # claims 65535 bytes
    msgs, parser = _parse(fake + encode(MID.WAKE_UP))
    assert [m.mid for m in msgs] == [MID.WAKE_UP]
    assert parser.counters.oversize == 1


def test_payload_helpers() -> None:
    settings_ = [OutputSetting(0x2010, 100), OutputSetting(0x1020, 0xFFFF)]
    assert decode_output_configuration(encode_output_configuration(settings_)) == settings_
    assert decode_output_configuration(b"\x00\x01\x02") is None
    assert decode_device_id(b"\x00\xb4\x21\xe6") == 0x00B421E6
    assert decode_device_id(b"\x01") is None
    assert decode_product_code(b"MTi-630   \x00") == "MTi-630"
    fw = decode_firmware_revision(b"\x04\x02\x01\x00")
    assert fw is not None and str(fw) == "4.2.1"
    assert decode_firmware_revision(b"\x04") is None
    assert decode_error(b"\x04").description == "message sent is invalid"
    assert decode_error(b"\x77").description.startswith("undocumented")
    assert decode_error(b"").code == -1


messages_st = st.lists(
    st.builds(
        lambda mid, payload: (mid, payload),
        st.integers(0, 255),
        st.binary(max_size=300),
    ),
    min_size=1,
    max_size=6,
)


@settings(max_examples=200, deadline=None)
@given(messages_st, st.data())
def test_garbage_without_preamble_between_messages_never_loses_one(
    messages: list[tuple[int, bytes]], data: st.DataObject
) -> None:
    garbage = st.binary(max_size=40).map(lambda b: b.replace(b"\xfa", b"\x00"))
    stream = b""
    for mid, payload in messages:
        stream += data.draw(garbage) + encode(mid, payload)
    stream += data.draw(garbage)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
    chunks = [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True)]
    msgs, parser = _parse(*chunks)
    assert [(m.mid, m.payload) for m in msgs] == messages
    assert parser.counters.checksum_errors == 0


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=2000), st.lists(st.integers(1, 64), max_size=20))
def test_arbitrary_bytes_never_raise(stream: bytes, sizes: list[int]) -> None:
    parser = XbusParser()
    pos = 0
    for size in sizes:
        parser.receive_data(stream[pos : pos + size])
        pos += size
    parser.receive_data(stream[pos:])
    # Every message emitted was in the input: a whole frame (short or extended length form) with a valid checksum,
    # each after the previous one.
    at = 0
    for msg in parser.events_received():
        at = _frame_end(stream, msg, at)
    c = parser.counters
    assert c.discarded_bytes + parser.buffered <= len(stream)


def _frame_end(stream: bytes, msg: XbusMessage, start: int) -> int:
    """End of the first frame of ``msg`` in ``stream`` at or after ``start`` (asserts there is one)."""
    n = len(msg.payload)
    forms = [bytes((msg.bid, msg.mid, 0xFF, n >> 8, n & 0xFF))] + ([bytes((msg.bid, msg.mid, n))] if n < 255 else [])
    found = []
    for header in forms:
        body = header + msg.payload
        frame = b"\xfa" + body + bytes(((-sum(body)) & 0xFF,))  # the checksum by its definition, not checksum()
        i = stream.find(frame, start)
        if i >= 0:
            found.append(i + len(frame))
    assert found, f"{msg} is not a frame of the input after offset {start}"
    return min(found)


@settings(max_examples=200, deadline=None)
@given(messages_st, st.data())
def test_corrupted_bytes_and_truncation(messages: list[tuple[int, bytes]], data: st.DataObject) -> None:
    frames = [encode(mid, payload) for mid, payload in messages]
    victim = data.draw(st.integers(0, len(frames) - 1))
    bad = bytearray(frames[victim])
    index = data.draw(st.integers(4, len(bad) - 1))  # a payload or checksum byte: the frame must be rejected
    bad[index] ^= data.draw(st.integers(1, 255))
    if bad[index] == 0xFA:
        bad[index] ^= 0x01
    stream = b"".join(bytes(bad) if i == victim else f for i, f in enumerate(frames))
    # A false preamble inside the corrupted frame can announce a long payload; the parser then waits for that
    # many bytes before its checksum fails and it resynchronises. On a live link more bytes always come; here
    # padding without 0xFA plays that role.
    msgs, parser = _parse(stream, bytes(MAX_PAYLOAD + 8))
    others = [(m, p) for i, (m, p) in enumerate(messages) if i != victim]
    got = [(m.mid, m.payload) for m in msgs]
    # Every intact message is recovered, in order; the corrupted one is not (it may only be "recovered" by a
    # chance 1/256 checksum match of a sub-span, which the subsequence check tolerates). The one exception an
    # 8-bit checksum allows: a false preamble inside the corrupted frame whose span happens to check out
    # (1 in 256) is emitted as a spurious message and swallows what it spans. Then that message must be there.
    spurious = [g for g in got if g not in messages]
    it = iter(got)
    assert spurious or all(any(g == o for g in it) for o in others)
    assert parser.counters.checksum_errors >= 1 or len(got) > len(others)
    # Truncation: a stream cut anywhere yields a prefix of the messages and never raises.
    cut = data.draw(st.integers(0, len(stream)))
    partial, _ = _parse(stream[:cut])
    assert len(partial) <= len(msgs) + 1

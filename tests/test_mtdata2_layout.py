"""MTData2 payloads laid out as the last one of their length are unpacked with one struct call (the synthetic rig's
event loop decodes 13 sensors x 100 messages a second): the same items as the packet-by-packet walk (the decoder
as it was, kept as ``_decode_walk``), on real MTi bytes, on the simulator's MTw layout in every precision, and on
payloads whose headers differ from the cached layout's in any byte."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mocapd.protocols import mtdata2
from mocapd.protocols.mtdata2 import CoordFrame, DataId, MtData2, Precision, _decode_walk, decode_mtdata2, encode_packet
from mocapd.protocols.xbus import MID, XbusParser

CAPTURES = [Path(__file__).parent / "data" / "xbus_einride" / str(i) / "output.bin" for i in range(1, 6)]


def _same(a: MtData2, b: MtData2) -> bool:
    """The same items (ids, values to the last digit, value types, frames, precisions) and counts."""
    return repr(a) == repr(b) and [type(i.value) for i in a.items.values()] == [type(i.value) for i in b.items.values()]


def _payloads(path: Path) -> list[bytes]:
    parser = XbusParser()
    parser.receive_data(path.read_bytes())
    return [m.payload for m in parser.events_received() if m.mid == MID.MTDATA2]


REAL = [payload for path in CAPTURES for payload in _payloads(path)]


def _mtw(precision: Precision, counter: int, rng: np.random.Generator) -> bytes:
    """An MTw-like payload: packet counter, sample time, quaternion and acceleration in ``precision``."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return (
        encode_packet(DataId.PACKET_COUNTER, counter & 0xFFFF)
        + encode_packet(DataId.SAMPLE_TIME_FINE, 100 * counter)
        + encode_packet(DataId.QUATERNION | CoordFrame.ENU | precision, tuple(q))
        + encode_packet(DataId.ACCELERATION | precision, tuple(rng.normal(0.0, 9.81, 3)))
    )


def test_real_mti_messages_decode_the_same_through_the_layout() -> None:
    """Five real captures (100 messages each): every message, the first of its layout walked, the rest unpacked
    with the cached layout, gives the walk's items."""
    mtdata2._LAYOUTS.clear()
    for payload in REAL:
        assert _same(decode_mtdata2(payload), _decode_walk(payload))
    assert len(REAL) == 500 and mtdata2._LAYOUTS  # their layouts were cached and used
    laid_out = sum(len(p) in mtdata2._LAYOUTS for p in REAL)
    assert laid_out >= 450, laid_out


def test_the_simulators_layout_in_every_precision_decodes_the_same() -> None:
    rng = np.random.default_rng(0)
    mtdata2._LAYOUTS.clear()
    for precision in Precision:
        for counter in range(200):
            payload = _mtw(precision, 65_500 + counter, rng)
            assert _same(decode_mtdata2(payload), _decode_walk(payload))
        assert len(payload) in mtdata2._LAYOUTS


@settings(max_examples=400, deadline=None)
@given(st.data())
def test_a_payload_of_a_cached_length_with_other_headers_decodes_as_the_walk(data: st.DataObject) -> None:
    """Any header byte changed (an id, a precision, a size: packets shifted, unknown, malformed, truncated) or any
    data byte: the items and counts are the walk's."""
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    if data.draw(st.booleans()):
        base = _mtw(data.draw(st.sampled_from(list(Precision))), 7, rng)
    else:  # a real one, with UTC time and GNSS outputs among the others
        base = data.draw(st.sampled_from(REAL))
    mtdata2._LAYOUTS.clear()
    decode_mtdata2(base)  # its layout cached
    changed = bytearray(base)
    for _ in range(data.draw(st.integers(1, 4))):
        changed[data.draw(st.integers(0, len(base) - 1))] = data.draw(st.integers(0, 255))
    payload = bytes(changed)
    assert _same(decode_mtdata2(payload), _decode_walk(payload))
    assert _same(decode_mtdata2(base), _decode_walk(base))

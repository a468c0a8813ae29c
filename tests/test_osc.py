"""OSC 1.0 encoding: byte layouts from the specification, decoded by python-osc (an independent implementation)."""

from __future__ import annotations

import pytest
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage

from mocapd.errors import InputError
from mocapd.protocols.osc import encode_bundle, encode_message, osc_blob, osc_string, pack_bundles


def test_strings_and_blobs_are_padded_as_specified() -> None:
    assert osc_string("") == b"\x00\x00\x00\x00"
    assert osc_string("abc") == b"abc\x00"
    assert osc_string("abcd") == b"abcd\x00\x00\x00\x00"  # always at least one NUL
    assert osc_string("/VMC/Ext/T") == b"/VMC/Ext/T\x00\x00"
    assert osc_blob(b"\x01\x02\x03") == b"\x00\x00\x00\x03\x01\x02\x03\x00"
    assert osc_blob(b"") == b"\x00\x00\x00\x00"
    with pytest.raises(InputError, match="NUL"):
        osc_string("a\x00b")


def test_message_bytes_match_the_documented_example() -> None:
    assert encode_message("/VMC/Ext/T", [1.5]) == (
        b"/VMC/Ext/T\x00\x00" + b",f\x00\x00" + b"\x3f\xc0\x00\x00"
    )  # fmt: skip


def test_python_osc_decodes_every_argument_type() -> None:
    raw = encode_message("/a/b", [7, -2, 0.25, "Hüfte", b"\x00\xff\x10", "x"])
    assert len(raw) % 4 == 0
    msg = OscMessage(raw)
    assert msg.address == "/a/b"
    assert msg.params == [7, -2, 0.25, "Hüfte", b"\x00\xff\x10", "x"]


def test_bundles_decode_with_python_osc() -> None:
    a = encode_message("/x", [1])
    b = encode_message("/y", ["z", 2.0])
    raw = encode_bundle([a, b])
    assert raw[:8] == b"#bundle\x00" and raw[8:16] == b"\x00" * 7 + b"\x01"  # time tag 1: "immediately"
    assert raw[16:20] == len(a).to_bytes(4, "big")
    bundle = OscBundle(raw)
    msgs = list(bundle)
    assert [m.address for m in msgs] == ["/x", "/y"]
    assert msgs[1].params == ["z", 2.0]


def test_pack_bundles_splits_in_order_within_the_limit() -> None:
    msgs = [encode_message("/m", [i, float(i)]) for i in range(40)]  # 16 bytes each, 20 with the size field
    bundles = pack_bundles(msgs, 16 + 20 * 8)
    assert len(bundles) == 5 and all(len(b) <= 176 for b in bundles)
    got = [m.params[0] for b in bundles for m in OscBundle(b)]
    assert got == list(range(40))
    with pytest.raises(InputError, match="does not fit"):
        pack_bundles([encode_message("/long", ["x" * 100])], 64)


def test_unsupported_arguments_are_refused() -> None:
    with pytest.raises(InputError, match="boolean"):
        encode_message("/b", [True])
    with pytest.raises(InputError, match="range"):
        encode_message("/i", [2**31])
    with pytest.raises(InputError, match="start with"):
        encode_message("nope", [])
    with pytest.raises(InputError, match="multiple of 4"):
        encode_bundle([b"abc"])

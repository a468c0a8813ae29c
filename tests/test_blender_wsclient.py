"""The live-link add-on's WebSocket client (tools/blender/mocapd_link/wsclient.py) on RFC 6455 byte fixtures.

Loaded from its file: the add-on package imports ``bpy``, which mocapd's venv does not have; the client itself
imports only the standard library. tests/test_blender_link.py runs it against the daemon's real server.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

PATH = Path(__file__).resolve().parents[1] / "tools" / "blender" / "mocapd_link" / "wsclient.py"


def _load() -> ModuleType:
    spec = importlib.util.spec_from_file_location("mocapd_link_wsclient", PATH)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


ws = _load()
HELLO = b"\x81\x05Hello"  # RFC 6455 5.7: a single-frame unmasked text message
FRAGMENTED = b"\x01\x03Hel\x80\x02lo"  # 5.7: "Hello" in two fragments
PING = b"\x89\x05Hello"
BIG = b"\x82\x7e\x01\x00" + bytes(range(256))  # 256-byte binary message, 16-bit length


def test_masked_client_frame_matches_the_rfc_example() -> None:
    assert ws.encode_frame(ws.OP_TEXT, b"Hello", bytes.fromhex("37fa213d")) == bytes.fromhex("818537fa213d7f9f4d5158")
    long = ws.encode_frame(ws.OP_BINARY, bytes(70000), b"\0\0\0\0")
    assert long[:2] == b"\x82\xff" and int.from_bytes(long[2:10], "big") == 70000


def test_every_split_of_the_stream_gives_the_same_messages() -> None:
    data = HELLO + FRAGMENTED + PING + BIG
    want = [(ws.OP_TEXT, b"Hello"), (ws.OP_TEXT, b"Hello"), (ws.OP_PING, b"Hello"), (ws.OP_BINARY, bytes(range(256)))]
    for cut in range(len(data) + 1):
        p = ws.FrameParser()
        assert p.feed(data[:cut]) + p.feed(data[cut:]) == want, cut


def test_protocol_violations_are_refused() -> None:
    with pytest.raises(ws.ProtocolError, match="masked"):
        ws.FrameParser().feed(bytes.fromhex("818537fa213d7f9f4d5158"))
    with pytest.raises(ws.ProtocolError, match="continuation"):
        ws.FrameParser().feed(b"\x80\x02lo")
    with pytest.raises(ws.ProtocolError, match="larger"):
        ws.FrameParser().feed(b"\x82\x7f" + (ws.MAX_MESSAGE + 1).to_bytes(8, "big"))
    with pytest.raises(ws.ProtocolError, match="ws://"):
        ws.Connection("http://127.0.0.1:1/")

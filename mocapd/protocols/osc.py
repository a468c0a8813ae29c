"""Open Sound Control 1.0 encoding: messages and bundles, written from the OSC 1.0 specification
(opensoundcontrol.org, "The Open Sound Control 1.0 Specification", M. Wright, 2002).

Atomic data types (all big-endian, every item a multiple of 4 bytes)::

    int32    'i'  4 bytes, two's complement
    float32  'f'  4 bytes, IEEE 754
    string   's'  the bytes (UTF-8 here; OSC 1.0 says ASCII, VMC allows UTF-8), then 1 to 4 NUL bytes so that
                  the total is a multiple of 4 (there is always at least one NUL)
    blob     'b'  int32 byte count n, the n bytes, then 0 to 3 NUL bytes to a multiple of 4

Message: address pattern (string, starts with '/'), type tag string (string: ',' then one tag per argument),
then the arguments in order. Example, ``/VMC/Ext/T`` with the float 1.5::

    2f 56 4d 43 2f 45 78 74 2f 54 00 00   "/VMC/Ext/T" + 2 NUL (10 + 2 = 12)
    2c 66 00 00                           ",f" + 2 NUL
    3f c0 00 00                           1.5

Bundle: the string "#bundle" (8 bytes with its NUL), a 64-bit time tag (NTP fixed point: seconds since 1900 in the
high 32 bits, fraction in the low 32; the value 1 means "immediately"), then elements, each an int32 size followed
by a message or bundle of that many bytes.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

from mocapd.errors import InputError

OscArg = int | float | str | bytes
BUNDLE_TAG = b"#bundle\x00"
IMMEDIATELY = 1
"""The special time tag "process immediately" (0x0000000000000001)."""
BUNDLE_HEADER_SIZE = 16  # "#bundle\0" + time tag
ELEMENT_SIZE_FIELD = 4
_INT32 = struct.Struct(">i")
_TIMETAG = struct.Struct(">Q")


def osc_string(s: str) -> bytes:
    """An OSC-string: UTF-8 bytes, NUL-terminated and NUL-padded to a multiple of 4."""
    raw = s.encode("utf-8")
    if b"\x00" in raw:
        raise InputError(f"OSC strings cannot contain NUL: {s!r}")
    return raw + b"\x00" * (4 - len(raw) % 4)


def osc_blob(b: bytes) -> bytes:
    """An OSC-blob: int32 size, the bytes, NUL padding to a multiple of 4."""
    return _INT32.pack(len(b)) + b + b"\x00" * (-len(b) % 4)


def _tag(arg: OscArg) -> tuple[str, bytes]:
    if isinstance(arg, bool):  # bool is an int subclass; OSC 1.0 has no boolean type here
        raise InputError("OSC 1.0 has no boolean argument type; send an int")
    if isinstance(arg, int):
        if not -(2**31) <= arg < 2**31:
            raise InputError(f"OSC int32 argument out of range: {arg}")
        return "i", _INT32.pack(arg)
    if isinstance(arg, float):
        return "f", struct.pack(">f", arg)
    if isinstance(arg, str):
        return "s", osc_string(arg)
    if isinstance(arg, bytes):
        return "b", osc_blob(arg)
    raise InputError(f"unsupported OSC argument type {type(arg).__name__}")


def message_prefix(address: str, tags: str) -> bytes:
    """Address pattern + type tag string (``tags`` without the leading comma), for messages built by hand."""
    if not address.startswith("/"):
        raise InputError(f"OSC address must start with '/': {address!r}")
    return osc_string(address) + osc_string("," + tags)


def encode_message(address: str, args: Sequence[OscArg] = ()) -> bytes:
    """One OSC message (a multiple of 4 bytes)."""
    tagged = [_tag(a) for a in args]
    return message_prefix(address, "".join(t for t, _ in tagged)) + b"".join(b for _, b in tagged)


def encode_bundle(elements: Sequence[bytes], timetag: int = IMMEDIATELY) -> bytes:
    """A bundle of already encoded messages or bundles."""
    if not 0 <= timetag < 2**64:
        raise InputError(f"OSC time tag out of range: {timetag}")
    parts = [BUNDLE_TAG, _TIMETAG.pack(timetag)]
    for e in elements:
        if len(e) % 4:
            raise InputError(f"OSC bundle element of {len(e)} bytes is not a multiple of 4")
        parts.append(_INT32.pack(len(e)))
        parts.append(e)
    return b"".join(parts)


def pack_bundles(messages: Sequence[bytes], max_bytes: int, timetag: int = IMMEDIATELY) -> list[bytes]:
    """Pack messages, in order, into as few bundles as fit within ``max_bytes`` each.

    Raises
    ------
    InputError
        A single message does not fit in a bundle of ``max_bytes``.
    """
    room = max_bytes - BUNDLE_HEADER_SIZE
    out: list[bytes] = []
    current: list[bytes] = []
    used = 0
    for m in messages:
        need = ELEMENT_SIZE_FIELD + len(m)
        if need > room:
            raise InputError(f"OSC message of {len(m)} bytes does not fit a {max_bytes}-byte bundle")
        if used + need > room:
            out.append(encode_bundle(current, timetag))
            current, used = [], 0
        current.append(m)
        used += need
    if current:
        out.append(encode_bundle(current, timetag))
    return out

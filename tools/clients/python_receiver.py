"""Minimal Python receiver for the mocapd WebSocket pose stream (protocol: docs/streaming.md, "WebSocket").

Needs only ``websockets`` and ``msgpack``::

    python tools/clients/python_receiver.py --url ws://127.0.0.1:8766/ --frames 100 --convention unity

Prints the hello, then one line per frame with each subject's root position; exits 0 after ``--frames`` frames
(0: until Ctrl-C), 1 if the stream ends first or answers with an error.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from typing import Any
from urllib.parse import quote

import msgpack
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosedError, InvalidHandshake


def parse(message: bytes | str) -> dict[str, Any]:
    """Binary messages are msgpack, text messages JSON."""
    out: dict[str, Any] = msgpack.unpackb(message) if isinstance(message, bytes) else json.loads(message)
    return out


async def receive(url: str, frames: int, convention: str, rate_hz: float | None) -> int:
    got = 0
    async with connect(url, max_size=1 << 22) as ws:
        request: dict[str, Any] = {"type": "subscribe", "convention": convention}
        if rate_hz is not None:
            request["rate_hz"] = rate_hz
        await ws.send(msgpack.packb(request))
        async for message in ws:
            m = parse(message)
            if m["type"] == "hello":
                print(f"hello v{m['v']}: convention {m['convention']} ({m['units']}), {m['rate_hz']:g} Hz, "
                      f"{len(m['bones'])} bones, skeletons {','.join(m['skeletons'])}", flush=True)  # fmt: skip
            elif m["type"] == "frame":
                got += 1
                roots = "; ".join(f"{s['id']} root ({', '.join(f'{v:.3f}' for v in s['root'])})" for s in m["subjects"])
                print(f"frame {m['frame']} t_solve_ns {m['t_solve_ns']}: {roots or 'no subjects'}", flush=True)
                if 0 < frames <= got:
                    return 0
            elif m["type"] == "error":
                print(f"error from server: {m['code']}: {m['message']}", file=sys.stderr)
                return 1
    print(f"stream closed after {got} frames", file=sys.stderr)
    return 1 if frames > 0 else 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    p.add_argument("--url", default="ws://127.0.0.1:8766/")
    p.add_argument("--frames", type=int, default=0, help="stop after this many frames (0: never)")
    p.add_argument("--convention", default="native", choices=["native", "unity", "unreal", "mvn"])
    p.add_argument("--rate", type=float, default=None, help="at most this many frames per second")
    p.add_argument("--token", default="", help="the daemon's [websocket] token, when it has one")
    a = p.parse_args(argv)
    url = a.url + (("&" if "?" in a.url else "?") + "token=" + quote(a.token) if a.token else "")
    try:
        return asyncio.run(receive(url, a.frames, a.convention, a.rate))
    except KeyboardInterrupt:
        return 0
    except (OSError, InvalidHandshake) as exc:
        print(f"cannot connect to {a.url}: {exc}", file=sys.stderr)
        return 1
    except ConnectionClosedError as exc:
        print(f"the stream broke off: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())

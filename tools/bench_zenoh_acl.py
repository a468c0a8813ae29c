"""What per-host identities (``[zenoh] identities``: Zenoh's access control on the solver host's session) cost a
camera host's detections.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs). Prints one JSON object::

    python -m tools.bench_zenoh_acl [--messages 1500] [--rounds 3] [--rate 400] [--bytes 2048]

Two Zenoh sessions on loopback, opened by :func:`mocapd.io.zenoh_link.open_session` as mocapd opens them: a solver
host (listening, user/password, ``users_file``) and a camera host (connecting as its own user) that publishes
``--messages`` payloads of ``--bytes`` on its camera's detections key at ``--rate`` Hz, each stamped with
``time.monotonic_ns()``; the solver host's subscriber records send -> receive. Rounds alternate the solver host's
session with identities (access control on) and without (off), in one process, so the two are compared on the same
machine load: the per-message cost of the check is the difference of the medians.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import struct
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from mocapd.io.zenoh_link import detections_key, open_session
from mocapd.service.config import parse_config


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _round(folder: Path, acl: bool, messages: int, rate: float, size: int) -> list[float]:
    """Send -> receive delays (ms) of one round."""
    endpoint = f"tcp/127.0.0.1:{_port()}"
    base: dict[str, Any] = {
        "rig": "bench", "listen": [endpoint], "user": "solver", "password_file": str(folder / "pw-solver"),
        "users_file": str(folder / "users"),
    }  # fmt: skip
    if acl:
        base["identities"] = {"hostA": "user:hostA"}
    solver = open_session(parse_config({"zenoh": base}).zenoh, {"hostA": ["cam0"]})
    host = open_session(parse_config({"zenoh": {"rig": "bench", "listen": [], "connect": [endpoint], "user": "hostA",
                                                "password_file": str(folder / "pw-hostA")}}).zenoh)  # fmt: skip
    delays: list[float] = []
    done = threading.Event()

    def on_sample(sample: Any) -> None:
        now = time.monotonic_ns()
        sent = struct.unpack_from("<q", sample.payload.to_bytes())[0]
        if sent > 0:
            delays.append((now - sent) / 1e6)
            if len(delays) >= messages:
                done.set()

    key = detections_key("bench", "cam0")
    sub = solver.declare_subscriber(key, on_sample)
    pub = host.declare_publisher(key)
    try:
        pad = bytes(max(0, size - 8))
        for _ in range(200):  # until the route is up (the subscriber's declaration reached the camera host)
            pub.put(struct.pack("<q", -1) + pad)
            time.sleep(0.01)
        period = 1.0 / rate
        nxt = time.monotonic()
        for _ in range(messages):
            pub.put(struct.pack("<q", time.monotonic_ns()) + pad)
            nxt += period
            time.sleep(max(0.0, nxt - time.monotonic()))
        done.wait(10.0)
    finally:
        sub.undeclare()  # type: ignore[no-untyped-call]
        host.close()  # type: ignore[no-untyped-call]
        solver.close()  # type: ignore[no-untyped-call]
    return delays


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--messages", type=int, default=1500)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--rate", type=float, default=400.0, help="messages per second")
    p.add_argument("--bytes", type=int, default=2048, help="payload size (a frame of 2 people: about 1-2 KB)")
    args = p.parse_args()
    out: dict[str, Any] = {"messages": args.messages, "rounds": args.rounds, "rate_hz": args.rate,
                           "bytes": args.bytes, "loadavg": os.getloadavg()}  # fmt: skip
    runs: dict[str, list[list[float]]] = {"acl_off": [], "acl_on": []}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for user in ("solver", "hostA"):
            (folder / f"pw-{user}").write_text(f"{user}-pw\n", encoding="utf-8")
        (folder / "users").write_text("solver:solver-pw\nhostA:hostA-pw\n", encoding="utf-8")
        for _ in range(args.rounds):
            for name, acl in (("acl_off", False), ("acl_on", True)):
                runs[name].append(_round(folder, acl, args.messages, args.rate, args.bytes))
    for name, rounds in runs.items():
        d = np.concatenate([np.asarray(r) for r in rounds])
        out[name] = {
            "received": len(d), "sent": args.messages * args.rounds,
            "p50_ms": round(float(np.percentile(d, 50)), 4), "p95_ms": round(float(np.percentile(d, 95)), 4),
            "round_p50_ms": [round(float(np.percentile(r, 50)), 4) for r in rounds],
        }  # fmt: skip
    out["added_p50_ms"] = round(out["acl_on"]["p50_ms"] - out["acl_off"]["p50_ms"], 4)
    print(json.dumps(out))


if __name__ == "__main__":
    main()

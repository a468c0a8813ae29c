"""The status server answers from snapshots: however many clients poll /status and /metrics at once, the daemon
renders at most ``max_hz`` snapshots a second (issue 18, D11: 1 500 polls took the output down to 5–30 Hz because
each one rendered the whole document on the tick's event loop). Real loopback HTTP clients; counts, no timings."""

from __future__ import annotations

import asyncio
import json
import math
import time
from typing import Any

import pytest

from mocapd.service.http_status import StatusServer
from mocapd.service.metrics import render_metrics

CONCURRENT = 200


async def get(port: int, target: str) -> tuple[int, bytes]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {target} HTTP/1.1\r\nHost: localhost\r\n\r\n".encode())
    await writer.drain()
    data = await reader.read()
    writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split(b" ")[1]), body


class CountingStatus:
    """A status provider that numbers its documents (each call is one render of the daemon's state)."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self) -> dict[str, Any]:
        self.calls += 1
        # Big enough to cost something to serialise, like a daemon with many sensors (D4 grew it to 113 KB).
        return {"snapshot": self.calls, "sensors": {f"s{i}": {"samples": i, "streaming": True} for i in range(500)}}


def counting_metrics(calls: list[int]) -> Any:
    def render(status: dict[str, Any]) -> bytes:
        calls.append(status["snapshot"])
        return f"snapshot {status['snapshot']}\n".encode()

    return render


@pytest.mark.asyncio
async def test_concurrent_polls_share_bounded_snapshots() -> None:
    status = CountingStatus()
    metric_calls: list[int] = []
    max_hz = 4.0
    server = StatusServer(status, counting_metrics(metric_calls), max_hz=max_hz)
    port = await server.start()
    try:
        t0 = time.monotonic()
        targets = ["/metrics" if i % 5 == 0 else "/status" for i in range(CONCURRENT)]
        replies = await asyncio.gather(*(get(port, t) for t in targets))
        elapsed = time.monotonic() - t0
    finally:
        await server.close()
    assert all(code == 200 for code, _ in replies)
    # Bounded renders: one snapshot per 1/max_hz at most (+1 for the first), however many requests came.
    assert 1 <= status.calls <= math.ceil(elapsed * max_hz) + 1
    assert server.renders == status.calls
    # Each snapshot rendered at most once per format, and every reply is a whole, consistent snapshot.
    assert sorted(set(metric_calls)) == metric_calls
    seen = set()
    for target, (_, body) in zip(targets, replies, strict=True):
        if target == "/status":
            doc = json.loads(body)
            assert doc["sensors"]["s499"] == {"samples": 499, "streaming": True}
            seen.add(doc["snapshot"])
        else:
            seen.add(int(body.split()[1]))
    assert seen <= set(range(1, status.calls + 1))
    assert server.snapshots.json_renders <= status.calls and server.snapshots.metrics_renders <= status.calls


@pytest.mark.asyncio
async def test_a_new_snapshot_after_its_period() -> None:
    """A stepped clock: requests within 1/max_hz share one snapshot, the first after it takes a new one."""
    now = [0]
    status = CountingStatus()
    server = StatusServer(status, render_metrics, max_hz=2.0, clock=lambda: now[0])
    port = await server.start()
    try:
        first = [json.loads((await get(port, "/status"))[1])["snapshot"] for _ in range(5)]
        now[0] += 499_000_000
        same = json.loads((await get(port, "/status"))[1])["snapshot"]
        now[0] += 1_000_000
        fresh = json.loads((await get(port, "/status"))[1])["snapshot"]
    finally:
        await server.close()
    assert first == [1] * 5 and same == 1 and fresh == 2 and status.calls == 2


@pytest.mark.asyncio
async def test_websocket_status_messages_read_the_same_snapshots() -> None:
    """The daemon's WebSocket status messages (here 30 a second to each of 4 clients) come from the status server's
    snapshots too: the daemon renders no more documents than the snapshot rate allows."""
    from websockets.asyncio.client import connect

    from mocapd.io.ws_server import WebSocketStreamServer
    from mocapd.service.assembly import assembled
    from mocapd.service.config import load_config
    from mocapd.service.demo.synthetic import synthetic_config

    cfg = load_config()
    cfg = cfg.model_copy(update={
        "daemon": cfg.daemon.model_copy(update={"http_port": 0}),
        "websocket": cfg.websocket.model_copy(update={"port": 0, "status_hz": 30.0}),
    })  # fmt: skip
    with assembled(synthetic_config(cfg)) as demo:
        d = demo.daemon
        # Every status document (and the once-a-second status line) asks the scheduler for its state: count those.
        calls = [0]
        scheduler_status = d.scheduler.status

        def counted() -> dict[str, Any]:
            calls[0] += 1
            return scheduler_status()

        d.scheduler.status = counted  # type: ignore[method-assign]
        task = asyncio.create_task(d.run())
        await asyncio.wait_for(d.ready.wait(), 120)
        ws = next(s for s in d.sinks if isinstance(s, WebSocketStreamServer))
        received = [0]

        async def client() -> None:
            async with connect(f"ws://127.0.0.1:{ws.port}/") as c:
                await c.send(json.dumps({"type": "subscribe", "encoding": "json"}))
                async for msg in c:  # the first hello is in the default encoding (msgpack): skip bytes
                    if isinstance(msg, str) and json.loads(msg)["type"] == "status":
                        received[0] += 1
                        if received[0] >= 4 * 60:
                            return

        calls[0] = 0
        t0 = time.monotonic()
        await asyncio.wait_for(asyncio.gather(*(client() for _ in range(4))), 120)
        elapsed = time.monotonic() - t0
        d.request_stop()
        assert await asyncio.wait_for(task, 10) == 0
    assert received[0] >= 4 * 60
    # 240 status messages; the documents behind them: one per 1/4 s at most (+1 for the first), plus the status
    # line's once a second.
    assert calls[0] <= math.ceil(elapsed * 4.0) + 1 + math.ceil(elapsed) + 1


@pytest.mark.asyncio
async def test_metrics_count_the_rejections_of_the_network_doors() -> None:
    """A garbage IMU bridge datagram and an out-of-range WebSocket subscribe reach the daemon's /metrics as
    ``mocapd_input_rejected_total{door, reason}`` (the same counts /status shows)."""
    import socket

    import msgpack
    from websockets.asyncio.client import connect

    from mocapd.io.ws_server import WebSocketStreamServer
    from mocapd.service.assembly import assembled
    from mocapd.service.config import load_config
    from mocapd.service.demo.synthetic import synthetic_config

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        bridge_port = int(probe.getsockname()[1])
    cfg = load_config()
    bridge_cfg = cfg.imu.bridge.model_copy(update={"enabled": True, "port": bridge_port})
    imu = cfg.imu.model_copy(update={"bridge": bridge_cfg})
    cfg = cfg.model_copy(update={
        "daemon": cfg.daemon.model_copy(update={"http_port": 0}),
        "websocket": cfg.websocket.model_copy(update={"port": 0}),
        "imu": imu,
    })  # fmt: skip
    with assembled(synthetic_config(cfg)) as demo:
        d = demo.daemon
        task = asyncio.create_task(d.run())
        await asyncio.wait_for(d.ready.wait(), 120)
        ws = next(s for s in d.sinks if isinstance(s, WebSocketStreamServer))
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
            for _ in range(3):
                sender.sendto(b"\xc1 not msgpack", ("127.0.0.1", bridge_port))
        async with connect(f"ws://127.0.0.1:{ws.port}/") as c:
            await c.send(json.dumps({"type": "subscribe", "rate_hz": 1e-20}))
            async with asyncio.timeout(30):
                while (m := await c.recv()) and (msgpack.unpackb(m) if isinstance(m, bytes) else json.loads(m))[
                    "type"
                ] != "error":
                    pass
        assert d.http is not None
        text = ""
        for _ in range(200):  # /metrics is rendered from a snapshot at most 4 times a second
            text = (await get(d.http.port, "/metrics"))[1].decode()
            if 'door="imu_bridge"' in text and 'reason="bad_field"' in text:
                break
            await asyncio.sleep(0.05)
        d.request_stop()
        assert await asyncio.wait_for(task, 10) == 0
    samples = [ln.rsplit(" ", 1) for ln in text.splitlines() if ln.startswith("mocapd_input")]
    lines = {name: float(value) for name, value in samples}
    bridge = {k: v for k, v in lines.items() if 'door="imu_bridge"' in k}
    assert sum(bridge.values()) == 3, lines
    assert lines['mocapd_input_rejected_total{door="websocket",reason="bad_field"}'] == 1.0, lines

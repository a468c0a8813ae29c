"""The SlimeVR server's receive thread: datagrams are read while the event loop is busy (a long solve), none is
lost, and each is filed at the kernel's time of arrival; the batch reader (``recvmmsg`` and its fallback) on real
loopback sockets, IPv4 and IPv6."""

from __future__ import annotations

import asyncio
import socket
import time
from typing import Any

import numpy as np
import pytest

from mocapd.io.recvmmsg import BatchReader
from mocapd.io.slimevr import DRAIN_SLICE, SlimeVrListener
from mocapd.io.xsens_serial import ImuSample
from mocapd.protocols.slimevr import HANDSHAKE_REPLY, Handshake, Rotation, SensorInfo, encode_bundle, encode_packet

MS = 1_000_000


@pytest.mark.parametrize("native", [True, False], ids=["recvmmsg", "recvmsg"])
@pytest.mark.parametrize("family", [socket.AF_INET, socket.AF_INET6], ids=["ipv4", "ipv6"])
def test_batch_reader_returns_every_datagram_in_order_with_sender_and_arrival_time(native: bool, family: int) -> None:
    host = "127.0.0.1" if family == socket.AF_INET else "::1"
    rx = socket.socket(family, socket.SOCK_DGRAM)
    tx = socket.socket(family, socket.SOCK_DGRAM)
    try:
        rx.bind((host, 0))
        tx.bind((host, 0))
        reader = BatchReader(rx, 16, use_recvmmsg=native)
        assert reader.read(0.05) == []  # nothing: waits the time-out, then returns
        sent = []
        for i in range(40):
            sent.append(time.monotonic_ns())
            tx.sendto(bytes([i]) * (i + 1), rx.getsockname()[:2])
            time.sleep(0.001)
        time.sleep(0.2)  # read late: the arrival times are the kernel's, not the reads'
        got: list[tuple[bytes, tuple[str, int], int | None]] = []
        while len(got) < 40:
            batch = reader.read(1.0)
            assert 0 < len(batch) <= 16
            got += batch
        assert [d for d, _, _ in got] == [bytes([i]) * (i + 1) for i in range(40)]
        assert {a for _, a, _ in got} == {tx.getsockname()[:2]}
        arrival = np.array([t if t is not None else -1 for _, _, t in got], dtype=np.int64)
        assert np.all(np.diff(arrival) >= 0)
        lag = arrival - np.array(sent)
        assert np.all(lag >= 0) and np.median(lag) < 5 * MS, lag / MS  # at the send, not 200 ms later
    finally:
        rx.close()
        tx.close()


def _tracker(port: int, mac: str) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(2.0)
    s.sendto(encode_packet(Handshake(2, 3, 2, 22, "0.6.3", mac), 0), ("127.0.0.1", port))
    while s.recv(2048) != HANDSHAKE_REPLY:
        pass
    s.sendto(encode_packet(SensorInfo(0, 1, 3), 1), ("127.0.0.1", port))
    return s


@pytest.mark.asyncio
async def test_datagrams_sent_while_the_event_loop_is_busy_are_all_received_at_their_arrival_time() -> None:
    """Two trackers send 400 datagrams a second each while the event loop is blocked for a second (a long solve on
    a busy machine). The kernel holds about 40 of them (64 KiB asked): read on the event loop, most would be
    dropped. The receive thread reads them as they come; the server gets every one, each sample filed at the time
    its datagram arrived."""
    got: list[ImuSample] = []
    listener = SlimeVrListener(got.append, port=0, rcvbuf=65536)
    port = await listener.start()
    runner = asyncio.create_task(listener.run())
    loop = asyncio.get_running_loop()
    trackers = [await loop.run_in_executor(None, _tracker, port, f"0A:00:00:00:00:0{k}") for k in range(2)]
    try:
        while sum(len(t.sensors) for t in listener.server.trackers.values()) < 2:
            await asyncio.sleep(0.01)
        got.clear()
        sent_at: list[int] = []
        q = (1.0, 0.0, 0.0, 0.0)

        def send_for(seconds: float) -> None:  # paced sending from another thread while the loop is blocked
            end = time.monotonic() + seconds
            n = 1  # the sensor info was packet 1
            while time.monotonic() < end:
                n += 1
                sent_at.append(time.monotonic_ns())
                for t in trackers:
                    t.sendto(encode_packet(Rotation(0, q, acc=(0.5, 0.0, 0.0)), n), ("127.0.0.1", port))
                time.sleep(0.0025)

        sender = loop.run_in_executor(None, send_for, 1.0)
        time.sleep(1.0)  # the event loop is blocked: nothing on it reads
        await sender
        await asyncio.sleep(0.3)
        st = listener.status()
        assert st["receiver"]["thread"] and st["receiver"]["kernel_drops"] == 0
        for t in st["trackers"]:
            assert t["packets"] == len(sent_at) + 1 and t["lost"] == 0 and t["loss_percent"] == 0.0
        assert st["receiver"]["largest_batch"] >= 100  # queued while the loop was blocked, handed over at once
        # Each sample at its datagram's arrival (the sender's clock is this host's monotonic clock), not at the end
        # of the block when the event loop handed them to the server.
        mine = np.array([s.host_ns for s in got if s.sensor == "0A:00:00:00:00:00/0" and not _held(s)])
        assert len(mine) == len(sent_at)
        lag = mine - np.array(sent_at)
        assert np.all(lag >= 0) and np.median(lag) < 5 * MS, np.percentile(lag / MS, [50, 95, 100])
    finally:
        for t in trackers:
            t.close()
        listener.close()
        await asyncio.wait_for(runner, 2)


def _held(s: ImuSample) -> bool:
    """The server repeats a quiet tracker's orientation, without the acceleration (0.5 m/s² along x here) that the
    tracker sent: those are stamped when repeated, not received."""
    return s.acc is None or s.acc[0] == 0.0


@pytest.mark.asyncio
async def test_a_burst_is_handed_to_the_server_in_slices_with_the_event_loop_running_between() -> None:
    """Issue 45 (the soak's output rate): every 10 s the soak's swarm of 64 trackers shook hands and sent 128
    bundles of 128 sensor infos at once (~0.9 ms of decoding each), and the listener handed the whole backlog to
    the server in one event-loop callback: a tenth of a second in which no output tick could run. Now one callback
    takes at most DRAIN_SLICE datagrams (or 2 ms of work) and schedules the rest behind whatever else is ready: a
    callback that runs on every turn of the loop sees the server's count between the burst's first and last
    datagram (on the old code it sees only before and after)."""
    listener = SlimeVrListener(lambda _s: None, port=0)
    port = await listener.start()
    runner = asyncio.create_task(listener.run())
    loop = asyncio.get_running_loop()
    trackers = [await loop.run_in_executor(None, _tracker, port, f"0A:00:00:00:00:0{k}") for k in range(8)]
    counts: list[int] = []
    running = True

    def every_turn() -> None:
        counts.append(listener.server.counters.datagrams)
        if running:
            loop.call_soon(every_turn)

    try:
        while len(listener.server.trackers) < 8:
            await asyncio.sleep(0.01)
        bundle = [SensorInfo(i, 1, 3) for i in range(128)]
        start = listener.server.counters.datagrams
        burst = 5 * DRAIN_SLICE
        for n in range(burst // 8):
            for t in trackers:
                t.sendto(encode_bundle(list(bundle), 2 + n, compact=True), ("127.0.0.1", port))
        time.sleep(0.3)  # the event loop is blocked while the receive thread queues the burst
        every_turn()
        while listener.server.counters.datagrams < start + burst:
            await asyncio.sleep(0.001)
        running = False
        await asyncio.sleep(0)
        assert listener.status()["receiver"]["largest_batch"] >= burst // 2  # queued while the loop was blocked
        between = [c for c in counts if start < c < start + burst]
        assert len(set(between)) >= 2, counts[:20]
    finally:
        running = False
        for t in trackers:
            t.close()
        listener.close()
        await asyncio.wait_for(runner, 2)


@pytest.mark.asyncio
async def test_the_listener_ticks_without_making_a_task_each_time() -> None:
    """Issue 45 (the soak's cost): between its 10 ms ticks the listener waited on its stop event with ``wait_for``,
    which made a task and cancelled it every tick: ~18 ms of the event loop's CPU a second with no tracker at all.
    It sleeps now (a stop ends it within a tick). Counted: tasks made while it ticks 20 times (its clock is read
    once a tick)."""
    ticks = 0

    def clock() -> int:
        nonlocal ticks
        ticks += 1
        return time.monotonic_ns()

    listener = SlimeVrListener(lambda _s: None, port=0, clock=clock)
    await listener.start()
    loop = asyncio.get_running_loop()
    made = 0
    default = loop.get_task_factory()

    def factory(loop: asyncio.AbstractEventLoop, coro: Any, **kwargs: Any) -> asyncio.Task[Any]:
        nonlocal made
        made += 1
        return asyncio.Task(coro, loop=loop, **kwargs)

    loop.set_task_factory(factory)
    try:
        runner = asyncio.create_task(listener.run())
        while ticks < 20:
            await asyncio.sleep(0.005)
        listener.stop()
        await asyncio.wait_for(runner, 2)
    finally:
        loop.set_task_factory(default)
        listener.close()
    assert made == 1, made  # the runner itself; the old code made one more every tick


@pytest.mark.asyncio
async def test_a_tracker_whose_datagrams_wait_in_the_backlog_is_not_timed_out() -> None:
    """The backlog of a blocked event loop is handed to the server in slices, and the listener ticks between them:
    a tick must not time out a tracker whose datagrams are still queued (its time-out counts silence before the
    oldest queued datagram). A tracker streams 400 datagrams a second while the loop is blocked for 1.5 s, longer
    than the 1 s time-out; once the backlog is in, it has never been timed out."""
    listener = SlimeVrListener(lambda _s: None, port=0)
    port = await listener.start()
    runner = asyncio.create_task(listener.run())
    loop = asyncio.get_running_loop()
    tracker = await loop.run_in_executor(None, _tracker, port, "0A:00:00:00:00:01")
    try:
        while sum(len(t.sensors) for t in listener.server.trackers.values()) < 1:
            await asyncio.sleep(0.01)
        sent = 0

        def send_for(seconds: float) -> None:
            nonlocal sent
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                sent += 1
                tracker.sendto(encode_packet(Rotation(0, (1.0, 0.0, 0.0, 0.0)), 1 + sent), ("127.0.0.1", port))
                time.sleep(0.0025)

        sender = loop.run_in_executor(None, send_for, 1.5)
        time.sleep(1.5)  # the event loop is blocked: the receive thread queues everything
        await sender
        t = listener.server.trackers["0A:00:00:00:00:01"]
        while t.packets < sent + 1:
            await asyncio.sleep(0.005)
        assert listener.status()["receiver"]["largest_batch"] > DRAIN_SLICE  # handed over in several slices
        assert t.timeouts == 0 and listener.server.counters.timeouts == 0
    finally:
        tracker.close()
        listener.close()
        await asyncio.wait_for(runner, 2)

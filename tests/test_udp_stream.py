"""The UDP pose sinks on real loopback sockets: decimation, character ids, subject filters, and sends that fail
(closed port, oversized datagram, not started) being counted instead of raised."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import numpy as np
import pytest

from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import Skeleton
from mocapd.errors import InputError
from mocapd.io.udp_stream import MvnUdpSink, UdpSender, VmcUdpSink
from mocapd.pipeline.scheduler import PersonPose, PoseFrame
from mocapd.protocols.mvn import parse_header

SKELETON = Skeleton.from_height(1.75)


def person(identity: str, x: float = 0.0) -> PersonPose:
    theta = np.zeros(66)
    theta[:3] = [x, SKELETON.root_height, 0.0]
    return PersonPose(identity, 0, None, theta, Kinematics(SKELETON).forward(theta).positions, 1.0, 2, 0, 3, True)


def frame(n: int, people: list[PersonPose]) -> PoseFrame:
    return PoseFrame(n, n * 16_666_667, n * 16_666_667, people, 0)


@pytest.fixture
def receiver() -> Iterator[socket.socket]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    yield sock
    sock.close()


def pending(sock: socket.socket) -> list[bytes]:
    out = []
    while True:
        try:
            out.append(sock.recv(65536))
        except BlockingIOError:
            return out


def closed_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port: int = s.getsockname()[1]
    s.close()
    return port


@pytest.mark.asyncio
async def test_mvn_sink_decimates_and_pins_character_ids(receiver: socket.socket) -> None:
    port = receiver.getsockname()[1]
    sink = MvnUdpSink(SKELETON, [("127.0.0.1", port)], rate_divisor=3, character_ids={"suit:b": 5},
                      subjects={"suit:a", "suit:b"})  # fmt: skip
    await sink.start()
    for n in range(7):
        sink.publish(frame(n, [person("track:4"), person("suit:a"), person("suit:b", 1.0)]))
    await sink.aclose()
    got = [parse_header(d) for d in pending(receiver)]
    # Frames 0, 3, 6; suit:a takes the lowest free id, suit:b its pinned 5, track:4 is not in the list.
    assert [(h.sample_counter, h.character_id) for h in got] == [(0, 0), (0, 5), (3, 0), (3, 5), (6, 0), (6, 5)]
    assert [h.time_code_ms for h in got[::2]] == [0, 50, 100]
    st = sink.status()
    assert st["frames_seen"] == 7 and st["frames_sent"] == 3 and st["datagrams_sent"] == 6
    assert st["bytes_sent"] == 6 * 760 and st["slots"] == {"suit:a": 0, "suit:b": 5}


@pytest.mark.asyncio
async def test_sends_to_a_closed_port_never_raise() -> None:
    dest = [("127.0.0.1", closed_port())]
    mvn = MvnUdpSink(SKELETON, dest)
    vmc = VmcUdpSink(SKELETON, dest)
    for sink in (mvn, vmc):
        await sink.start()
        for n in range(50):  # ICMP port-unreachable comes back; a connected socket would raise ECONNREFUSED
            sink.publish(frame(n, [person("suit:a")]))
        st = sink.status()
        assert st["frames_sent"] == 50
        assert st["datagrams_sent"] + st["datagrams_dropped"] == 50 * (1 if sink is mvn else 2)
        await sink.aclose()


def test_sender_counts_failures_by_errno(receiver: socket.socket) -> None:
    dest = ("127.0.0.1", receiver.getsockname()[1])
    sender = UdpSender()
    assert not sender.send(b"x", dest)  # not opened yet
    sender.open()
    assert sender.send(b"x", dest)
    assert not sender.send(bytes(70_000), dest)  # larger than any UDP datagram: EMSGSIZE from the kernel
    sender.close()
    c = sender.counters()
    assert c["datagrams_sent"] == 1 and c["bytes_sent"] == 1
    assert c["errors"] == {"not_started": 1, "EMSGSIZE": 1} and c["datagrams_dropped"] == 2


def test_non_finite_poses_are_skipped_and_counted(receiver: socket.socket) -> None:
    sink = MvnUdpSink(SKELETON, [("127.0.0.1", receiver.getsockname()[1])])
    sink.sender.open()
    bad = person("suit:bad")
    bad.theta[5] = np.nan
    sink.publish(frame(0, [bad, person("suit:ok")]))
    sink.sender.close()
    assert [parse_header(d).character_id for d in pending(receiver)] == [1]  # suit:bad held slot 0, sent nothing
    assert sink.status()["skipped_subjects"] == 1


def test_benchmark_reports_sizes_and_costs() -> None:
    from mocapd.service.bench.streams import run

    r = run(subjects=2, rate=60.0, n_frames=20)
    assert r["mvn"]["bytes_per_frame"] == 2 * 760 and r["mvn"]["datagrams_per_frame"] == 2
    assert r["vmc"]["datagrams_per_frame"] == 4 and r["mvn"]["dropped"] == 0 and r["vmc"]["dropped"] == 0
    assert r["rokoko"]["datagrams_per_frame"] == 1 and r["rokoko"]["dropped"] == 0
    assert r["rokoko"]["publish_us"]["median"] > 0 and r["rokoko"]["budget_fraction"] > 0
    assert r["subjects"] == 2 and r["frames"] == 20
    timings = [r["mvn"]["serialise_us"], r["mvn"]["publish_us"], r["mvn"]["sendto_us_per_datagram"],
               r["vmc"]["serialise_us"], r["vmc"]["publish_us"], *r["baseline"].values()]  # fmt: skip
    assert len(timings) == 7 and all(0 < t["median"] <= t["p95"] for t in timings), timings
    # The budget is both streams' median publish cost over the 60 Hz frame period (rounded to 4 decimals).
    both_us = r["mvn"]["publish_us"]["median"] + r["vmc"]["publish_us"]["median"]
    assert r["budget_fraction"] == pytest.approx(both_us / (1e6 / 60.0), abs=2e-4)


def test_sink_arguments_are_checked() -> None:
    with pytest.raises(InputError, match="at least one destination"):
        MvnUdpSink(SKELETON, [])
    with pytest.raises(InputError, match="rate_divisor"):
        VmcUdpSink(SKELETON, [("127.0.0.1", 39539)], rate_divisor=0)
    with pytest.raises(InputError, match="does not fit"):
        VmcUdpSink(SKELETON, [("127.0.0.1", 39539)], max_datagram_bytes=64)

"""The SlimeVR server state machine (pure): handshake and replies, sensors, packet numbers, keep-alive, time-outs,
holding quiet sensors, acceleration as specific force, and hostile input."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mocapd.core.rotations import quat_from_rotvec, quat_rotate
from mocapd.protocols.slimevr import (
    HANDSHAKE_REPLY,
    Acceleration,
    Battery,
    FeatureFlags,
    Handshake,
    Heartbeat,
    Packet,
    PingPong,
    Rotation,
    SensorInfo,
    SignalStrength,
    Temperature,
    TrackerError,
    encode_bundle,
    encode_feature_flags,
    encode_heartbeat,
    encode_packet,
    encode_ping,
    encode_sensor_info_ack,
)
from mocapd.protocols.slimevr_server import (
    SERVER_FEATURES,
    STANDARD_GRAVITY,
    SensorSample,
    ServerOptions,
    SlimeVrServer,
    TrackerConnected,
    TrackerEvicted,
    TrackerRefused,
    TrackerTimedOut,
)

A = ("127.0.0.1", 40001)
B = ("127.0.0.1", 40002)
MAC = "A1:B2:C3:D4:E5:F6"
MS = 1_000_000
IDENTITY = (1.0, 0.0, 0.0, 0.0)


def connect(server: SlimeVrServer, addr: tuple[str, int] = A, *, version: int = 22, sensors: int = 2) -> None:
    server.receive_datagram(encode_packet(Handshake(2, 3, 2, version, "0.6.3", MAC), 0), addr, 0)
    for k in range(sensors):
        server.receive_datagram(encode_packet(SensorInfo(k, 1, 3), k + 1), addr, 0)


def samples(server: SlimeVrServer) -> list[SensorSample]:
    return [e for e in server.events_received() if isinstance(e, SensorSample)]


def test_handshake_is_answered_and_sensors_acknowledged() -> None:
    s = SlimeVrServer()
    connect(s)
    assert s.datagrams_to_send() == [(HANDSHAKE_REPLY, A), (encode_sensor_info_ack(0, 1), A),
                                     (encode_sensor_info_ack(1, 1), A)]  # fmt: skip
    assert s.events_received() == [TrackerConnected(MAC, A, handover=False)]
    t = s.trackers[MAC]
    assert (t.firmware, t.protocol_version, sorted(t.sensors)) == ("0.6.3", 22, [0, 1])


def test_rotations_become_samples_with_sensor_ids_from_mac_and_index() -> None:
    s = SlimeVrServer()
    connect(s)
    s.events_received()
    q = (0.5, 0.5, 0.5, 0.5)
    s.receive_datagram(encode_packet(Rotation(1, q), 10), A, 5 * MS)
    (smp,) = samples(s)
    assert smp.sensor == f"{MAC}/1" and smp.host_ns == 5 * MS and smp.quat == q and not smp.held
    # Without an acceleration the sensor is taken at rest: specific force = R_iᵀ (0, 0, g).
    expected = quat_rotate(np.array([0.5, -0.5, -0.5, -0.5]), np.array([0.0, 0.0, STANDARD_GRAVITY]))
    np.testing.assert_allclose(smp.acc, expected, atol=1e-12)
    assert s.trackers[MAC].sensors[1].without_acceleration == 1


def test_acceleration_is_gravity_free_in_and_specific_force_out() -> None:
    s = SlimeVrServer()
    connect(s)
    q = tuple(float(v) for v in quat_from_rotvec(np.array([0.3, -0.2, 1.0])))
    lin = (1.0, -2.0, 0.5)
    # Same datagram (a bundle): the rotation gets its own acceleration.
    s.receive_datagram(encode_bundle([Rotation(0, q), Acceleration(0, lin)], 10), A, 1 * MS)  # type: ignore[arg-type]
    (smp,) = samples(s)
    up = quat_rotate(np.array([q[0], -q[1], -q[2], -q[3]]), np.array([0.0, 0.0, STANDARD_GRAVITY]))
    np.testing.assert_allclose(smp.acc, np.array(lin) + up, atol=1e-6)
    # Separate packets: the last acceleration applies to rotations within acc_max_age_ns.
    s.receive_datagram(encode_packet(Acceleration(1, (0.0, 0.0, 3.0)), 11), A, 2 * MS)
    s.receive_datagram(encode_packet(Rotation(1, IDENTITY), 12), A, 3 * MS)
    s.receive_datagram(encode_packet(Rotation(1, IDENTITY), 13), A, 200 * MS)
    first, late = samples(s)
    assert first.acc == (0.0, 0.0, 3.0 + STANDARD_GRAVITY)
    assert late.acc == (0.0, 0.0, STANDARD_GRAVITY)


def test_old_protocol_acceleration_is_turned_like_the_server_does() -> None:
    s = SlimeVrServer()
    connect(s, version=17)
    s.receive_datagram(encode_bundle([Rotation(0, IDENTITY), Acceleration(0, (1.0, 0.0, 0.0))], 10), A, MS)
    (smp,) = samples(s)
    np.testing.assert_allclose(smp.acc, (0.0, -1.0, STANDARD_GRAVITY), atol=1e-12)  # −90° about +Z


def test_packet_numbers_count_losses_and_drop_late_packets() -> None:
    s = SlimeVrServer()
    connect(s)  # numbers 0, 1, 2
    for n in (3, 4, 8, 6, 9, 9):
        s.receive_datagram(encode_packet(Rotation(0, IDENTITY), n), A, n * MS)
    t = s.trackers[MAC]
    assert (t.lost, t.reordered) == (3, 2)  # 5, 6, 7 skipped; 6 late and 9 repeated
    assert len(samples(s)) == 4
    # Number 0 always passes (an echoed ping carries the server's 0).
    s.receive_datagram(encode_ping(1), A, 20 * MS)
    assert t.reordered == 2


def test_keepalive_ping_round_trip_and_timeout() -> None:
    opts = ServerOptions(heartbeat_interval_ns=500 * MS, timeout_ns=1000 * MS)
    s = SlimeVrServer(opts)
    connect(s, sensors=0)
    s.datagrams_to_send()
    s.tick(0)
    sent = s.datagrams_to_send()
    assert sent == [(encode_heartbeat(), A), (encode_ping(1), A)]
    s.tick(100 * MS)
    assert s.datagrams_to_send() == []  # not due yet
    s.receive_datagram(sent[1][0], A, 30 * MS)  # the tracker echoes the ping
    assert s.trackers[MAC].rtt_ms == 30.0
    s.tick(1031 * MS)
    assert s.events_received()[-1] == TrackerTimedOut(MAC)
    assert s.status()["trackers"][0]["connected"] is False
    s.receive_datagram(encode_packet(Battery(3.9, 0.7), 20), A, 1100 * MS)
    assert s.trackers[MAC].timed_out is False


def test_quiet_sensors_are_held_while_connected_only() -> None:
    s = SlimeVrServer(ServerOptions(hold_after_ns=20 * MS, timeout_ns=1000 * MS))
    connect(s, sensors=1)
    q = (0.0, 1.0, 0.0, 0.0)
    s.receive_datagram(encode_packet(Rotation(0, q), 5), A, 0)
    s.events_received()
    s.tick(10 * MS)
    assert samples(s) == []
    s.tick(25 * MS)
    (held,) = samples(s)
    assert held.held and held.quat == q and held.host_ns == 25 * MS
    np.testing.assert_allclose(held.acc, (0.0, 0.0, -STANDARD_GRAVITY), atol=1e-12)  # upside down, at rest
    s.tick(1500 * MS)  # silent for more than the time-out: no more holding
    assert samples(s) == []


def test_handover_to_a_new_address_keeps_the_tracker() -> None:
    s = SlimeVrServer()
    connect(s, A)
    s.receive_datagram(encode_packet(Rotation(0, IDENTITY), 50), A, MS)
    connect(s, B)  # same MAC from another port (the tracker rebooted or changed IP): numbering starts over
    s.receive_datagram(encode_packet(Rotation(0, IDENTITY), 3), B, 2 * MS)
    s.receive_datagram(encode_packet(Rotation(0, IDENTITY), 51), A, 3 * MS)  # the old address is forgotten
    t = s.trackers[MAC]
    assert t.address == B and t.handovers == 1 and t.reordered == 0
    assert s.counters.unknown_source == 1
    assert [e.sensor for e in samples(s)] == [f"{MAC}/0", f"{MAC}/0"]


def test_tracker_without_mac_is_named_by_address_and_old_firmware_has_sensor_0() -> None:
    s = SlimeVrServer()
    s.receive_datagram(encode_packet(Handshake(0, 3, 0, 5, "owo", None), 0), A, 0)
    s.receive_datagram(encode_packet(Rotation(0, IDENTITY), 1), A, MS)
    assert [e.sensor for e in samples(s)] == ["127.0.0.1:40001/0"]


def test_other_packets_update_the_tracker_state() -> None:
    s = SlimeVrServer()
    connect(s)
    s.datagrams_to_send()
    others: list[Packet] = [Battery(3.9, 0.62), SignalStrength(255, -58), Temperature(1, 36.5), TrackerError(0, 3),
                            FeatureFlags(b"\x07")]  # fmt: skip
    for n, p in enumerate(others, start=10):
        s.receive_datagram(encode_packet(p, n), A, n * MS)
    st_ = s.status()["trackers"][0]
    assert (st_["battery_voltage"], st_["battery_level"], st_["rssi_dbm"], st_["errors"]) == (
        3.9000000953674316, 0.6200000047683716, -58, 1)  # fmt: skip
    assert st_["sensors"][0]["status"] == "error" and st_["sensors"][1]["temperature_c"] == 36.5
    assert s.datagrams_to_send() == [(encode_feature_flags(SERVER_FEATURES), A)]
    assert s.trackers[MAC].firmware_features == b"\x07"


def test_unknown_sources_unannounced_sensors_and_bad_packets_are_counted() -> None:
    s = SlimeVrServer()
    s.receive_datagram(encode_packet(Rotation(0, IDENTITY), 1), A, 0)
    connect(s, sensors=1)
    s.receive_datagram(encode_packet(Rotation(5, IDENTITY), 10), A, 0)
    s.receive_datagram(b"\x00\x00\x00\x11", A, 0)
    s.receive_datagram(bytes.fromhex("00000011" + "000000000000000b" + "0001" + "00000000" * 4 + "00"), A, 0)
    c = s.counters
    assert (c.unknown_source, c.unannounced_sensor, c.bad_datagrams) == (1, 1, 2)
    assert samples(s) == []


def _packets() -> st.SearchStrategy[Packet]:
    unit = st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: 0.5 < math.hypot(*q) < 2).map(
        lambda q: tuple(v / math.hypot(*q) for v in q))  # fmt: skip
    small = st.integers(0, 4)
    return st.one_of(
        st.builds(Rotation, small, unit),
        st.builds(Acceleration, small, st.tuples(*[st.floats(-50, 50)] * 3)),
        st.builds(SensorInfo, small, st.integers(0, 2), st.integers(0, 20)),
        st.builds(PingPong, st.integers(0, 2**32 - 1)),
        st.builds(Battery, st.none(), st.floats(0, 1, width=32)),
    )


@settings(deadline=None, max_examples=150)
@given(st.lists(st.tuples(st.booleans(), st.integers(0, 40), st.binary(max_size=64), _packets()), max_size=30))
def test_hostile_and_mutated_streams_never_raise(steps: list[tuple[bool, int, bytes, Packet]]) -> None:
    s = SlimeVrServer(ServerOptions(hold_after_ns=MS, timeout_ns=50 * MS))
    connect(s)
    now = 0
    for use_raw, n, raw, packet in steps:
        now += MS
        data = bytearray(raw if use_raw else encode_packet(packet, n))
        if use_raw and raw:  # a mutated real packet
            data = bytearray(encode_packet(packet, n))
            data[len(raw) % len(data)] ^= raw[0] | 1
        s.receive_datagram(bytes(data), A if n % 3 else B, now)
        s.tick(now)
    for e in s.events_received():
        if isinstance(e, SensorSample):
            assert all(math.isfinite(v) for v in (*e.quat, *e.acc))
            assert abs(math.hypot(*e.quat) - 1.0) < 1e-6
    st_ = s.status()
    assert st_["datagrams"] == len(steps) + 3
    assert len(st_["bad_reasons"]) <= 32


def test_the_table_of_trackers_is_bounded_and_a_live_tracker_is_never_pushed_out() -> None:
    """Found by the wire fuzzing of issue 18: every handshake from a new source port (or MAC) made a tracker, each
    with up to 256 sensors, heartbeats and pings every 500 ms, and a /status entry, without a cap."""
    s = SlimeVrServer(ServerOptions(max_trackers=4, timeout_ns=1000 * MS))
    hello = [encode_packet(Handshake(2, 3, 2, 22, "0.6.3", f"A1:B2:C3:D4:E5:{k:02X}"), 0) for k in range(10)]
    for k in range(10):
        s.receive_datagram(hello[k], ("127.0.0.1", 41000 + k), k * MS)
    assert [t.key for t in s.trackers.values()] == [f"A1:B2:C3:D4:E5:{k:02X}" for k in range(4)]
    assert s.counters.refused_trackers == 6 and s.status()["refused_trackers"] == 6
    refused = [e for e in s.events_received() if isinstance(e, TrackerRefused)]
    assert [e.address[1] for e in refused] == list(range(41004, 41010))
    assert sum(1 for d, _ in s.datagrams_to_send() if d == HANDSHAKE_REPLY) == 4  # the refused got no reply
    # Trackers 1..3 keep talking; tracker 0 falls silent and times out: a new tracker takes its place.
    s.receive_datagram(hello[0], ("127.0.0.1", 41000), 500 * MS)  # tracker 0 re-shakes hands: a handover
    for k in (1, 2, 3):
        s.receive_datagram(encode_packet(SensorInfo(0, 1, 3), 1), ("127.0.0.1", 41000 + k), 1200 * MS)
    s.tick(1600 * MS)
    assert [t.key for t in s.trackers.values() if t.timed_out] == ["A1:B2:C3:D4:E5:00"]
    s.receive_datagram(hello[9], ("127.0.0.1", 41009), 1700 * MS)
    assert sorted(t.key[-2:] for t in s.trackers.values()) == ["01", "02", "03", "09"]
    assert s.counters.replaced_trackers == 1
    s.receive_datagram(hello[8], ("127.0.0.1", 41008), 1700 * MS)  # all four live again: refused
    assert s.counters.refused_trackers == 7 and len(s.trackers) == 4
    s.receive_datagram(encode_packet(SensorInfo(0, 1, 3), 2), ("127.0.0.1", 41000), 1800 * MS)  # forgotten
    assert s.counters.unknown_source == 1


def test_a_full_table_admits_a_newcomer_in_place_of_the_tracker_that_delivered_nothing_longest() -> None:
    """Issue 45 (the soak): trackers that only heartbeat held every place for ever. With the table full, a newcomer
    takes the place of a tracker that has delivered no rotation for the grace period: first one that never sent
    one (the earliest connected), then the one whose last rotation is oldest; a tracker streaming, or one within
    its grace since its handshake, is never evicted, and a handover does not restart the grace."""
    o = ServerOptions(max_trackers=4, max_sensors=4, timeout_ns=60_000 * MS, idle_grace_ns=1000 * MS)
    s = SlimeVrServer(o)
    addr = [("127.0.0.1", 42000 + k) for k in range(10)]
    mac = [f"0A:00:00:00:00:{k:02X}" for k in range(10)]
    number = [0] * 10

    def send(k: int, data: bytes, at_ms: int) -> None:
        s.receive_datagram(data, addr[k], at_ms * MS)

    def hello(k: int, at_ms: int) -> None:
        send(k, encode_packet(Handshake(2, 3, 2, 22, "fw", mac[k]), 0), at_ms)
        number[k] = 0

    def nxt(k: int) -> int:
        number[k] += 1
        return number[k]

    for k in range(4):  # 0 and 1 stream rotations; 2 and 3 announce a sensor each, then only heartbeat
        hello(k, 10 * k)
        send(k, encode_packet(SensorInfo(0, 1, 3), nxt(k)), 10 * k)
    for t in range(0, 3000, 100):
        for k in (0, 1):
            send(k, encode_packet(Rotation(0, IDENTITY), nxt(k)), t)
        for k in (2, 3):
            send(k, encode_packet(Heartbeat(), nxt(k)), t)
        if t == 500:
            hello(4, t)  # within everyone's grace: refused
            assert mac[4] not in s.trackers and s.counters.refused_trackers == 1
        if t == 900:
            hello(3, t)  # a handover: tracker 3 keeps its place and its first handshake's time
    assert not any(t.timed_out for t in s.trackers.values())
    s.events_received()
    hello(4, 3000)  # 2 and 3 delivered nothing for 3 s: 2, connected first, goes
    assert sorted(s.trackers) == sorted([mac[0], mac[1], mac[3], mac[4]])
    gone = [e for e in s.events_received() if isinstance(e, TrackerEvicted)]
    assert gone == [TrackerEvicted(mac[2], addr[2], 3000 * MS - 20 * MS, 1)]
    send(4, encode_packet(SensorInfo(0, 1, 3), nxt(4)), 3000)  # the freed sensor
    send(4, encode_packet(SensorInfo(1, 1, 3), nxt(4)), 3000)  # the budget is full: 3 holds one and idles
    assert mac[3] not in s.trackers and len(s.trackers[mac[4]].sensors) == 2
    hello(5, 3010)  # the sensor budget's eviction freed a place too
    hello(6, 3020)  # 4 and 5 are within their grace, 0 and 1 stream: refused
    send(4, encode_packet(SensorInfo(2, 1, 3), nxt(4)), 3020)  # 0 and 1 hold the other sensors: refused
    assert mac[5] in s.trackers and mac[6] not in s.trackers
    assert s.counters.refused_trackers == 2 and s.counters.refused_sensors == 1
    assert s.counters.evicted_trackers == 2 and s.status()["evicted_trackers"] == 2
    for t in range(3100, 4200, 100):  # 0 and 4 stream; 1 stops (its last rotation at 2900 ms); 5 heartbeats
        for k in (0, 4):
            send(k, encode_packet(Rotation(0, IDENTITY), nxt(k)), t)
        for k in (1, 5):
            send(k, encode_packet(Heartbeat(), nxt(k)), t)
    hello(6, 4100)  # 1 and 5 delivered nothing for more than 1 s: 5, which never delivered, goes first
    hello(7, 4150)  # then 1; never the streaming 0 and 4
    assert sorted(s.trackers) == [mac[0], mac[4], mac[6], mac[7]]
    assert s.counters.evicted_trackers == 4 and s.counters.replaced_trackers == 0


def test_a_datagram_from_an_address_that_has_not_shaken_hands_is_refused_before_it_is_decoded() -> None:
    """Issue 45 (the soak's cost): a datagram from an address that has not shaken hands was decoded before it was
    dropped (a bundle of 128 sensor infos: ~0.8 ms), so garbage from fresh ports counted as bad and as unknown.
    Now it is counted once, as unknown_source, from its header alone; only a header too short to say is bad."""
    s = SlimeVrServer()
    s.receive_datagram(b"\xff" * 40, A, 0)  # an unknown packet type: decoded, a bad datagram as well
    s.receive_datagram(encode_bundle([SensorInfo(i, 1, 3) for i in range(128)], 1, compact=True), A, 0)
    s.receive_datagram(bytes(5), A, 0)  # shorter than the header
    c = s.counters
    assert (c.datagrams, c.unknown_source, c.bad_datagrams) == (3, 2, 1)
    connect(s, sensors=1)  # a handshake from the same address is still heard
    s.receive_datagram(b"\xff" * 40, A, 0)
    assert (c.unknown_source, c.bad_datagrams) == (2, 2)


class _CountingTable(dict[str, object]):
    """The server's table of trackers, counting the walks over it (the cost of a search for room)."""

    walks = 0

    def values(self) -> Any:
        self.walks += 1
        return super().values()


def test_a_bundle_of_refused_sensor_infos_searches_the_table_for_room_once() -> None:
    """Issue 45 (the soak's cost): each of the 128 sensor infos of a swarm tracker's bundle, refused because the
    budget was full, searched the whole table for a tracker to make room (1.4 ms a bundle). A failed search is
    remembered until the table changes: one search a bundle, and the room is found again once there is some."""
    o = ServerOptions(timeout_ns=60_000 * MS, idle_grace_ns=1000 * MS)
    s = SlimeVrServer(o)
    table = _CountingTable()
    s.trackers = table  # type: ignore[assignment]
    for k in range(64):
        addr = ("127.0.0.1", 43000 + k)
        s.receive_datagram(encode_packet(Handshake(2, 3, 2, 22, "fw", f"0A:00:00:00:00:{k:02X}"), 0), addr, 0)
        s.receive_datagram(encode_bundle([SensorInfo(i, 1, 3) for i in range(16)], 1, compact=True), addr, 0)
    assert s.status()["sensors_total"] == 128
    table.walks = 0
    late = ("127.0.0.1", 43063)  # holds no sensor: every one of its 128 is refused
    s.receive_datagram(encode_bundle([SensorInfo(i, 1, 3) for i in range(16, 144)], 2, compact=True), late, 500 * MS)
    assert s.counters.refused_sensors == 64 * 16 - 128 + 128
    assert table.walks <= 2, table.walks
    s.receive_datagram(encode_bundle([SensorInfo(0, 1, 3)], 3, compact=True), late, 1500 * MS)  # past the grace
    assert len(s.trackers["0A:00:00:00:00:3F"].sensors) == 1 and s.counters.evicted_trackers == 1

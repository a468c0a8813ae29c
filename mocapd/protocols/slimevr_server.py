"""The SlimeVR server side of the tracker protocol as a sans-I/O state machine (bytes and times in, events out).

Datagram formats: :mod:`mocapd.protocols.slimevr`. What the server does, following SlimeVR-Server's
``TrackersUDPServer.kt`` (commit ``554976390b7c``):

- a handshake (type 3) from any address opens a connection, or hands an existing one (same MAC) over to the new
  address, resets its packet numbering, and is answered with the 64-byte handshake reply;
- sensors exist once announced by a sensor info packet (15), which is acknowledged; trackers of protocol version
  < 9 have sensor 0 from the handshake on;
- a connection's packets must carry increasing packet numbers (0 is always accepted: handshakes, echoed pings):
  a number not above the last one is a late or duplicated datagram, counted as reordered and dropped (an older
  orientation must not overwrite a newer one); a step forward counts the numbers skipped as lost;
- every ``heartbeat_interval_ns`` each connection gets a heartbeat (answered by the tracker) and a ping (echoed:
  the round trip is reported); a connection silent for ``timeout_ns`` is timed out until it speaks again;
- feature flags (22) are answered with the server's (bundles and compact bundles, which are parsed);
- acceleration of trackers with protocol version < 22 is turned by −90° about +Z, the server's correction for
  firmware that applied the board rotation to acceleration wrongly (SlimeVR-Tracker-ESP pull request 480).

What mocapd adds at the door (issue 34), because anyone on the network can send a datagram:

- packet numbers are followed by :class:`~mocapd.protocols.sequence.SequenceNumbers`: a step forward of more
  than ``max_number_step`` or back by more than ``max_number_behind`` is not adopted (one datagram numbered 2⁶⁴−1
  locked a tracker out: every later one was "reordered"); it is dropped and counted (``number_jumps``), and two
  such numbers in a row that follow each other resynchronise the connection (``number_resyncs``);
- sensors are bounded per tracker (``max_sensors_per_tracker``, 16: a SlimeVR glove has 10) and in total
  (``max_sensors``): a sensor info beyond either is refused, counted (``refused_sensors``) and not acknowledged,
  unless another tracker holding sensors can make room (below; issue 45: silent trackers held the budget until a
  restart); 64 trackers announcing 256 sensors each had held the daemon's loop busy enough to drop the output rate
  by a third;
- **admission by delivered data** (issue 45): when the table of trackers or the sensor budget is full, a newcomer
  (a handshake of a new tracker, a sensor info beyond the budget) takes the place of the tracker that has
  delivered no rotation for the longest time: a timed-out tracker (``replaced_trackers``), or a connected one that
  has delivered none for ``idle_grace_ns`` since its last rotation or, never having sent one, since it first shook
  hands (``evicted_trackers``, a :class:`TrackerEvicted` event). A swarm that handshakes, announces sensors and then
  only heartbeats delivers nothing a user needs and no longer holds the places a real suit arriving after it
  needs; a tracker streaming rotations is never evicted for a newcomer. A handover (the same MAC shaking hands
  again) does not restart the grace. Arrival order no longer decides who is served: a place is held by
  delivering rotations, not by talking. A sender streaming rotations from 64 trackers is a suit as far as the
  protocol can tell (it has no authentication) and keeps its places. No share per source address: UDP source
  addresses are not checked (a sender on the network can use any, the real trackers' too) and one address
  legitimately carries many trackers (emulators, the tests);
- :meth:`SlimeVrServer.status` lists at most ``max_listed_trackers`` trackers (connected ones first, then the
  most recently heard) beside counts of all of them, so ``/status`` stays a few tens of KB however many trackers
  a sender invents; time-outs are counted per tracker and in total.

What mocapd adds, because its buffers are sampled at fixed instants:

- samples: each orientation becomes a :class:`SensorSample` with the sensor's specific force in the sensor frame
  (mocapd's IMU model, gravity included: the tracker's gravity-free acceleration plus ``R_iᵀ (0, 0, g)``); the
  acceleration is the one that came with the rotation in the same datagram (bundles, packet 23) or the latest
  one received within ``acc_max_age_ns``, otherwise none (rest assumed, counted);
- holding: firmware sends an orientation only when it changed (``OPTIMIZE_UPDATES``), so a still tracker goes
  quiet. While its connection is alive, :meth:`SlimeVrServer.tick` repeats a sensor's last orientation when it is
  older than ``hold_after_ns`` (marked ``held``), so look-ups see "unchanged", not a dropout; a timed-out tracker
  is not held, and its buffers run dry as any lost sensor's do.

Sensor ids are ``"<MAC>/<sensor index>"`` (``"AA:BB:CC:DD:EE:FF/0"``), or ``"<host>:<port>/<index>"`` for a tracker
that sent no MAC. Nothing here reads a clock: every call takes the host time ``now_ns``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Any

from mocapd.protocols.sequence import SequenceNumbers
from mocapd.protocols.slimevr import (
    DATA_TYPE_NORMAL,
    HANDSHAKE_REPLY,
    USER_ACTION_RESET_FULL,
    USER_ACTION_RESET_YAW,
    Acceleration,
    Battery,
    FeatureFlags,
    Handshake,
    Heartbeat,
    Ignored,
    Packet,
    PingPong,
    Quat,
    Rotation,
    SensorInfo,
    ServerFeature,
    SignalStrength,
    Tap,
    Temperature,
    TrackerError,
    Tx,
    UserAction,
    Vec3,
    decode_datagram,
    encode_feature_flags,
    encode_heartbeat,
    encode_ping,
    encode_sensor_info_ack,
)

Address = tuple[str, int]
STANDARD_GRAVITY = 9.80665
SERVER_FEATURES = ServerFeature.BUNDLE | ServerFeature.BUNDLE_COMPACT


@dataclass(frozen=True, slots=True)
class ServerOptions:
    """Timing of the server side (ns)."""

    heartbeat_interval_ns: int = 500_000_000
    """Heartbeat and ping to every connection this often (the SlimeVR server's 500 ms)."""
    timeout_ns: int = 1_000_000_000
    """A connection silent this long is timed out (the SlimeVR server's 1 s)."""
    hold_after_ns: int = 20_000_000
    """Repeat a live sensor's last orientation when it is older than this."""
    acc_max_age_ns: int = 100_000_000
    """A separate acceleration packet applies to rotations up to this much later."""
    gravity: float = STANDARD_GRAVITY
    max_trackers: int = 64
    """Trackers known at once. A handshake from a new tracker beyond this takes the place of the one that has
    delivered no rotation for longest (a timed-out one, or one idle for ``idle_grace_ns``); with none such it is
    refused (counted): a sender cycling through source ports or MACs cannot grow the table, and cannot push out a
    tracker that streams."""
    idle_grace_ns: int = 5_000_000_000
    """A connected tracker that has delivered no rotation for this long (since its last one, or since it first
    shook hands) may be evicted for a newcomer when the table or the sensor budget is full. Firmware streams within
    a fraction of a second of its handshake; a still tracker sends nothing (it sends on change) and, evicted, shakes
    hands again within 3 s of hearing nothing, as after any loss."""
    max_sensors_per_tracker: int = 16
    """Sensors one tracker may announce (the firmware's MAX_SENSORS_COUNT: 1-2 on a tracker, 10 on a glove)."""
    max_sensors: int = 128
    """Sensors of all trackers together (a full-body suit and two gloves are ~40)."""
    max_number_step: int = 1 << 16
    """Largest step forward of a packet number taken as the next one (~5 minutes of packets at 200 a second)."""
    max_number_behind: int = 1 << 10
    """A packet number this far behind the last one is a late datagram (reordered); farther, a jump."""
    max_listed_trackers: int = 16
    """Trackers listed one by one in :meth:`SlimeVrServer.status` (all of them are counted)."""

    def __post_init__(self) -> None:
        for name in ("heartbeat_interval_ns", "timeout_ns", "hold_after_ns", "acc_max_age_ns", "max_trackers",
                     "idle_grace_ns", "max_sensors_per_tracker", "max_sensors", "max_number_step",
                     "max_number_behind", "max_listed_trackers"):  # fmt: skip
            if getattr(self, name) <= 0:
                raise ValueError(f"ServerOptions.{name} must be > 0, got {getattr(self, name)}")


@dataclass(slots=True)
class SensorState:
    """One sensor of a tracker."""

    index: int
    status: int = 1
    imu_type: int = 0
    rotations: int = 0
    held: int = 0
    without_acceleration: int = 0
    temperature_c: float | None = None
    quat: Quat | None = None
    acc: Vec3 | None = None  # the latest gravity-free acceleration (sensor frame)
    acc_ns: int = 0
    last_sample_ns: int = 0


@dataclass(slots=True)
class TrackerState:
    """One tracker (one ESP board, one or more sensors) as the server knows it."""

    key: str
    mac: str | None
    address: Address
    board: int
    mcu: int
    firmware: str
    protocol_version: int
    connected_ns: int
    last_packet_ns: int
    timed_out: bool = False
    numbers: SequenceNumbers = field(default_factory=lambda: SequenceNumbers(1 << 16, 1 << 10, last=0))
    packets: int = 0
    handovers: int = 0
    timeouts: int = 0
    battery_voltage: float | None = None
    battery_level: float | None = None
    rssi_dbm: int | None = None
    rtt_ms: float | None = None
    pings: dict[int, int] = field(default_factory=dict)  # ping id -> sent at (the last few, a late echo still counts)
    next_keepalive_ns: int = 0
    firmware_features: bytes | None = None
    errors: int = 0
    sensors: dict[int, SensorState] = field(default_factory=dict)
    last_rotation_ns: int | None = None  # the last rotation delivered (a sample), None before the first

    @property
    def delivered_ns(self) -> int:
        """Since when it has delivered nothing: its last rotation, or its first handshake before one."""
        return self.connected_ns if self.last_rotation_ns is None else self.last_rotation_ns

    def sensor_id(self, index: int) -> str:
        return f"{self.key}/{index}"

    @property
    def lost(self) -> int:
        """Packet numbers skipped (a step forward counts the ones between)."""
        return self.numbers.lost

    @property
    def reordered(self) -> int:
        """Late or duplicated datagrams dropped."""
        return self.numbers.reordered + self.numbers.duplicates


@dataclass(frozen=True, slots=True)
class SensorSample:
    """One orientation of one sensor for the IMU buffers.

    ``quat`` (w, x, y, z): sensor frame → the tracker's +Z-up fusion frame; ``acc``: specific force in the sensor
    frame (m/s², gravity included, the convention of mocapd's IMU model); ``held``: a repeat of the last orientation
    of a quiet but connected tracker.
    """

    sensor: str
    host_ns: int
    quat: Quat
    acc: Vec3
    held: bool = False


@dataclass(frozen=True, slots=True)
class TrackerConnected:
    key: str
    address: Address
    handover: bool  # an existing tracker (same MAC) came back from a new address, or re-shook hands


@dataclass(frozen=True, slots=True)
class TrackerTimedOut:
    key: str


@dataclass(frozen=True, slots=True)
class TrackerRefused:
    """A new tracker's handshake was not answered: the table of trackers is full of live ones."""

    address: Address


@dataclass(frozen=True, slots=True)
class TrackerEvicted:
    """A connected tracker that had delivered no rotation for ``idle_ns`` was forgotten to make room for a
    newcomer (the table of trackers or the sensor budget was full)."""

    key: str
    address: Address
    idle_ns: int
    sensors: int


@dataclass(frozen=True, slots=True)
class TrackerGesture:
    """The wearer asked for a heading reset on a tracker: a double tap its firmware detected (packet 13, then
    ``sensor`` is the tapped sensor's id), or a reset asked with its button (packet 21: ``kind`` "yaw reset" or
    "full reset"). The SlimeVR server resets on the button; mocapd resets on both."""

    key: str
    sensor: str | None
    kind: str


Event = SensorSample | TrackerConnected | TrackerTimedOut | TrackerRefused | TrackerEvicted | TrackerGesture


@dataclass(slots=True)
class ServerCounters:
    datagrams: int = 0
    bad_datagrams: int = 0
    """Undecodable datagrams or packets (short, unknown type, non-finite or non-unit values), counted per reason."""
    unknown_source: int = 0
    """Datagrams from an address that has not shaken hands (dropped)."""
    unannounced_sensor: int = 0
    """Orientations of a sensor that sent no sensor info (dropped, as the SlimeVR server does)."""
    refused_trackers: int = 0
    """Handshakes of new trackers refused: ``max_trackers`` trackers are known and all deliver rotations."""
    replaced_trackers: int = 0
    """Timed-out trackers forgotten to make room for a new one."""
    evicted_trackers: int = 0
    """Connected trackers that had delivered no rotation for ``idle_grace_ns``, forgotten for a newcomer."""
    refused_sensors: int = 0
    """Sensor infos refused: the tracker has ``max_sensors_per_tracker`` sensors, or all have ``max_sensors``."""
    number_jumps: int = 0
    """Datagrams dropped because their packet number jumped too far from the connection's (not adopted)."""
    number_resyncs: int = 0
    """Connections whose packet numbering was followed to a new place (two consecutive numbers agreed on it)."""
    timeouts: int = 0
    """Trackers timed out (each time one went silent for ``timeout_ns``)."""
    ignored: Counter[str] = field(default_factory=Counter)
    bad_reasons: Counter[str] = field(default_factory=Counter)


class SlimeVrServer:
    """Tracker connections of one server socket.

    Feed every received datagram to :meth:`receive_datagram`, call :meth:`tick` regularly (every
    ``hold_after_ns`` or so), then send :meth:`datagrams_to_send` and handle :meth:`events_received`.
    """

    def __init__(self, options: ServerOptions | None = None) -> None:
        self.options = options or ServerOptions()
        self.trackers: dict[str, TrackerState] = {}
        self.counters = ServerCounters()
        self._by_address: dict[Hashable, TrackerState] = {}
        self._out: list[tuple[bytes, Address]] = []
        self._events: list[Event] = []
        self._ping_counter = 0
        self._sensors = 0  # sensors of all trackers
        #: (for sensors, asking tracker) -> the time before which no tracker can make room for it (a cache of a
        #: failed search, cleared when the table changes or a tracker times out)
        self._no_room: dict[tuple[bool, str | None], int] = {}

    # ------------------------------------------------------------------------------------------ I/O boundary
    def datagrams_to_send(self) -> list[tuple[bytes, Address]]:
        out, self._out = self._out, []
        return out

    def events_received(self) -> list[Event]:
        out, self._events = self._events, []
        return out

    def receive_datagram(self, data: bytes, address: Address, now_ns: int) -> None:
        """Process one datagram received from ``address`` at host time ``now_ns``."""
        c = self.counters
        c.datagrams += 1
        # Refused before it is decoded: a datagram that is no handshake from an address that has not shaken hands
        # (a bundle of 128 sensor infos costs ~0.8 ms to decode; garbage from fresh ports, a forgotten swarm).
        if (len(data) >= 12 and int.from_bytes(data[:4], "big") != Tx.HANDSHAKE
                and address not in self._by_address):  # fmt: skip
            c.unknown_source += 1
            return
        decoded = decode_datagram(data)
        if decoded.error is not None:
            self._bad(decoded.error)
        if decoded.packet_type == Tx.HANDSHAKE and decoded.packets:
            packet = decoded.packets[0]
            assert isinstance(packet, Handshake)
            self._handshake(packet, address, now_ns)
            return
        tracker = self._by_address.get(address)
        if tracker is None:
            if decoded.packet_type >= 0:
                c.unknown_source += 1
            return
        if decoded.packet_type < 0:
            return
        if decoded.number != 0:
            verdict = tracker.numbers.take(decoded.number)
            if verdict == "resync":
                c.number_resyncs += 1
            elif verdict == "jump":
                c.number_jumps += 1
                return
            elif verdict != "next":  # late or repeated: an older orientation must not overwrite a newer one
                return
        tracker.packets += 1
        tracker.last_packet_ns = now_ns
        if tracker.timed_out:
            tracker.timed_out = False
        rotations: dict[int, Rotation] = {}
        accelerations: dict[int, Vec3] = {}
        for p in decoded.packets:
            self._packet(tracker, p, now_ns, rotations, accelerations)
        for index, rot in rotations.items():
            self._sample(tracker, index, rot, accelerations.get(index), now_ns)

    def tick(self, now_ns: int, heard_until_ns: int | None = None) -> None:
        """Heartbeats, pings, time-outs and held orientations due at ``now_ns``.

        ``heard_until_ns``: the arrival time of the oldest datagram received but not yet handed to
        :meth:`receive_datagram` (a backlog handed over in slices): a tracker is timed out only by silence before
        it, never for datagrams that wait in the caller's queue."""
        o = self.options
        heard = now_ns if heard_until_ns is None else min(now_ns, heard_until_ns)
        for t in self.trackers.values():
            if now_ns >= t.next_keepalive_ns:
                t.next_keepalive_ns = now_ns + o.heartbeat_interval_ns
                self._out.append((encode_heartbeat(), t.address))
                self._ping_counter = (self._ping_counter + 1) & 0xFFFFFFFF
                t.pings[self._ping_counter] = now_ns
                if len(t.pings) > 8:
                    del t.pings[next(iter(t.pings))]
                self._out.append((encode_ping(self._ping_counter), t.address))
            if not t.timed_out and heard - t.last_packet_ns > o.timeout_ns:
                t.timed_out = True
                self._no_room.clear()
                t.timeouts += 1
                self.counters.timeouts += 1
                self._events.append(TrackerTimedOut(t.key))
            if t.timed_out:
                continue
            for s in t.sensors.values():
                if s.quat is not None and now_ns - s.last_sample_ns >= o.hold_after_ns:
                    s.held += 1
                    s.last_sample_ns = now_ns
                    self._events.append(SensorSample(t.sensor_id(s.index), now_ns, s.quat,
                                                     self._specific_force(s.quat, None), held=True))  # fmt: skip

    # ------------------------------------------------------------------------------------------ packets
    def _bad(self, reason: str) -> None:
        self.counters.bad_datagrams += 1
        # A hostile sender can vary the reason (unknown type numbers): keep at most 32 distinct keys.
        key = reason.split(" (", maxsplit=1)[0][:60]
        reasons = self.counters.bad_reasons
        reasons[key if key in reasons or len(reasons) < 31 else "other"] += 1

    def _handshake(self, h: Handshake, address: Address, now_ns: int) -> None:
        o = self.options
        old = self.trackers.get(h.mac) if h.mac else None
        if old is None:
            old = self._by_address.get(address)
        if old is not None:
            self._by_address.pop(old.address, None)
            old.address = address
            old.numbers.reset(0)  # a new connection numbers its packets from 1
            old.handovers += 1
            old.firmware, old.protocol_version, old.board, old.mcu = h.firmware, h.protocol_version, h.board, h.mcu
            old.last_packet_ns = now_ns
            old.timed_out = False
            tracker = old
        else:
            if len(self.trackers) >= self.options.max_trackers and not self._make_room(now_ns):
                self.counters.refused_trackers += 1
                self._events.append(TrackerRefused(address))
                return
            key = h.mac or f"{address[0]}:{address[1]}"
            tracker = TrackerState(key, h.mac, address, h.board, h.mcu, h.firmware, h.protocol_version,
                                   connected_ns=now_ns, last_packet_ns=now_ns, next_keepalive_ns=now_ns,
                                   numbers=SequenceNumbers(o.max_number_step, o.max_number_behind, last=0))  # fmt: skip
            self.trackers[key] = tracker
            self._no_room.clear()
            if h.protocol_version < 9:  # old firmware announces no sensors: sensor 0 exists from the start
                self._add_sensor(tracker, 0, h.imu, now_ns)
        self._by_address[address] = tracker
        self._out.append((HANDSHAKE_REPLY, address))
        self._events.append(TrackerConnected(tracker.key, address, handover=old is not None))

    def _make_room(self, now_ns: int, keep: TrackerState | None = None, *, for_sensors: bool = False) -> bool:
        """Forget the tracker (not ``keep``; with ``for_sensors``, one that holds sensors) that has delivered no
        rotation for longest, if it is timed out or has delivered none for ``idle_grace_ns``: one that never sent a
        rotation first (it gave the solve nothing: a sender that fills the table with handshakes and heartbeats
        cannot push out a real tracker that missed a second), then the one whose last rotation is oldest. False
        when every other tracker streams (or is within its grace)."""
        memo = (for_sensors, None if keep is None else keep.key)
        if now_ns < self._no_room.get(memo, -1):  # a bundle of 128 sensor infos asks 128 times at one instant
            return False
        grace = self.options.idle_grace_ns
        gone: TrackerState | None = None
        best = (True, 0)
        until = now_ns + grace  # the earliest another tracker can become evictable (timeouts clear the memo)
        for t in self.trackers.values():
            if t is keep or (for_sensors and not t.sensors):
                continue
            since = t.delivered_ns
            if t.timed_out or now_ns - since > grace:
                rank = (t.last_rotation_ns is not None, since)
                if gone is None or rank < best:
                    gone, best = t, rank
            else:
                until = min(until, since + grace + 1)
        if gone is None:
            if len(self._no_room) >= 4 * self.options.max_trackers:
                self._no_room.clear()
            self._no_room[memo] = until
            return False
        self._forget(gone)
        if gone.timed_out:
            self.counters.replaced_trackers += 1
        else:
            self.counters.evicted_trackers += 1
            self._events.append(TrackerEvicted(gone.key, gone.address, now_ns - gone.delivered_ns, len(gone.sensors)))
        return True

    def _forget(self, gone: TrackerState) -> None:
        del self.trackers[gone.key]
        self._sensors -= len(gone.sensors)
        if self._by_address.get(gone.address) is gone:
            del self._by_address[gone.address]
        self._no_room.clear()

    def _packet(self, t: TrackerState, p: Packet, now_ns: int, rotations: dict[int, Rotation],
                accelerations: dict[int, Vec3]) -> None:  # fmt: skip
        if isinstance(p, Rotation):
            if p.data_type != DATA_TYPE_NORMAL:
                self.counters.ignored["correction rotation"] += 1
            elif p.sensor not in t.sensors:
                self.counters.unannounced_sensor += 1
            else:
                rotations[p.sensor] = p
                if p.acc is not None:
                    accelerations[p.sensor] = self._acc(t, p.acc)
        elif isinstance(p, Acceleration):
            s = t.sensors.get(p.sensor)
            if s is None:
                self.counters.unannounced_sensor += 1
                return
            s.acc, s.acc_ns = self._acc(t, p.acc), now_ns
            accelerations[p.sensor] = s.acc
        elif isinstance(p, SensorInfo):
            s = t.sensors.get(p.sensor) or self._add_sensor(t, p.sensor, p.imu_type, now_ns)
            if s is None:  # not acknowledged: the firmware repeats it, each refusal counted
                return
            s.status, s.imu_type = p.status, p.imu_type
            self._out.append((encode_sensor_info_ack(p.sensor, p.status), t.address))
        elif isinstance(p, PingPong):
            sent = t.pings.pop(p.ping_id, None)
            if sent is not None:
                t.rtt_ms = (now_ns - sent) / 1e6
            else:
                self.counters.ignored["unknown ping id"] += 1
        elif isinstance(p, Battery):
            t.battery_voltage, t.battery_level = p.voltage, p.level
        elif isinstance(p, SignalStrength):
            t.rssi_dbm = p.rssi_dbm
        elif isinstance(p, Temperature):
            if p.sensor in t.sensors:
                t.sensors[p.sensor].temperature_c = p.celsius
        elif isinstance(p, TrackerError):
            t.errors += 1
            if p.sensor in t.sensors:
                t.sensors[p.sensor].status = 2
        elif isinstance(p, FeatureFlags):
            t.firmware_features = p.flags
            self._out.append((encode_feature_flags(SERVER_FEATURES), t.address))
        elif isinstance(p, Tap):
            if p.double and p.sensor in t.sensors:
                self._events.append(TrackerGesture(t.key, t.sensor_id(p.sensor), "double tap"))
            else:
                self.counters.ignored["tap"] += 1
        elif isinstance(p, UserAction):
            kind = {USER_ACTION_RESET_YAW: "yaw reset", USER_ACTION_RESET_FULL: "full reset"}.get(p.action)
            if kind is not None:
                self._events.append(TrackerGesture(t.key, None, kind))
            else:
                self.counters.ignored["user action"] += 1
        elif isinstance(p, Ignored):
            self.counters.ignored[Tx(p.packet_type).name.lower()] += 1
        elif isinstance(p, Heartbeat):
            return
        else:  # a second handshake inside a bundle is refused by the decoder; nothing else is left
            self.counters.ignored[type(p).__name__] += 1

    def _add_sensor(self, t: TrackerState, index: int, imu_type: int, now_ns: int) -> SensorState | None:
        """A new sensor of ``t``, or None (counted) when the tracker or the server has all it may hold."""
        o = self.options
        if len(t.sensors) >= o.max_sensors_per_tracker:
            self.counters.refused_sensors += 1
            return None
        # The budget of all trackers is full: the sensors of a tracker that delivers nothing are freed (it is
        # forgotten, as for a handshake beyond max_trackers). Issue 45: 8 handshakes and 128 sensor infos, then
        # silence (or heartbeats only), held the budget for ever and every later tracker's sensors were refused.
        while self._sensors >= o.max_sensors:
            if not self._make_room(now_ns, t, for_sensors=True):
                self.counters.refused_sensors += 1
                return None
        if not t.sensors:
            self._no_room.clear()  # a tracker with sensors can make room for sensors: the memo is stale
        s = t.sensors[index] = SensorState(index, imu_type=imu_type)
        self._sensors += 1
        return s

    # Per-datagram arithmetic is written out on floats: numpy costs ~100 µs per tiny array call here, and a suit
    # of trackers sends thousands of datagrams a second into the daemon's event loop.
    def _acc(self, t: TrackerState, acc: Vec3) -> Vec3:
        if t.protocol_version >= 22:
            return acc
        return (acc[1], -acc[0], acc[2])  # turned by −90° about +Z

    def _specific_force(self, quat: Quat, linear: Vec3 | None) -> Vec3:
        """Sensor-frame specific force: gravity-free acceleration + ``R_iᵀ (0, 0, g)`` (at rest without one)."""
        w, x, y, z = quat
        g = self.options.gravity
        # R_iᵀ e_z is the third row of R_i.
        fx, fy, fz = 2.0 * (x * z - w * y) * g, 2.0 * (y * z + w * x) * g, (1.0 - 2.0 * (x * x + y * y)) * g
        if linear is not None:
            fx, fy, fz = fx + linear[0], fy + linear[1], fz + linear[2]
        return (fx, fy, fz)

    def _sample(self, t: TrackerState, index: int, rot: Rotation, acc: Vec3 | None, now_ns: int) -> None:
        s = t.sensors[index]
        if acc is None and s.acc is not None and now_ns - s.acc_ns <= self.options.acc_max_age_ns:
            acc = s.acc
        if acc is None:
            s.without_acceleration += 1
        s.quat = rot.quat
        s.rotations += 1
        s.last_sample_ns = now_ns
        t.last_rotation_ns = now_ns
        if s.status == 0:
            s.status = 1  # data from a sensor reported offline: it is working (as the SlimeVR server does)
        self._events.append(SensorSample(t.sensor_id(index), now_ns, rot.quat, self._specific_force(rot.quat, acc)))

    # ------------------------------------------------------------------------------------------ status
    def status(self) -> dict[str, Any]:
        """Counters, counts of trackers and sensors, and the first ``max_listed_trackers`` trackers (connected
        ones first, then the most recently heard) for /status."""
        c = self.counters
        ranked = sorted(self.trackers.values(), key=lambda t: (t.timed_out, -t.last_packet_ns))
        listed = ranked[: self.options.max_listed_trackers]
        return {
            "datagrams": c.datagrams,
            "bad_datagrams": c.bad_datagrams,
            "bad_reasons": dict(c.bad_reasons),
            "unknown_source": c.unknown_source,
            "unannounced_sensor": c.unannounced_sensor,
            "refused_trackers": c.refused_trackers,
            "replaced_trackers": c.replaced_trackers,
            "evicted_trackers": c.evicted_trackers,
            "refused_sensors": c.refused_sensors,
            "number_jumps": c.number_jumps,
            "number_resyncs": c.number_resyncs,
            "timeouts": c.timeouts,
            "ignored": dict(c.ignored),
            "trackers_total": len(self.trackers),
            "trackers_connected": sum(not t.timed_out for t in self.trackers.values()),
            "sensors_total": self._sensors,
            "trackers_listed": len(listed),
            "trackers": [self._tracker_status(t) for t in listed],
        }

    @staticmethod
    def _tracker_status(t: TrackerState) -> dict[str, Any]:
        return {
            "id": t.key,
            "address": f"{t.address[0]}:{t.address[1]}",
            "firmware": t.firmware,
            "protocol_version": t.protocol_version,
            "board": t.board,
            "mcu": t.mcu,
            "connected": not t.timed_out,
            "packets": t.packets,
            "lost": t.lost,
            "reordered": t.reordered,
            "number_jumps": t.numbers.jumps,
            "handovers": t.handovers,
            "timeouts": t.timeouts,
            "battery_voltage": t.battery_voltage,
            "battery_level": t.battery_level,
            "rssi_dbm": t.rssi_dbm,
            "rtt_ms": None if t.rtt_ms is None else round(t.rtt_ms, 2),
            "errors": t.errors,
            "sensors": [
                {
                    "id": t.sensor_id(s.index),
                    "status": {0: "offline", 1: "ok", 2: "error"}.get(s.status, str(s.status)),
                    "imu_type": s.imu_type,
                    "rotations": s.rotations,
                    "held": s.held,
                    "without_acceleration": s.without_acceleration,
                    "temperature_c": s.temperature_c,
                }
                for s in sorted(t.sensors.values(), key=lambda s: s.index)
            ],
        }

"""UDP pose sinks: the MVN (``MXTP02``), VMC (OSC), VRChat OSC trackers and Rokoko Studio Live (JSON v3) streams of
:mod:`mocapd.protocols.mvn`, ``.vmc``, ``.vrchat`` and ``.rokoko``.

Each sink owns one non-blocking, unconnected IPv4 UDP socket (opened in :meth:`start`, on the event loop) and
sends from :meth:`publish`, which the daemon calls from its tick loop: a send never blocks and never raises. A full
socket buffer (``EAGAIN``) or an error the kernel reports for an earlier datagram (``ECONNREFUSED`` after an ICMP
port-unreachable, ``ENETUNREACH``, ...) drops that datagram and is counted by errno name in :meth:`status`; UDP
has no delivery guarantee anyway and the next frame supersedes this one. Destinations come only from the
configuration (``[udp]`` in config.toml, validated by :mod:`mocapd.service.config.udp`).
"""

from __future__ import annotations

import errno
import os
import socket
from collections import Counter
from collections.abc import Collection, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from mocapd.core.skeleton import Skeleton
from mocapd.errors import InputError, MocapdError
from mocapd.pipeline.scheduler import PersonPose, PoseFrame
from mocapd.protocols.mvn import MvnEncoder
from mocapd.protocols.rokoko import RokokoActor, RokokoEncoder
from mocapd.protocols.subjects import SubjectSlots
from mocapd.protocols.vmc import VmcEncoder
from mocapd.protocols.vrchat import ROLES, VrChatEncoder

Destination = tuple[str, int]


class UdpSender:
    """A non-blocking UDP socket that counts what it sent and what it dropped."""

    def __init__(self, fileno: int | None = None) -> None:
        self._sock: socket.socket | None = None
        self._fileno = fileno  # an inherited UDP socket to send from (the camera demo's, made outside its netns)
        self.datagrams_sent = 0
        self.bytes_sent = 0
        self.errors: Counter[str] = Counter()

    def open(self) -> None:
        if self._sock is None:
            if self._fileno is not None:
                sock = socket.socket(fileno=os.dup(self._fileno))  # our own descriptor: close() leaves the original
            else:
                sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.setblocking(False)
            self._sock = sock

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def send(self, data: bytes, destination: Destination) -> bool:
        """Send one datagram now; False (and counted) when it was dropped."""
        if self._sock is None:
            self.errors["not_started"] += 1
            return False
        try:
            n = self._sock.sendto(data, destination)
        except BlockingIOError:
            self.errors["EAGAIN"] += 1
            return False
        except OSError as exc:  # ECONNREFUSED from an earlier ICMP error, ENETUNREACH, EMSGSIZE, ...
            self.errors[errno.errorcode.get(exc.errno or 0, "OSError")] += 1
            return False
        self.datagrams_sent += 1
        self.bytes_sent += n
        return True

    def counters(self) -> dict[str, Any]:
        return {"datagrams_sent": self.datagrams_sent, "bytes_sent": self.bytes_sent,
                "datagrams_dropped": sum(self.errors.values()), "errors": dict(self.errors)}  # fmt: skip


class _UdpPoseSink:
    """What the MVN and VMC sinks share: decimation, subject slots, the socket and the counters."""

    name = "udp"

    def __init__(
        self,
        destinations: Sequence[Destination],
        *,
        capacity: int,
        rate_divisor: int = 1,
        pinned: Mapping[str, int] | None = None,
        subjects: Collection[str] | None = None,
        release_after_frames: int = 120,
        fileno: int | None = None,
    ) -> None:
        if not destinations:
            raise InputError("a UDP sink needs at least one destination")
        if rate_divisor < 1:
            raise InputError(f"rate_divisor must be >= 1, got {rate_divisor}")
        self.destinations = [(str(h), int(p)) for h, p in destinations]
        self.rate_divisor = rate_divisor
        self.slots = SubjectSlots(capacity, pinned, subjects, release_after_frames)
        self.sender = UdpSender(fileno)
        self.frames_seen = 0
        self.frames_sent = 0
        self.skipped_subjects = 0  # non-finite pose or an encoder refusal (counted, never raised)

    async def start(self) -> None:
        self.sender.open()

    async def aclose(self) -> None:
        self.sender.close()

    def _due(self) -> bool:
        self.frames_seen += 1
        return (self.frames_seen - 1) % self.rate_divisor == 0

    def _subjects(self, frame: PoseFrame) -> list[tuple[int, PersonPose]]:
        """This frame's streamed subjects with their slots."""
        out = []
        for slot, person in zip(self.slots.assign([p.identity for p in frame.people]), frame.people, strict=True):
            if slot is None:
                continue
            if not np.all(np.isfinite(person.theta)):
                self.skipped_subjects += 1
                continue
            out.append((slot, person))
        return out

    def status(self) -> dict[str, Any]:
        """Counters for /status."""
        return {
            "destinations": [f"{h}:{p}" for h, p in self.destinations],
            "rate_divisor": self.rate_divisor,
            "frames_seen": self.frames_seen,
            "frames_sent": self.frames_sent,
            **self.sender.counters(),
            "skipped_subjects": self.skipped_subjects,
            "unassigned_subjects": self.slots.unassigned,
            "slots": self.slots.held(),
        }


class MvnUdpSink(_UdpPoseSink):
    """MVN network streaming: every streamed subject, as its own character id, to every destination.

    Parameters
    ----------
    skeleton : Skeleton
        The sized skeleton of the solved pose vectors.
    destinations : sequence of (host, port)
    rate_divisor : int
        Send every n-th output frame.
    character_ids : mapping identity -> character id, optional
        Pinned ids; other subjects get the lowest free id (0 .. 255).
    subjects : collection of identities, optional
        Stream only these (default: everyone).
    max_datagram_bytes : int
        Split a character over several datagrams above this size.
    release_after_frames : int
        Sent frames of absence after which an automatic character id is freed.
    """

    name = "mvn"

    def __init__(
        self,
        skeleton: Skeleton,
        destinations: Sequence[Destination],
        *,
        rate_divisor: int = 1,
        character_ids: Mapping[str, int] | None = None,
        subjects: Collection[str] | None = None,
        max_datagram_bytes: int = 1472,
        release_after_frames: int = 120,
        fileno: int | None = None,
    ) -> None:
        super().__init__(destinations, capacity=256, rate_divisor=rate_divisor, pinned=character_ids,
                         subjects=subjects, release_after_frames=release_after_frames, fileno=fileno)  # fmt: skip
        self.encoder = MvnEncoder(skeleton, max_datagram_bytes=max_datagram_bytes)

    def publish(self, frame: PoseFrame) -> None:
        if not self._due():
            return
        subjects = self._subjects(frame)
        chars = [(slot, p.theta) for slot, p in subjects]
        self.encoder.time_code_ms(frame.t_solve_ns)  # the stream's clock starts with the first frame, subjects or not
        if not chars:
            return
        try:
            datagrams = self.encoder.encode(frame.frame, frame.t_solve_ns, chars, [p.skeleton for _, p in subjects],
                                            [frame.pose_time_ns(p) for _, p in subjects],
                                            [p.hands for _, p in subjects])  # fmt: skip
        except MocapdError:
            self.skipped_subjects += len(chars)
            return
        for d in datagrams:
            for dest in self.destinations:
                self.sender.send(d, dest)
        self.frames_sent += 1


class VmcUdpSink(_UdpPoseSink):
    """VMC protocol: one avatar per destination; the subject in slot k drives the avatar at destination k.

    Parameters
    ----------
    skeleton : Skeleton
    destinations : sequence of (host, port)
        One per avatar (Marionette).
    rate_divisor : int
    subjects : sequence of identities, optional
        ``subjects[k]`` drives ``destinations[k]``; default: subjects take destinations in order of appearance.
    max_datagram_bytes : int
        Split a frame over several bundles above this size.
    release_after_frames : int
    """

    name = "vmc"

    def __init__(
        self,
        skeleton: Skeleton,
        destinations: Sequence[Destination],
        *,
        rate_divisor: int = 1,
        subjects: Sequence[str] | None = None,
        max_datagram_bytes: int = 1472,
        release_after_frames: int = 120,
        fileno: int | None = None,
    ) -> None:
        pinned = None if subjects is None else {s: k for k, s in enumerate(subjects)}
        super().__init__(destinations, capacity=len(destinations), rate_divisor=rate_divisor, pinned=pinned,
                         subjects=subjects, release_after_frames=release_after_frames, fileno=fileno)  # fmt: skip
        self.encoder = VmcEncoder(skeleton, max_datagram_bytes=max_datagram_bytes)

    def publish(self, frame: PoseFrame) -> None:
        if not self._due():
            return
        subjects = self._subjects(frame)
        t = frame.t_solve_ns
        self.encoder.seconds(t)  # the stream's clock starts with the first frame sent, subjects or not
        if not subjects:
            return
        thetas = np.stack([p.theta for _, p in subjects])
        tracked = [p.views > 0 or p.imus > 0 for _, p in subjects]
        try:
            bundles = self.encoder.encode_many(t, thetas, tracked, [p.skeleton for _, p in subjects],
                                               [frame.pose_time_ns(p) for _, p in subjects],
                                               [p.hands for _, p in subjects])  # fmt: skip
        except MocapdError:
            self.skipped_subjects += len(subjects)
            return
        for (slot, _), per_subject in zip(subjects, bundles, strict=True):
            for b in per_subject:
                self.sender.send(b, self.destinations[slot])
        self.frames_sent += 1


class VrChatUdpSink(_UdpPoseSink):
    """VRChat OSC trackers: one subject's body as up to eight trackers and a head, to one destination.

    Parameters
    ----------
    skeleton : Skeleton
    destination : (host, port)
        VRChat's OSC input (default port 9000).
    subject : str or None
        The identity streamed (``suit:<id>``, ``track:<k>``); None: the first subject to appear, until it has been
        gone for ``release_after_frames``.
    roles : sequence of str
        Trackers sent (:data:`mocapd.protocols.vrchat.ROLES`).
    user_height_m : float or None
        Positions are scaled by this over the skeleton's height (None: 1).
    rate_divisor, release_after_frames, fileno
        As for the other UDP streams.
    """

    name = "vrchat"

    def __init__(
        self,
        skeleton: Skeleton,
        destination: Destination,
        *,
        subject: str | None = None,
        roles: Sequence[str] = ROLES,
        user_height_m: float | None = None,
        rate_divisor: int = 1,
        release_after_frames: int = 120,
        fileno: int | None = None,
    ) -> None:
        pinned = None if subject is None else {subject: 0}
        subjects = None if subject is None else [subject]
        super().__init__([destination], capacity=1, rate_divisor=rate_divisor, pinned=pinned, subjects=subjects,
                         release_after_frames=release_after_frames, fileno=fileno)  # fmt: skip
        self.encoder = VrChatEncoder(skeleton, roles=roles, user_height_m=user_height_m)

    def publish(self, frame: PoseFrame) -> None:
        if not self._due():
            return
        for _, person in self._subjects(frame):
            try:
                bundle = self.encoder.encode(person.theta, person.skeleton)
            except MocapdError:
                self.skipped_subjects += 1
                continue
            self.sender.send(bundle, self.destinations[0])
            self.frames_sent += 1


ACTOR_COLOURS: tuple[tuple[int, int, int], ...] = (
    (255, 59, 48), (48, 209, 88), (10, 132, 255), (255, 214, 10),
    (191, 90, 242), (255, 159, 10), (100, 210, 255), (255, 55, 95),
)  # fmt: skip
"""Actor colours by slot: the live viewer's palette (mocapd/web/viewer.js)."""
MAX_ACTORS = 64


def colour(slot: int) -> tuple[int, int, int]:
    """The colour of a subject slot: the live viewer's, in its order."""
    return ACTOR_COLOURS[slot % len(ACTOR_COLOURS)]


class RokokoUdpSink(_UdpPoseSink):
    """Rokoko Studio Live: every streamed subject as an actor of one scene datagram per frame, to every destination.

    Actors come in the order of their slots (``subjects[k]`` is slot k; otherwise the lowest free slot in order of
    appearance), and a subject lost for less than ``release_after_frames`` (a listed one: always) stays in the scene
    at its last pose with ``hasBody`` false: the plugins' actor lists keep their order while the same people are
    tracked (the Blender add-on remembers an armature's actor by its position in that list).

    Parameters
    ----------
    skeleton : Skeleton
    destinations : sequence of (host, port)
        Rokoko plugins' receivers (default port 14043); each gets every frame.
    fps : float
        The output rate of the frames published (the stream's ``fps`` is it over ``rate_divisor``).
    rate_divisor : int
    subjects : sequence of identities, optional
        Stream only these, in this order (default: everyone, at most 64 at a time).
    actor_names : mapping identity -> actor name, optional
        The name each subject's actor has in the plugins (default: the identity).
    compression : str
        ``"lz4"`` or ``"none"`` (:mod:`mocapd.protocols.rokoko`).
    max_datagram_bytes : int
        Actors that would make the datagram larger are left out of that frame (counted).
    release_after_frames, fileno
        As for the other UDP streams.
    """

    name = "rokoko"

    def __init__(
        self,
        skeleton: Skeleton,
        destinations: Sequence[Destination],
        *,
        fps: float,
        rate_divisor: int = 1,
        subjects: Sequence[str] | None = None,
        actor_names: Mapping[str, str] | None = None,
        compression: str = "lz4",
        max_datagram_bytes: int = 32768,
        release_after_frames: int = 120,
        fileno: int | None = None,
    ) -> None:
        pinned = None if subjects is None else {s: k for k, s in enumerate(subjects)}
        super().__init__(destinations, capacity=max(MAX_ACTORS, len(pinned or ())), rate_divisor=rate_divisor,
                         pinned=pinned, subjects=subjects, release_after_frames=release_after_frames,
                         fileno=fileno)  # fmt: skip
        self.encoder = RokokoEncoder(skeleton, fps=fps / rate_divisor, compression=compression,
                                     max_datagram_bytes=max_datagram_bytes)  # fmt: skip
        self.actor_names = dict(actor_names or {})
        self._last: dict[str, RokokoActor] = {}  # identity -> its last actor, while it holds a slot
        self.oversize_actors = 0  # actors left out of a frame because the datagram would have been too large

    def publish(self, frame: PoseFrame) -> None:
        if not self._due():
            return
        present = {p.identity: (slot, p) for slot, p in self._subjects(frame)}
        held = self.slots.held()
        for ident in [i for i in self._last if i not in held]:  # released: the actor leaves the scene
            del self._last[ident]
        for ident, (slot, p) in present.items():
            self._last[ident] = RokokoActor(self.actor_names.get(ident, ident), p.theta, colour(slot), p.skeleton,
                                            hands=p.hands)  # fmt: skip
        actors = [
            a if ident in present else replace(a, tracked=False)
            for ident, a in sorted(self._last.items(), key=lambda kv: held[kv[0]])
        ]
        try:
            datagram = self.encoder.encode(frame.frame, frame.t_solve_ns, actors)
        except MocapdError:
            self.skipped_subjects += len(actors)
            return
        self.oversize_actors += len(actors) - datagram.actors
        for dest in self.destinations:
            self.sender.send(datagram.data, dest)
        self.frames_sent += 1

    def status(self) -> dict[str, Any]:
        return {**super().status(), "compression": self.encoder.compression, "oversize_actors": self.oversize_actors}

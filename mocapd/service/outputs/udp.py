"""The UDP pose streams of ``[udp]`` (MVN network streaming, VMC, VRChat OSC trackers, Rokoko Studio Live) as pose
sinks."""

from __future__ import annotations

from typing import TYPE_CHECKING

from mocapd.core.skeleton import Skeleton
from mocapd.service.config import Config
from mocapd.service.config.udp import RELEASE_AFTER_S

if TYPE_CHECKING:
    from mocapd.service.daemon import Daemon, PoseSink


def build_udp_sinks(config: Config, daemon: Daemon, fileno: int | None = None) -> list[PoseSink]:
    """The enabled UDP streams of ``config.udp`` as pose sinks for ``daemon`` (its rig's skeleton and rate)."""
    return udp_sinks(config, daemon.rig.skeleton, fileno)


def udp_sinks(config: Config, skeleton: Skeleton, fileno: int | None = None) -> list[PoseSink]:
    """The enabled UDP streams of ``config.udp`` for poses on ``skeleton`` (people carrying their own sized
    skeleton are sent on theirs), at ``config.daemon.output_rate_hz``; a replay has no daemon but the same needs.
    ``fileno``: an inherited UDP socket to send from (the camera demo runs in a private network namespace)."""
    from mocapd.io.udp_stream import MvnUdpSink, RokokoUdpSink, VmcUdpSink, VrChatUdpSink

    u = config.udp
    rate = config.daemon.output_rate_hz

    def release(divisor: int) -> int:
        return max(1, round(RELEASE_AFTER_S * rate / divisor))

    sinks: list[PoseSink] = []
    if u.mvn.enabled:
        m = u.mvn
        mvn = MvnUdpSink(
            skeleton,
            [(d.host, d.port) for d in m.destinations],
            rate_divisor=m.rate_divisor,
            character_ids=dict(m.character_ids),
            subjects=m.subjects,
            max_datagram_bytes=m.max_datagram_bytes,
            release_after_frames=release(m.rate_divisor),
            fileno=fileno,
        )
        sinks.append(mvn)
    if u.vmc.enabled:
        v = u.vmc
        vmc = VmcUdpSink(
            skeleton,
            [(d.host, d.port) for d in v.destinations],
            rate_divisor=v.rate_divisor,
            subjects=v.subjects,
            max_datagram_bytes=v.max_datagram_bytes,
            release_after_frames=release(v.rate_divisor),
            fileno=fileno,
        )
        sinks.append(vmc)
    if u.vrchat.enabled:
        c = u.vrchat
        vrchat = VrChatUdpSink(
            skeleton,
            (c.destination.host, c.destination.port),
            subject=c.subject or None,
            roles=c.trackers,
            user_height_m=c.user_height_m or None,
            rate_divisor=c.rate_divisor,
            release_after_frames=release(c.rate_divisor),
            fileno=fileno,
        )
        sinks.append(vrchat)
    if u.rokoko.enabled:
        r = u.rokoko
        rokoko = RokokoUdpSink(
            skeleton,
            [(d.host, d.port) for d in r.destinations],
            fps=rate,
            rate_divisor=r.rate_divisor,
            subjects=r.subjects,
            actor_names=dict(r.actor_names),
            compression=r.compression,
            max_datagram_bytes=r.max_datagram_bytes,
            release_after_frames=release(r.rate_divisor),
            fileno=fileno,
        )
        sinks.append(rokoko)
    return sinks


# ---------------------------------------------------------------------------------------------- helpers

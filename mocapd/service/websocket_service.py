"""Wires the WebSocket stream (and the viewer on its port) into the daemon from ``[websocket]``."""

from __future__ import annotations

from typing import TYPE_CHECKING

from mocapd.io.ws_server import ServerSettings, WebSocketStreamServer
from mocapd.protocols.ws_stream import StreamDescription, StreamOptions
from mocapd.service.config import Config

if TYPE_CHECKING:
    from mocapd.service.app import Daemon


def build_websocket_sinks(config: Config, daemon: Daemon) -> list[WebSocketStreamServer]:
    """The WebSocket stream server of ``config.websocket`` for ``daemon`` (none when disabled).

    Add the result to ``daemon.sinks`` before ``daemon.run()``; the server listens when the daemon starts its
    sinks. Every subject uses the rig's skeleton (key ``"default"``) until per-person skeletons exist.
    """
    ws = config.websocket
    if not ws.enabled:
        return []
    settings = ServerSettings(
        host=ws.host, port=ws.port, token=ws.token, max_clients=ws.max_clients, queue_messages=ws.queue_messages,
        max_message_bytes=ws.max_message_bytes, status_hz=ws.status_hz, viewer=ws.viewer,
        defaults=StreamOptions(encoding=ws.encoding, convention=ws.convention, globals=ws.globals),
    )  # fmt: skip
    description = StreamDescription(rate_hz=config.daemon.output_rate_hz, skeletons={"default": daemon.rig.skeleton})
    return [WebSocketStreamServer(settings, description, status=daemon.status, clock=daemon.clock)]

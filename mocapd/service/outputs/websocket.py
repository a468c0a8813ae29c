"""Wires the WebSocket stream (and the viewer on its port) into the daemon from ``[websocket]``."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from mocapd.core.skeleton import Skeleton
from mocapd.io.ws_server import Command, ServerSettings, WebSocketStreamServer
from mocapd.pipeline.camera_views import CameraViewOptions, CameraViews
from mocapd.protocols.ws_stream import StreamDescription, StreamOptions
from mocapd.service.config import Config
from mocapd.service.outputs.camera_views import attach_camera_views

if TYPE_CHECKING:
    from mocapd.service.daemon import Daemon


def build_websocket_sinks(
    config: Config, daemon: Daemon, sock: socket.socket | None = None
) -> list[WebSocketStreamServer]:
    """The WebSocket stream server of ``config.websocket`` for ``daemon`` (none when disabled).

    Add the result to ``daemon.sinks`` before ``daemon.run()``; the server listens when the daemon starts its
    sinks. Subjects on the rig's skeleton share the key ``"default"``; a body-sized person's own skeleton gets a
    key of its own, announced in a fresh hello before the first frame that uses it. The server also sends the
    viewer's camera panels: their taps are attached to ``daemon`` here.
    """
    ws = config.websocket
    if not ws.enabled:
        return []
    views = None
    if ws.cameras:
        options = CameraViewOptions(
            max_width=ws.camera_width, rate_hz=ws.camera_rate_hz, jpeg_quality=ws.camera_quality
        )
        views = attach_camera_views(daemon, options)
    # Status messages read the status server's snapshot: at any status_hz they add no renders of their own.
    status = daemon.http.snapshots.document
    commands: dict[str, Command] = {
        "reset_heading": lambda args, who: daemon.reset_heading(args.get("suit"), who, remote=True),
        "calibrate_imu": lambda args, who: daemon.calibrate_imu(args.get("suit"), args.get("pose"), who,
                                                                cancel=bool(args.get("cancel"))),
    }  # fmt: skip
    return websocket_sinks(config, daemon.rig.skeleton, status=status, clock=daemon.clock, sock=sock,
                           camera_views=views, output=daemon.scheduler.options.prediction.output,
                           commands=commands)  # fmt: skip


def websocket_sinks(
    config: Config,
    skeleton: Skeleton,
    *,
    status: Callable[[], Mapping[str, Any]] | None = None,
    clock: Callable[[], int] = time.monotonic_ns,
    sock: socket.socket | None = None,
    camera_views: CameraViews | None = None,
    output: str = "delayed",
    commands: Mapping[str, Command] | None = None,
) -> list[WebSocketStreamServer]:
    """The server of ``config.websocket`` for poses on ``skeleton`` without a daemon (a replay: no health), with
    camera panels from ``camera_views`` when given; ``output`` is the output mode the hello announces (the
    daemon's, or the recorded session's)."""
    ws = config.websocket
    if not ws.enabled:
        return []
    settings = ServerSettings(
        host=ws.host, port=ws.port, token=ws.token, max_clients=ws.max_clients, queue_messages=ws.queue_messages,
        max_message_bytes=ws.max_message_bytes, status_hz=ws.status_hz, viewer=ws.viewer, avatar=ws.avatar,
        defaults=StreamOptions(encoding=ws.encoding, convention=ws.convention, globals=ws.globals),
        allowed_hosts=config.web.allowed_hosts, allowed_origins=config.web.allowed_origins,
    )  # fmt: skip
    description = StreamDescription(config.daemon.output_rate_hz, {"default": skeleton}, output=output)
    server = WebSocketStreamServer(
        settings, description, status=status, clock=clock, sock=sock, camera_views=camera_views, commands=commands
    )
    return [server]

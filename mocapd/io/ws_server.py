"""The WebSocket pose stream server (a daemon pose sink) and the live web viewer page, on one port.

The protocol (messages, options, encoding) is :mod:`mocapd.protocols.ws_stream`; this module only moves its
messages. ``publish`` runs in the solver's tick loop and never waits: it wraps the frame in one shared
:class:`~mocapd.protocols.ws_stream.FrameEncoder` (each distinct option set is encoded once per frame). A client
that keeps up (nothing queued, its socket taking data) gets the bytes written at once, without a task switch
(websockets' ``broadcast``); any other client gets the frame appended to its bounded queue, which its own sender
task drains with awaited sends, encoding lazily through the shared encoder. A full queue drops its oldest message
and counts it: a client that reads slowly, or not at all, gets fewer frames while the tick loop and every other
client carry on.

Replies to client requests (hello, errors) go on a separate small control queue that is sent first and never
dropped; a client that floods requests without reading the replies is closed (1008).

Camera panels: with a :class:`~mocapd.pipeline.camera_views.CameraViews`, a client that subscribes with
``cameras: true`` gets ``camera`` messages. One task runs only while some client asks: at the highest rate asked
it assembles the panels and encodes their JPEGs in a worker thread (``asyncio.to_thread``: the copies,
projections and encoding never run on the event loop the solver ticks on), then queues each message for the
clients due one, on their ordinary bounded queues (a slow client loses its own oldest messages).

Plain HTTP GETs on the same port (no ``Upgrade: websocket``) serve the viewer (``/``, ``/viewer.js`` and
``/avatar.js`` from ``mocapd/web/``), the avatar view's model (``/avatar.vrm``, :mod:`mocapd.protocols.vrm_avatar`)
and its libraries (``/lib/...``, from the cache when set-up fetched them: :mod:`mocapd.io.viewer_libs`); everything
else is 404. With a token configured, both the page and the stream need it
(``?token=...`` in the URL or ``Authorization: Bearer ...``), checked in constant time; the page's own scripts,
libraries and model do not (the browser requests them without the page's query; they hold nothing of the session).

Every request, page or handshake, must name this machine in its ``Host`` (421 otherwise: DNS rebinding) and come
from no web page, the viewer's own origin or a configured one (403 otherwise: another site's page, a ``file://``
page), :mod:`mocapd.protocols.web_access`: so the poses, the camera images and the heading reset are out of reach
of pages from anywhere else.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import hmac
import logging
import socket
import time
from collections import deque
from collections.abc import Callable, Coroutine, Mapping
from http import HTTPStatus
from importlib import resources
from typing import Any
from urllib.parse import parse_qs

import cv2
import numpy as np
from websockets.asyncio.server import Server, ServerConnection, broadcast, serve
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response
from websockets.protocol import State

from mocapd.core.per_skeleton import skeleton_key
from mocapd.core.skeleton import Skeleton
from mocapd.errors import ConfigError, MocapdError, RateLimitError
from mocapd.io import ports
from mocapd.io.rejections import Rejections
from mocapd.io.viewer_libs import viewer_lib_files
from mocapd.pipeline.camera_views import CameraView, CameraViews, encode_jpeg
from mocapd.protocols.fingers import hands_of
from mocapd.protocols.vrm_avatar import default_avatar
from mocapd.protocols.web_access import WebAccess
from mocapd.protocols.ws_stream import (
    ClientSession,
    FrameEncoder,
    FramePoses,
    Message,
    StreamDescription,
    StreamOptions,
    camera_message,
)

log = logging.getLogger(__name__)

CONTROL_LIMIT = 32
"""Unsent replies a client may accumulate before it is closed as abusive."""
CLOSE_TIMEOUT_S = 1.0
"""How long a closing handshake may take before the TCP connection is dropped (a stalled client never answers)."""

WEB_FILES = {"/": ("viewer.html", "text/html; charset=utf-8"), "/viewer.js": ("viewer.js", "text/javascript"),
             "/avatar.js": ("avatar.js", "text/javascript")}  # fmt: skip
AVATAR_PATH = "/avatar.vrm"
"""The avatar view's model: ``[websocket] avatar``'s file, or :func:`mocapd.protocols.vrm_avatar.default_avatar`
built on the first request."""


def load_web_files() -> dict[str, tuple[str, bytes]]:
    """The viewer's files from package data, and the avatar view's libraries from the cache when set-up fetched
    them (:mod:`mocapd.io.viewer_libs`): URL path -> (content type, body)."""
    root = resources.files("mocapd.web")
    files = {path: (ctype, root.joinpath(name).read_bytes()) for path, (name, ctype) in WEB_FILES.items()}
    return files | viewer_lib_files()


def listen_error(host: str, port: int, exc: OSError) -> ConfigError:
    """What to tell the user when the stream's port cannot be bound (also where the socket is made elsewhere)."""
    return ports.listen_error("[websocket] port", host, port, exc)


MAX_SKELETONS = 64  # per-person skeletons kept for the hello before old ones are forgotten
SKELETON_KEEP_S = 10.0
"""A per-person skeleton no published frame has used for this long leaves the hello when a new one joins it (the
subject left, or was sized again). Each hello carries every skeleton it lists (0.2 ms to build with 3, 3.4 ms with 64
in JSON) and every new client and accepted subscribe gets one: kept until 64 piled up, the skeletons of the tracks
a long run had come and gone made every hello of its later minutes costlier. Not at once: a frame still queued for
a client may name the skeleton of a subject that has just left, after the new hello."""
#: the daemon's side of a client request: its arguments and who asked in, a JSON-able answer out
Command = Callable[[dict[str, Any], str], Any]


class _Client:
    """One connection: its protocol session, queues and counters."""

    def __init__(self, conn: ServerConnection, session: ClientSession, queue_messages: int, number: int) -> None:
        self.conn = conn
        self.session = session
        self.number = number
        self.queue: deque[FrameEncoder | Message] = deque(maxlen=queue_messages)
        self.control: deque[Message] = deque()
        self.wake = asyncio.Event()
        self.sent = 0
        self.dropped = 0
        self.sending = False
        self.camera_due_ns: dict[int, int] = {}  # camera -> earliest time of its next camera message

    def idle(self) -> bool:
        """Nothing queued or in flight and the socket takes data now: a message may be written directly."""
        return (
            not self.queue
            and not self.control
            and not self.sending
            and self.conn.protocol.state is State.OPEN
            and self.conn.transport.get_write_buffer_size() == 0
        )

    def push(self, item: FrameEncoder | Message) -> None:
        if len(self.queue) == self.queue.maxlen:
            self.dropped += 1  # deque(maxlen) drops the oldest on append
        self.queue.append(item)
        self.wake.set()


@dataclasses.dataclass(frozen=True)
class ServerSettings:
    """What :class:`WebSocketStreamServer` needs from ``[websocket]`` (see :mod:`mocapd.service.config.websocket`)."""

    host: str = "127.0.0.1"
    port: int = 0
    token: str = ""
    max_clients: int = 64
    queue_messages: int = 8
    max_message_bytes: int = 4096
    status_hz: float = 1.0
    viewer: bool = True
    defaults: StreamOptions = dataclasses.field(default_factory=StreamOptions)
    allowed_hosts: tuple[str, ...] = ()
    """More Host names than this machine's addresses (``[web] allowed_hosts``)."""
    allowed_origins: tuple[str, ...] = ()
    """More origins than the viewer's own whose pages may connect (``[web] allowed_origins``)."""
    avatar: str = ""
    """A VRM file (0.x or 1.0) the viewer's avatar view shows instead of mocapd's mannequin (``[websocket]
    avatar``; "" = the mannequin)."""


MAX_AVATAR_BYTES = 256 << 20
"""The largest avatar file the server reads (VRoid models are 10-60 MB)."""


def read_avatar(path: str) -> bytes:
    """The VRM file ``path`` (``[websocket] avatar``), read once at start; ConfigError with what is wrong."""
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_AVATAR_BYTES + 1)
    except OSError as e:
        raise ConfigError(f"[websocket] avatar: cannot read {path!r}: {e.strerror or e}") from e
    if len(data) > MAX_AVATAR_BYTES:
        raise ConfigError(f"[websocket] avatar: {path!r} is larger than {MAX_AVATAR_BYTES >> 20} MiB")
    if data[:4] != b"glTF":
        raise ConfigError(f"[websocket] avatar: {path!r} is not a VRM (a binary glTF file starts with 'glTF')")
    return data


class WebSocketStreamServer:
    """Streams published pose frames to WebSocket clients; serves the viewer page on the same port.

    Parameters
    ----------
    settings : ServerSettings
        Address, limits and client defaults.
    description : StreamDescription
        Output rate and skeletons, for the hello.
    status : callable, optional
        Returns the daemon's health document (``Daemon.status``) for status messages.
    clock : callable
        Host monotonic nanoseconds (the ``t_publish_ns`` of frames).
    sock : socket, optional
        Serve on this listening socket instead of binding ``settings.host:port``.
    commands : mapping, optional
        The daemon's side of client requests (``"reset_heading"`` -> a function of the request's arguments and
        who asked, e.g. "WebSocket client 3 from 127.0.0.1:40312").
    """

    name = "websocket"
    """Its section of the daemon's /status: ``sinks.websocket`` (:meth:`status`)."""

    def __init__(
        self,
        settings: ServerSettings,
        description: StreamDescription,
        *,
        status: Callable[[], Mapping[str, Any]] | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
        sock: socket.socket | None = None,
        camera_views: CameraViews | None = None,
        commands: Mapping[str, Command] | None = None,
    ) -> None:
        self.settings = settings
        self.camera_views = camera_views
        #: what clients may ask the daemon for (``reset_heading``), each called on the event loop with the request
        self.commands: Mapping[str, Command] = commands if commands is not None else {}
        bound = str(sock.getsockname()[0]) if sock is not None else settings.host
        #: the Host and Origin rules: this machine's names, the viewer's own origin and the configured ones
        self.access = WebAccess(bound, settings.allowed_hosts, settings.allowed_origins)
        if camera_views is not None:
            description = dataclasses.replace(
                description, cameras=tuple((c.name, c.width, c.height) for c in camera_views.cameras),
                camera_rate_hz=camera_views.options.rate_hz,
            )  # fmt: skip
        self._sock = sock  # an inherited listening socket (the camera demo's, bound outside its netns)
        # Per-person skeletons (body sizing) join the hello's skeletons as they appear: a live registry.
        self._skeletons: dict[str, Skeleton] = dict(description.skeletons)
        self._default_key = description.skeleton_key  # subjects on the rig's skeleton
        self._key_of: dict[str, str] = {}  # subject id -> skeleton key
        self._key_by_value: dict[bytes, str] = {}  # skeleton_key -> key in the hello (replayed poses are copies)
        self._key_used: dict[str, int] = {}  # key -> frames_published when a frame last used it
        #: frames after which an unused per-person skeleton may leave the hello (:data:`SKELETON_KEEP_S`)
        self.skeleton_keep_frames = max(1, round(SKELETON_KEEP_S * float(description.rate_hz)))
        self.description = dataclasses.replace(
            description, skeletons=self._skeletons, skeleton_of=self._skeleton_key,
            max_message_bytes=settings.max_message_bytes,
        )  # fmt: skip
        self._status = status
        self.clock = clock
        self.port = settings.port
        self.clients: set[_Client] = set()
        self.frames_published = 0
        self.non_finite = 0
        self.refused = {"unauthorised": 0, "full": 0, "not_found": 0, "bad_request": 0, "host": 0, "origin": 0}
        #: pages and handshakes refused for their Host or Origin (logged at most once per 10 s)
        self.foreign = Rejections("websocket server", log)
        #: client requests answered with an error, per error code (every client's, also after it left)
        self.rejected = Rejections("websocket", log)
        self._connections = 0
        self._latest_subjects: tuple[str, ...] = ()
        self._server: Server | None = None
        self._status_task: asyncio.Task[None] | None = None
        self._camera_task: asyncio.Task[None] | None = None
        self._camera_wake = asyncio.Event()  # a client changed its camera options: the loop's rate may change
        self.camera_messages = 0
        self._web = load_web_files() if settings.viewer else {}
        self._avatar = read_avatar(settings.avatar) if settings.viewer and settings.avatar else None

    # ------------------------------------------------------------------------------------------ sink API
    async def start(self) -> None:
        """Listen (port 0: any free port, then :attr:`port` is the bound one) and start status messages."""
        s = self.settings
        try:
            where: dict[str, Any] = {"sock": self._sock} if self._sock is not None else {"host": s.host, "port": s.port}
            self._server = await serve(
                self._handler, process_request=self._process_request, max_size=s.max_message_bytes,
                max_queue=4, compression=None, close_timeout=CLOSE_TIMEOUT_S, **where,
            )  # fmt: skip
        except OSError as exc:
            raise listen_error(s.host, s.port, exc) from exc
        self.port = int(next(iter(self._server.sockets)).getsockname()[1])
        if self._status is not None and s.status_hz > 0:
            self._status_task = asyncio.create_task(self._status_loop(1.0 / s.status_hz))

    def publish(self, frame: FramePoses) -> None:
        """Queue ``frame`` for every client whose options select it; never waits."""
        self.frames_published += 1
        if self._register_skeletons(frame) | self._announce_fingers(frame):
            for c in self.clients:  # a new skeleton: every client gets a fresh hello before the frame that uses it
                c.control.append(c.session.hello())
                c.wake.set()
        self._latest_subjects = tuple(p.identity for p in frame.people)
        wanted = [c for c in self.clients if c.session.wants(frame.frame)]
        for c in self.clients:
            c.session.latest_subjects = self._latest_subjects
        if not wanted:
            return  # nobody to convert for
        enc = FrameEncoder(frame, self.clock(), self.description)  # converted lazily, once
        direct: dict[tuple[Any, ...], list[_Client]] = {}
        for c in wanted:
            if c.idle():
                direct.setdefault(c.session.options.encoding_key, []).append(c)
            else:
                c.push(enc)  # behind a queue: its sender task writes it (or drops the oldest)
        # Fast path: clients keeping up get the bytes written now, synchronously (websockets' broadcast: no task
        # switch, no await), one encoding per option set. A socket that stops taking data sends that client down
        # the queued path above on the next frame, so nothing here can grow without bound.
        for group in direct.values():
            broadcast([c.conn for c in group], enc.message(group[0].session.options))
            for c in group:
                c.sent += 1
        if direct:
            self.non_finite += enc.non_finite

    def _announce_fingers(self, frame: FramePoses) -> bool:
        """With the first frame that has fingers the hello names the finger bones from then on (True: resend it);
        a stream that never has fingers keeps the hello it always had."""
        if self.description.fingers or not any(h is not None for h in hands_of(frame.people)):
            return False
        self.description = dataclasses.replace(self.description, fingers=True)
        for c in self.clients:
            c.session.description = self.description
        return True

    def _skeleton_key(self, subject_id: str) -> str:
        return self._key_of.get(subject_id) or self._default_key(subject_id)

    def _register_skeletons(self, frame: FramePoses) -> bool:
        """Give every subject's own skeleton a key; True when a skeleton is new (the hello must be resent)."""
        new = False
        for p in frame.people:
            sk = p.skeleton
            if sk is None:
                self._key_of.pop(p.identity, None)
                continue
            value = skeleton_key(sk)
            key = self._key_by_value.get(value)
            if key is None:
                self._forget_skeletons(frame)
                key = self._key_by_value[value] = f"{p.identity}#{self.frames_published}"
                self._skeletons[key] = sk
                new = True
            self._key_of[p.identity] = key
            self._key_used[key] = self.frames_published
        return new

    def _forget_skeletons(self, frame: FramePoses) -> None:
        """Before a new skeleton joins the hello: the per-person ones no frame has used for
        :attr:`skeleton_keep_frames` leave it, and at :data:`MAX_SKELETONS` every one this frame's people do not use
        (people come and go)."""
        live = {self._key_of.get(q.identity) for q in frame.people}
        full = len(self._key_by_value) >= MAX_SKELETONS
        for v, k in list(self._key_by_value.items()):
            unused = self.frames_published - self._key_used.get(k, 0) >= self.skeleton_keep_frames
            if k not in live and (full or unused):
                del self._key_by_value[v]
                self._skeletons.pop(k, None)
                self._key_used.pop(k, None)
        for identity in [i for i, k in self._key_of.items() if k not in self._skeletons]:
            del self._key_of[identity]  # subjects gone with their skeletons

    async def aclose(self) -> None:
        """Stop status messages, close every connection (going away, 1001) and stop listening."""
        if self._camera_task is not None:
            self._camera_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._camera_task
            self._camera_task = None
        if self._status_task is not None:
            self._status_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._status_task
            self._status_task = None
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(TimeoutError):  # a stalled client's close is bounded by CLOSE_TIMEOUT_S
                await asyncio.wait_for(self._server.wait_closed(), 2 * CLOSE_TIMEOUT_S + 1.0)
            self._server = None

    # ------------------------------------------------------------------------------------------ info
    @property
    def url(self) -> str:
        return f"ws://{self._host_for_url()}:{self.port}/"

    @property
    def viewer_url(self) -> str:
        q = f"?token={self.settings.token}" if self.settings.token else ""
        return f"http://{self._host_for_url()}:{self.port}/{q}"

    def _host_for_url(self) -> str:
        h = self.settings.host
        return f"[{h}]" if ":" in h else h

    def status(self) -> dict[str, Any]:
        """:meth:`stats`, for the daemon's /status."""
        return self.stats()

    def stats(self) -> dict[str, Any]:
        """Counters for status pages and benchmarks."""
        return {
            "clients": len(self.clients),
            "frames_published": self.frames_published,
            "non_finite_subjects": self.non_finite,
            "refused": dict(self.refused),
            "rejected_requests": self.rejected.as_dict(),
            "per_client": [
                {"client": c.number, "sent": c.sent, "dropped": c.dropped, "queued": len(c.queue),
                 "requests": c.session.requests, "errors": c.session.errors}
                for c in sorted(self.clients, key=lambda c: c.number)
            ],
        }  # fmt: skip

    # ------------------------------------------------------------------------------------------ HTTP side
    def _authorised(self, request: Request) -> bool:
        token = self.settings.token
        if not token:
            return True
        query = parse_qs(request.path.partition("?")[2])
        offered = query.get("token", [""])[0]
        auth = request.headers.get("Authorization", "")
        if auth.startswith("Bearer "):
            offered = auth[len("Bearer ") :]
        return hmac.compare_digest(offered.encode(), token.encode())

    @staticmethod
    def _needs_token(request: Request) -> bool:
        """Whether a configured token guards ``request``: the stream and the page do; the page's own scripts,
        libraries and avatar model do not (the browser fetches them without the page's query, so guarding them
        broke the viewer; they are the same files for everyone and carry nothing of the session, and the Host and
        Origin checks still apply to them)."""
        if request.headers.get("Upgrade", "").lower() == "websocket":
            return True
        return request.path.partition("?")[0] == "/"

    def _foreign(self, conn: ServerConnection, request: Request) -> Response | None:
        """The answer to a request from another site (a foreign Host: 421; a foreign Origin: 403) or without the
        token (401), counted; None for the rest."""
        host, origin = request.headers.get_all("Host"), request.headers.get_all("Origin")
        why = self.access.refusal(host, origin)
        if why is None:
            if self._authorised(request) or not self._needs_token(request):
                return None
            self.refused["unauthorised"] += 1
            return conn.respond(HTTPStatus.UNAUTHORIZED, "a token is required: ?token=... or Authorization: Bearer\n")
        self.refused[why] += 1
        self.foreign.reject(why, f"{request.path[:80]}: Host {host}, Origin {origin}, from {_peer(conn)}")
        if why == "host":
            return conn.respond(HTTPStatus.MISDIRECTED_REQUEST, "this server answers only to its own names\n")
        return conn.respond(HTTPStatus.FORBIDDEN, "pages from other sites may not connect\n")

    def _process_request(
        self, conn: ServerConnection, request: Request
    ) -> Response | Coroutine[Any, Any, Response | None] | None:
        if conn.protocol.eof_sent:
            # Bytes that are not a WebSocket frame followed the request head (a body, pipelined requests): the
            # protocol has already ended its side, and websockets (17.4) would then fail its own assertion sending
            # any answer ("unexpected internal error", a traceback per request). Drop the connection unanswered.
            self.refused["bad_request"] += 1
            return _drop(conn)
        refused = self._foreign(conn, request)
        if refused is not None:
            return refused
        if request.headers.get("Upgrade", "").lower() != "websocket":
            return self._get(conn, request.path.partition("?")[0])
        if len(self.clients) >= self.settings.max_clients:
            self.refused["full"] += 1
            return conn.respond(HTTPStatus.SERVICE_UNAVAILABLE, "too many clients\n")
        return None

    def _get(self, conn: ServerConnection, path: str) -> Response | Coroutine[Any, Any, Response]:
        """The answer to a plain GET of ``path``: a viewer file, the avatar's model, or 404."""
        page = self._web.get(path)
        if page is None and path == AVATAR_PATH and self._web:
            return _page(conn, "model/gltf-binary", self._avatar) if self._avatar is not None else _avatar(conn)
        if page is None:
            self.refused["not_found"] += 1
            return conn.respond(HTTPStatus.NOT_FOUND, "not found: the viewer is at /, the stream at ws://.../\n")
        return _page(conn, *page)

    # ------------------------------------------------------------------------------------------ WebSocket side
    async def _handler(self, conn: ServerConnection) -> None:
        if len(self.clients) >= self.settings.max_clients:  # handshakes in flight together passed the HTTP check
            self.refused["full"] += 1
            await conn.close(1013, "too many clients")
            return
        self._connections += 1
        session = ClientSession(self.description, self.settings.defaults)
        session.latest_subjects = self._latest_subjects
        client = _Client(conn, session, self.settings.queue_messages, self._connections)
        client.control.append(session.hello())
        self.clients.add(client)
        sender = asyncio.create_task(self._send_loop(client))
        client.wake.set()
        try:
            async for message in conn:
                error = session.receive_message(message)
                if error is not None:
                    self.rejected.reject(error.code, f"client {client.number}: {error}")
                client.control.extend(session.messages_to_send())
                for name, args in session.commands_received():
                    client.control.append(self._command(session, name, args, self._who(client, conn)))
                if len(client.control) > CONTROL_LIMIT:
                    await conn.close(1008, "too many unanswered requests")
                    break
                client.wake.set()
                if session.options.cameras and (self._camera_task is None or self._camera_task.done()):
                    self._camera_task = asyncio.create_task(self._camera_loop())
                elif error is None:
                    self._camera_wake.set()
        except ConnectionClosed:
            pass  # oversized message (1009), reset, or going away: this client only
        finally:
            self.clients.discard(client)
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sender

    @staticmethod
    def _who(client: _Client, conn: ServerConnection) -> str:
        """A client as the log names who asked: its number, address and the page's origin (if a page)."""
        origin = conn.request.headers.get("Origin") if conn.request is not None else None
        return f"WebSocket client {client.number} from {_peer(conn)}" + (f", page {origin[:80]!r}" if origin else "")

    def _command(self, session: ClientSession, name: str, args: dict[str, Any], who: str) -> Message:
        """Carry out a client's request for the daemon (a heading reset) and answer it."""
        handler = self.commands.get(name)
        if handler is None:
            return session.error("unsupported", f"{name}: this server has no daemon to ask (a replay?)")
        try:
            result = handler(args, who)
        except RateLimitError as exc:
            self.rejected.reject("rate_limited", f"{who}: {exc}")
            return session.error("rate_limited", str(exc))
        except MocapdError as exc:
            return session.error("failed", str(exc))
        return session.reply({"reset_heading": "heading_reset", "calibrate_imu": "imu_calibration"}.get(name, name),
                             result)  # fmt: skip

    async def _send_loop(self, client: _Client) -> None:
        conn = client.conn
        try:
            while True:
                await client.wake.wait()
                client.wake.clear()
                client.sending = True
                while client.control or client.queue:
                    if client.control:
                        msg = client.control.popleft()
                    else:
                        item = client.queue.popleft()
                        if isinstance(item, FrameEncoder):
                            first = not item.prepared
                            msg = item.message(client.session.options)
                            if first:
                                self.non_finite += item.non_finite
                        else:
                            msg = item
                    await conn.send(msg)  # waits only for this client's socket
                    client.sent += 1
                client.sending = False
        except ConnectionClosed:
            return

    async def _status_loop(self, period_s: float) -> None:
        assert self._status is not None
        while True:
            await asyncio.sleep(period_s)
            if not self.clients:
                continue
            health = self._status()
            now = self.clock()
            for c in list(self.clients):
                if c.session.options.status:
                    stream = {"clients": len(self.clients), "sent": c.sent, "dropped": c.dropped}
                    c.push(c.session.status(health, now, stream))

    # ------------------------------------------------------------------------------------------ camera panels
    def _camera_clients(self) -> list[_Client]:
        return [c for c in self.clients if c.session.options.cameras]

    async def _camera_loop(self) -> None:
        """Camera messages while some client asks for them (then the task ends)."""
        views = self.camera_views
        assert views is not None
        while True:
            self._camera_wake.clear()
            wanted = self._camera_clients()
            if not wanted:
                return
            rate = max(c.session.options.camera_rate_hz for c in wanted)
            panels = await asyncio.to_thread(_panels, views, views.now())
            now = self.clock()
            for panel, jpeg, size in panels:
                cache: dict[str, Message] = {}
                for c in self._camera_clients():
                    if now < c.camera_due_ns.get(panel.camera, 0):
                        continue
                    c.camera_due_ns[panel.camera] = now + round(0.9e9 / c.session.options.camera_rate_hz)
                    enc = c.session.options.encoding
                    if enc not in cache:
                        cache[enc] = camera_message(panel, jpeg, size, enc)
                    c.push(cache[enc])
                    self.camera_messages += 1
            # Until the next panel is due, or a client changes its options (one that asked for one message per
            # 100 s must not hold back the next client's 4 Hz).
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._camera_wake.wait(), 1.0 / rate)


def _peer(conn: ServerConnection) -> str:
    peer = conn.remote_address
    if isinstance(peer, tuple) and len(peer) >= 2:
        return f"[{peer[0]}]:{peer[1]}" if ":" in str(peer[0]) else f"{peer[0]}:{peer[1]}"
    return "?"


def _page(conn: ServerConnection, ctype: str, body: bytes) -> Response:
    """A 200 answer carrying ``body`` as ``ctype``, not to be cached (the page changes with the daemon)."""
    r = conn.respond(HTTPStatus.OK, "")
    del r.headers["Content-Type"]
    del r.headers["Content-Length"]
    r.headers["Content-Type"] = ctype
    r.headers["Content-Length"] = str(len(body))
    r.headers["Cache-Control"] = "no-store"
    return dataclasses.replace(r, body=body)


async def _avatar(conn: ServerConnection) -> Response:
    """The avatar view's model, built once per process in a worker thread (~30 ms: not on the solver's loop)."""
    return _page(conn, "model/gltf-binary", await asyncio.to_thread(default_avatar))


async def _drop(conn: ServerConnection) -> None:
    """Close a connection during its opening handshake without an answer (once it is closed, websockets sends
    none: the handshake finds the connection no longer connecting)."""
    conn.transport.abort()
    await conn.wait_closed()


def _panels(views: CameraViews, now_ns: int) -> list[tuple[CameraView, bytes | None, tuple[int, int]]]:
    """In a worker thread: the ready camera views with their JPEG bytes and the JPEG's (width, height)."""
    out = []
    for view in views.views(now_ns):
        snap = view.snapshot
        jpeg: bytes | None = None
        size = (0, 0)
        if snap is not None and snap.jpeg is not None:
            jpeg = snap.jpeg
            size = _jpeg_size(jpeg)
        elif snap is not None and snap.image is not None:
            jpeg = encode_jpeg(snap.image, views.options.jpeg_quality)
            size = (int(snap.image.shape[1]), int(snap.image.shape[0]))
        out.append((view, jpeg, size))
    return out


def _jpeg_size(jpeg: bytes) -> tuple[int, int]:
    """(width, height) of a JPEG (decoded header and all: recorded frames are small)."""
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_UNCHANGED)
    return (0, 0) if img is None else (int(img.shape[1]), int(img.shape[0]))

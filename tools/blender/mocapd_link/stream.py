"""The pose stream as the add-on sees it: a reader thread keeps the newest frame and the newest skeletons.

No Blender import here. The thread only parses; everything that touches Blender runs on Blender's main thread
(the add-on's timer), which takes the newest frame with :meth:`StreamLink.take`. A frame that arrives while an
older one waits replaces it: the armatures always show the newest pose, never a backlog.
"""

from __future__ import annotations

import json
import threading
from typing import Any

from .wsclient import Connection, ProtocolError

SUBSCRIBE = {"type": "subscribe", "encoding": "json", "convention": "native", "globals": False, "status": False}
"""What the add-on asks for: JSON (no msgpack in Blender's Python), mocapd's own axes (the armature object turns
Y-up into Blender's Z-up), local rotations only."""


class StreamLink:
    """A connection to the daemon's WebSocket stream (docs/streaming.md) read on a background thread.

    Attributes
    ----------
    skeletons : dict
        The newest hello's ``skeletons`` (key → ``bones``, ``parents``, ``offsets``).
    newest_frame : int
        Counter of the newest frame received (-1 before the first).
    received : int
        Frame messages received.
    error : str or None
        Why the connection ended, when it failed.
    """

    def __init__(self, url: str, subjects: list[str] | None = None) -> None:
        self.url = url
        self.request = dict(SUBSCRIBE, subjects=subjects)
        self.skeletons: dict[str, Any] = {}
        self.newest_frame = -1
        self.received = 0
        self.error: str | None = None
        self._latest: dict[str, Any] | None = None
        self._lock = threading.Lock()
        self._conn: Connection | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Connect (raises OSError or ProtocolError when the daemon cannot be reached) and start reading."""
        self._conn = Connection(self.url)
        self._conn.send_text(json.dumps(self.request))
        self._thread = threading.Thread(target=self._run, name="mocapd-link", daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _run(self) -> None:
        conn = self._conn
        assert conn is not None
        try:
            while True:
                msg = conn.receive()
                if msg is None:
                    return
                if isinstance(msg, bytes):  # the msgpack hello/frames sent before our subscribe took effect
                    continue
                self._handle(json.loads(msg))
        except (OSError, ProtocolError, ValueError) as exc:
            self.error = f"{type(exc).__name__}: {exc}"

    def _handle(self, msg: dict[str, Any]) -> None:
        kind = msg.get("type")
        if kind == "hello":
            with self._lock:
                self.skeletons = dict(msg.get("skeletons", {}))
        elif kind == "frame":
            with self._lock:
                self._latest = msg
                self.newest_frame = int(msg["frame"])
                self.received += 1
        elif kind == "error":
            self.error = f"server: {msg.get('code')}: {msg.get('message')}"

    def take(self) -> tuple[dict[str, Any] | None, dict[str, Any]]:
        """The newest frame not taken yet (or None) and the skeletons to pose it with."""
        with self._lock:
            frame, self._latest = self._latest, None
            return frame, self.skeletons

    def stop(self) -> None:
        if self._conn is not None:
            self._conn.close()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

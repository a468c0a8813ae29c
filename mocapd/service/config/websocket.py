"""The ``[websocket]`` section of config.toml: the WebSocket pose stream and the live web viewer on its port,
parsed once into a frozen dataclass (unknown keys and bad values are errors naming the key)."""

from __future__ import annotations

import ipaddress
import math
from dataclasses import dataclass
from typing import Any

from mocapd.errors import ConfigError
from mocapd.protocols.ws_stream import ENCODINGS, STREAM_CONVENTIONS

_KEYS = {
    "enabled", "host", "port", "token", "max_clients", "queue_messages", "max_message_bytes", "encoding",
    "convention", "globals", "status_hz", "viewer", "cameras", "camera_rate_hz", "camera_width", "camera_quality",
}  # fmt: skip


@dataclass(frozen=True, slots=True)
class WebSocketConfig:
    """``[websocket]``."""

    enabled: bool = True
    """Serve the stream (and the viewer) at all."""
    host: str = "127.0.0.1"
    """Listening address. Anything but loopback needs ``token``."""
    port: int = 8766
    """TCP port (0: any free port, printed at start-up)."""
    token: str = ""
    """Shared secret clients must present (``?token=`` or ``Authorization: Bearer``); "" = none (loopback only)."""
    max_clients: int = 64
    """Connections beyond this are refused with HTTP 503."""
    queue_messages: int = 8
    """Per-client queue of outgoing frame/status messages; when full, the oldest is dropped (and counted)."""
    max_message_bytes: int = 4096
    """Largest client message; a larger one closes that client's connection (close code 1009)."""
    encoding: str = "msgpack"
    """Default encoding of new clients: "msgpack" or "json"."""
    convention: str = "native"
    """Default coordinate convention of new clients."""
    globals: bool = False
    """Whether new clients get global joint positions by default."""
    status_hz: float = 1.0
    """Status messages per second (0: none)."""
    viewer: bool = True
    """Serve the live web viewer at http://host:port/."""
    cameras: bool = True
    """Offer camera views (the viewer's camera panels; sent only to clients that ask)."""
    camera_rate_hz: float = 4.0
    """Most camera messages per second per camera a client may ask for."""
    camera_width: int = 320
    """Width (pixels) the camera panels' frames are downscaled to."""
    camera_quality: int = 70
    """JPEG quality of the camera panels' frames (1..100)."""

    @property
    def loopback(self) -> bool:
        return is_loopback(self.host)


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback address (127.0.0.0/8, ::1) or ``localhost``."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def parse_websocket_config(t: dict[str, Any]) -> WebSocketConfig:
    """Validate a ``[websocket]`` table (already read from TOML)."""
    unknown = set(t) - _KEYS
    if unknown:
        raise ConfigError(f"unknown key(s) {sorted(unknown)} in [websocket]; allowed: {sorted(_KEYS)}")
    d = WebSocketConfig()
    out: dict[str, Any] = {}
    for key in ("enabled", "globals", "viewer", "cameras"):
        if key in t:
            if not isinstance(t[key], bool):
                raise ConfigError(f"websocket.{key} = {t[key]!r}; allowed: true or false")
            out[key] = t[key]
    for key in ("host", "token"):
        if key in t and not isinstance(t[key], str):
            raise ConfigError(f"websocket.{key} = {t[key]!r}; allowed: a string")
    host = t.get("host", d.host)
    if not host:
        raise ConfigError('websocket.host = ""; allowed: an IP address or "localhost"')
    out["host"] = host
    token = t.get("token", d.token)
    if not is_loopback(host) and len(token) < 16:
        raise ConfigError(
            f"websocket.host = {host!r} is not loopback: websocket.token must then be set (at least 16 characters), "
            "so only clients that know it can connect"
        )
    out["token"] = token
    for key, lo, hi in (("port", 0, 65535), ("max_clients", 1, 10_000), ("queue_messages", 1, 10_000),
                        ("max_message_bytes", 256, 1 << 20), ("camera_width", 16, 4096),
                        ("camera_quality", 1, 100)):  # fmt: skip
        if key in t:
            v = t[key]
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ConfigError(f"websocket.{key} = {v!r}; allowed: an integer {lo}..{hi}")
            out[key] = v
    if "encoding" in t:
        if t["encoding"] not in ENCODINGS:
            raise ConfigError(f"websocket.encoding = {t['encoding']!r}; allowed: {list(ENCODINGS)}")
        out["encoding"] = t["encoding"]
    if "convention" in t:
        if t["convention"] not in STREAM_CONVENTIONS:
            raise ConfigError(f"websocket.convention = {t['convention']!r}; allowed: {list(STREAM_CONVENTIONS)}")
        out["convention"] = t["convention"]
    if "status_hz" in t:
        v = t["status_hz"]
        if isinstance(v, bool) or not isinstance(v, int | float) or not (math.isfinite(v) and 0 <= v <= 60):
            raise ConfigError(f"websocket.status_hz = {v!r}; allowed: a number 0..60 (0 = no status messages)")
        out["status_hz"] = float(v)
    if "camera_rate_hz" in t:
        v = t["camera_rate_hz"]
        if isinstance(v, bool) or not isinstance(v, int | float) or not (math.isfinite(v) and 0.1 <= v <= 30):
            raise ConfigError(f"websocket.camera_rate_hz = {v!r}; allowed: a number 0.1..30")
        out["camera_rate_hz"] = float(v)
    return WebSocketConfig(**{**{k: getattr(d, k) for k in _KEYS}, **out})

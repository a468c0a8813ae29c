"""The ``[websocket]`` section of config.toml: the WebSocket pose stream and the live web viewer on its port."""

from __future__ import annotations

import ipaddress
import re
from typing import Annotated, Literal, Self

from pydantic import AfterValidator, Field, model_validator

from mocapd.service.config.schema import Allowed, PathStr, RuleError, Section, Text

MIN_TOKEN = 16
_TOKEN = re.compile(r"[!-~]*")  # printable ASCII, no spaces: it travels in a URL query or an HTTP header


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback address (127.0.0.0/8, ::1) or ``localhost``."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _host(value: str) -> str:
    if value != "localhost":
        try:
            ipaddress.ip_address(value)
        except ValueError:
            raise ValueError('allowed: an IP address or "localhost" (names are not resolved)') from None
    return value


def _token(value: str) -> str:
    if not _TOKEN.fullmatch(value):
        raise ValueError("allowed: printable ASCII characters without spaces")
    return value


Host = Annotated[Text, AfterValidator(_host), Allowed('an IP address or "localhost"')]
Token = Annotated[Text, AfterValidator(_token)]


class WebSocketConfig(Section):
    """``[websocket]``."""

    enabled: bool = True
    """Serve the stream (and the viewer) at all."""
    host: Host = "127.0.0.1"
    """Listening address. Anything but loopback needs ``token``."""
    port: int = Field(8766, ge=0, le=65535)
    """TCP port (0: any free port, printed at start-up)."""
    token: Token = ""
    """Shared secret clients must present (``?token=`` or ``Authorization: Bearer``); "" = none (loopback only)."""
    max_clients: int = Field(64, ge=1, le=10_000)
    """Connections beyond this are refused with HTTP 503."""
    queue_messages: int = Field(8, ge=1, le=10_000)
    """Per-client queue of outgoing frame/status messages; when full, the oldest is dropped (and counted)."""
    max_message_bytes: int = Field(4096, ge=256, le=1 << 20)
    """Largest client message; a larger one closes that client's connection (close code 1009)."""
    encoding: Literal["msgpack", "json"] = "msgpack"
    """Default encoding of new clients."""
    convention: Literal["native", "unity", "unreal", "mvn"] = "native"
    """Default coordinate convention of new clients."""
    globals: bool = False
    """Whether new clients get global joint positions by default."""
    status_hz: float = Field(1.0, ge=0.0, le=60.0)
    """Status messages per second (0: none)."""
    viewer: bool = True
    """Serve the live web viewer at http://host:port/."""
    avatar: PathStr = ""
    """A VRM file (0.x or 1.0, e.g. a VRoid model) for the viewer's avatar view; "" = mocapd's mannequin."""
    cameras: bool = True
    """Offer camera views (the viewer's camera panels; sent only to clients that ask)."""
    camera_rate_hz: float = Field(4.0, ge=0.1, le=30.0)
    """Most camera messages per second per camera a client may ask for."""
    camera_width: int = Field(320, ge=16, le=4096)
    """Width (pixels) the camera panels' frames are downscaled to."""
    camera_quality: int = Field(70, ge=1, le=100)
    """JPEG quality of the camera panels' frames."""

    @model_validator(mode="after")
    def _token_off_loopback(self) -> Self:
        if not is_loopback(self.host) and len(self.token) < MIN_TOKEN:
            raise RuleError(
                f"{{0}} is not loopback: {{1}} must then be set (at least {MIN_TOKEN} characters), so only "
                "clients that know it can connect",
                "host",
                "token",
                values=(self.host, "*" * len(self.token)),
            )
        return self

    @property
    def loopback(self) -> bool:
        return is_loopback(self.host)

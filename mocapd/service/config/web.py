"""The ``[web]`` section of config.toml: which Host names and page origins the daemon's web surface (the status
server and the WebSocket stream with its viewer) accepts besides its own (:mod:`mocapd.protocols.web_access`)."""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator, Field

from mocapd.protocols.web_access import HOST_NAME, normal_origin
from mocapd.service.config.schema import Allowed, Section, Seq, Text, unique

MAX_ENTRIES = 16


def _web_host(value: str) -> str:
    if not HOST_NAME.fullmatch(value.lower()) or value.replace(".", "").isdigit():
        raise ValueError("allowed: a host name (letters, digits, - and dots), without a port")
    return value.lower()


def _origin(value: str) -> str:
    norm = normal_origin(value)
    if norm is None or value.strip() != value or value.endswith("/"):
        raise ValueError('allowed: "http://host[:port]" or "https://host[:port]", without a path')
    return norm


WebHost = Annotated[
    Text, AfterValidator(_web_host), Allowed("a host name without a port, e.g. studio.local"),
    Field(examples=["studio.local"]),
]  # fmt: skip
Origin = Annotated[
    Text, AfterValidator(_origin), Allowed('an origin, e.g. "http://localhost:3000"'),
    Field(examples=["http://localhost:3000"]),
]  # fmt: skip


class WebConfig(Section):
    """``[web]``."""

    allowed_hosts: Annotated[Seq[WebHost], Field(max_length=MAX_ENTRIES), AfterValidator(unique)] = ()
    """More Host names to accept than loopback, ``localhost`` and the listening addresses (a name of this machine
    a browser uses, e.g. ``studio.local`` with ``[websocket] host = "0.0.0.0"``); any other name is refused."""
    allowed_origins: Annotated[Seq[Origin], Field(max_length=MAX_ENTRIES), AfterValidator(unique)] = ()
    """Web pages of these origins may also open the WebSocket (and read its poses and camera images); a page of
    any other origin, or a ``file://`` page, is refused."""

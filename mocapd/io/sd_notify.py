"""The systemd notification protocol, spoken directly: one datagram per message on ``$NOTIFY_SOCKET``.

``READY=1`` when serving, ``STATUS=...`` for ``systemctl status``, ``WATCHDOG=1`` at half the unit's
``WatchdogSec`` (``$WATCHDOG_USEC``), ``STOPPING=1`` at shutdown. Without ``$NOTIFY_SOCKET`` (not started by
systemd) every call is a no-op. An abstract socket is written ``@name`` in the variable.
"""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)


class SdNotifier:
    """Sends notifications to the service manager (if any)."""

    def __init__(self, environ: dict[str, str] | None = None) -> None:
        env = dict(os.environ if environ is None else environ)
        path = env.get("NOTIFY_SOCKET", "")
        self.address: str | None = ("\0" + path[1:] if path.startswith("@") else path) or None
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        for_us = not pid or pid == str(os.getpid())
        self.watchdog_s: float | None = int(usec) / 1e6 if usec.isdigit() and int(usec) > 0 and for_us else None
        self.sent = 0
        self.errors = 0
        self._sock: socket.socket | None = None

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, *fields: str) -> bool:
        """Send ``KEY=value`` fields as one message; False when there is no manager or the send failed
        (counted and logged: a daemon must not die because systemd went away)."""
        if self.address is None:
            return False
        if self._sock is None:
            # Non-blocking: a manager that does not read (its queue full) must never stall the daemon's event
            # loop, and with it the output and the stop (a send then fails with EAGAIN, counted like any other).
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC | socket.SOCK_NONBLOCK)
        try:
            self._sock.sendto("\n".join(fields).encode(), self.address)
        except OSError as exc:
            self.errors += 1
            log.warning("sd_notify to %r failed: %s", self.address, exc)
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

"""A port that cannot be bound, said in one line: which config key, which address, and which process holds it.

"Address already in use" alone sends a technician hunting; the kernel knows the answer. A socket bound to a port
appears in ``/proc/net/tcp`` (``tcp6``, ``udp``, ``udp6``) with its inode, and the process holding it has a file
descriptor ``/proc/<pid>/fd/N -> socket:[inode]``. Both are read only when a bind has failed. The tables show the
network namespace of the process reading them — the one the bind failed in. Processes of other users are not
readable without privileges: then the message says the holder could not be seen.
"""

from __future__ import annotations

import contextlib
import errno
import os
from dataclasses import dataclass
from pathlib import Path

from mocapd.errors import ConfigError

#: /proc/net/tcp state of a listening socket
_LISTEN = "0A"


@dataclass(frozen=True, slots=True)
class PortHolder:
    """A process holding a socket on the port."""

    pid: int
    command: str

    def __str__(self) -> str:
        return f"pid {self.pid} ({self.command})"


def _inodes(port: int, protocol: str, proc_root: Path) -> set[str]:
    """Inodes of the sockets bound to ``port`` (TCP: listening ones) in this network namespace."""
    found: set[str] = set()
    for table in (protocol, f"{protocol}6"):
        with contextlib.suppress(OSError):
            lines = (proc_root / "net" / table).read_text().splitlines()[1:]
            for line in lines:
                fields = line.split()
                if len(fields) < 10:
                    continue
                local, state, inode = fields[1], fields[3], fields[9]
                if int(local.rsplit(":", 1)[1], 16) != port or inode == "0":
                    continue
                if protocol == "tcp" and state != _LISTEN:
                    continue
                found.add(inode)
    return found


def _command(pid_dir: Path) -> str:
    with contextlib.suppress(OSError):
        argv = (pid_dir / "cmdline").read_bytes().split(b"\0")
        words = [a.decode(errors="replace") for a in argv if a]
        if words:
            text = " ".join(words)
            return text if len(text) <= 120 else text[:117] + "..."
    return "?"


def port_holders(port: int, protocol: str = "tcp", proc_root: Path = Path("/proc")) -> list[PortHolder]:
    """The processes holding a socket bound to ``port`` (``protocol`` "tcp" or "udp"), lowest pid first."""
    inodes = _inodes(port, protocol, proc_root)
    if not inodes:
        return []
    wanted = {f"socket:[{i}]" for i in inodes}
    holders = []
    for pid_dir in proc_root.iterdir():
        if not pid_dir.name.isdigit():
            continue
        try:
            fds = list((pid_dir / "fd").iterdir())
        except OSError:  # gone, or another user's
            continue
        for fd in fds:
            with contextlib.suppress(OSError):
                if os.readlink(fd) in wanted:
                    holders.append(PortHolder(int(pid_dir.name), _command(pid_dir)))
                    break
    return sorted(holders, key=lambda h: h.pid)


def holder_text(port: int, protocol: str = "tcp") -> str:
    """``in use by pid 1234 (mocapd run ...)``, or what can be said when the holder cannot be seen."""
    holders = port_holders(port, protocol)
    if holders:
        return "in use by " + ", ".join(str(h) for h in holders[:3]) + (" and others" if len(holders) > 3 else "")
    return "in use (by a process this user cannot see)"


def bind_failure(key: str, host: str, port: int, exc: OSError, protocol: str = "tcp") -> str:
    """One line for a failed bind of ``host:port`` configured by ``key`` (e.g. ``[daemon] http_port``)."""
    in_use = exc.errno == errno.EADDRINUSE
    why = f"address {holder_text(port, protocol)}" if in_use else exc.strerror or str(exc)
    verb = "listen on" if protocol == "tcp" else "bind udp"
    return f"cannot {verb} {host}:{port} ({key}): {why}; stop that program or choose another port (0: any free port)"


class ListenError(ConfigError):
    """A configured port could not be bound (the message names the key, the address and the holder)."""


def listen_error(key: str, host: str, port: int, exc: OSError, protocol: str = "tcp") -> ListenError:
    """:func:`bind_failure` as an exception (a :class:`~mocapd.errors.ConfigError`: the user's choice of port)."""
    return ListenError(bind_failure(key, host, port, exc, protocol))

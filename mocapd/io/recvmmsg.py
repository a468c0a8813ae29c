"""Read many UDP datagrams per call: Linux ``recvmmsg(2)`` through ctypes, for a receive thread.

Why hand-written: Python's ``socket`` has no ``recvmmsg``, and a thread that reads one datagram per
``recvfrom`` releases and re-takes the interpreter lock (GIL) around every call. While another thread computes (the
event loop solving a tick), a thread that wants the lock back gets it only every ``sys.getswitchinterval()``
(5 ms): one datagram per 5 ms, 200 a second, against the 1 600 a second of 16 SlimeVR trackers at 100 Hz.
:class:`BatchReader` blocks in one ``recvmmsg`` call with the lock released (ctypes releases it around foreign
calls) until at least one datagram is there (``MSG_WAITFORONE``), and returns every datagram already queued, up to
``batch``: one lock hand-over per batch. The wait is bounded by the socket's ``SO_RCVTIMEO`` (set here), so the
thread sees a stop request.

Each datagram carries the kernel's time of arrival (``SO_TIMESTAMPNS``, ``CLOCK_REALTIME``, turned into
``CLOCK_MONOTONIC`` nanoseconds with the two clocks' offset read right after the call): the datagrams of a batch
read after a stall arrived over that stall, and an IMU sample must be filed at the time it came, not at the time
it was read.

Where ``recvmmsg`` is not available (not Linux), it falls back to ``select`` and ``recvmsg`` until the socket is
empty (the lock is then handed over per datagram).

Layouts (x86-64 and aarch64 Linux, LP64): ``struct iovec {void *base; size_t len}``, ``struct msghdr {void *name;
socklen_t namelen; struct iovec *iov; size_t iovlen; void *control; size_t controllen; int flags}``, ``struct
mmsghdr {struct msghdr hdr; unsigned len}``; addresses in ``struct sockaddr_storage`` (128 bytes): family (u16,
host order) at 0, port (u16, network order) at 2, IPv4 address at 4, IPv6 address at 8.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import select
import socket
import struct
import sys
import time

MAX_DATAGRAM = 2048
"""Bytes read per datagram at most (SlimeVR datagrams are well under 1 KiB; a longer one is cut and caught as bad)."""
MSG_WAITFORONE = 0x10000

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux asm-generic; Python 3.11 does not name it
CONTROL = 64
"""Bytes of ancillary data per datagram (one ``struct cmsghdr`` of 16 bytes and a ``struct timespec``)."""

Datagram = tuple[bytes, tuple[str, int], int | None]
"""(payload, (host, port), arrival time in monotonic ns, or None when the kernel gave none)."""


class _Iovec(ctypes.Structure):
    _fields_ = [("base", ctypes.c_void_p), ("len", ctypes.c_size_t)]


class _Msghdr(ctypes.Structure):
    _fields_ = [
        ("name", ctypes.c_void_p),
        ("namelen", ctypes.c_uint32),
        ("iov", ctypes.POINTER(_Iovec)),
        ("iovlen", ctypes.c_size_t),
        ("control", ctypes.c_void_p),
        ("controllen", ctypes.c_size_t),
        ("flags", ctypes.c_int),
    ]


class _Mmsghdr(ctypes.Structure):
    _fields_ = [("hdr", _Msghdr), ("len", ctypes.c_uint)]


def _libc_recvmmsg() -> ctypes._CFuncPtr | None:  # type: ignore[name-defined]
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.recvmmsg
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.POINTER(_Mmsghdr), ctypes.c_uint, ctypes.c_int, ctypes.c_void_p]
    fn.restype = ctypes.c_int
    return fn


_RECVMMSG = _libc_recvmmsg()


class BatchReader:
    """Reads the datagrams of a bound UDP socket in batches (see the module docstring).

    The socket must stay in blocking mode (``settimeout(None)``, the default): the wait is bounded by the
    ``SO_RCVTIMEO`` that :meth:`read` sets from its time-out.
    """

    def __init__(self, sock: socket.socket, batch: int = 64, *, use_recvmmsg: bool = True) -> None:
        self.sock = sock
        self.batch = batch
        self.native = use_recvmmsg and _RECVMMSG is not None
        self._timeout_s: float | None = None
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            self.timestamps = True
        except OSError:
            self.timestamps = False
        if self.native:
            self._bufs = (ctypes.c_char * MAX_DATAGRAM * batch)()
            self._names = (ctypes.c_char * 128 * batch)()
            self._controls = (ctypes.c_char * CONTROL * batch)()
            self._iov = (_Iovec * batch)()
            self._msgs = (_Mmsghdr * batch)()
            for i in range(batch):
                self._iov[i].base = ctypes.addressof(self._bufs[i])
                self._iov[i].len = MAX_DATAGRAM
                h = self._msgs[i].hdr
                h.name = ctypes.addressof(self._names[i])
                h.iov = ctypes.pointer(self._iov[i])
                h.iovlen = 1
                h.control = ctypes.addressof(self._controls[i])

    def read(self, timeout_s: float) -> list[Datagram]:
        """The datagrams queued now, waiting up to ``timeout_s`` for the first; [] when none came.

        Raises OSError for a socket error (e.g. an ICMP error of an earlier send, or a closed socket).
        """
        if not self.native:
            return self._read_python(timeout_s)
        if timeout_s != self._timeout_s:
            sec = int(timeout_s)
            timeval = struct.pack("ll", sec, int((timeout_s - sec) * 1e6))
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, timeval)
            self._timeout_s = timeout_s
        for i in range(self.batch):
            h = self._msgs[i].hdr
            h.namelen = 128
            h.controllen = CONTROL
        assert _RECVMMSG is not None
        n = _RECVMMSG(self.sock.fileno(), self._msgs, self.batch, MSG_WAITFORONE, None)
        if n < 0:
            err = ctypes.get_errno()
            if err in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EINTR):
                return []
            raise OSError(err, os.strerror(err))
        offset = _realtime_offset_ns()
        out: list[Datagram] = []
        at = ctypes.string_at
        for i in range(n):
            m = self._msgs[i]
            control = at(ctypes.addressof(self._controls[i]), m.hdr.controllen)
            name = at(ctypes.addressof(self._names[i]), 128)
            out.append((at(ctypes.addressof(self._bufs[i]), m.len), _address(name), _arrival(control, offset)))
        return out

    def _read_python(self, timeout_s: float) -> list[Datagram]:
        ready, _, _ = select.select([self.sock], [], [], timeout_s)
        if not ready:
            return []
        raw: list[tuple[bytes, tuple[str, int], bytes | None]] = []
        while len(raw) < self.batch:
            try:
                data, ancillary, _, addr = self.sock.recvmsg(MAX_DATAGRAM, CONTROL, socket.MSG_DONTWAIT)
            except BlockingIOError:
                break
            stamp = next((d for level, kind, d in ancillary if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS),
                         None)  # fmt: skip
            raw.append((data, (str(addr[0]), int(addr[1])), stamp))
        offset = _realtime_offset_ns()
        return [(data, addr, None if ts is None else _timespec_ns(ts) - offset) for data, addr, ts in raw]


def _realtime_offset_ns() -> int:
    """CLOCK_REALTIME - CLOCK_MONOTONIC now (ns): the kernel stamps datagrams on the first, mocapd runs on the
    second."""
    return time.clock_gettime_ns(time.CLOCK_REALTIME) - time.monotonic_ns()


def _timespec_ns(data: bytes) -> int:
    sec, nsec = struct.unpack_from("qq", data)
    return int(sec) * 1_000_000_000 + int(nsec)


def _arrival(control: bytes, offset_ns: int) -> int | None:
    """The ``SCM_TIMESTAMPNS`` time (monotonic ns) in one datagram's ancillary data (``struct cmsghdr {size_t len;
    int level; int type;}`` then the data, 8-byte aligned), or None."""
    pos = 0
    while pos + 16 <= len(control):
        length, level, kind = struct.unpack_from("Nii", control, pos)
        if length < 16:
            return None
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and pos + 32 <= len(control):
            return _timespec_ns(control[pos + 16 : pos + 32]) - offset_ns
        pos += (length + 7) & ~7
    return None


def _address(name: bytes) -> tuple[str, int]:
    """(host, port) of a ``struct sockaddr_storage`` holding an IPv4 or IPv6 address."""
    family = int.from_bytes(name[0:2], sys.byteorder)
    port = int.from_bytes(name[2:4], "big")
    if family == socket.AF_INET6:
        return socket.inet_ntop(socket.AF_INET6, name[8:24]), port
    return socket.inet_ntop(socket.AF_INET, name[4:8]), port

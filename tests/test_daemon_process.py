"""The daemon as a process: sd_notify over a real datagram socket, SIGTERM shutdown within 2 s with the recorded
session flushed and closed, and the sd_notify client on its own."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

from mocapd.io.sd_notify import SdNotifier
from mocapd.io.session import open_session
from tests.rigs import synthetic_toml, write

REPO = Path(__file__).resolve().parents[1]


def _recv_until(sock: socket.socket, needle: str, timeout: float) -> list[str]:
    got: list[str] = []
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        sock.settimeout(max(0.01, end - time.monotonic()))
        try:
            msg = sock.recv(4096).decode()
        except TimeoutError:
            break
        got.append(msg)
        if needle in msg.split("\n"):
            return got
    raise AssertionError(f"no {needle} within {timeout} s; got {got}")


def test_sigterm_stops_the_daemon_within_two_seconds_with_the_session_closed(tmp_path: Path) -> None:
    notify_path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(notify_path))
    session_dir = tmp_path / "session"
    env = {**os.environ, "NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": "1000000"}
    env.pop("WATCHDOG_PID", None)
    cmd = [sys.executable, "-m", "mocapd", "demo", "--synthetic", "--http-port", "0",
           "--record", str(session_dir)]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    assert proc.stdout is not None
    stdout = proc.stdout
    threading.Thread(target=lambda: lines.extend(stdout), daemon=True).start()
    try:
        _recv_until(sock, "READY=1", 180)
        messages = _recv_until(sock, "WATCHDOG=1", 5)  # pinged at half of WatchdogSec
        # More than 30 frames published before the stop (half a second at 60 Hz; a loaded machine takes longer).
        _wait_published(_status_url(lines, 10.0), 31, 60.0)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=10)
        elapsed = time.monotonic() - t0
        messages += _recv_until(sock, "STOPPING=1", 1)
    finally:
        if proc.poll() is None:
            proc.kill()
        sock.close()
    time.sleep(0.2)  # the reader thread takes the last lines
    out = "".join(lines)
    assert rc == 0, out
    assert elapsed < 2.0, f"shutdown took {elapsed:.2f} s"
    assert "ready: status http://127.0.0.1:" in out
    session = open_session(session_dir)
    frames = session.poses()
    assert session.closed_cleanly and not session.reports["poses"].damaged  # flushed and closed, not cut
    # every published frame is in the session
    assert len(frames) > 30 and [f.frame for f in frames] == list(range(1, len(frames) + 1))
    assert len(session.imu()) > 100 and len(session.keypoints()) > 30
    assert session.manifest["writer"]["dropped"] == 0
    # a status with READY=1 / STOPPING=1 ("STOPPING=1\nSTATUS=stopping"), or the daemon's per-second line
    assert any(line.startswith("STATUS=") for m in messages for line in m.splitlines())


def _status_url(lines: list[str], timeout: float) -> str:
    """The /status URL the daemon prints once it is ready."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for line in list(lines):
            if line.startswith("ready: status http://"):
                return line.split()[2]
        time.sleep(0.05)
    raise AssertionError(f"no status URL printed: {''.join(lines)}")


def _wait_published(status_url: str, frames: int, timeout: float) -> None:
    """Until the daemon's /status says it has published at least ``frames`` frames."""
    end = time.monotonic() + timeout
    published = 0
    while time.monotonic() < end:
        with urllib.request.urlopen(status_url, timeout=5) as r:
            published = json.loads(r.read())["output"]["frames"]
        if published >= frames:
            return
        time.sleep(0.1)
    raise AssertionError(f"{published} frames published in {timeout} s, waited for {frames}")


def test_notifier_speaks_the_datagram_protocol(tmp_path: Path) -> None:
    path = tmp_path / "n.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    n = SdNotifier({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "3000000", "WATCHDOG_PID": str(os.getpid())})
    assert n.enabled and n.watchdog_s == 3.0
    assert n.notify("READY=1", "STATUS=hello")
    assert sock.recv(100) == b"READY=1\nSTATUS=hello"
    sock.close()
    assert not n.notify("WATCHDOG=1")  # the manager went away: counted, not raised
    assert n.errors == 1
    n.close()
    abstract = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    name = f"mocapd-test-{os.getpid()}"
    abstract.bind("\0" + name)
    m = SdNotifier({"NOTIFY_SOCKET": "@" + name, "WATCHDOG_USEC": "5", "WATCHDOG_PID": "1"})
    assert m.watchdog_s is None  # the watchdog is someone else's
    assert m.notify("STOPPING=1") and abstract.recv(100) == b"STOPPING=1"
    abstract.close()
    m.close()
    assert not SdNotifier({}).notify("READY=1")


def test_run_serves_until_sigint(tmp_path: Path) -> None:
    notify_path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(notify_path))
    env = {**os.environ, "NOTIFY_SOCKET": str(notify_path)}
    env.pop("WATCHDOG_USEC", None)
    config = write(tmp_path / "synthetic.toml", synthetic_toml())
    cmd = [sys.executable, "-m", "mocapd", "run", "--config", str(config), "--verbose"]
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        ready = _recv_until(sock, "READY=1", 180)
        assert any("STATUS=serving http://127.0.0.1:" in m for m in ready)
        time.sleep(1.5)
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=10)
        _recv_until(sock, "STOPPING=1", 1)
    finally:
        if proc.poll() is None:
            proc.kill()
        sock.close()
    out = proc.stdout.read() if proc.stdout else ""
    assert rc == 0, out
    assert "output" in out and "people [" in out  # the per-second status line


def test_a_manager_that_does_not_read_never_blocks_the_notifier(tmp_path: Path) -> None:
    """A full notification queue (a service manager, or a test, that stopped reading) fails the send, counted:
    a blocking send held a daemon's event loop, and with it its stop, for as long as nobody read (issue 32)."""
    path = tmp_path / "n.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    n = SdNotifier({"NOTIFY_SOCKET": str(path)})
    t0 = time.monotonic()
    sent = [n.notify(f"STATUS={'x' * 1000} {i}") for i in range(2000)]  # far more than a datagram queue holds
    assert time.monotonic() - t0 < 5.0
    assert sent[0] and not sent[-1] and n.errors == sent.count(False) > 0
    n.close()
    sock.close()

"""Camera networks without hardware: links of fake GigE Vision cameras behind veth pairs, for discovery tests.

Must run inside a private network namespace (``unshare -rn``): it creates network interfaces. Each link is a veth
pair. Its host end (``gige1``...) stays in this namespace with address ``10.77.<k>.1/24``; its other end goes into
a network namespace of its own, where the link's fake cameras (:mod:`mocapd.sim.fake_gige`, one process each)
serve at ``10.77.<k>.2``, ``.3`` ... So, as on a real rig, a discovery broadcast sent on one link reaches only the
cameras on that link, and each link's packets can be counted on its host end
(:meth:`FakeGigENetwork.tx_packets`).

IPv6 is switched off in these namespaces first: its autoconfiguration chatter (router solicitations, DAD) would
add packets on the links that nobody sent on purpose.

::

    with FakeGigENetwork(video, {"gige1": ["CAM-A", "CAM-B"], "gige2": ["CAM-C"]}) as net:
        net.cameras  # [FakeCameraOnLink(link="gige1", serial="CAM-A", address="10.77.1.2"), ...]
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import subprocess
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import psutil

from mocapd.errors import DeviceError
from mocapd.io import lifecycle
from mocapd.sim.fake_gige import server_command

START_TIMEOUT_S = 60.0


@dataclass(frozen=True, slots=True)
class FakeCameraOnLink:
    """One fake camera: the host-side interface it is reached through, its serial and address."""

    link: str
    serial: str
    address: str


def _ip(*args: str, netns_pid: int | None = None) -> None:
    cmd = ["ip", *args] if netns_pid is None else ["nsenter", f"--net=/proc/{netns_pid}/ns/net", "ip", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise DeviceError(f"{' '.join(cmd)} failed: {proc.stderr.strip()}")


def _disable_ipv6(netns_pid: int | None = None) -> None:
    # /proc/sys/net shows the namespace of the process that opens it, hence nsenter for the cameras' side.
    script = (
        "for f in /proc/sys/net/ipv6/conf/all/disable_ipv6 /proc/sys/net/ipv6/conf/default/disable_ipv6; "
        'do [ -w "$f" ] && echo 1 > "$f"; done; true'
    )
    cmd = ["sh", "-c", script]
    if netns_pid is not None:
        cmd = ["nsenter", f"--net=/proc/{netns_pid}/ns/net", *cmd]
    subprocess.run(cmd, check=True)


def _own_netns() -> str:
    return os.readlink("/proc/self/ns/net")


class FakeGigENetwork:
    """Links of fake GigE Vision cameras (see the module docstring).

    Parameters
    ----------
    video : Path
        Video every camera serves (see :mod:`mocapd.sim.fake_gige`).
    links : mapping of str to sequence of str
        Host-side interface name -> serial numbers of the cameras on that link.
    size : str or None
        ``WIDTHxHEIGHT`` the frames are resized to (small keeps start-up fast).
    max_frames : int
        Frames of the video served.
    """

    def __init__(
        self, video: Path, links: Mapping[str, Sequence[str]], *, size: str | None = "64x48", max_frames: int = 2
    ) -> None:
        self.video = video
        self.links = {name: list(serials) for name, serials in links.items()}
        self.size = size
        self.max_frames = max_frames
        self.cameras: list[FakeCameraOnLink] = []
        self._holders: list[subprocess.Popen[str]] = []
        self._servers: list[subprocess.Popen[str]] = []

    def __enter__(self) -> FakeGigENetwork:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def start(self) -> None:
        """Create the links and start every camera; returns once all serve.

        Raises
        ------
        DeviceError
            If this namespace has interfaces other than lo (it is not a fresh private one: nothing is changed),
            or a link or camera cannot be made.
        """
        present = sorted(set(psutil.net_if_addrs()) - {"lo"})
        if present:
            raise DeviceError(
                f"FakeGigENetwork must run in a fresh private network namespace (unshare -rn); this one has {present}"
            )
        _disable_ipv6()
        _ip("link", "set", "lo", "up")
        for k, (link, serials) in enumerate(self.links.items(), start=1):
            pid = self._camera_namespace()
            peer = f"cam{k}"
            _ip("link", "add", link, "type", "veth", "peer", "name", peer)
            _ip("link", "set", peer, "netns", str(pid))
            _ip("addr", "add", f"10.77.{k}.1/24", "dev", link)
            _ip("link", "set", link, "up")
            _ip("link", "set", "lo", "up", netns_pid=pid)
            on_link = [FakeCameraOnLink(link, serial, f"10.77.{k}.{i}") for i, serial in enumerate(serials, start=2)]
            for cam in on_link:
                _ip("addr", "add", f"{cam.address}/24", "dev", peer, netns_pid=pid)
            _ip("link", "set", peer, "up", netns_pid=pid)
            for cam in on_link:
                self._start_server(cam, pid)
            self.cameras += on_link
        for proc, cam in zip(self._servers, self.cameras, strict=True):
            self._wait_ready(proc, cam)

    def _camera_namespace(self) -> int:
        """A process holding a new network namespace (the far side of one link)."""
        holder = subprocess.Popen(lifecycle.guarded_command(["unshare", "-n", "sleep", "infinity"]), text=True)
        self._holders.append(holder)
        own = _own_netns()
        for _ in range(500):  # unshare(2) happens right after exec: a few ms
            with contextlib.suppress(FileNotFoundError, PermissionError):
                if os.readlink(f"/proc/{holder.pid}/ns/net") != own:
                    _disable_ipv6(holder.pid)
                    return holder.pid
            if holder.poll() is not None:
                break
            time.sleep(0.01)
        raise DeviceError("could not create a network namespace for fake cameras (unshare -n failed)")

    def _start_server(self, cam: FakeCameraOnLink, netns_pid: int) -> None:
        cmd = server_command(self.video, cam.address, self.max_frames, "Mono8", serial=cam.serial, size=self.size)
        self._servers.append(
            subprocess.Popen(
                ["nsenter", f"--net=/proc/{netns_pid}/ns/net", *cmd],
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
            )
        )

    @staticmethod
    def _wait_ready(proc: subprocess.Popen[str], cam: FakeCameraOnLink) -> None:
        assert proc.stdout is not None
        # The server prints one JSON line when it serves, or exits.
        readable, _, _ = select.select([proc.stdout], [], [], START_TIMEOUT_S)
        line = proc.stdout.readline() if readable else ""
        try:
            ready = json.loads(line).get("ready") is True
        except json.JSONDecodeError:
            ready = False
        if not ready:
            raise DeviceError(f"fake camera {cam.serial} at {cam.address} did not start (exit {proc.poll()})")

    @staticmethod
    def tx_packets(link: str) -> int:
        """Packets sent so far out of host-side interface ``link`` (the kernel's counter, from /proc/net/dev:
        unlike /sys, which shows the namespace it was mounted in, /proc/net shows this process's)."""
        return int(psutil.net_io_counters(pernic=True)[link].packets_sent)

    def close(self) -> None:
        """Stop the cameras and the namespaces (the links go with them)."""
        for proc in [*self._servers, *self._holders]:
            if proc.poll() is None:
                proc.terminate()
        for proc in [*self._servers, *self._holders]:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            if proc.stdout is not None:
                proc.stdout.close()
        self._servers.clear()
        self._holders.clear()

"""A multi-camera GigE Vision rig without hardware: fake cameras serving videos, captured by mocapd.

Runs inside a private network namespace (re-executes itself under ``unshare -rn`` unless ``--in-netns``), gives
lo one address per camera (127.0.0.1, 127.0.0.2, ...), starts one :mod:`mocapd.sim.fake_gige` server process per
video, captures every camera with :class:`mocapd.io.aravis_camera.AravisSource` (the real capture path) for
``--duration`` seconds and prints one JSON object:

* per camera: frames captured, transport counters (missing frames, resent packets, bad buffers), whether every
  frame is bit-identical to the decoded source frame it should be (in order; computed by
  :func:`reference_image`, independently of mocapd's pixel conversion), whether host/camera timestamps and
  frame ids increase, latency statistics (ms) and the capture thread's CPU use (% of one core);
* the fake servers' CPU use;
* with ``--read-hz R``: a reader thread (the detector's stand-in) takes the newest frame of every camera R times a
  second; per camera the frames it read and the conversions the ring did (a lazy ring converts only those), and
  the reader thread's CPU (where the conversions of a lazy ring now run).

Used by the integration tests and by ``mocapd bench capture`` (:mod:`mocapd.service.bench.capture`)::

    python -m mocapd.sim.fake_rig --videos a.mp4 b.mp4 --max-frames 20 --duration 3 --fps 30 --format RGB8
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hashlib
import json
import math
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mocapd.io.aravis_camera import AravisCameraConfig, AravisSource
from mocapd.io.pixels import pixel_format
from mocapd.pipeline.frame_ring import FrameRef, FrameRing
from mocapd.sim.fake_gige import add_loopback_aliases, load_video_rgb, server_command

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int, tid: int | None = None) -> float:
    """CPU time of a process (all its threads) or of one of its threads, from /proc, in seconds (NaN if gone).

    A thread's from its ``schedstat`` (time on a CPU, nanoseconds): ``stat``'s user + system time is in whole clock
    ticks (10 ms), and read a thread that ran 9 ms in a window as 0 (an Aravis stream thread at 10 fps on a fast
    machine did). A process's from its ``stat``, which sums every thread, ended ones included (its ``schedstat`` is
    its main thread's alone); likewise a thread's where the kernel has no schedstat.
    """
    base = f"/proc/{pid}/task/{tid}" if tid is not None else f"/proc/{pid}"
    gone = (FileNotFoundError, ProcessLookupError)
    try:
        if tid is not None:
            with contextlib.suppress(*gone):  # ended, or no schedstat: the stat below says which
                return int(Path(f"{base}/schedstat").read_text().split()[0]) / 1e9
        fields = Path(f"{base}/stat").read_text().rsplit(")", 1)[1].split()
    except gone:  # the thread ended (camera reopened): no figure rather than a wrong one
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def cpu_by_thread_name(capture_tids: set[int]) -> dict[str, float]:
    """CPU seconds of this process's threads summed by kind: mocapd capture threads, Aravis stream threads
    (``arv_gv_stream``), the rest (``python``: event loop, checks)."""
    out: dict[str, float] = {}
    for task in Path(f"/proc/{os.getpid()}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
        except FileNotFoundError:
            continue
        name = "mocapd_capture" if int(task.name) in capture_tids else name
        out[name] = out.get(name, 0.0) + cpu_seconds(os.getpid(), int(task.name))
    return {k: v for k, v in out.items() if not math.isnan(v)}  # threads that ended meanwhile


@dataclass
class CameraCheck:
    """What the rig checks for one camera while it captures."""

    hashes: list[str]
    frames: int = 0
    identical: int = 0
    in_order: int = 0
    first_index: int | None = None
    sent_index: int = 0
    overtaken: int = 0
    debug_frames: list[Any] | None = None
    debug: list[dict[str, Any]] = field(default_factory=list)
    last: FrameRef | None = None
    host_increasing: bool = True
    device_increasing: bool = True
    ids_increasing: bool = True
    mismatched: list[int] = field(default_factory=list)
    out_of_order: list[tuple[int, int]] = field(default_factory=list)

    def add(self, ref: FrameRef, image: np.ndarray[Any, Any] | None, verify: bool) -> None:
        self.frames += 1
        if self.last is not None:
            self.host_increasing &= ref.host_ns > self.last.host_ns
            self.device_increasing &= ref.device_ns > self.last.device_ns
            # GigE Vision block ids are 16-bit and skip 0 when they wrap: 65535 is followed by 1.
            step = (ref.frame_id - self.last.frame_id) % 65535
            self.ids_increasing &= step == 1
            self.sent_index += step
        self.last = ref
        if not verify:
            return
        if image is None:  # the capture thread overwrote the slot before the check could copy it
            self.overtaken += 1
            return
        digest = hashlib.blake2b(image.tobytes(), digest_size=16).hexdigest()
        if digest not in self.hashes:
            self.mismatched.append(ref.seq)
            if self.debug_frames:
                flat = image.reshape(-1)
                eq = [float(np.mean(flat == f.reshape(-1))) for f in self.debug_frames]
                best = int(np.argmax(eq))
                diff = np.flatnonzero(flat != self.debug_frames[best].reshape(-1))
                others = [
                    j
                    for j, f in enumerate(self.debug_frames)
                    if j != best and np.array_equal(flat[diff], f.reshape(-1)[diff])
                ]
                self.debug.append(
                    {
                        "seq": ref.seq,
                        "fid": ref.frame_id,
                        "best": best,
                        "best_equal": round(max(eq), 5),
                        "diff_first": int(diff[0]),
                        "diff_last": int(diff[-1]),
                        "diff_is_frame": others,
                    }
                )
            return
        self.identical += 1
        if self.first_index is None:
            self.first_index = self.hashes.index(digest) - self.sent_index
        # The server sends video frame k % n as its k-th frame; frame ids count the frames sent, so the
        # expected video frame follows from the frame id even when a frame was lost. Compare digests, not
        # indices: a video may hold identical consecutive frames.
        if self.hashes[(self.first_index + self.sent_index) % len(self.hashes)] == digest:
            self.in_order += 1
        else:
            self.out_of_order.append((ref.seq, self.hashes.index(digest)))


# GenICam names a Bayer pattern after its first row (BayerRG8: R at pixel (0, 0), G at (0, 1)); the second row
# holds the other two colours of the 2x2 cell.
GENICAM_BAYER_ROWS = {"BayerRG8": ("RG", "GB"), "BayerBG8": ("BG", "GR"), "BayerGR8": ("GR", "BG"),
                      "BayerGB8": ("GB", "RG")}  # fmt: skip


def reference_image(rgb: np.ndarray[Any, Any], fmt_name: str) -> np.ndarray[Any, Any]:
    """The image a camera delivering ``rgb`` in ``fmt_name`` must produce in mocapd's ring, computed without
    mocapd's pixel code (:mod:`mocapd.io.pixels`), so that it can judge the capture path.

    RGB8 is the frame itself, Mono8 its OpenCV grey conversion. A Bayer format is sampled here from the frame by
    the GenICam definition of its pattern and demosaiced with ``cv2.demosaicing``, whose code names the pattern
    after the second row's second and third pixels (OpenCV's convention) — for a 2x2 cell, the second row's
    two colours swapped.

    Returns
    -------
    ndarray, shape (h, w, channels), uint8
    """
    if fmt_name == "RGB8":
        return rgb.copy()
    if fmt_name == "Mono8":
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[:, :, None]
    rows = GENICAM_BAYER_ROWS[fmt_name]
    channel = {"R": 0, "G": 1, "B": 2}
    raw = np.empty(rgb.shape[:2], np.uint8)
    for dy, row in enumerate(rows):
        for dx, colour in enumerate(row):
            raw[dy::2, dx::2] = rgb[dy::2, dx::2, channel[colour]]
    code = getattr(cv2, f"COLOR_Bayer{rows[1][1]}{rows[1][0]}2RGB")
    image: np.ndarray[Any, Any] = cv2.demosaicing(raw, code)
    return image


def expected_hashes(frames: list[Any], fmt_name: str) -> list[str]:
    """Digests of the ring images mocapd must produce from each source frame (:func:`reference_image`)."""
    return [hashlib.blake2b(reference_image(rgb, fmt_name).tobytes(), digest_size=16).hexdigest() for rgb in frames]


async def capture(sources: list[AravisSource], checks: list[CameraCheck], duration_s: float, verify: bool) -> None:
    def make_handler(source: AravisSource, check: CameraCheck) -> Any:
        def on_frame(ref: FrameRef) -> None:
            check.add(ref, source.ring.read(ref.seq) if verify else None, verify)

        return on_frame

    tasks = [asyncio.create_task(s.run(make_handler(s, c))) for s, c in zip(sources, checks, strict=True)]
    await asyncio.sleep(duration_s)
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)


class Reader:
    """A thread reading the newest frame of every camera ``rate_hz`` times a second, as the detector does."""

    def __init__(self, sources: list[AravisSource], rate_hz: float) -> None:
        self.sources = sources
        self.period_s = 1.0 / rate_hz
        self.read = [0] * len(sources)
        self.thread_id: int | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._main, name="reader")

    def _main(self) -> None:
        self.thread_id = threading.get_native_id()
        last = [-1] * len(self.sources)
        while not self._stop.wait(self.period_s):
            for i, s in enumerate(self.sources):
                ref = s.ring.latest()
                if ref is not None and ref.seq != last[i] and s.ring.read(ref.seq) is not None:
                    last[i] = ref.seq
                    self.read[i] += 1

    def __enter__(self) -> Reader:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def percentile_ms(values: np.ndarray[Any, Any], q: float) -> float | None:
    return round(float(np.percentile(values, q)) / 1e6, 3) if values.size else None


def run_rig(args: argparse.Namespace) -> dict[str, Any]:
    n = len(args.videos)
    addresses = add_loopback_aliases(n)
    size = tuple(int(v) for v in args.size.lower().split("x")) if args.size else None
    servers = []
    for i, (video, address) in enumerate(zip(args.videos, addresses, strict=True)):
        cmd = server_command(video, address, args.max_frames, args.format, f"FAKE{i + 1:02d}", args.size or None)
        servers.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True))
    sources: list[AravisSource] = []
    try:
        infos = [json.loads(s.stdout.readline()) for s in servers if s.stdout is not None]
        fmt = pixel_format(args.format)
        checks = []
        for i, (video, info) in enumerate(zip(args.videos, infos, strict=True)):
            w, h = info["width"], info["height"]
            config = AravisCameraConfig(
                f"cam{i + 1:02d}",
                address=info["address"],
                pixel_format=fmt.name,
                region=(0, 0, w, h),
                frame_rate=args.fps,
                packet_size=args.packet_size,
                # Verification copies and hashes every frame on the event loop: give it slack on a busy machine.
                ring_slots=32 if args.verify else 8,
                # Loopback on a shared 2-core machine: the fake servers and this process can be descheduled for
                # longer than a real camera link would stall, so resent packets get more time to arrive.
                frame_retention_ms=1000.0 if args.verify else 100.0,
                packet_timeout_ms=50.0 if args.verify else 20.0,
            )
            # --eager: a ring of finished images, so capture demosaics every frame (mocapd before its rings turned
            # lazy), for a before/after comparison in one benchmark run.
            ring = FrameRing(config.name, config.ring_slots, h, w, fmt.channels) if args.eager else None
            sources.append(AravisSource(config, ring))
            frames = load_video_rgb(Path(video), args.max_frames, size) if args.verify else []  # type: ignore[arg-type]
            checks.append(CameraCheck(expected_hashes(frames, fmt.name) if args.verify else [], debug_frames=frames))
        server_cpu0 = [cpu_seconds(s.pid) for s in servers]
        wall0, cpu0 = time.monotonic(), time.process_time()
        thread_cpu: dict[str, float] = {}
        thread_names: dict[str, float] = {}
        reader = Reader(sources, args.read_hz) if args.read_hz > 0 else None
        reader_cpu: list[float] = []

        async def main() -> None:
            task = asyncio.create_task(capture(sources, checks, args.duration, args.verify))
            await asyncio.sleep(min(1.0, args.duration / 2))
            start = {s.name: cpu_seconds(os.getpid(), s.thread_id) for s in sources}
            tids = {s.thread_id for s in sources if s.thread_id is not None}
            by_name0 = cpu_by_thread_name(tids)
            r0 = cpu_seconds(os.getpid(), reader.thread_id) if reader and reader.thread_id else 0.0
            t_start = time.monotonic()
            await asyncio.sleep(max(0.0, args.duration - min(1.0, args.duration / 2) - 0.2))
            span = time.monotonic() - t_start
            by_name1 = cpu_by_thread_name(tids)
            for k, v in by_name1.items():
                thread_names[k] = round(100 * (v - by_name0.get(k, 0.0)) / span, 2)
            for s in sources:
                thread_cpu[s.name] = (cpu_seconds(os.getpid(), s.thread_id) - start[s.name]) / span
            if reader is not None and reader.thread_id is not None:
                reader_cpu.append((cpu_seconds(os.getpid(), reader.thread_id) - r0) / span)
            await task

        if reader is not None:
            with reader:
                asyncio.run(main())
        else:
            asyncio.run(main())
        wall = time.monotonic() - wall0
        process_cpu = time.process_time() - cpu0
        server_cpu = [(cpu_seconds(p.pid) - c) / wall for p, c in zip(servers, server_cpu0, strict=True)]
    finally:
        for source in sources:
            source.release()  # while its server still answers (AravisSource.release)
        for proc in servers:
            proc.terminate()
        for proc in servers:
            proc.wait(timeout=10)
    cameras = []
    for i, (s, c) in enumerate(zip(sources, checks, strict=True)):
        lat, conv = s.latency.recent(), s.convert.recent()
        cameras.append(
            {
                "name": s.name,
                "frames": c.frames,
                "expected_frames_approx": round(args.fps * args.duration),
                "missing_frames": s.counters.missing_frames,
                "resent_packets": s.counters.resent_packets,
                "bad_buffers": s.counters.bad_buffers,
                "failures": s.counters.failures,
                "last_error": s.counters.last_error,
                "timeouts": s.counters.timeouts,
                "verified": c.identical if args.verify else None,
                "in_order": c.in_order if args.verify else None,
                "mismatched": len(c.mismatched),
                "overtaken": c.overtaken,
                "out_of_order": c.out_of_order[:10],
                "debug": c.debug,
                "host_ts_increasing": c.host_increasing,
                "device_ts_increasing": c.device_increasing,
                "frame_ids_consecutive": c.ids_increasing,
                "latency_ms_median": percentile_ms(lat, 50),
                "latency_ms_p95": percentile_ms(lat, 95),
                "convert_ms_median": percentile_ms(conv, 50),
                "convert_ms_p95": percentile_ms(conv, 95),
                "capture_thread_cpu_pct": round(100 * thread_cpu.get(s.name, float("nan")), 2),
                "lazy_ring": s.ring.lazy,
                "frames_read": None if reader is None else reader.read[i],
                "conversions": s.ring.conversions,
            }
        )
    return {
        "format": args.format,
        "fps": args.fps,
        "duration_s": args.duration,
        "size": [infos[0]["width"], infos[0]["height"]],
        "cameras": cameras,
        "capture_process_cpu_pct": round(100 * process_cpu / wall, 1),
        "capture_process_cpu_pct_by_thread_name": thread_names,
        "fake_server_cpu_pct": [round(100 * c, 1) for c in server_cpu],
        "eager": args.eager,
        "read_hz": args.read_hz,
        "reader_thread_cpu_pct": round(100 * reader_cpu[0], 2) if reader_cpu else None,
    }


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--videos", nargs="+", required=True, help="one video per fake camera")
    parser.add_argument("--max-frames", type=int, default=20, help="frames of each video served (looped)")
    parser.add_argument("--size", default=None, help="resize videos to WIDTHxHEIGHT")
    parser.add_argument(
        "--format", default="RGB8", choices=["RGB8", "Mono8", *GENICAM_BAYER_ROWS], help="camera pixel format"
    )
    parser.add_argument("--fps", type=float, default=30.0, help="acquisition frame rate, Hz")
    parser.add_argument("--duration", type=float, default=3.0, help="capture time, s")
    parser.add_argument("--packet-size", type=int, default=8192, help="GigE stream packet size, bytes")
    parser.add_argument("--no-verify", dest="verify", action="store_false", help="skip the bit-identity check")
    parser.add_argument(
        "--read-hz", type=float, default=0.0, help="a reader takes every camera's newest frame this often (0: none)"
    )
    parser.add_argument("--eager", action="store_true", help="convert every frame at capture (eager rings)")
    parser.add_argument("--in-netns", action="store_true", help="already inside a private network namespace")
    parser.add_argument("--json", type=Path, default=None, help="also write the result here")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if not args.in_netns:
        # Aravis must never talk to a real network: re-run inside a private network namespace.
        cmd = ["unshare", "-rn", sys.executable, "-m", "mocapd.sim.fake_rig", *(argv or sys.argv[1:]), "--in-netns"]
        return subprocess.run(cmd, check=False).returncode
    result = run_rig(args)
    text = json.dumps(result, indent=1)
    print(text, flush=True)
    if args.json is not None:
        args.json.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

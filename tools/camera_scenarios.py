"""Single-purpose fake-camera scenarios, run inside a private network namespace; each prints one JSON object.

    python -m tools.camera_scenarios reconnect --video cam01.mp4
    python -m tools.camera_scenarios bayer --video cam01.mp4 --format BayerRG8
    python -m tools.camera_scenarios lazy --video cam01.mp4 --format BayerRG8

``reconnect``: two fake cameras; one server is killed and later restarted. Reports frames of each camera before,
during and after the outage, the failure/reopen counters and the error that was reported.

``lazy``: one Bayer camera whose frames are read one in three (each twice): reports frames captured, frames read
and conversions done (a frame is demosaiced only when read, once), and whether each frame read is identical to the
eager conversion of its raw bytes (what capture did before it turned lazy) and to the expected image.

``bayer`` / ``mono``: one camera in a Bayer or Mono8 format; compares what mocapd's ring holds with the expected
image of the source frames (``mocapd.sim.fake_rig.reference_image``: OpenCV's demosaicing of a mosaic sampled by the
GenICam definition, not mocapd's own conversion) and, for Bayer, with the source RGB itself, to catch swapped
channels.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mocapd.io.aravis_camera import AravisCameraConfig, AravisSource
from mocapd.io.pixels import convert_into, pixel_format
from mocapd.pipeline.frame_ring import FrameRef
from mocapd.sim.fake_gige import add_loopback_aliases, load_video_rgb, server_command
from mocapd.sim.fake_rig import reference_image


def start_server(video: Path, address: str, max_frames: int, prepare: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen(server_command(video, address, max_frames, prepare), stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    json.loads(proc.stdout.readline())
    return proc


def mean_abs_difference(a: np.ndarray[Any, Any], b: np.ndarray[Any, Any]) -> float:
    """Mean absolute difference of two uint8 images of one shape, as ``np.abs(a.astype(int) - b.astype(int)).mean()``
    gives it, bit for bit (an L1 norm is an exact integer sum in a double), without its four full-size int64 arrays:
    on 1920x1088 frames that took 60 ms a pair, 64 pairs a Bayer run, most of the run's time.

    Parameters
    ----------
    a, b : ndarray, shape (h, w, channels), uint8
    """
    return float(cv2.norm(np.ascontiguousarray(a), np.ascontiguousarray(b), cv2.NORM_L1)) / a.size


async def wait_for(predicate: Any, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        await asyncio.sleep(0.05)
    return False


async def reconnect(video: Path) -> dict[str, Any]:
    frames = load_video_rgb(video, 4)
    h, w, _ = frames[0].shape
    servers = [start_server(video, a, 4, "RGB8") for a in ("127.0.0.1", "127.0.0.2")]
    sources = [
        AravisSource(
            AravisCameraConfig(
                f"cam{i + 1}",
                address=a,
                pixel_format="RGB8",
                region=(0, 0, w, h),
                frame_rate=10,
                packet_size=8192,
                lost_after_s=1.0,
            ),
            backoff_s=(0.2, 1.0),
        )
        for i, a in enumerate(("127.0.0.1", "127.0.0.2"))
    ]
    counts = [0, 0]

    def handler(i: int) -> Any:
        def on_frame(_ref: FrameRef) -> None:
            counts[i] += 1

        return on_frame

    tasks = [asyncio.create_task(s.run(handler(i))) for i, s in enumerate(sources)]
    result: dict[str, Any] = {}
    try:
        result["started"] = await wait_for(lambda: min(counts) >= 5, 15)
        servers[0].kill()
        servers[0].wait()
        await asyncio.sleep(0.5)  # let frames already handed to the loop be counted
        before = list(counts)
        result["failure_reported"] = await wait_for(lambda: sources[0].counters.failures >= 1, 15)
        await asyncio.sleep(1.0)
        during = [counts[0] - before[0], counts[1] - before[1]]
        servers[0] = start_server(video, "127.0.0.1", 4, "RGB8")
        mid = list(counts)
        result["recovered"] = await wait_for(lambda: counts[0] >= mid[0] + 5, 20)
        result.update(
            frames_before=before,
            frames_during_outage=during,
            frames_after=[counts[0] - mid[0], counts[1] - mid[1]],
            failures=sources[0].counters.failures,
            reopens=sources[0].counters.reopens,
            last_error=sources[0].counters.last_error,
            other_failures=sources[1].counters.failures,
        )
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for source in sources:
            source.release()  # while its server still answers (AravisSource.release)
        for s in servers:
            s.terminate()
            s.wait()
    return result


async def one_format(video: Path, fmt_name: str) -> dict[str, Any]:
    fmt = pixel_format(fmt_name)
    frames = load_video_rgb(video, 4)
    h, w, _ = frames[0].shape
    server = start_server(video, "127.0.0.1", 4, fmt_name)
    expected = [reference_image(rgb, fmt.name) for rgb in frames]  # not mocapd's own conversion
    source = AravisSource(
        AravisCameraConfig(
            "cam",
            address="127.0.0.1",
            pixel_format=fmt_name,
            region=(0, 0, w, h),
            frame_rate=10,
            packet_size=8192,
        )
    )
    got: list[np.ndarray[Any, Any]] = []

    def on_frame(ref: FrameRef) -> None:
        image = source.ring.read(ref.seq)
        if image is not None:
            got.append(image)

    task = asyncio.create_task(source.run(on_frame))
    try:
        await wait_for(lambda: len(got) >= 8, 15)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        source.release()  # while its server still answers (AravisSource.release)
        server.terminate()
        server.wait()
    matches = [any(np.array_equal(g, e) for e in expected) for g in got]
    result: dict[str, Any] = {
        "frames": len(got),
        "identical_to_expected": sum(matches),
        "shape": list(got[0].shape) if got else None,
        "missing_frames": source.counters.missing_frames,
    }
    if fmt.channels == 3 and got:
        # Closest source frame, compared as RGB and with R/B swapped: demosaicing must keep the channel order.
        errors = [min(mean_abs_difference(g, f) for f in frames) for g in got]
        swapped = [min(mean_abs_difference(g[..., ::-1], f) for f in frames) for g in got]
        result.update(mean_abs_error_rgb=max(errors), mean_abs_error_swapped=min(swapped))
    if fmt.channels == 1 and got:
        gray = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY)[:, :, None] for f in frames]
        result["identical_to_gray_source"] = sum(any(np.array_equal(g, e) for e in gray) for g in got)
    return result


async def lazy(video: Path, fmt_name: str, read_every: int = 3, frames_wanted: int = 24) -> dict[str, Any]:
    fmt = pixel_format(fmt_name)
    frames = load_video_rgb(video, 4)
    h, w, _ = frames[0].shape
    expected = [reference_image(rgb, fmt.name) for rgb in frames]  # not mocapd's own conversion
    config = AravisCameraConfig("cam", address="127.0.0.1", pixel_format=fmt_name, region=(0, 0, w, h),
                                frame_rate=10, packet_size=8192, ring_slots=16)  # fmt: skip
    source = AravisSource(config)
    ring = source.ring
    out: dict[str, Any] = {"lazy": ring.lazy, "captured": 0, "conversions_before_reading": None, "read": 0,
                           "overtaken": 0, "identical_to_eager": 0, "identical_to_expected": 0,
                           "second_read_converted": 0}  # fmt: skip

    def on_frame(ref: FrameRef) -> None:
        out["captured"] += 1
        if (ref.seq + 1) % read_every or ring.raw is None:  # frames 0 .. read_every - 2 are never read
            return
        if out["conversions_before_reading"] is None:
            out["conversions_before_reading"] = ring.conversions
        raw = ring.raw[ref.seq % ring.n_slots].copy()  # the bytes the camera sent, before anyone read the frame
        image = ring.read(ref.seq)
        out["read"] += 1
        if image is None or not ring.is_valid(ref.seq):
            out["overtaken"] += 1
            return
        before = ring.conversions
        again = ring.view(ref.seq)  # a second reader of the same frame: no second conversion
        out["second_read_converted"] += ring.conversions - before
        eager = np.empty_like(image)
        convert_into(fmt, raw, h, w, eager)
        out["identical_to_eager"] += int(np.array_equal(image, eager) and np.array_equal(again, eager))
        out["identical_to_expected"] += int(any(np.array_equal(image, e) for e in expected))

    server = start_server(video, "127.0.0.1", 4, fmt_name)
    task = asyncio.create_task(source.run(on_frame))
    try:
        await wait_for(lambda: out["captured"] >= frames_wanted, 20)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        source.release()  # while its server still answers (AravisSource.release)
        server.terminate()
        server.wait()
    out["conversions"] = ring.conversions
    out["missing_frames"] = source.counters.missing_frames
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenario", choices=["reconnect", "bayer", "mono", "lazy"])
    parser.add_argument("--video", type=Path, required=True)
    parser.add_argument("--format", default="BayerRG8")
    parser.add_argument("--in-netns", action="store_true", help="already inside a private network namespace")
    args = parser.parse_args(argv)
    if not args.in_netns:
        cmd = [
            "unshare",
            "-rn",
            sys.executable,
            "-m",
            "tools.camera_scenarios",
            *(argv or sys.argv[1:]),
            "--in-netns",
        ]
        return subprocess.run(cmd, cwd=Path(__file__).resolve().parents[1], check=False).returncode
    add_loopback_aliases(2)
    if args.scenario == "reconnect":
        result = asyncio.run(reconnect(args.video))
    elif args.scenario == "lazy":
        result = asyncio.run(lazy(args.video, args.format))
    else:
        result = asyncio.run(one_format(args.video, "Mono8" if args.scenario == "mono" else args.format))
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

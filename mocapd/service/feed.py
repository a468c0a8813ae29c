"""``mocapd feed keypoints``: another detector's keypoints into a running daemon, as a camera host over Zenoh.

An external detector (OpenPose ``--write_json``, MMPose's ``pred_out_dir``, RTMLib) writes per-frame files; the
feed reads them (:mod:`mocapd.io.keypoint_files`), converts each camera's people onto the keypoint format the
daemon solves (``[detector.model] keypoint_format`` of the solver host; :mod:`mocapd.core.keypoint_sets`) and
publishes them exactly as ``mocapd detect-host`` does (:class:`~mocapd.service.detect_host.DetectionPublisher`:
detections on ``mocapd/<rig>/<camera>/detections``, the host's status, its clock for the solver host's offset
estimate; docs/scaling.md). The daemon takes the cameras as ``source = "zenoh"`` cameras of this host.

Times: frame ``f`` was captured at ``t0 + (f - f0) / fps`` on this host's monotonic clock, ``t0`` the moment the
first frame was read less ``latency_s`` (the detector's delay, what it took to write the first file); a frame is
published once that time has come (a folder written beforehand is replayed at its frame rate) or as soon as its file
appears (``follow``: a detector writing live). The daemon's scheduler then solves each instant with every camera's
frame of it, as for its own cameras.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from mocapd.core.keypoint_sets import SOLVE_FORMAT, convert
from mocapd.core.keypoints import keypoint_format
from mocapd.core.sorting import Detections2D
from mocapd.errors import InputError
from mocapd.io.calibration_files import CalibrationSet
from mocapd.io.keypoint_files import KeypointInput, match_cameras, read_keypoint_inputs, read_new_frames
from mocapd.io.zenoh_link import host_name, open_session
from mocapd.protocols.keypoint_files import to_pixels
from mocapd.service.config import Config
from mocapd.service.detect_host import DetectionPublisher


@dataclass
class FeedOptions:
    """How ``mocapd feed keypoints`` reads and times the files."""

    inputs: list[str]
    fps: float
    layout: str = "auto"
    keypoint_set: str | None = None
    solve_format: str | None = None
    """The daemon's keypoint format (default: the one the files' set is solved in, :data:`SOLVE_FORMAT`)."""
    latency_s: float = 0.0
    follow: bool = False
    """Keep reading the folders for new files until stopped (a detector writing live)."""
    poll_s: float = 0.05
    seconds: float | None = None


@dataclass
class FeedState:
    """What was published: per camera, the frames sent; the frames read but not yet due."""

    sent: dict[str, int] = field(default_factory=dict)
    seen: dict[str, set[int]] = field(default_factory=dict)
    files: dict[str, set[str]] = field(default_factory=dict)
    """Per camera, the names of the files read (following a folder)."""
    t0_ns: int | None = None
    f0: int | None = None


def _frames(
    inp: KeypointInput, state: FeedState, fmt: str, sizes: list[tuple[str, int, int]]
) -> list[tuple[int, int, Detections2D]]:
    """The frames not published yet: (frame, camera index, detections in ``fmt``), by frame then camera;
    ``sizes``: each camera's (name, width, height), for keypoints given as fractions of the image."""
    target = keypoint_format(fmt)
    out = []
    for ci, cam in enumerate(inp.cameras):
        seen = state.seen.setdefault(cam.name, set())
        for f, (kp, cf) in cam.parsed.frames.items():
            if f in seen:
                continue
            seen.add(f)
            if kp.shape[0] == 0:
                dets = Detections2D.empty(target.n_keypoints)
            else:
                px = to_pixels(kp, sizes[ci][1], sizes[ci][2]) if cam.parsed.normalized else kp
                dets = Detections2D(*convert(cam.parsed.keypoint_set, px, cf, target.keypoints))
            out.append((f, ci, dets))
    out.sort(key=lambda x: (x[0], x[1]))
    return out


def camera_sizes(inp: KeypointInput, calib: CalibrationSet) -> list[tuple[str, int, int]]:
    """The inputs' cameras as the calibration names and sizes them (the solver host checks each frame's size)."""
    index = match_cameras([c.name for c in inp.cameras], calib.names)
    return [(calib.cameras[i].name, *calib.cameras[i].size) for i in index]


async def feed(
    config: Config,
    calib: CalibrationSet,
    opts: FeedOptions,
    *,
    stop: asyncio.Event,
    on_ready: Callable[[str, list[str]], None] | None = None,
    clock: Callable[[], int] = time.monotonic_ns,
) -> dict[str, Any]:
    """Publish the inputs' frames until they are done (``follow``: until ``stop``); returns what was sent."""
    inp = read_keypoint_inputs(opts.inputs, opts.layout, opts.keypoint_set)
    source = opts.keypoint_set or next((c.parsed.keypoint_set for c in inp.cameras if c.parsed.keypoint_set), None)
    if opts.solve_format is None and source is None:
        raise InputError("no person was detected in any input yet: name the keypoint set (--keypoints) or the "
                         "daemon's format (--solve-format)")  # fmt: skip
    fmt = opts.solve_format or SOLVE_FORMAT[str(source)]
    cameras = camera_sizes(inp, calib)
    z = config.zenoh
    host = host_name(z)
    loop = asyncio.get_running_loop()
    session = await loop.run_in_executor(None, functools.partial(open_session, z))
    publisher = DetectionPublisher(session, z.rig, host, cameras, clock=clock)
    state = FeedState(sent={name: 0 for name, _, _ in cameras})
    for cam in inp.cameras:  # what is there now was read above
        state.files[cam.name] = {f.name for f in cam.source.iterdir()} if cam.source.is_dir() else set()
    period_ns = round(1e9 / opts.fps)
    started = clock()
    next_status = started
    try:
        if on_ready is not None:
            on_ready(host, [name for name, _, _ in cameras])
        while not stop.is_set():
            for f, ci, dets in _frames(inp, state, fmt, cameras):
                if state.t0_ns is None or state.f0 is None:
                    state.t0_ns, state.f0 = clock() - round(opts.latency_s * 1e9), f
                capture = state.t0_ns + (f - state.f0) * period_ns
                while clock() < capture and not stop.is_set():  # sent no earlier than captured
                    if clock() >= next_status:
                        publisher.publish_status([True] * len(cameras))
                        next_status = clock() + round(z.status_period_s * 1e9)
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(stop.wait(), min((capture - clock()) / 1e9, z.status_period_s))
                if stop.is_set():
                    break
                publisher.sink(ci, capture, dets, clock())
                state.sent[cameras[ci][0]] += 1
            if clock() >= next_status:
                publisher.publish_status([True] * len(cameras))
                next_status = clock() + round(z.status_period_s * 1e9)
            if not opts.follow or (opts.seconds is not None and clock() - started >= opts.seconds * 1e9):
                break
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), opts.poll_s)
            for cam in inp.cameras:  # the files written since (only those: a long run does not re-read its past)
                new = read_new_frames(cam, inp.layout, opts.keypoint_set, state.files.setdefault(cam.name, set()))
                cam.parsed.frames.update(new.frames)
                if new.keypoint_set and not cam.parsed.keypoint_set:
                    cam.parsed.keypoint_set = new.keypoint_set
        return {"host": host, "rig": z.rig, "keypoint_format": fmt, "fps": opts.fps, "sent": state.sent,
                "publish_errors": publisher.errors}  # fmt: skip
    finally:
        publisher.close()
        await loop.run_in_executor(None, session.close)


def run(config: Config, calib: CalibrationSet, opts: FeedOptions,
        on_ready: Callable[[str, list[str]], None] | None = None) -> dict[str, Any]:  # fmt: skip
    """``mocapd feed keypoints``: publish until the files are done (or, following, until SIGINT/SIGTERM)."""
    from mocapd.io import lifecycle

    async def main(stop: asyncio.Event) -> dict[str, Any]:
        return await feed(config, calib, opts, stop=stop, on_ready=on_ready)

    return lifecycle.run_until_stopped(main)


__all__ = ["FeedOptions", "camera_sizes", "feed", "run"]

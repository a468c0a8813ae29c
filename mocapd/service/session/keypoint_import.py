"""Other detectors' 2D keypoints as a mocapd session: ``mocapd import keypoints``.

The session is what a live recording of a camera rig makes (``docs/sessions.md``): ``keypoints.mcs`` holds one
``T_KEYPOINTS`` record per camera and frame (people-grouped, as every detector here writes them), ``imu.mcs`` and
``poses.mcs`` are empty, and ``manifest.json`` describes the rig: the calibrated cameras, the shipped config with
``[detector.model] keypoint_format`` set to the format the keypoints are solved in, the skeleton at ``--height``,
the keypoint format's track targets, the default pose prior, and an ``imported`` section (where the keypoints came
from, their set, the frame rate, the frames per camera). ``mocapd resolve`` then solves it as any take: one output
tick per frame (the scheduler's rate is the frame rate), and ``mocapd export`` writes BVH/CSV/glTF.

Frame ``f`` of every camera is captured at ``T0 + (f - f0) / fps`` (``f0`` the first frame of any camera, ``T0`` the
session clock's 1 s, as for ``import mtw``); a camera without a file for a frame detected nobody then. Each
input's keypoint set is converted by name onto the format mocapd solves it in
(:data:`mocapd.core.keypoint_sets.SOLVE_FORMAT`).
"""

from __future__ import annotations

import itertools
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mocapd.core.camera import Camera
from mocapd.core.keypoint_sets import SOLVE_FORMAT, convert
from mocapd.core.keypoints import keypoint_format
from mocapd.core.skeleton import Skeleton
from mocapd.errors import InputError
from mocapd.io.calibration_files import CalibrationSet, core_cameras
from mocapd.io.imu_recordings import T0_NS
from mocapd.io.keypoint_files import MAX_FPS, MIN_FPS, KeypointInput, match_cameras
from mocapd.io.output_files import atomic_directory, check_output_dir
from mocapd.io.prior import resolve_prior
from mocapd.io.session import MANIFEST, STREAMS, SUFFIX, WriterCounters, write_json_atomic
from mocapd.protocols.keypoint_files import to_pixels
from mocapd.protocols.session_format import T_HEADER, T_KEYPOINTS, encode_header, encode_keypoints, encode_record
from mocapd.service.config import DEFAULT_CONFIG, config_document, load_config
from mocapd.service.outputs.recorder import camera_dict
from mocapd.service.session.importer import manifest_head

IMPORT_ENROL_AFTER_S = 0.1
"""``[tracking.enrolment] enrol_after_s`` of an imported take (with the default 3 agreeing frames)."""
LATENCY_S = 0.15
"""The fixed delay written into the session's scheduler (offline every detection is there; ``run_live``'s)."""


@dataclass
class KeypointTake:
    """The detections of an import, ready to write.

    Attributes
    ----------
    cameras : the calibrated cameras, in the order of the inputs
    keypoint_format : the mocapd format they are solved in
    records : (capture_ns, camera index, keypoints (n, k, 2), confidences (n, k)), sorted by time then camera
    """

    cameras: list[Camera]
    keypoint_format: str
    source_set: str
    records: list[tuple[int, int, np.ndarray, np.ndarray]]
    frames: dict[str, int]
    first_frame: int
    last_frame: int
    timed_by: str = "fps"
    """``"fps"``, or ``"timestamps"`` where a timestamps file timed any camera."""


def keypoint_take(
    inp: KeypointInput,
    calib: CalibrationSet,
    fps: float,
    timestamps: dict[str | None, dict[int, float]] | None = None,
) -> KeypointTake:
    """The inputs' cameras matched with the calibration, their detections converted and timed at ``fps``, or by
    ``timestamps`` (per camera name, None for every camera without its own: frame -> seconds; the earliest time
    used is the session's start)."""
    if not (isinstance(fps, float | int) and math.isfinite(fps) and MIN_FPS <= fps <= MAX_FPS):
        raise InputError(f"--fps {fps!r}: allowed {MIN_FPS:g} to {MAX_FPS:g}")
    sets = {c.parsed.keypoint_set for c in inp.cameras if c.parsed.keypoint_set}
    if not sets:
        raise InputError("no person was detected in any input: nothing to import")
    if len(sets) > 1:
        raise InputError(f"the cameras' keypoint sets differ: {sorted(sets)}")
    source = sets.pop()
    fmt = keypoint_format(SOLVE_FORMAT[source])
    names = [c.name for c in inp.cameras]
    if len(set(names)) != len(names):
        raise InputError(f"two inputs are the same camera: {names}; name them (NAME=PATH)")
    index = match_cameras(names, calib.names)
    all_cams = core_cameras(calib)
    cameras = [all_cams[i] for i in index]
    frame_ids = [f for c in inp.cameras for f in c.parsed.frames]
    if not frame_ids:
        raise InputError("the inputs hold no frames")
    first, last = min(frame_ids), max(frame_ids)
    clocks = _frame_times(inp, timestamps or {}, fps, first)
    records = []
    for ci, cam in enumerate(inp.cameras):
        for f, (kp, cf) in sorted(cam.parsed.frames.items()):
            if kp.shape[0] == 0:
                out_kp, out_cf = np.zeros((0, fmt.n_keypoints, 2)), np.zeros((0, fmt.n_keypoints))
            else:
                # MediaPipe's fractions of the image: pixels of this camera's
                px = to_pixels(kp, cameras[ci].width, cameras[ci].height) if cam.parsed.normalized else kp
                out_kp, out_cf = convert(source, px, cf, fmt.keypoints)
            records.append((T0_NS + clocks[ci][f], ci, out_kp, out_cf))
    records.sort(key=lambda r: (r[0], r[1]))
    frames = {c.name: len(c.parsed.frames) for c in inp.cameras}
    timed = "timestamps" if timestamps else "fps"
    return KeypointTake(cameras, fmt.name, source, records, frames, first, last, timed)


def people_in_take(take: KeypointTake, max_instants: int = 400) -> np.ndarray:
    """The take's people triangulated at up to ``max_instants`` instants spread over it (the association the
    scheduler starts from, :class:`~mocapd.core.sorting.DetectionSorter`), shape (n, n_kp, 3), NaN where not
    triangulated: what ``--up auto`` measures the world's up and floor on."""
    from mocapd.core.sorting import Detections2D, DetectionSorter

    n_kp = keypoint_format(take.keypoint_format).n_keypoints
    sorter = DetectionSorter(take.cameras, keypoint_names=keypoint_format(take.keypoint_format).keypoints)
    by_time: dict[int, list[Detections2D]] = {}
    for t, ci, kp, cf in take.records:
        by_time.setdefault(t, [Detections2D.empty(n_kp) for _ in take.cameras])[ci] = Detections2D(kp, cf)
    times = sorted(by_time)
    pick = np.unique(np.linspace(0, len(times) - 1, min(max_instants, len(times))).round().astype(int))
    people = [c.points for i in pick.tolist() for c in sorter.candidates(by_time[times[i]])]
    return np.asarray(people, dtype=np.float64).reshape(-1, n_kp, 3)


def median_rate(timestamps: dict[str | None, dict[int, float]]) -> float:
    """The frame rate of timestamps (1 / the median time between consecutive frames), within the accepted rates."""
    steps = [(ts[b] - ts[a]) / (b - a) for ts in timestamps.values() for a, b in itertools.pairwise(sorted(ts))]
    if not steps:
        raise InputError("--timestamps: one frame only: give the output rate (--fps HZ)")
    return float(np.clip(1.0 / float(np.median(steps)), MIN_FPS, MAX_FPS))


def _frame_times(
    inp: KeypointInput, timestamps: dict[str | None, dict[int, float]], fps: float, first: int
) -> list[dict[int, int]]:
    """Per camera, frame -> ns after the session's start: from the timestamps where given, else ``(f - first) /
    fps``; the earliest timestamp used is 0."""
    unknown = sorted(str(k) for k in timestamps if k is not None and k not in {c.name for c in inp.cameras})
    if unknown:
        raise InputError(f"--timestamps for camera(s) {unknown}, which no input is; the inputs: "
                         f"{[c.name for c in inp.cameras]}")  # fmt: skip
    seconds: list[dict[int, float]] = []
    for cam in inp.cameras:
        ts = timestamps.get(cam.name, timestamps.get(None))
        if ts is None:
            seconds.append({f: (f - first) / fps for f in cam.parsed.frames})
            continue
        missing = sorted(set(cam.parsed.frames) - set(ts))
        if missing:
            more = " ..." if len(missing) > 5 else ""
            raise InputError(f"camera {cam.name}: no timestamp for frame(s) {missing[:5]}{more} (the file has frames "
                             f"{min(ts)}-{max(ts)})")  # fmt: skip
        seconds.append({f: ts[f] for f in cam.parsed.frames})
    t0 = min((t for s in seconds for t in s.values()), default=0.0)
    return [{f: round((t - t0) * 1e9) for f, t in s.items()} for s in seconds]


def keypoints_manifest(take: KeypointTake, *, fps: float, height: float, source: str, layout: str,
                       calibration: str) -> dict[str, Any]:  # fmt: skip
    """The manifest of an imported keypoint take (see the module docstring)."""
    cfg = load_config()
    raw = config_document(cfg)
    raw.setdefault("detector", {}).setdefault("model", {})["keypoint_format"] = take.keypoint_format
    raw.setdefault("daemon", {}).update({"output_rate_hz": float(fps), "latency_s": LATENCY_S})
    raw.setdefault("imu", {}).setdefault("body", {})["height_m"] = height
    # Every tick of an imported take is a detection frame: a person is published at their 4th frame (the evidence
    # rule, docs/tracking.md; the live default is the same 0.1 s since the tracker counts detection frames, written
    # here so a take keeps it whatever the config it was imported with says).
    raw.setdefault("tracking", {}).setdefault("enrolment", {})["enrol_after_s"] = IMPORT_ENROL_AFTER_S
    o = cfg.daemon.model_copy(update={"output_rate_hz": float(fps), "latency_s": LATENCY_S}).scheduler_options(
        [c.name for c in take.cameras])  # fmt: skip
    skeleton = Skeleton.from_height(height)
    targets = keypoint_format(take.keypoint_format).track_targets(skeleton)
    duration = (max((r[0] for r in take.records), default=T0_NS) - T0_NS) / 1e9
    return {
        **manifest_head(raw),
        "scheduler": {
            "rate_hz": o.rate_hz, "latency_ns": o.latency_ns, "keypoint_max_age_ns": o.keypoint_max_age_ns,
            "keypoint_max_gap_ns": o.keypoint_max_gap_ns, "match_px": o.match_px,
            "camera_offsets_ns": [0] * len(take.cameras), "imu_offsets_ns": {},
            "body_size_frames": o.body_size_frames, "body_size_first_frames": o.body_size_first_frames,
            "lr_flips": o.flips.enabled, "output": "delayed", "heading_correction": o.heading.enabled,
        },
        "cameras": [camera_dict(c) for c in take.cameras],
        "skeleton": {"offsets": skeleton.offsets.tolist(), "root_height": skeleton.root_height,
                     "height": skeleton.height, "from": {"height_m": height, "source": "--height"}},
        "targets": {"names": list(targets.names), "bones": targets.bones.tolist(), "offsets": targets.offsets.tolist()},
        "prior": "prior.npz",
        "suits": [],
        "devices": {"imu": [], "keypoint_sources": [c.name for c in take.cameras]},
        "imported": {
            "from": source, "layout": layout, "config_file": str(DEFAULT_CONFIG), "calibration": calibration,
            "keypoint_set": take.source_set, "keypoint_format": take.keypoint_format, "fps": fps,
            "first_frame": take.first_frame, "frames": take.frames, "duration_s": round(duration, 3),
            "timestamps": take.timed_by,
        },
    }  # fmt: skip


def write_keypoint_session(directory: str | Path, take: KeypointTake, manifest: dict[str, Any]) -> Path:
    """Write the session: manifest, the default prior, every detection into ``keypoints.mcs``, empty ``imu.mcs``
    and ``poses.mcs``; built beside its final name and renamed into place when complete."""
    path = check_output_dir(directory, what="session directory")
    prior = resolve_prior("default")
    counters = WriterCounters()
    with atomic_directory(path) as tmp:
        if prior is not None:
            np.savez(tmp / "prior.npz", M=prior.M, mu=prior.mu, sigma=prior.sigma)
        else:
            manifest = {**manifest, "prior": None}
        for name in STREAMS:
            with (tmp / f"{name}{SUFFIX}").open("wb", buffering=1 << 20) as fh:
                fh.write(encode_record(T_HEADER, encode_header(name)))
                if name == "keypoints":
                    for t, cam, kp, cf in take.records:
                        data = encode_record(T_KEYPOINTS, encode_keypoints(cam, t, t, kp, cf))
                        fh.write(data)
                        counters.bytes += len(data)
                fh.flush()
                os.fsync(fh.fileno())
        counters.queued = counters.written = len(take.records)
        counters.flushes = 1
        ended = max((r[0] for r in take.records), default=T0_NS)
        write_json_atomic(tmp / MANIFEST, {**manifest, "closed": True, "ended_monotonic_ns": ended,
                                           "writer": asdict(counters)})  # fmt: skip
    return path

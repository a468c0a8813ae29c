"""``mocapd eval video``: the systems run on a take and the whole evaluation written out (docs/accuracy-video.md).

The metrics are :mod:`mocapd.eval.video` (and :mod:`mocapd.eval.heldout`, :mod:`mocapd.eval.video_metrics`); this
module runs the systems, which are the daemon's own parts (:mod:`mocapd.service.video_systems`) and Pose2Sim
(:mod:`mocapd.eval.pose2sim_system`), on every variant of each take, and writes ``results.json``, ``report.md``
and the pictures.
"""

from __future__ import annotations

import json
import platform
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mocapd.core.sorting import Detections2D
from mocapd.errors import InputError
from mocapd.eval.pose2sim_system import POSE2SIM_VERSION, pose2sim_missing, run_pose2sim
from mocapd.eval.video import ALL, DLT, LIVE, P2S, P2S_FILT, RESOLVE, SYSTEMS, TakeRun, take_results, variant_names
from mocapd.eval.video_input import (
    Take,
    TakeDetections,
    detect_take,
    eval_detector_config,
    pose2sim_take,
    time_aligned,
    with_calibration,
)
from mocapd.io.pose2sim_demo import DEMOS
from mocapd.io.progress import Progress
from mocapd.pipeline.landmarks import LandmarkRunner
from mocapd.service.config import Config, load_config
from mocapd.service.video_systems import dlt_from_live, run_live, run_resolve


@dataclass(frozen=True)
class VideoEvalOptions:
    """What ``mocapd eval video`` runs."""

    takes: tuple[str, ...] = DEMOS
    max_frames: int | None = None
    """Only the first frames of each take (CI)."""
    config: Path | None = None
    """mocapd config whose tracking, solver and daemon settings run (default: the shipped one)."""
    precision: str = "fp32"
    """Detector precision the detections are made at (fp32: the same on every machine)."""
    pose2sim: bool = True
    """Run Pose2Sim (it is an optional install)."""
    images: int = 3
    """Frames per camera drawn with every system's held-out projection (0: no pictures)."""
    use_cache: bool = True
    progress: bool = True
    calibration: Path | None = None
    """Score the takes with this calibration file's cameras instead of the demos' own (e.g. one from ``mocapd
    calibrate cameras --from-people``); Pose2Sim converts only the demos' own Qualisys file, so it is left out."""


def _subset(frames: list[list[Detections2D]], keep: list[int]) -> list[list[Detections2D]]:
    return [[row[c] for c in keep] for row in frames]


def run_systems(
    take: Take,
    dets: TakeDetections,
    config: Config,
    work: Path,
    with_pose2sim: bool,
    progress: Callable[[int], None] | None = None,
) -> TakeRun:
    """Every system on every variant of ``take`` (sessions and Pose2Sim projects under ``work``)."""
    run = TakeRun(take, dets, {s: {} for s in SYSTEMS})
    n = dets.n_frames
    for name, keep in variant_names(take).items():
        cams = [take.cameras[c] for c in keep]
        frames = _subset(dets.frames, keep)
        session = work / "sessions" / take.name / name
        if session.exists():
            shutil.rmtree(session)
        session.parent.mkdir(parents=True, exist_ok=True)
        live = run_live(config, cams, frames, take.fps, session, progress=progress)
        resolved = run_resolve(session, n, take.fps, progress)
        dlt = dlt_from_live(live.live, cams, frames)
        run.people[LIVE][name] = live.live.points
        run.people[RESOLVE][name] = resolved.points
        run.people[DLT][name] = dlt.points
        if name == ALL:
            run.skeletons = dict(live.live.skeletons)
    if with_pose2sim:
        out = run_pose2sim(take, dets.frames, work / "pose2sim" / take.name, variant_names(take))
        for name, o in out.items():
            run.people[P2S][name] = {f"P{i}": a for i, a in enumerate(o.raw)}
            run.people[P2S_FILT][name] = {f"P{i}": a for i, a in enumerate(o.filtered)}
        if progress is not None:
            progress(len(out))
    return run


def run_video_eval(opts: VideoEvalOptions, out: Path, say: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The whole evaluation; writes ``results.json``, ``report.md`` and the pictures into ``out``. ``say``: one line
    per take whose calibration's time offsets are applied (:func:`time_offsets_line`)."""
    from mocapd.eval.video_report import draw_held_out, write_report
    from mocapd.pipeline.detector import OnnxPoseDetector

    started = time.monotonic()
    load = _loadavg()
    config = load_config(opts.config)
    if opts.calibration is not None and opts.pose2sim:
        raise InputError("Pose2Sim runs on the demos' own calibration only: with --calibration give --no-pose2sim")
    missing = pose2sim_missing() if opts.pose2sim else "not asked for (--no-pose2sim)"
    takes = [pose2sim_take(t) for t in opts.takes]
    if opts.calibration is not None:
        takes = [with_calibration(t, opts.calibration) for t in takes]
    out.mkdir(parents=True, exist_ok=True)
    work = out / "work"
    det_cfg = eval_detector_config(config.detector.options(), opts.precision)
    detector: list[OnnxPoseDetector] = []

    def make_detector() -> OnnxPoseDetector:
        if not detector:
            detector.append(OnnxPoseDetector.from_config(det_cfg))
        return detector[0]

    # [detector] landmarks of the config: BlazePose's landmarks as the COCO-17 keypoints (detect_take). "auto" (the
    # daemon's per-pass choice from live costs) runs as "off" here: an offline pass has no tick to budget for.
    landmarks = LandmarkRunner(det_cfg.landmark_model) if det_cfg.landmark_model is not None else None

    results: dict[str, Any] = {"takes": {}}
    for take in takes:
        n = take.n_frames if opts.max_frames is None else min(opts.max_frames, take.n_frames)
        n_var = len(take.cameras) + 1
        total = n * len(take.cameras) + 2 * n_var * n + (n_var if missing is None else 0)
        with Progress(total, f"eval video {take.name}", enabled=None if opts.progress else False) as bar:
            dets = detect_take(take, make_detector, n, bar, opts.use_cache, landmarks)
            if dets.from_cache:
                bar(n * len(take.cameras))
            dets = time_aligned(take, dets)
            if take.time_offsets_s and say is not None:
                say(time_offsets_line(take))
            run = run_systems(take, dets, config, work, missing is None, bar)
        if missing is not None:
            run.notes[P2S] = f"not run: {missing}"
        res = take_results(run)
        res["detections"] = {"cache_key": dets.key, "from_cache": dets.from_cache, **dets.meta}
        res["time_offsets_s"] = dict(zip(take.camera_names, take.time_offsets_s or [0.0] * len(take.cameras),
                                         strict=True))  # fmt: skip
        if opts.images > 0:
            res["images"] = [str(p.relative_to(out)) for p in draw_held_out(run, out / "images", opts.images)]
        results["takes"][take.name] = res
    results["setup"] = {
        "config": str(opts.config) if opts.config else "the shipped config.toml",
        "precision": opts.precision,
        "landmarks": det_cfg.landmark_model or "off",
        "max_frames": opts.max_frames,
        "calibration": str(opts.calibration) if opts.calibration else "each demo's own (Qualisys)",
        "pose2sim": POSE2SIM_VERSION if missing is None else f"not run: {missing}",
        "wall_s": round(time.monotonic() - started, 1),
        "machine": {"python": platform.python_version(), "loadavg_start": load, "loadavg_end": _loadavg()},
    }
    (out / "results.json").write_text(json.dumps(_clean(results), indent=2))
    write_report(results, out / "report.md")
    return results


def time_offsets_line(take: Take) -> str:
    """What :func:`~mocapd.eval.video_input.time_aligned` did to ``take``'s detections, in one line."""
    moved = ", ".join(f"{name} {s * 1e3:+.1f} ms ({s * take.fps:+.2f} frames)"
                      for name, s in zip(take.camera_names, take.time_offsets_s, strict=True) if s)  # fmt: skip
    return (
        f"{take.name}: the calibration's time offsets applied (time_offset_s; each camera's frames blended to the "
        f"others' time): {moved}"
    )


def _loadavg() -> list[float]:
    try:
        return [float(v) for v in Path("/proc/loadavg").read_text().split()[:3]]
    except OSError:
        return []


def _clean(x: Any) -> Any:
    """JSON-safe: NaN and inf as null, numpy scalars as Python numbers."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x

"""``mocapd calibrate cameras --from-people``: the cameras' extrinsics from people walking, no board (issue 43).

Sources of detections:

* a recorded session directory (``mocapd run`` with recording on): its keypoint stream, grouped into synchronised
  moments (each camera's record nearest in capture time to the reference camera's, within half a frame), and its
  cameras' names, image sizes and intrinsics from the manifest;
* a detections file (``.npz``, the layout of ``mocapd eval video``'s cache, :mod:`mocapd.eval.video_input`, with the
  cameras' names in its ``meta``): then ``--intrinsics-from FILE`` gives the cameras;
* ``pose2sim:Demo_SinglePerson`` / ``pose2sim:Demo_MultiPerson``: the Pose2Sim demo videos through mocapd's
  detector, exactly as ``mocapd eval video`` detects them (same cache, ``~/.cache/mocapd/eval-video/``), with the
  intrinsics of the demo's Qualisys calibration (its extrinsics are not used).

Intrinsics: the source's, or ``--intrinsics-from FILE`` (any calibration file ``mocapd calibrate convert`` reads), or
``--guess-intrinsics``: a pinhole with its principal point at the image centre, no distortion and a field of view
of ``--fov-deg`` across the image's longer side (then the focal length and principal point are refined).

The core (:mod:`mocapd.core.self_calibration`) does the rest; this module turns its report into text or JSON.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from tokenize import TokenError  # numpy's header parser raises it for a damaged .npy header
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.self_calibration import (
    CalibrationComparison,
    SelfCalibration,
    SelfCalibrationOptions,
    calibrate_from_people,
    compare_calibrations,
)
from mocapd.core.sorting import Detections2D
from mocapd.core.time_offsets import CameraTimeOffset, estimate_time_offsets
from mocapd.errors import CalibrationError, InputError
from mocapd.io.calibration_files import CalibrationSet, CameraCalibration, core_cameras, read_any

FloatArray = NDArray[np.float64]
DEMO_PREFIX = "pose2sim:"


@dataclass(frozen=True)
class PeopleInput:
    """Synchronised detections: ``frames[moment][camera]``, the cameras (intrinsics), each moment's time (s)."""

    frames: list[list[Detections2D]]
    cameras: list[Camera]
    times_s: FloatArray
    source: str
    reference: list[Camera] | None = None
    """The source's own extrinsics where it has trustworthy ones (the demo's board calibration)."""


def load_people(
    source: str, intrinsics: Path | None = None, fps: float = 30.0, config: Path | None = None
) -> PeopleInput:
    """The detections of ``source``: a session directory, a detections ``.npz`` (its cameras from ``intrinsics``,
    its moments ``1/fps`` apart) or ``pose2sim:<demo>`` (module docstring; detected by ``config``'s detector,
    default the shipped config's)."""
    if source.startswith(DEMO_PREFIX):
        return _demo(source.removeprefix(DEMO_PREFIX), config)
    path = Path(source)
    if path.suffix == ".npz" and path.is_file():
        return _npz(path, intrinsics, fps)
    if not (path / "manifest.json").is_file():
        raise InputError(f"{source}: neither a session directory (no manifest.json), a detections .npz nor "
                         "pose2sim:<demo>")  # fmt: skip
    return _session(path)


def _npz(path: Path, intrinsics: Path | None, fps: float) -> PeopleInput:
    import json

    from mocapd.eval.video_input import load_detections

    if intrinsics is None:
        raise InputError(f"{path}: a detections file has no cameras: give --intrinsics-from FILE")
    try:
        with np.load(path, allow_pickle=False) as z:
            names = json.loads(str(z["meta"])).get("cameras")
    except (OSError, ValueError, KeyError, json.JSONDecodeError, TokenError) as exc:
        raise InputError(f"{path}: not a detections file ({exc})") from None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise InputError(f"{path}: its meta names no cameras")
    dets = load_detections(path, len(names))
    if dets is None:
        raise InputError(f"{path}: damaged, or not {len(names)} cameras' detections")
    given = {c.name: c for c in core_cameras(read_any(intrinsics))}
    missing = [n for n in names if n not in given]
    if missing:
        raise CalibrationError(f"camera(s) {missing} are not in {intrinsics} (it has {sorted(given)})")
    cams = [replace(given[n], R=np.eye(3), t=np.zeros(3)) for n in names]
    return PeopleInput(dets.frames, cams, np.arange(dets.n_frames) / fps, f"detections {path}")


def _session(path: Path) -> PeopleInput:
    from mocapd.io.session import open_session
    from mocapd.service.session.solve import session_rig

    session = open_session(path)
    cameras = session_rig(session).cameras
    recs = session.keypoints()
    if not recs:
        raise InputError(f"{path}: the session has no keypoints (record with the detector running)")
    n = len(cameras)
    per: list[list[tuple[int, Detections2D]]] = [[] for _ in range(n)]
    for r in recs:
        if 0 <= r.camera < n:
            per[r.camera].append((r.capture_ns, Detections2D(r.keypoints, r.confidences)))
    for lst in per:
        lst.sort(key=lambda x: x[0])
    ref = max(range(n), key=lambda c: len(per[c]))
    t_ref = np.array([t for t, _ in per[ref]], dtype=np.int64)
    if len(t_ref) < 2:
        raise InputError(f"{path}: too few detected frames to calibrate from")
    tol = 0.5 * float(np.median(np.diff(t_ref)))
    frames = []
    n_kp = per[ref][0][1].keypoints.shape[1]
    times = [np.array([t for t, _ in lst], dtype=np.int64) for lst in per]
    for k, t in enumerate(t_ref):
        row = []
        for c in range(n):
            if c == ref:
                row.append(per[ref][k][1])
                continue
            i = int(np.searchsorted(times[c], t))
            best = min((j for j in (i - 1, i) if 0 <= j < len(times[c])), key=lambda j: abs(times[c][j] - t),
                       default=None)  # fmt: skip
            ok = best is not None and abs(int(times[c][best]) - int(t)) <= tol
            row.append(per[c][best][1] if ok and best is not None else Detections2D.empty(n_kp))
        frames.append(row)
    return PeopleInput(frames, cameras, (t_ref - t_ref[0]) / 1e9, f"session {path}")


def _demo(name: str, config: Path | None = None) -> PeopleInput:
    from mocapd.eval.video_input import detect_take, eval_detector_config, pose2sim_take
    from mocapd.pipeline.detector import OnnxPoseDetector
    from mocapd.pipeline.landmarks import LandmarkRunner
    from mocapd.service.config import load_config

    det_cfg = eval_detector_config(load_config(config).detector.options())
    take = pose2sim_take(name)
    made: list[OnnxPoseDetector] = []

    def make() -> OnnxPoseDetector:
        if not made:
            made.append(OnnxPoseDetector.from_config(det_cfg))
        return made[0]

    # [detector] landmarks (presets/eval-video-landmarks-heavy.toml): BlazePose's landmarks as the COCO-17 keypoints,
    # as `mocapd eval video` detects them (same cache).
    landmarks = LandmarkRunner(det_cfg.landmark_model) if det_cfg.landmark_model is not None else None
    dets = detect_take(take, make, landmarks=landmarks)
    cams = [replace(c, R=np.eye(3), t=np.zeros(3)) for c in take.cameras]
    times = np.arange(dets.n_frames) / take.fps
    what = "" if landmarks is None else f", BlazePose {landmarks.variant} landmarks"
    return PeopleInput(dets.frames, cams, times, f"{DEMO_PREFIX}{name} ({take.source}{what})", list(take.cameras))


def guessed_cameras(cameras: list[Camera], fov_deg: float) -> list[Camera]:
    """The cameras with guessed intrinsics: principal point at the centre, no distortion, ``fov_deg`` across the
    longer image side."""
    out = []
    for c in cameras:
        f = 0.5 * max(c.width, c.height) / np.tan(np.radians(fov_deg) / 2.0)
        K = np.array([[f, 0.0, (c.width - 1) / 2.0], [0.0, f, (c.height - 1) / 2.0], [0.0, 0.0, 1.0]])
        out.append(replace(c, K=K, dist=np.zeros(5)))
    return out


def with_intrinsics(cameras: list[Camera], calib: CalibrationSet) -> list[Camera]:
    """The cameras with the intrinsics (K, distortion) of ``calib`` (by name; every camera must be there)."""
    given = {c.name: c for c in core_cameras(calib)}
    missing = [c.name for c in cameras if c.name not in given]
    if missing:
        raise CalibrationError(f"camera(s) {missing} are not in the intrinsics file (it has {sorted(given)})")
    return [replace(c, K=given[c.name].K, dist=given[c.name].dist) for c in cameras]


def moments_between(times_s: FloatArray, start_s: float, length_s: float = 1.0) -> tuple[int, int]:
    """The moment indices (first, last excluded) from ``start_s`` for ``length_s`` seconds."""
    lo = int(np.searchsorted(times_s, start_s))
    hi = int(np.searchsorted(times_s, start_s + length_s))
    if hi <= lo:
        raise CalibrationError(f"no moment between {start_s} s and {start_s + length_s} s (the take lasts "
                               f"{float(times_s[-1]) if len(times_s) else 0.0:.1f} s)")  # fmt: skip
    return lo, hi


def calibrate(
    people: PeopleInput, options: SelfCalibrationOptions, reference: list[Camera] | None = None
) -> tuple[CalibrationSet, dict[str, Any]]:
    """Self-calibrate, time each camera against the others (:mod:`mocapd.core.time_offsets`, on the cameras just
    calibrated), and build the calibration file's contents and the JSON report.

    A camera found a frame or more late was calibrated on people it saw at other moments than the rest, which pulls
    its pose towards the lag and its timing back towards zero (on the synthetic rig, 2 frames came back as 1.7):
    then its detections are moved by the whole frames found and the rig is calibrated and timed again once, and its
    offset is the frames moved plus the second estimate."""
    fps = frame_rate(people.times_s)
    res = calibrate_from_people(people.frames, people.cameras, options)
    offsets = estimate_time_offsets(people.frames, res.cameras, fps)
    whole = [0 if o.offset_frames is None else round(o.offset_frames) for o in offsets]
    if any(whole):
        res = calibrate_from_people(moved_frames(people.frames, whole), people.cameras, options)
        again = estimate_time_offsets(moved_frames(people.frames, whole), res.cameras, fps)
        offsets = [plus_frames(o, k, fps) for o, k in zip(again, whole, strict=True)]
    ref = reference if reference is not None else None
    comparison = compare_calibrations(res.cameras, ref) if ref is not None else None
    calib = CalibrationSet(
        tuple(
            CameraCalibration(
                c.name,
                (c.width, c.height),
                c.K,
                c.dist,
                c.R,
                c.t,
                round(q.rms_px, 3) if np.isfinite(q.rms_px) else None,
                None if o.offset_s is None else round(o.offset_s, 4),
            )
            for c, q, o in zip(res.cameras, res.report.cameras, offsets, strict=True)
        ),
        f"mocapd calibrate cameras --from-people ({people.source})",
    )
    return calib, {**report_json(res, comparison), "time_offsets": time_offsets_json(offsets)}


def moved_frames(frames: list[list[Detections2D]], whole: list[int]) -> list[list[Detections2D]]:
    """The moments with camera ``c``'s detections taken ``whole[c]`` frames later (its frames run that late); the
    moments some camera lacks at either end are left out."""
    lo, hi = max(0, -min(whole)), len(frames) - max(0, *whole)
    return [[frames[i + k][c] for c, k in enumerate(whole)] for i in range(lo, hi)]


def plus_frames(o: CameraTimeOffset, k: int, fps: float) -> CameraTimeOffset:
    """An estimate made on detections moved by ``k`` frames, as an offset of the unmoved camera."""
    curve = {s + k: r for s, r in o.curve_px.items()}
    at_zero = curve.get(0, float("nan"))  # the residual of the camera as it is, not as moved
    if o.offset_frames is None or o.offset_s is None:
        return replace(o, curve_px=curve, residual_at_zero_px=at_zero)
    return replace(o, offset_frames=round(o.offset_frames + k, 3), offset_s=o.offset_s + k / fps, curve_px=curve,
                   residual_at_zero_px=at_zero)  # fmt: skip


def frame_rate(times_s: FloatArray) -> float:
    """The moments' rate, Hz (the median step)."""
    steps = np.diff(np.asarray(times_s, np.float64))
    steps = steps[steps > 0]
    if steps.size == 0:
        raise CalibrationError("the moments have no time steps to take a frame rate from")
    return float(1.0 / np.median(steps))


def time_offsets_json(offsets: list[CameraTimeOffset]) -> dict[str, dict[str, Any]]:
    """The cameras' time offsets for the report (ms, ``[daemon.offsets]`` convention)."""
    return {
        o.name: {
            "offset_ms": None if o.offset_s is None else round(o.offset_s * 1e3, 1),
            "offset_frames": o.offset_frames,
            "quality": o.quality,
            "spread_frames": None if not np.isfinite(o.spread_frames) else o.spread_frames,
            "residual_px": None if not np.isfinite(o.residual_px) else o.residual_px,
            "residual_at_zero_px": None if not np.isfinite(o.residual_at_zero_px) else o.residual_at_zero_px,
            "speed_px": o.speed_px,
            "frames": o.frames,
            "curve_px": {str(k): v for k, v in o.curve_px.items()},
            "refused": o.reason or None,
        }
        for o in offsets
    }


def report_json(res: SelfCalibration, comparison: CalibrationComparison | None) -> dict[str, Any]:
    """The report as JSON-ready data."""
    r = res.report
    out: dict[str, Any] = {
        "verdict": r.verdict,
        "cameras": {
            q.name: {
                "observations": q.observations,
                "rejected": q.rejected,
                "rms_px": round(q.rms_px, 3),
                "median_px": round(q.median_px, 3),
                "coverage": round(q.coverage, 3),
                "empty": q.empty,
            }
            for q in r.cameras
        },
        "shared_points": {f"{a}-{b}": n for (a, b), n in r.shared_points.items()},
        "pair_inliers": {f"{a}-{b}": n for (a, b), n in r.pair_inliers.items()},
        "moments": r.moments,
        "people_instances": r.people_instances,
        "points": r.points,
        "height_m": r.height_m,
        "height_given": r.height_given,
        "up_from": r.up_from,
        "floor_extent_m": list(r.floor_extent_m),
        "origin": r.origin,
        "advice": r.advice,
    }
    if comparison is not None:
        out["against_reference"] = {
            "rotation_deg": comparison.rotation_deg,
            "centre_mm": comparison.centre_mm,
            "scale_error": comparison.scale_error,
            "up_deg": comparison.up_deg,
            "relative_rotation_deg": comparison.relative_rotation_deg,
        }
    return out


def report_text(report: dict[str, Any], output: Path) -> str:
    """The report for people: per camera, the pairs, the world, the verdict and what to do."""
    given = "given" if report["height_given"] else "default, not measured"
    lines = [
        f"calibrated {len(report['cameras'])} cameras from {report['people_instances']} people-moments in "
        f"{report['moments']} moments ({report['points']} 3D keypoints) -> {output}",
        "",
        f"{'camera':<12} {'keypoints':>9} {'rejected':>8} {'rms px':>7} {'median px':>9} {'coverage':>8}  empty parts",
    ]
    for name, q in report["cameras"].items():
        lines.append(f"{name:<12} {q['observations']:>9} {q['rejected']:>8} {q['rms_px']:>7.2f} "
                     f"{q['median_px']:>9.2f} {q['coverage']:>8.0%}  {', '.join(q['empty']) or '-'}")  # fmt: skip
    lines.append("")
    lines.append("views shared (3D keypoints seen by both): " +
                 ", ".join(f"{k} {v}" for k, v in report["shared_points"].items()))  # fmt: skip
    lines.append(f"scale: people {report['height_m']:.2f} m tall ({given}); up: {report['up_from']}; "
                 f"floor walked {report['floor_extent_m'][0]:.1f} x {report['floor_extent_m'][1]:.1f} m")  # fmt: skip
    lines.append(f"origin: {report['origin']}")
    lines += _offsets_text(report.get("time_offsets", {}))
    if "against_reference" in report:
        c = report["against_reference"]
        lines.append("")
        lines.append("against the reference calibration (after a similarity alignment):")
        lines.append("  rotation deg: " + ", ".join(f"{k} {v:.3f}" for k, v in c["rotation_deg"].items()))
        lines.append("  centre mm:    " + ", ".join(f"{k} {v:.0f}" for k, v in c["centre_mm"].items()))
        lines.append(f"  scale error {c['scale_error']:+.2%}, up {c['up_deg']:.2f} deg, "
                     f"worst relative rotation {c['relative_rotation_deg']:.3f} deg")  # fmt: skip
    lines.append("")
    lines.append(f"verdict: {report['verdict']}")
    lines += [f"  - {a}" for a in report["advice"]]
    return "\n".join(lines)


def _offsets_text(offsets: dict[str, dict[str, Any]]) -> list[str]:
    """The time offsets' lines: per camera the offset and its confidence or why it was refused, and the config line
    that applies the ones found."""
    if not offsets:
        return []
    lines = ["", "time offsets (each camera against the others' triangulation; + = its frames run late):"]
    for name, o in offsets.items():
        if o["refused"]:
            lines.append(f"  {name:<12} not estimated: {o['refused']}")
        else:
            lines.append(f"  {name:<12} {o['offset_ms']:+7.1f} ms ({o['offset_frames']:+.2f} frames), margin "
                         f"{o['quality']:.2f}, spread {o['spread_frames']:.2f} frames, {o['residual_at_zero_px']:.1f}"
                         f" -> {o['residual_px']:.1f} px")  # fmt: skip
    found = {n: o["offset_ms"] for n, o in offsets.items() if o["offset_ms"] is not None}
    if any(abs(v) >= 1.0 for v in found.values()):
        pairs = ", ".join(f"{n} = {v / 1e3:.4f}" for n, v in found.items())
        lines.append(
            f"  to apply them (written beside each camera as time_offset_s): [daemon.offsets] cameras = {{ {pairs} }}"
        )
    return lines


def reference_cameras(path: Path, cameras: list[Camera]) -> list[Camera]:
    """The cameras of a reference calibration file, for the comparison."""
    given = {c.name: c for c in core_cameras(read_any(path))}
    return [given[c.name] for c in cameras if c.name in given]

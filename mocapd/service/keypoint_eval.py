"""``mocapd eval keypoints``: the multi-person benchmark of :mod:`mocapd.eval.keypoint_bench` run through the
commands a user runs.

The scene's detections are written as OpenPose BODY_25 folders and a calibration file under ``OUT/input``, then
``mocapd import keypoints`` makes a session of them and ``mocapd resolve`` solves it twice: ``--no-smooth -o`` (the
forward pass: the live daemon's scheduler, tracker and per-person solver over every frame, as live) and the
default (forward pass + RTS smoothing). Both, and the naive DLT of the truth-associated detections, are scored
(PCP per actor and limb, MPJPE, misses, false-positive tracks, identity switches) into ``OUT/keypoints.json`` and
``OUT/keypoints.md``, beside Pose2Sim on the same OpenPose folders and calibration (its own multi-person
association, triangulation and filtering, :func:`mocapd.eval.pose2sim_system.run_pose2sim_openpose`, in
``OUT/pose2sim``) when it is installed and not left out.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from mocapd.core.keypoints import BODY25_FORMAT, TrackTargets
from mocapd.core.kinematics import Kinematics
from mocapd.core.per_skeleton import skeleton_key
from mocapd.core.skeleton import Skeleton
from mocapd.eval.keypoint_bench import (
    FPS,
    LIMB_GROUPS,
    LIMBS,
    Estimates,
    FloatArray,
    Noise,
    build_scene,
    detect,
    dlt_baseline,
    score,
    visible,
    write_calibration,
    write_openpose,
)
from mocapd.io.imu_recordings import T0_NS
from mocapd.io.session import RESOLVED, open_session
from mocapd.protocols.session_format import PoseRecord
from mocapd.service.session.solve import session_rig


def _estimates(frames: list[PoseRecord], n_frames: int, rig: Skeleton) -> Estimates:
    """The session's poses by input frame (the instant each pose is for, on the frame clock), as the BODY_25
    keypoints of each person's solved pose on their own (sized) skeleton: the points the truth and the DLT have."""
    kins: dict[bytes, tuple[Kinematics, TrackTargets]] = {}
    out: list[list[tuple[str, FloatArray]]] = [[] for _ in range(n_frames)]
    for r in frames:
        for p in r.people:
            t = (p.t_pose_ns if p.t_pose_ns is not None else r.t_solve_ns) - T0_NS
            f = round(t * FPS / 1e9)
            if not 0 <= f < n_frames:
                continue
            sk = p.skeleton if p.skeleton is not None else rig
            key = skeleton_key(sk)
            if key not in kins:
                kins[key] = (Kinematics(sk), BODY25_FORMAT.track_targets(sk))
            kin, tg = kins[key]
            out[f].append((p.identity, np.asarray(kin.targets(kin.forward(p.theta), tg.bones, tg.offsets))))
    return Estimates(out)


def _pose2sim_estimates(people: list[FloatArray], n_frames: int) -> Estimates:
    """Pose2Sim's filtered people (each (n_frames, 25, 3), BODY_25's order) by frame, a person where it has a point."""
    out: list[list[tuple[str, FloatArray]]] = [[] for _ in range(n_frames)]
    for i, pts in enumerate(people):
        for f in range(min(n_frames, len(pts))):
            if np.isfinite(pts[f]).any():
                out[f].append((f"pose2sim:{i}", np.asarray(pts[f])))
    return Estimates(out)


def _run_pose2sim(folders: list[Path], inp: Path, out: Path, n_frames: int) -> list[FloatArray]:
    from mocapd.eval.pose2sim_system import run_pose2sim_openpose
    from mocapd.io.calibration_files import read_any, write_pose2sim_toml

    work = out / "pose2sim"
    work.mkdir(parents=True, exist_ok=True)
    write_pose2sim_toml(read_any(inp / "calibration.toml"), work / "Calib.toml")  # Pose2Sim's Z-up world
    return run_pose2sim_openpose(folders, work / "Calib.toml", FPS, n_frames, work).filtered


def _cli(argv: list[str]) -> None:
    from mocapd.errors import MocapdError
    from mocapd.service.cli import main

    with contextlib.redirect_stdout(io.StringIO()):
        rc = main(argv)
    if rc != 0:
        raise MocapdError(f"`mocapd {' '.join(argv)}` exited {rc}")


def run_keypoint_eval(out: Path, n_people: int = 3, seconds: float = 10.0, seed: int = 0,
                      noise: Noise | None = None, data_root: Path | None = None,
                      pose2sim: bool = True) -> dict[str, Any]:  # fmt: skip
    """Build, write, import, resolve and score the benchmark (see the module docstring); returns the report."""
    from mocapd.eval.pose2sim_system import POSE2SIM_VERSION, pose2sim_missing

    missing = pose2sim_missing() if pose2sim else "not asked for (--no-pose2sim)"
    noise = noise if noise is not None else Noise()
    scene = build_scene(n_people, seconds, data_root)
    det = detect(scene, noise, seed)
    vis = visible(det, n_people)
    inp = out / "input"
    folders = write_openpose(det, scene.cameras, inp / "openpose")
    write_calibration(scene.cameras, inp / "calibration.toml")
    session = out / "session"
    _cli(["import", "keypoints", *map(str, folders), "-o", str(session), "--calibration",
          str(inp / "calibration.toml"), "--fps", str(FPS)])  # fmt: skip
    forward_file = out / "forward.mcs"
    _cli(["resolve", str(session), "--no-smooth", "-o", str(forward_file), "--force"])
    _cli(["resolve", str(session)])
    s = open_session(session)
    n, rig = scene.n_frames, session_rig(s).skeleton
    names = BODY25_FORMAT.keypoints
    systems = {
        "mocapd forward (live scheduler)": score(scene.keypoints, _estimates(s.require_poses_file(forward_file), n,
                                                                             rig), vis, names, LIMBS),
        "mocapd resolve": score(scene.keypoints, _estimates(s.require_poses(RESOLVED), n, rig), vis, names, LIMBS),
        "DLT, truth-associated views": score(scene.keypoints, dlt_baseline(scene, det), vis, names, LIMBS),
    }  # fmt: skip
    if missing is None:
        people = _run_pose2sim(folders, inp, out, n)
        systems["Pose2Sim (its association, triangulation, filter)"] = score(
            scene.keypoints, _pose2sim_estimates(people, n), vis, names, LIMBS)  # fmt: skip
    report = {
        "benchmark": {"people": n_people, "clips": scene.clips, "seconds": seconds, "fps": FPS, "seed": seed,
                      "cameras": len(scene.cameras), "image": [scene.cameras[0].width, scene.cameras[0].height],
                      "noise": noise.__dict__, "flipped_views": det.flips, "occluded_keypoints": det.occluded,
                      "false_positive_detections": det.false_positives,
                      "visible_person_frames": int(vis.sum()),
                      "pose2sim": POSE2SIM_VERSION if missing is None else f"not run: {missing}"},
        "commands": [f"mocapd import keypoints {inp}/openpose/cam*_json -o {session} --calibration "
                     f"{inp}/calibration.toml --fps {FPS:g}", f"mocapd resolve {session} --no-smooth -o {forward_file}",
                     f"mocapd resolve {session}"],
        "systems": systems,
    }  # fmt: skip
    (out / "keypoints.json").write_text(json.dumps(report, indent=2))
    (out / "keypoints.md").write_text(markdown(report))
    return report


def markdown(report: dict[str, Any]) -> str:
    """The report as markdown tables: per system PCP per actor and average, MPJPE, tracks; PCP per limb group."""
    b = report["benchmark"]
    lines = [f"# mocapd eval keypoints: {b['people']} people, {b['seconds']:g} s at {b['fps']:g} fps, "
             f"{b['cameras']} cameras {b['image'][0]}x{b['image'][1]}", "",
             f"Clips: {', '.join(b['clips'])}. Detector errors: {b['flipped_views']} flipped views, "
             f"{b['occluded_keypoints']} occluded keypoints, {b['false_positive_detections']} false-positive "
             f"detections; {b['visible_person_frames']} visible person-frames. Pose2Sim: {b.get('pose2sim', '-')}.",
             "",
             "| system | PCP per actor → average | MPJPE | misses (after 0.2 s) | first published (s) | ID switches "
             "| tracks (false positive) |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, s in report["systems"].items():
        actors = " / ".join(f"{a['pcp']:.2f}" for a in s["actors"])
        first = " / ".join("-" if a["first_published_s"] is None else f"{a['first_published_s']:.2f}"
                           for a in s["actors"])  # fmt: skip
        lines.append(f"| {name} | {actors} → **{s['pcp_average']:.2f}** | {s['mpjpe_mm']} mm | {s['misses']} "
                     f"({s['misses_after_first_0.2s']}) | {first} | {s['identity_switches']} | {s['tracks']} "
                     f"({s['false_positive_tracks']}) |")  # fmt: skip
    lines += ["", "PCP per limb group (mean over actors):", "",
              "| system | " + " | ".join(LIMB_GROUPS) + " |", "|---|" + "---|" * len(LIMB_GROUPS)]  # fmt: skip
    for name, s in report["systems"].items():
        vals = [np.mean([a["pcp_limbs"][g] for a in s["actors"]]) for g in LIMB_GROUPS]
        lines.append(f"| {name} | " + " | ".join(f"{v:.2f}" for v in vals) + " |")
    return "\n".join(lines) + "\n"

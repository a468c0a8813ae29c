"""Sensor-to-segment calibration in realistic postures (issue 42): ``python -m mocapd.eval.calibration_posture``.

A suit owner rarely holds a textbook T-pose: the upper arms hang 15-35° below horizontal, the elbows are 10-30° bent,
the knees 0-10°, and every sensor is strapped a few degrees askew. This evaluation simulates exactly that on the
development split's clips (CMU 131_02 and Bandai "normal"/"happy": never the evaluation split), 13 sensors at 60 Hz:

1. 2 s standing still in a random realistic posture (each side drawn on its own from the ranges above), facing +Z;
   1 s moving into the clip's first pose; then up to ``seconds`` of the clip;
2. each sensor strapped with its case along the segment (any of the 24 ways) and turned 5-15° about a random axis;
   orientations with 0.2° of jitter, specific force with 0.03 m/s² of noise (MTw-like, docs/imu.md);
3. calibrated from the first 2 s with the facing known (what ``calibrate imu --from`` does after its still-window
   search): **before**, the T-pose assumed exactly (``--pose t-pose --pose-exact``, mocapd before issue 42); **after**,
   the posture estimated from the hint ``--pose a-pose`` and from ``--pose t-pose``; the a-pose calibration with
   its mountings refined by the hinge axes of the whole take's motion (:mod:`mocapd.core.functional_calibration`),
   and then by gravity in its stances (:mod:`mocapd.core.stance_calibration`), what ``calibrate imu --from`` does;
   ``--sway DEG`` also leans the standing pelvis, trunk and legs (a posture the still window's priors take for
   upright), ``--clip`` chooses the clips (``WALKS``: the development split's walks);
4. solved IMU-only with the default options and prior (:class:`~mocapd.core.solver.PoseSolver`, foot contacts on)
   and measured over the clip (the standing and the move into it left out): joint position error relative to the
   hips joint by group (legs, trunk and head, arms; mm, mean over joints and frames), elbow / knee / hip flexion
   (:func:`~mocapd.core.plausibility.hinge_angles`, the thigh's sagittal angle in the pelvis) RMSE and bias (solved
   minus true, degrees), each calibration's posture error (its estimated upper-arm drop, elbow and knee bend
   against the simulated posture's) and its mountings' error per segment (``mount_<segment>_deg``: the angle from
   the simulated mountings, degrees); the functional rows say per hinge whether it refined and why not.

Prints JSON. Deterministic for a seed.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.functional_calibration import refine_mountings, still_orientations
from mocapd.core.ground import GroundOptions
from mocapd.core.imu import (
    IMU_SET_13,
    default_mounts,
    sensor_orientation_from_bone,
    specific_force_from_acceleration,
)
from mocapd.core.imu_calibration import (
    _AXIS_ALIGNED,
    ImuCalibration,
    calibrate_recording,
    heading_alignment,
    posture_angles,
    rest_orientations,
    window_samples,
)
from mocapd.core.kinematics import Kinematics
from mocapd.core.knee_extension import refine_knee_extension
from mocapd.core.plausibility import hinge_angles
from mocapd.core.prior import PcaPrior
from mocapd.core.rotations import quat_angle, quat_from_matrix, quat_from_rotvec, quat_multiply
from mocapd.core.skeleton import BONE_INDEX, BONE_NAMES, Skeleton
from mocapd.core.solver import PoseSolver
from mocapd.core.stance_calibration import refine_from_stances
from mocapd.eval.ground_optical import hip_flexion
from mocapd.eval.ground_real import calibrated_observations

FloatArray = NDArray[np.float64]
FPS = 60.0
STILL_S = 2.0
BLEND_S = 1.0
CLIPS = (
    "mocap/cmu/131_02.bvh",
    "mocap/bandai/dataset-1_walk_normal_001.bvh",
    "mocap/bandai/dataset-1_bye_normal_001.bvh",
    "mocap/bandai/dataset-1_guide_happy_001.bvh",
    "mocap/bandai/dataset-1_bow_normal_001.bvh",
)
"""Development-split clips (``mocapd/data/eval_splits.toml``): a CMU walk, a walk, a wave, a guiding gesture, a bow."""
WALKS = (
    "mocap/cmu/131_02.bvh",
    "mocap/bandai/dataset-1_walk_normal_001.bvh",
    "mocap/bandai/dataset-1_walk_happy_001.bvh",
    "mocap/bandai/dataset-1_walk-back_normal_001.bvh",
    "mocap/bandai/dataset-1_walk-left_normal_001.bvh",
    "mocap/bandai/dataset-1_walk-right_normal_001.bvh",
)
"""The development split's walks (``--clip WALKS``): the takes with stances, for gravity from stances."""
METHODS = {
    "before: T-pose assumed": ("t-pose", False, False, False, False),
    "after: --pose a-pose (estimated)": ("a-pose", True, False, False, False),
    "after: --pose t-pose (estimated)": ("t-pose", True, False, False, False),
    "after: --pose a-pose + hinge axes from the motion": ("a-pose", True, True, False, False),
    "after: --pose a-pose + hinge axes + gravity from stances": ("a-pose", True, True, False, True),
    "not done: --pose a-pose + hinge axes + knee extension applied + stances": ("a-pose", True, True, True, True),
}
"""Label -> (posture hint, posture estimated from the still window, mountings refined by the take's hinge axes:
:func:`mocapd.core.functional_calibration.refine_mountings`, by the knees' extension over it:
:func:`mocapd.core.knee_extension.refine_knee_extension`, and by gravity in its stances:
:func:`mocapd.core.stance_calibration.refine_from_stances`; the row before the last is what ``calibrate imu --from``
does with a take; the last applies the knees' extension, which ``calibrate imu --from`` measures only)."""
GROUPS = {
    "legs": [b for b in BONE_NAMES if "Leg" in b or "Foot" in b or "Toes" in b],
    "trunk_head": ["Spine", "Spine1", "Spine2", "Spine3", "Neck", "Head"],
    "arms": [b for b in BONE_NAMES if "Arm" in b or "Hand" in b],
}


def realistic_posture(
    skeleton: Skeleton, rng: np.random.Generator, sway_deg: float = 0.0
) -> tuple[FloatArray, dict[str, float]]:
    """θ (66,) of a still standing posture drawn from the realistic ranges, and its angles (degrees).

    ``sway_deg`` > 0 also leans the body forward or back as people stand (each drawn in ±``sway_deg`` about the
    left-right axis): the pelvis, the trunk (sternum and head) and each leg (its hip ahead of or behind its ankle, the
    foot flat), what the still window's priors take for upright (:mod:`mocapd.core.stance_calibration`)."""
    theta = skeleton.rest_pose()
    truth: dict[str, float] = {}
    pelvis, trunk = rng.uniform(-sway_deg, sway_deg, 2) if sway_deg > 0 else (0.0, 0.0)

    def turn(bone: str, rotvec_deg: tuple[float, float, float]) -> None:
        i = 3 + 3 * BONE_INDEX[bone]
        theta[i : i + 3] = np.radians(rotvec_deg)

    if sway_deg > 0:
        turn("Hips", (float(pelvis), 0.0, 0.0))
        turn("Spine", (float(trunk - pelvis), 0.0, 0.0))
    for side, s in (("Left", 1.0), ("Right", -1.0)):
        drop, elbow, knee = rng.uniform(15.0, 35.0), rng.uniform(10.0, 30.0), rng.uniform(0.0, 10.0)
        lean = float(rng.uniform(-sway_deg, sway_deg)) if sway_deg > 0 else 0.0
        turn(f"{side}UpperArm", (0.0, 0.0, -s * drop))
        turn(f"{side}LowerArm", (0.0, -s * elbow, 0.0))
        turn(f"{side}UpperLeg", (-knee / 2 + lean - float(pelvis), 0.0, 0.0))
        turn(f"{side}LowerLeg", (knee, 0.0, 0.0))
        turn(f"{side}Foot", (-knee / 2 - lean, 0.0, 0.0))
        truth |= {f"{side.lower()}_upper_arm_drop": drop, f"{side.lower()}_elbow_bend": elbow,
                  f"{side.lower()}_knee_bend": knee}  # fmt: skip
    return theta, truth


def strapped_mounting(rng: np.random.Generator) -> FloatArray:
    """A case along its segment (one of the 24 ways), turned 5-15° about a random axis; (4,)."""
    axis = rng.normal(size=3)
    askew = quat_from_rotvec(np.radians(rng.uniform(5.0, 15.0)) * axis / np.linalg.norm(axis))
    return np.asarray(quat_multiply(askew, _AXIS_ALIGNED[rng.integers(len(_AXIS_ALIGNED))]))


SEGMENTS = ("UpperArm", "LowerArm", "UpperLeg", "LowerLeg", "Hips", "Spine3", "Head", "Foot")
"""The segments whose mounting error the table gives (left and right together)."""


def mounting_errors(calib: ImuCalibration, true_mounts: dict[str, FloatArray]) -> dict[str, float]:
    """Per segment (:data:`SEGMENTS`), the angle of the calibration's mountings from the simulated ones (sensor id ->
    (4,), degrees, mean over the sensors on it)."""
    out: dict[str, list[float]] = {}
    for sid, bone in calib.bones.items():
        seg = next(s for s in SEGMENTS if bone.endswith(s))
        out.setdefault(seg, []).append(float(np.degrees(quat_angle(calib.q_ib[sid], true_mounts[sid]))))
    return {s: round(float(np.mean(v)), 1) for s, v in out.items()}


def simulate_take(
    skeleton: Skeleton, motion: FloatArray, rng: np.random.Generator, sway_deg: float = 0.0
) -> tuple[
    dict[str, tuple[FloatArray, FloatArray, FloatArray]],
    dict[str, str],
    FloatArray,
    dict[str, float],
    dict[str, FloatArray],
]:
    """Samples per sensor (t, q, acc), the assignment, the truth θ (n, 66), the posture's angles and the sensors'
    true mountings (4,)."""
    posture, angles = realistic_posture(skeleton, rng, sway_deg)
    posture[:3] = [motion[0, 0], motion[0, 1], motion[0, 2]]
    still = np.repeat(posture[None], round(STILL_S * FPS), axis=0)
    w = np.linspace(0.0, 1.0, round(BLEND_S * FPS))[:, None]
    theta = np.concatenate([still, (1.0 - w) * posture + w * motion[0], motion])
    kin = Kinematics(skeleton)
    fk = kin.forward(theta)
    mounts = default_mounts(IMU_SET_13, skeleton)
    bones = np.array([m.bone_index for m in mounts])
    sites = kin.targets(fk, bones, np.array([m.t_ib for m in mounts]))
    acc = np.zeros_like(sites)
    acc[1:-1] = (sites[2:] - 2 * sites[1:-1] + sites[:-2]) * FPS**2
    q_gb = quat_from_matrix(fk.rotations[:, bones])
    q_ig = heading_alignment(0.0)
    t = np.arange(len(theta)) / FPS
    samples, assignment, true_mounts = {}, {}, {}
    for k, m in enumerate(mounts):
        sid = f"00B4{0x3100 + k:04X}"
        jitter = quat_from_rotvec(rng.normal(0.0, np.radians(0.2) / np.sqrt(3), (len(theta), 3)))
        true_mounts[sid] = strapped_mounting(rng)
        q_i = quat_multiply(sensor_orientation_from_bone(q_ig, q_gb[:, k], true_mounts[sid]), jitter)
        f = specific_force_from_acceleration(q_ig, q_i, acc[:, k]) + rng.normal(0.0, 0.03, (len(theta), 3))
        samples[sid] = (t, q_i, f)
        assignment[sid] = m.bone
    return samples, assignment, theta, angles, true_mounts


def measure(theta: FloatArray, truth: FloatArray, skeleton: Skeleton) -> dict[str, Any]:
    """Errors of θ against the truth over the clip part (see the module docstring)."""
    part = slice(round((STILL_S + BLEND_S) * FPS), None)
    kin = Kinematics(skeleton)
    p = kin.forward(theta[part]).positions
    q = kin.forward(truth[part]).positions
    rel_p, rel_q = p - p[:, :1], q - q[:, :1]
    err = np.linalg.norm(rel_p - rel_q, axis=-1) * 1000.0
    out: dict[str, Any] = {"joint_error_mm": round(float(err[:, 1:].mean()), 1)}
    out |= {f"{g}_mm": round(float(err[:, [BONE_INDEX[b] for b in bones]].mean()), 1) for g, bones in GROUPS.items()}
    ours, true = hinge_angles(theta[part]), hinge_angles(truth[part])
    hips, hips_true = hip_flexion(theta[part]), hip_flexion(truth[part])
    for name, a, b in (
        ("elbow", [ours[f"{s}_elbow"] for s in ("left", "right")], [true[f"{s}_elbow"] for s in ("left", "right")]),
        ("knee", [ours[f"{s}_knee"] for s in ("left", "right")], [true[f"{s}_knee"] for s in ("left", "right")]),
        ("hip", [hips[s] for s in ("left", "right")], [hips_true[s] for s in ("left", "right")]),
    ):
        e = np.concatenate(a) - np.concatenate(b)
        e = e[np.isfinite(e)]
        out[f"{name}_rmse_deg"] = round(float(np.sqrt(np.mean(e**2))), 1)
        out[f"{name}_bias_deg"] = round(float(np.mean(e)), 1)
    return out


def run(
    seconds: float,
    seed: int,
    data_root: Path,
    prior: PcaPrior | None,
    sway_deg: float = 0.0,
    clips: tuple[str, ...] = CLIPS,
) -> dict[str, Any]:
    from mocapd.eval.data import load_clip

    rng = np.random.default_rng(seed)
    rows: dict[str, list[dict[str, Any]]] = {m: [] for m in METHODS}
    posture_err: dict[str, list[float]] = {m: [] for m in METHODS}
    for path in clips:
        clip = load_clip(data_root / path, FPS)
        motion = clip.theta[: round(seconds * FPS)]
        samples, bones, truth, angles, true_mounts = simulate_take(clip.skeleton, motion, rng, sway_deg)
        hinge_rows: dict[str, Any] = {}
        stance_rows: dict[str, Any] = {}
        knee_rows: dict[str, Any] = {}
        for label, (pose, estimate, functional, extension, stances) in METHODS.items():
            calib, window = calibrate_recording("sim", samples, bones, facing_heading_deg=0.0, span=(0.0, STILL_S),
                                                window_s=1.0, pose=pose, estimate_posture=estimate)  # fmt: skip
            if functional:
                t = next(iter(samples.values()))[0]
                orientations = {sid: q for sid, (_, q, _) in samples.items()}
                refined = refine_mountings(calib, orientations,
                                           still_orientations(orientations, window_samples(t, *window)))  # fmt: skip
                calib, hinge_rows = refined.calibration, refined.hinges
            if extension:
                extended = refine_knee_extension(calib, samples, window, apply=True)
                calib, knee_rows = extended.calibration, extended.knees
            if stances:
                by_stances = refine_from_stances(calib, samples, window)
                calib, stance_rows = by_stances.calibration, by_stances.sensors
            if not estimate:  # the posture as the exact hint took it
                hint = rest_orientations(pose) or {}
                calib_angles = posture_angles({b: hint.get(b, np.array([1.0, 0, 0, 0])) for b in BONE_NAMES})
            else:
                calib_angles = calib.posture
            posture_err[label] += [calib_angles[k] - v for k, v in angles.items() if k in calib_angles]
            _, obs, mounts = calibrated_observations(samples, calib, clip.skeleton)
            solver = PoseSolver(clip.skeleton, [], None, mounts, prior, ground=GroundOptions())
            solver.reset(truth[0])
            theta = np.array([solver.solve(o).theta for o in obs])
            row = {"clip": Path(path).stem, **measure(theta, truth, clip.skeleton),
                   **{f"mount_{k}_deg": v for k, v in mounting_errors(calib, true_mounts).items()}}  # fmt: skip
            rows[label].append(
                row
                | ({"hinges": hinge_rows} if functional else {})
                | ({"knees": knee_rows} if extension else {})
                | ({"stances": stance_rows} if stances else {})
            )
    summary = {}
    for label, rs in rows.items():
        keys = [k for k in rs[0] if k not in ("clip", "hinges", "knees", "stances")]
        pe = np.array(posture_err[label])
        summary[label] = {k: round(float(np.mean([r[k] for r in rs])), 1) for k in keys} | {
            "posture_error_rms_deg": round(float(np.sqrt(np.mean(pe**2))), 1)
        }
    return {"clips": list(clips), "seconds": seconds, "seed": seed, "sway_deg": sway_deg, "summary": summary,
            "per_clip": rows}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    from mocapd.eval.data import default_data_root
    from mocapd.io.prior import resolve_prior

    p = argparse.ArgumentParser(prog="python -m mocapd.eval.calibration_posture", description=__doc__.split("\n")[0])
    p.add_argument("--seconds", type=float, default=8.0, help="seconds of each clip after the calibration (default 8)")
    p.add_argument("--seed", type=int, default=42)
    p.add_argument("--data-root", type=Path, default=None)
    p.add_argument("--sway", type=float, default=0.0, metavar="DEG",
                   help="also lean the pelvis, the trunk and each leg in the still posture by up to DEG forward or "
                   "back (default 0: upright, as the still window's priors assume)")  # fmt: skip
    p.add_argument("--clip", action="append", default=None, metavar="PATH",
                   help="a development-split clip under the data root (repeatable; default: the five of CLIPS; "
                   "WALKS: the development walks, for gravity from stances)")  # fmt: skip
    args = p.parse_args(argv)
    clips = tuple(c for spec in (args.clip or list(CLIPS)) for c in (WALKS if spec == "WALKS" else (spec,)))
    load0, t0 = os.getloadavg(), time.perf_counter()
    root = args.data_root or default_data_root()
    out = run(args.seconds, args.seed, root, resolve_prior("default"), args.sway, clips)
    out["machine"] = {"cpus": os.cpu_count(), "seconds": round(time.perf_counter() - t0, 1),
                      "loadavg_start": [round(x, 2) for x in load0]}  # fmt: skip
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

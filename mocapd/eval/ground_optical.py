"""IMU-only solves of real recordings against optical ground truth (issue 28): ``mocapd eval ground --parts optical``.

The recording: the sample trial of the *Neura sparse* data set (UNSW; github.com/gait-tech/gaittoolbox, GPL-3.0,
``data/sample``), subject S02, ``Trial-Walk-1``: 25 s at 100 Hz, 11 s standing, then about 10 s walking 3.3 m out
and 4.3 m back, standing again. Nine Xsens MTx/MTw on the lower body (pelvis, thighs, shanks, above the ankles, feet;
MT Manager exports with quaternions and accelerations, ``rawimu/``), an 8-camera Vicon system synchronised by the
Awinda station's trigger (Plug-in-Gait markers, joint centres and joint angles, ``vicon/S02-Trial-Walk-1.mat``, the
same 2503 frames) and Xsens MVN Studio's own solve of the same sensors (``xsens/S02-Trial-Walk-1.bvh``). The data are
GPL-3.0: they are read from a folder given on the command line (default ``<data root>/imu/gaittoolbox``), never
shipped; :func:`missing_message` says how to get them.

What runs is what a user types: the seven sensors of a lower-body suit (pelvis, thighs, shanks, feet; the ankle
sensors are not used) read as MT Manager exports (:mod:`mocapd.io.mt_export`), calibrated from their stillest
standing second with the facing taken from the steps (``mocapd calibrate imu --from`` without ``--facing-from``,
:func:`mocapd.core.imu_calibration.facing_heading_from_steps`) and solved IMU-only at 100 Hz with the default options
(:class:`~mocapd.core.solver.PoseSolver`, foot contacts on), on two skeletons: the default one sized from a height
(1.70 m, the data set's mean) and one with the legs Vicon measured (thigh, shank, hip width: the joint centres'
median distances; the ankle joint's height standing, which includes the shoes). MVN's solve (its BVH retargeted onto
the 21 bones) is measured the same way.

Measures, over the whole take:

- **path length**: the horizontal path of the root (mocapd: the hips joint; MVN: its hips; Vicon: the centre of the
  four pelvis markers) sampled every 0.5 s (:func:`mocapd.eval.ground.walked_distance`), against Vicon's;
- **root height**: the hips joint's height change from the first second (standing) against the Vicon hip joint
  centres' mean above the floor (p95 and max of the difference; the lab's vertical is 1° off the floor's normal, so
  heights are taken above the plane through the still heel and toe markers);
- **knee and hip flexion**: mocapd's knee flexion (:func:`mocapd.core.plausibility.hinge_angles`) and hip flexion (the
  thigh's sagittal angle in the pelvis' frame) against Plug-in-Gait's ``L/R_Femur_L/R_Tibia`` and ``Root_L/R_Femur``
  flexion, during the walk: RMS error, and RMS error with each series' mean difference removed (a constant offset
  is the calibration posture against Plug-in-Gait's anatomical frames, not motion). The series are aligned in time by
  the lag that correlates the knee angles best (MVN's BVH starts 7 frames off).
- **the facing** (issue 42, friction 8: the facing found from the steps): each leg of the walk out and back, its
  direction from the standing pelvis's facing (mocapd: the hips bone's forward; Vicon: the ASIS midpoint from the
  PSIS midpoint), against Vicon's (:func:`walk_directions`): a facing δ off turns the solved walk by δ.

``mocapd eval ground --parts optical`` also runs the take through the commands a suit owner types (import mtw ->
calibrate imu --from -> resolve -> export, at 1.70 m: :mod:`mocapd.service.cli.optical_walk`) and measures it the same
way, beside these library rows.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.ground import GroundOptions
from mocapd.core.imu_calibration import calibrate_recording, facing_heading_from_steps
from mocapd.core.kinematics import Kinematics
from mocapd.core.plausibility import hinge_angles
from mocapd.core.prior import PcaPrior
from mocapd.core.rotations import matrix_from_rotvec
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.core.solver import PoseSolver
from mocapd.errors import InputError
from mocapd.eval.ground import walked_distance
from mocapd.eval.ground_real import calibrated_observations

FloatArray = NDArray[np.float64]

TRIAL = "S02-Trial-Walk-1"
RATE_HZ = 100.0
SENSORS = {
    "00B40B91": "Hips",
    "00B40C45": "LeftUpperLeg", "00B40C3C": "RightUpperLeg",
    "00B40BA5": "LeftLowerLeg", "00B40C35": "RightLowerLeg",
    "00B40C55": "LeftFoot", "00B40C48": "RightFoot",
}  # fmt: skip
"""The data set's sensor ids (its README) on a lower-body suit's bones: ``L/R_LowLeg2`` are the shanks;
``L/R_LowLeg`` (``00B40C44``, ``00B40C47``) sit just above the ankles and are left out."""
HEIGHT_M = 1.70
STANDING_S = 10.0
"""The take starts with 11 s of standing: calibration and the root height's reference come from here."""
WALK = (11.0, 21.0)
"""s: the walk (the angle errors are measured here)."""


def default_dir(data_root: Path) -> Path:
    return data_root / "imu" / "gaittoolbox"


def missing_message(directory: Path) -> str:
    return (
        f"no optical-truth recording under {directory}: it needs rawimu/{TRIAL}-000_<sensor>.txt, "
        f"vicon/{TRIAL}.mat and xsens/{TRIAL}.bvh from the sample data of github.com/gait-tech/gaittoolbox "
        "(GPL-3.0, not shipped with mocapd): `git clone https://github.com/gait-tech/gaittoolbox` and copy its "
        f"data/sample folder to {directory} (or give --optical-data DIR)"
    )


@dataclass(frozen=True)
class Vicon:
    """The Vicon trial: pelvis centre and hip joint centres (m, Z up), Plug-in-Gait flexion angles (degrees)."""

    pelvis: FloatArray  # (n, 3)
    hips: FloatArray  # (n, 3), the midpoint of the hip joint centres
    knee: dict[str, FloatArray]  # "left"/"right" -> (n,)
    hip_flexion: dict[str, FloatArray]
    legs: dict[str, float]  # thigh, shank, hip_width, ankle_height (m)
    facing: FloatArray  # (n, 2), the pelvis's horizontal forward (its ASIS midpoint from its PSIS midpoint), X and Y


def read_vicon(path: Path) -> Vicon:
    from scipy.io import loadmat

    m = loadmat(path, squeeze_me=True)
    mm = {k: np.asarray(m[k], dtype=np.float64) for k in m if not k.startswith("__")}
    pelvis = (mm["LASI"] + mm["RASI"] + mm["LPSI"] + mm["RPSI"]) / 4000.0
    hips = (mm["LHJC"] + mm["RHJC"]) / 2000.0
    # The lab's Z is not quite the floor's normal (the standing hips are 8 cm lower at one end of the walk than at
    # the other): heights are taken above the floor plane through the still heel and toe markers.
    feet = np.concatenate([mm[k] for k in ("LHEE", "RHEE", "LTOE", "RTOE")]) / 1000.0
    speed = np.concatenate([np.linalg.norm(np.gradient(mm[k], 1.0 / RATE_HZ, axis=0), axis=1)
                            for k in ("LHEE", "RHEE", "LTOE", "RTOE")]) / 1000.0  # fmt: skip
    on = feet[speed < 0.05]
    plane = np.linalg.lstsq(np.c_[on[:, :2], np.ones(len(on))], on[:, 2], rcond=None)[0]
    hips[:, 2] -= hips[:, :2] @ plane[:2] + plane[2]

    def dist(a: str, b: str) -> float:
        return float(np.median(np.linalg.norm(mm[a] - mm[b], axis=1))) / 1000.0

    still = slice(0, round(STANDING_S * RATE_HZ))
    legs = {
        "thigh": (dist("LHJC", "LKJC") + dist("RHJC", "RKJC")) / 2,
        "shank": (dist("LKJC", "LAJC") + dist("RKJC", "RAJC")) / 2,
        "hip_width": dist("LHJC", "RHJC"),
        "ankle_height": float(np.median(np.r_[mm["LAJC"][still, 2], mm["RAJC"][still, 2]])) / 1000.0,
    }
    return Vicon(
        pelvis=pelvis,
        hips=hips,
        knee={"left": mm["L_Femur_L_Tibia"], "right": mm["R_Femur_R_Tibia"]},
        hip_flexion={"left": mm["Root_L_Femur"][:, 0], "right": mm["Root_R_Femur"][:, 0]},
        legs=legs,
        facing=((mm["LASI"] + mm["RASI"]) / 2 - (mm["LPSI"] + mm["RPSI"]) / 2)[:, :2] / 1000.0,
    )


def measured_skeleton(legs: dict[str, float], height: float) -> Skeleton:
    """The default skeleton at ``height`` with the measured thigh, shank, hip width and ankle height."""
    base = Skeleton.from_bone_lengths(
        {"LeftLowerLeg": legs["thigh"], "RightLowerLeg": legs["thigh"], "LeftFoot": legs["shank"],
         "RightFoot": legs["shank"]}, height=height,
    )  # fmt: skip
    off = base.offsets.copy()
    for bone, sign in (("LeftUpperLeg", 1.0), ("RightUpperLeg", -1.0)):
        off[BONE_INDEX[bone], 0] = sign * legs["hip_width"] / 2
    leg = -float(off[[BONE_INDEX[b] for b in ("LeftUpperLeg", "LeftLowerLeg", "LeftFoot")], 1].sum())
    return Skeleton(off, root_height=leg + legs["ankle_height"], height=height)


def hip_flexion(theta: FloatArray) -> dict[str, FloatArray]:
    """Each thigh's flexion in the pelvis' frame (degrees; the knee forwards is positive)."""
    out = {}
    for side in ("left", "right"):
        i = BONE_INDEX[f"{side.capitalize()}UpperLeg"]
        d = -matrix_from_rotvec(theta[:, 3 + 3 * i : 6 + 3 * i])[:, :, 1]  # the thigh's direction (-Y)
        out[side] = np.degrees(np.arctan2(d[:, 2], -d[:, 1]))
    return out


def _lag(a: FloatArray, b: FloatArray, max_lag: int = 30) -> int:
    """The shift k (frames) maximising the correlation of a[t + k] with b[t]."""

    def corr(k: int) -> float:
        x, y = (a[k:], b[: len(b) - k]) if k >= 0 else (a[: len(a) + k], b[-k:])
        n = min(len(x), len(y))
        return float(np.corrcoef(x[:n], y[:n])[0, 1])

    return max(range(-max_lag, max_lag + 1), key=corr)


def _shift(x: FloatArray, k: int, n: int) -> FloatArray:
    """x[t + k] for t in 0..n-1 (edge values repeated)."""
    return np.asarray(x[np.clip(np.arange(n) + k, 0, len(x) - 1)])


def _left_of(facing: FloatArray, d: FloatArray) -> float:
    """Degrees from the horizontal direction ``facing`` (2,) to ``d`` (2,), counter-clockwise seen from above (to
    the left) positive; both in a right-handed pair of horizontal axes."""
    return float(np.degrees(np.arctan2(facing[0] * d[1] - facing[1] * d[0], facing @ d)))


def walk_directions(pos: FloatArray, facing: FloatArray, rate_hz: float) -> dict[str, float]:
    """Which way a walk out and back went from the facing held standing (friction 8's check of the facing): the
    path's start (its first second), its farthest point from there and its end (its last second), each leg's
    direction in degrees to the left of the first second's mean facing. ``pos`` and ``facing`` (n, 2): horizontal
    positions and forward directions in a right-handed pair of horizontal axes."""
    still = max(1, round(rate_hz))
    start, end = pos[:still].mean(axis=0), pos[-still:].mean(axis=0)
    far = pos[int(np.argmax(np.linalg.norm(pos - start, axis=1)))]
    f = facing[:still].mean(axis=0)
    return {"out_deg": _left_of(f, far - start), "back_deg": _left_of(f, end - far)}


def _wrap(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def measure(theta: FloatArray, skeleton: Skeleton, vicon: Vicon, rate_hz: float = RATE_HZ) -> dict[str, Any]:
    """Path, root height and flexion errors of poses θ (n, 66), in the Vicon trial's frames."""
    n = len(vicon.pelvis)
    walk = slice(round(WALK[0] * rate_hz), round(WALK[1] * rate_hz))
    knees = hinge_angles(theta)
    lag = _lag(knees["left_knee"], vicon.knee["left"])
    th = np.array([_shift(theta[:, j], lag, n) for j in range(theta.shape[1])]).T
    knees = hinge_angles(th)
    hips = hip_flexion(th)
    truth_path = walked_distance(vicon.pelvis[:, :2], rate_hz)
    path = walked_distance(th[:, [0, 2]], rate_hz)
    hip_y = Kinematics(skeleton).forward(th).positions[:, BONE_INDEX["LeftUpperLeg"], 1]
    hip_y = (hip_y + Kinematics(skeleton).forward(th).positions[:, BONE_INDEX["RightUpperLeg"], 1]) / 2
    still = slice(0, round(1.0 * rate_hz))
    dy = (hip_y - hip_y[still].mean()) - (vicon.hips[:, 2] - vicon.hips[still, 2].mean())
    angles: dict[str, Any] = {}
    for name, ours, truth in (
        ("knee", {s: knees[f"{s}_knee"] for s in ("left", "right")}, vicon.knee),
        ("hip", hips, {s: -v for s, v in vicon.hip_flexion.items()}),  # Plug-in-Gait's hip flexion is negative here
    ):
        e = np.concatenate([ours[s][walk] - truth[s][walk] for s in ("left", "right")])
        e0 = np.concatenate([(ours[s] - truth[s])[walk] - (ours[s] - truth[s])[walk].mean() for s in ("left", "right")])
        angles[name] = {"rms_deg": round(float(np.sqrt(np.mean(e**2))), 1),
                        "rms_without_offset_deg": round(float(np.sqrt(np.mean(e0**2))), 1)}  # fmt: skip
    # The facing the calibration gave, against Vicon's pelvis: mocapd's world is Y up with its horizontal axes (Z, X)
    # a right-handed pair seen from above, Vicon's Z up with (X, Y); each walk leg's direction from the standing
    # facing, in both, differs by how far the facing was off (friction 8: the facing from the steps).
    forward = matrix_from_rotvec(th[:, 3:6])[:, :, 2]  # the hips bone's +Z in the world
    solved_legs = walk_directions(th[:, [2, 0]], forward[:, [2, 0]], rate_hz)
    vicon_legs = walk_directions(vicon.pelvis[:, :2], vicon.facing, rate_hz)
    facing = {k: round(_wrap(solved_legs[k] - vicon_legs[k]), 1) for k in ("out_deg", "back_deg")}
    return {
        "lag_frames": lag,
        "path_m": round(path, 2),
        "vicon_path_m": round(truth_path, 2),
        "path_error_pct": round(100 * (path - truth_path) / truth_path, 1),
        "root_height_error_p95_cm": round(100 * float(np.percentile(np.abs(dy), 95)), 1),
        "root_height_error_max_cm": round(100 * float(np.abs(dy).max()), 1),
        "knee_flexion": angles["knee"],
        "hip_flexion": angles["hip"],
        "facing_vs_vicon": facing,
    }


def solve_take(
    directory: Path, skeleton: Skeleton, prior: PcaPrior | None, ground: GroundOptions | None = None
) -> tuple[FloatArray, dict[str, Any]]:
    """The IMU-only solve of the take (see the module docstring); θ per sample (n, 66) and how it was calibrated."""
    from mocapd.io.imu_recordings import streams_from_mt_exports
    from mocapd.io.mt_export import read_mt_export

    files = [directory / "rawimu" / f"{TRIAL}-000_{sid}.txt" for sid in SENSORS]
    streams = streams_from_mt_exports([(p.name, read_mt_export(p)) for p in files])
    samples = {st.sensor: (st.time_ns / 1e9, st.quat, st.acc) for st in streams}
    from mocapd.core.imu_calibration import stillest_common_window

    window = stillest_common_window(samples, 1.0, (0.0, STANDING_S))
    heading = facing_heading_from_steps(samples, SENSORS, window)
    if heading is None:
        raise InputError(f"{directory}: no steps to take the facing direction from")
    calib, window = calibrate_recording("s02", samples, SENSORS, facing_heading_deg=heading, span=(0.0, STANDING_S))
    _, obs, mounts = calibrated_observations(samples, calib, skeleton)
    solver = PoseSolver(skeleton, [], None, mounts, prior, ground=ground or GroundOptions())
    theta = np.array([solver.solve(o).theta for o in obs])
    return theta, {"calibration_window_s": [round(v, 2) for v in window], "facing_from_steps_deg": round(heading, 1)}


def run_optical(prior: PcaPrior | None, directory: Path) -> dict[str, Any]:
    """The Neura sparse S02 walk: mocapd on two skeletons and MVN, against Vicon (see the module docstring)."""
    from mocapd.core.retarget import retarget
    from mocapd.io.bvh import read_bvh

    required = [directory / "vicon" / f"{TRIAL}.mat", directory / "xsens" / f"{TRIAL}.bvh"]
    required += [directory / "rawimu" / f"{TRIAL}-000_{sid}.txt" for sid in SENSORS]
    if not all(p.is_file() for p in required):
        raise InputError(missing_message(directory))
    vicon = read_vicon(directory / "vicon" / f"{TRIAL}.mat")
    out: dict[str, Any] = {
        "recording": f"Neura sparse {TRIAL} (github.com/gait-tech/gaittoolbox data/sample, GPL-3.0)",
        "sensors": len(SENSORS),
        "vicon_legs_m": {k: round(v, 3) for k, v in vicon.legs.items()},
    }
    for label, skeleton in (
        (f"mocapd, height {HEIGHT_M} m", Skeleton.from_height(HEIGHT_M)),
        ("mocapd, Vicon-measured legs", measured_skeleton(vicon.legs, HEIGHT_M)),
    ):
        theta, info = solve_take(directory, skeleton, prior)
        out[label] = {**info, **measure(theta, skeleton, vicon)}
    mvn = retarget(read_bvh(directory / "xsens" / f"{TRIAL}.bvh"))
    out["Xsens MVN"] = measure(mvn.theta, mvn.skeleton, vicon, mvn.fps)
    return out


__all__ = ["SENSORS", "measure", "missing_message", "run_optical", "solve_take", "walk_directions"]

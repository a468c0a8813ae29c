"""Root drift without cameras on real recordings (issue 14): the OpenSense MTw take and the MVNX file.

``mtw``: the 8 MT Manager exports of ``imu/opensense_mtw`` go through what ``mocapd import mtw`` and
``mocapd calibrate imu --from`` run: the reader and stream alignment (:mod:`mocapd.io.imu_recordings`), the
calibration from the stillest standing second of the first 4 s
(:func:`mocapd.core.imu_calibration.calibrate_recording`: T-pose rest for the legs, i.e. standing straight; the
heading from the pelvis sensor's +z axis, which points forward in this take: with -z the knees bend backwards and
the body walks backwards), then Eq. 8/12 with that calibration and :class:`~mocapd.core.solver.PoseSolver` at the
sensors' 100 Hz with the default options, foot contacts on and off. Sensor placement (OpenSim's test code for this
data set): 00B42279 pelvis, 00B42268 back (Spine3), 00B4227C/00B4227D right thigh/shank, 00B421EE/00B421ED left
thigh/shank, 00B421EF/00B421E6 right/left foot.

There is no position truth. What is reported: the root height over the take (the standing posture fixes it at the
start: it should stay within a few centimetres of that while walking, and not float), the horizontal drift while
the subject stands still (the first seconds), and, because the subject walks back and forth between two places,
the spread of the turning points on each side (where the walking direction reverses): a drift-free estimate puts
every turn on one side at the same place.

``mvnx``: the MVN upper-body file (11 sensors, 1.9 s): MVN's own segment orientations of the sensor-bearing
segments as the IMU orientations (MVN's calibration, which needs the T-pose frames mocapd does not have), IMU-only,
and the root's displacement against MVN's pelvis.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.ground import GroundOptions
from mocapd.core.imu import ImuMount, default_mounts, measured_global_acceleration
from mocapd.core.imu_calibration import ImuCalibration, bone_orientation, calibrate_recording
from mocapd.core.observations import Observations
from mocapd.core.prior import PcaPrior
from mocapd.core.rotations import quat_normalize
from mocapd.core.skeleton import Skeleton
from mocapd.core.solver import PoseSolver
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

MTW_ASSIGNMENT = {
    "00B42279": "Hips", "00B42268": "Spine3",
    "00B4227C": "RightUpperLeg", "00B4227D": "RightLowerLeg", "00B421EF": "RightFoot",
    "00B421EE": "LeftUpperLeg", "00B421ED": "LeftLowerLeg", "00B421E6": "LeftFoot",
}  # fmt: skip
MTW_FACING = ("00B42279", np.array([0.0, 0.0, 1.0]))
STILL_S = 4.0
"""The take starts with the subject standing still for about 5 s (accelerometers quiet); the first 4 s are used."""


def calibrated_observations(
    samples: dict[str, tuple[FloatArray, FloatArray, FloatArray]], calib: ImuCalibration, skeleton: Skeleton
) -> tuple[FloatArray, list[Observations], tuple[ImuMount, ...]]:
    """Observations on the common sample grid of the calibrated sensors (all at one rate, one time base).

    Returns times (s, (n,)), one :class:`Observations` per sample (no cameras), and the mounts.
    """
    sensors = sorted(calib.bones)
    t_all = [samples[s][0] for s in sensors]
    t = t_all[0][(t_all[0] >= max(x[0] for x in t_all)) & (t_all[0] <= min(x[-1] for x in t_all))]
    if t.size < 3:
        raise InputError("the calibrated sensors share fewer than 3 samples")
    dt = float(np.median(np.diff(t)))
    q = np.zeros((t.size, len(sensors), 4))
    acc = np.zeros((t.size, len(sensors), 3))
    for k, s in enumerate(sensors):
        ts, qs, acs = samples[s]
        idx = np.clip(np.searchsorted(ts, t - dt / 2), 0, len(ts) - 1)
        q[:, k] = bone_orientation(calib.q_ig, quat_normalize(qs[idx]), calib.q_ib[s])
        acc[:, k] = measured_global_acceleration(calib.q_ig, qs[idx], acs[idx])
    mounts = default_mounts(tuple(calib.bones[s] for s in sensors), skeleton)
    obs = [
        Observations(imu_orientations=q[i], imu_accelerations=acc[i - 1] if i >= 1 else None, dt=dt)
        for i in range(t.size)
    ]
    return t - t[0], obs, mounts


def turning_points(xz: FloatArray, fps: float, min_leg_m: float = 1.0) -> dict[str, list[float]]:
    """Where the walk reverses along its main axis: positions (m) of the extremes on each side."""
    c = xz - xz.mean(axis=0)
    axis = np.linalg.svd(c, full_matrices=False)[2][0]
    s = c @ axis
    w = max(1, round(0.5 * fps))
    smooth = np.convolve(s, np.ones(w) / w, mode="same")
    ends: dict[str, list[float]] = {"plus": [], "minus": []}
    last = 0.0
    for i in range(w, len(s) - w):
        seg = smooth[i - w : i + w + 1]
        if smooth[i] == seg.max() and smooth[i] - last > min_leg_m:
            ends["plus"].append(round(float(s[i]), 3))
            last = smooth[i]
        elif smooth[i] == seg.min() and last - smooth[i] > min_leg_m:
            ends["minus"].append(round(float(s[i]), 3))
            last = smooth[i]
    return ends


def _real_metrics(t: FloatArray, theta: FloatArray, fps: float) -> dict[str, Any]:
    y = theta[:, 1]
    still = t < STILL_S
    xz = theta[:, [0, 2]]
    drift_still = np.linalg.norm(xz[still] - xz[0], axis=1)
    ends = turning_points(xz[~still], fps)
    spread = {k: round(100 * (max(v) - min(v)), 1) if len(v) > 1 else None for k, v in ends.items()}
    path = float(np.linalg.norm(np.diff(xz[:: max(1, round(0.5 * fps))], axis=0), axis=1).sum())
    return {
        "seconds": round(float(t[-1]), 1),
        "root_height_start_m": round(float(y[0]), 3),
        "root_height_end_m": round(float(y[-1]), 3),
        "root_height_min_max_m": [round(float(y.min()), 3), round(float(y.max()), 3)],
        "root_height_p5_p95_m": [round(float(np.percentile(y, 5)), 3), round(float(np.percentile(y, 95)), 3)],
        "standing_first_s": STILL_S,
        "standing_horizontal_drift_max_cm": round(100 * float(drift_still.max()), 1),
        "walked_m": round(path, 1),
        "turning_points_m": ends,
        "turning_point_spread_cm": spread,
    }


def run_mtw(prior: PcaPrior | None, data_root: Path | None = None) -> dict[str, Any]:
    """The OpenSense MTw take (see the module docstring)."""
    from mocapd.eval.data import default_data_root
    from mocapd.io.imu_recordings import streams_from_mt_exports
    from mocapd.io.mt_export import read_mt_export

    root = default_data_root() if data_root is None else Path(data_root)
    files = sorted((root / "imu" / "opensense_mtw").glob("*.txt"))
    if not files:
        raise InputError(f"no MT Manager exports under {root / 'imu' / 'opensense_mtw'}")
    streams = streams_from_mt_exports([(p.name, read_mt_export(p)) for p in files])
    skeleton = Skeleton.from_height(1.75)
    samples = {st.sensor: (st.time_ns / 1e9, st.quat, st.acc) for st in streams}
    calib, window = calibrate_recording(
        "mtw", samples, MTW_ASSIGNMENT, facing_from=MTW_FACING, span=(0.0, STILL_S), pose="t-pose"
    )
    t, obs, mounts = calibrated_observations(samples, calib, skeleton)
    fps = 1.0 / obs[0].dt
    out: dict[str, Any] = {
        "sensors": len(mounts),
        "rate_hz": round(fps, 1),
        "calibration_window_s": [round(v, 2) for v in window],
        "facing_heading_deg": round(calib.facing_heading_deg, 1),
    }
    for label, ground in (("contacts", True), ("no_contacts", False)):
        solver = PoseSolver(skeleton, [], None, mounts, prior, ground=GroundOptions(enabled=ground))
        theta = np.array([solver.solve(o).theta for o in obs])
        out[label] = _real_metrics(t, theta, fps)
    return out


def run_mvnx(prior: PcaPrior | None, data_root: Path | None = None) -> dict[str, Any]:
    """The MVNX upper-body file against MVN's pelvis (see the module docstring)."""
    from mocapd.eval.data import default_data_root
    from mocapd.io.imu_recordings import MVN_SENSOR_BONES
    from mocapd.io.mvnx import read_mvnx

    root = default_data_root() if data_root is None else Path(data_root)
    rec = read_mvnx(root / "imu" / "mvnx" / "mpiea_upperbody_test_mocap.mvnx")
    bones = [MVN_SENSOR_BONES[s] for s in rec.sensors if s in MVN_SENSOR_BONES]
    seg = [rec.segments.index(s) for s in rec.sensors if s in MVN_SENSOR_BONES]
    skeleton = Skeleton.from_height(1.75)
    mounts = default_mounts(tuple(bones), skeleton)
    dt = 1.0 / rec.fps
    q = rec.segment_orientation[:, seg]
    pelvis = rec.segment_position[:, rec.segments.index("Pelvis")]
    out: dict[str, Any] = {"frames": int(q.shape[0]), "seconds": round(float(q.shape[0] * dt), 2),
                           "sensors_used": bones, "mvn_pelvis_displacement_cm": round(
                               100 * float(np.linalg.norm(pelvis - pelvis[0], axis=1).max()), 1)}  # fmt: skip
    for label, ground in (("contacts", True), ("no_contacts", False)):
        solver = PoseSolver(skeleton, [], None, mounts, prior, ground=GroundOptions(enabled=ground))
        start = skeleton.rest_pose()
        start[3:6] = 0.0
        solver.reset(start)
        theta = np.array([solver.solve(Observations(imu_orientations=q[i], dt=dt)).theta for i in range(len(q))])
        disp = theta[:, :3] - theta[0, :3]
        out[label] = {
            "root_displacement_max_cm": round(100 * float(np.linalg.norm(disp, axis=1).max()), 1),
            "root_vs_mvn_pelvis_max_cm": round(
                100 * float(np.linalg.norm(disp - (pelvis - pelvis[0]), axis=1).max()), 1
            ),
        }
    return out


__all__ = ["MTW_ASSIGNMENT", "run_mtw", "run_mvnx", "turning_points"]

"""Synthetic sensors from real motion, with documented noise models (issue 3 §3; docs/accuracy.md).

Camera rigs
    ``totalcapture_ring``: 8 HD cameras (1920×1080, 60° horizontal field of view) on a 4.5 m-radius circle around
    a ~4×4 m volume, 2.5 m high, looking at the volume centre 1 m above the floor; subsets are "the first N
    adjacent cameras" (seed 003 §4.1.1). ``outdoor_arc``: 4 cameras on a 120° arc (outdoor sets).

2D detections (any keypoint set on the truth's track targets, the offsets the solver uses; the harness: COCO-17)
    ``realistic`` (default): keypoints hidden by the body itself (ray to the camera passes through another body
    part, capsules with per-segment radii) or outside the image are missed; Gaussian noise σ = 1.5 % of the
    person's height in pixels; 5 % gross outliers, uniform in a disc of radius 30 % of the height; in 2 % of
    person-frames (per camera) one limb's left and right keypoints are swapped (they keep their confident
    scores, as a real detector's swaps do); 5 % of keypoints randomly missed; confidence
    ``c = u / (1 + (e / 4σ)²)`` with ``u ~ U(0.8, 1)`` and ``e`` the pixel error, so it falls as the error grows.
    ``clean``: σ = 1 px, nothing else (confidence 1, no occlusion), for debugging.

IMUs (13 or 6, DESIGN.md) through the model of :mod:`mocapd.core.imu`
    True mount = calibrated mount (what the solver uses) · calibration error (5° RMS angle, random axis, fixed per
    sensor and clip). Sensor orientation ``R_i`` from the truth bone orientation by the inverse of Eq. 8 with a
    world heading that random-walks 1°/√min, then 1° RMS noise per sample. Specific force: the second difference
    of the sensor's world position (60 Hz) with gravity, rotated into the sensor frame, plus 0.2 m/s² RMS noise.
    The solver receives Eq. 8/Eq. 12 of the noisy readings with the calibrated mounts and no heading correction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera, look_at, project_points, stack_cameras
from mocapd.core.imu import (
    ImuMount,
    measured_bone_orientation,
    measured_global_acceleration,
    sensor_orientation_from_bone,
    specific_force_from_acceleration,
)
from mocapd.core.keypoints import TrackTargets
from mocapd.core.kinematics import Kinematics
from mocapd.core.retarget import Retargeted
from mocapd.core.rotations import quat_from_matrix, quat_from_rotvec, quat_multiply
from mocapd.core.skeleton import BONE_INDEX

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def _hfov_focal(width: int, hfov_deg: float) -> float:
    return float(0.5 * width / np.tan(np.deg2rad(hfov_deg) / 2.0))


def totalcapture_ring(n: int = 8, radius: float = 4.5, height: float = 2.5, hfov_deg: float = 60.0) -> list[Camera]:
    """The 8-camera ring (first ``n`` adjacent cameras of it)."""
    cams = []
    for i in range(8):
        a = 2.0 * np.pi * i / 8
        pos = np.array([radius * np.sin(a), height, radius * np.cos(a)])
        cams.append(look_at(f"ring{i}", pos, np.array([0.0, 1.0, 0.0]), 1920, 1080, _hfov_focal(1920, hfov_deg)))
    return cams[:n]


def outdoor_arc(radius: float = 6.0, height: float = 2.0, hfov_deg: float = 60.0) -> list[Camera]:
    """Four cameras spread over a 120° arc, looking at the volume centre."""
    cams = []
    for i in range(4):
        a = np.deg2rad(-60.0 + 40.0 * i)
        pos = np.array([radius * np.sin(a), height, radius * np.cos(a)])
        cams.append(look_at(f"arc{i}", pos, np.array([0.0, 1.0, 0.0]), 1920, 1080, _hfov_focal(1920, hfov_deg)))
    return cams


@dataclass(frozen=True)
class DetectionNoise:
    """The 2D detector model (see the module doc). Fractions are probabilities per keypoint unless noted."""

    sigma_height: float = 0.015
    """Gaussian σ as a fraction of the person's height in pixels (0 → use ``sigma_px``)."""
    sigma_px: float = 0.0
    """Extra absolute Gaussian σ (pixels)."""
    outlier: float = 0.05
    outlier_radius_height: float = 0.30
    swap: float = 0.02
    """Probability per person-frame and camera of one limb's left/right swap."""
    missed: float = 0.05
    occlusion: bool = True
    confidence_falls: bool = True

    @classmethod
    def realistic(cls) -> DetectionNoise:
        return cls()

    @classmethod
    def clean(cls) -> DetectionNoise:
        return cls(0.0, 1.0, 0.0, 0.0, 0.0, 0.0, False, False)


@dataclass(frozen=True)
class ImuNoise:
    calibration_deg: float = 5.0
    """RMS angle of the mounting-calibration error (fixed per sensor and clip)."""
    orientation_deg: float = 1.0
    """RMS angle of per-sample orientation noise."""
    heading_walk_deg_per_sqrt_min: float = 1.0
    """Heading random walk: its standard deviation after one minute (degrees)."""
    acceleration: float = 0.2
    """RMS of the acceleration noise per axis (m/s²)."""

    @classmethod
    def clean(cls) -> ImuNoise:
        return cls(0.0, 0.0, 0.0, 0.0)


# Body capsules for self-occlusion: (bone whose joint starts the segment, bone whose joint ends it, radius m at
# 1.75 m). Keypoints on a capsule's own bones are not hidden by it.
_CAPSULES: tuple[tuple[str, str, float], ...] = (
    ("Hips", "Spine3", 0.13), ("Spine3", "Neck", 0.12), ("Neck", "Head", 0.05),
    ("LeftUpperArm", "LeftLowerArm", 0.05), ("LeftLowerArm", "LeftHand", 0.04),
    ("RightUpperArm", "RightLowerArm", 0.05), ("RightLowerArm", "RightHand", 0.04),
    ("LeftUpperLeg", "LeftLowerLeg", 0.07), ("LeftLowerLeg", "LeftFoot", 0.05),
    ("RightUpperLeg", "RightLowerLeg", 0.07), ("RightLowerLeg", "RightFoot", 0.05),
)  # fmt: skip

# The points of a limb a detector swaps left for right together: the arm (shoulder to hand) and the leg (hip to
# foot), by name so that every keypoint set swaps its own (COCO-17: arm 5/6, 7/8, 9/10, leg 11/12, 13/14, 15/16).
_SWAP_LIMBS = (
    ("shoulder", "elbow", "wrist", "pinky", "index", "thumb"),
    ("hip", "knee", "ankle", "heel", "foot_index", "big_toe", "small_toe"),
)


def _swap_pairs(names: tuple[str, ...]) -> list[list[tuple[int, int]]]:
    """Per limb of :data:`_SWAP_LIMBS`, the (left, right) index pairs of ``names`` on it."""
    return [
        [(names.index(f"left_{p}"), names.index(f"right_{p}")) for p in limb
         if f"left_{p}" in names and f"right_{p}" in names]
        for limb in _SWAP_LIMBS
    ]  # fmt: skip


def _occluded(
    cam_center: FloatArray, pts: FloatArray, kp_bones: NDArray[np.intp], joints: FloatArray, s: float
) -> BoolArray:
    """Which keypoints a body capsule hides from a camera.

    Parameters
    ----------
    cam_center : (3,); pts : (f, k, 3) keypoints; kp_bones : (k,) bone of each keypoint; joints : (f, 21, 3).
    """
    occ = np.zeros(pts.shape[:2], dtype=bool)
    for a_name, b_name, r0 in _CAPSULES:
        a, b = BONE_INDEX[a_name], BONE_INDEX[b_name]
        r = r0 * s
        own = np.isin(kp_bones, [a, b]) | ((a_name == "Neck") & (kp_bones == BONE_INDEX["Head"]))
        A, B = joints[:, a][:, None], joints[:, b][:, None]  # (f, 1, 3)
        # Closest points between segment C→P (camera to keypoint) and A→B.
        d1 = pts - cam_center
        d2 = B - A
        r_ = cam_center - A
        aa = np.sum(d1 * d1, -1)
        ee = np.sum(d2 * d2, -1)
        ff = np.sum(d2 * r_, -1)
        cc = np.sum(d1 * r_, -1)
        bb = np.sum(d1 * d2, -1)
        den = aa * ee - bb * bb
        sc = np.clip(np.where(den > 1e-12, (bb * ff - cc * ee) / np.where(den > 1e-12, den, 1.0), 0.0), 0.0, 1.0)
        tc = np.clip((bb * sc + ff) / np.maximum(ee, 1e-12), 0.0, 1.0)
        sc = np.clip((tc * bb - cc) / np.maximum(aa, 1e-12), 0.0, 1.0)
        p1 = cam_center + sc[..., None] * d1
        p2 = A + tc[..., None] * d2
        dist = np.linalg.norm(p1 - p2, axis=-1)
        # Hidden when the ray passes through the capsule clearly before reaching the keypoint.
        before = sc * np.sqrt(aa) < np.sqrt(aa) - 1.5 * r
        occ |= (dist < r) & before & ~own
    return occ


def simulate_detections(
    clip: Retargeted,
    cameras: list[Camera],
    targets: TrackTargets,
    noise: DetectionNoise,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray]:
    """Detections of the clip's person in every camera.

    Returns
    -------
    uv : array, shape (n_frames, n_cams, n_kp, 2) — NaN where missed
    conf : array, shape (n_frames, n_cams, n_kp) — 0 where missed
    """
    kin = Kinematics(clip.skeleton)
    fk = kin.forward(clip.theta)
    pts = kin.targets(fk, targets.bones, targets.offsets)  # (f, k, 3)
    f, k = pts.shape[:2]
    n_c = len(cameras)
    K, dist, R, t = stack_cameras(cameras)
    uv_true = np.zeros((f, n_c, k, 2))
    valid = np.zeros((f, n_c, k), dtype=bool)
    h_px = np.zeros((f, n_c))
    s = clip.skeleton.height / 1.75
    for c, cam in enumerate(cameras):
        uv, _, ok = project_points(K[c], dist[c], R[c], t[c], pts.reshape(-1, 3), jacobian=False)
        uv = uv.reshape(f, k, 2)
        ok = ok.reshape(f, k) & (uv[..., 0] >= 0) & (uv[..., 0] < cam.width) & (uv[..., 1] >= 0)
        ok &= uv[..., 1] < cam.height
        if noise.occlusion:
            ok &= ~_occluded(cam.center, pts, targets.bones, fk.positions, s)
        uv_true[:, c], valid[:, c] = uv, ok
        depth = (fk.positions[:, 0] @ R[c].T + t[c])[:, 2]
        h_px[:, c] = K[c, 0, 0] * clip.skeleton.height / np.maximum(depth, 0.1)
    sigma = noise.sigma_height * h_px[..., None] + noise.sigma_px  # (f, c, 1)
    uv = uv_true + rng.normal(size=uv_true.shape) * sigma[..., None]
    if noise.outlier > 0:
        bad = rng.uniform(size=(f, n_c, k)) < noise.outlier
        ang = rng.uniform(0, 2 * np.pi, size=(f, n_c, k))
        rad = noise.outlier_radius_height * h_px[..., None] * np.sqrt(rng.uniform(size=(f, n_c, k)))
        jump = np.stack((np.cos(ang), np.sin(ang)), -1) * rad[..., None]
        uv = np.where(bad[..., None], uv_true + jump, uv)
    err = np.linalg.norm(uv - uv_true, axis=-1)
    if noise.confidence_falls:
        conf = rng.uniform(0.8, 1.0, size=(f, n_c, k)) / (1.0 + (err / (4.0 * np.maximum(sigma, 1e-9))) ** 2)
    else:
        conf = np.ones((f, n_c, k))
    if noise.swap > 0:
        swaps = np.argwhere(rng.uniform(size=(f, n_c)) < noise.swap)
        limbs = rng.integers(0, 2, size=len(swaps))
        pairs = _swap_pairs(targets.names)
        for (fi, ci), limb in zip(swaps, limbs, strict=True):
            for left, right in pairs[limb]:
                uv[fi, ci, [left, right]] = uv[fi, ci, [right, left]]
                conf[fi, ci, [left, right]] = conf[fi, ci, [right, left]]
                valid[fi, ci, [left, right]] = valid[fi, ci, [right, left]]
    if noise.missed > 0:
        valid &= rng.uniform(size=(f, n_c, k)) >= noise.missed
    conf = np.where(valid, np.clip(conf, 0.0, 1.0), 0.0)
    uv = np.where(valid[..., None], uv, np.nan)
    return uv, conf


def _random_rotvecs(rng: np.random.Generator, n: tuple[int, ...], rms_deg: float) -> FloatArray:
    """Rotation vectors with isotropic Gaussian components whose angle has the given RMS (degrees)."""
    return np.asarray(rng.normal(scale=np.deg2rad(rms_deg) / np.sqrt(3.0), size=(*n, 3)))


def simulate_imus(
    clip: Retargeted, mounts: tuple[ImuMount, ...], noise: ImuNoise, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray]:
    """IMU measurements as the solver receives them (Eq. 8 and Eq. 12 applied with the calibrated mounts).

    Returns
    -------
    orientations : array, shape (n_frames, n_imu, 4)
        Measured global bone orientations.
    accelerations : array, shape (n_frames, n_imu, 3)
        Row ``t`` holds the measured global acceleration at ``t - 1`` (gravity removed), as the solver's
        :class:`Observations` expect; rows 0 and 1 are NaN (no second difference yet).
    """
    n = len(mounts)
    f = clip.n_frames
    dt = 1.0 / clip.fps
    if n == 0:
        return np.zeros((f, 0, 4)), np.zeros((f, 0, 3))
    kin = Kinematics(clip.skeleton)
    fk = kin.forward(clip.theta)
    bones = np.array([m.bone_index for m in mounts], dtype=np.intp)
    q_gb = quat_from_matrix(fk.rotations[:, bones])  # (f, n, 4)
    sites = kin.targets(fk, bones, np.array([m.t_ib for m in mounts]))
    q_cal = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))  # the calibrated mounting R_ib (any value: it cancels)
    q_true = quat_multiply(q_cal, quat_from_rotvec(_random_rotvecs(rng, (n,), noise.calibration_deg)))
    step = np.deg2rad(noise.heading_walk_deg_per_sqrt_min) * np.sqrt(dt / 60.0)
    heading = np.cumsum(rng.normal(scale=step, size=(f, n)), axis=0)
    q_ig = quat_from_rotvec(heading[..., None] * np.array([0.0, 1.0, 0.0]))
    q_i = sensor_orientation_from_bone(q_ig, q_gb, q_true)  # what the sensor reports (clean)
    q_i_noisy = quat_multiply(q_i, quat_from_rotvec(_random_rotvecs(rng, (f, n), noise.orientation_deg)))
    ident = np.array([1.0, 0.0, 0.0, 0.0])
    q_meas = measured_bone_orientation(ident, q_i_noisy, q_cal)
    acc = np.full((f, n, 3), np.nan)
    if f >= 3:
        a_g = (sites[2:] - 2 * sites[1:-1] + sites[:-2]) / (dt * dt)  # at frames 1 .. f-2
        f_s = specific_force_from_acceleration(q_ig[1:-1], q_i[1:-1], a_g)
        f_s = f_s + rng.normal(scale=noise.acceleration, size=f_s.shape)
        acc[2:] = measured_global_acceleration(ident, q_i_noisy[1:-1], f_s)
    return q_meas, acc

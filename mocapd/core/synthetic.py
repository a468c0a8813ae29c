"""Synthetic rigs, motion and exact observations for solver tests, benchmarks and the offline demo.

This is not the accuracy harness's sensor simulator (that one adds documented noise models to real recorded
motion); it produces *exact* measurements of a known pose so a solver's behaviour can be checked in isolation.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera, look_at, project_points, stack_cameras
from mocapd.core.imu import ImuMount
from mocapd.core.keypoints import TrackTargets
from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import quat_from_matrix
from mocapd.core.skeleton import BONE_INDEX, N_BONES, POSE_DIM, Skeleton
from mocapd.core.solver import Observations

FloatArray = NDArray[np.float64]


def ring_rig(
    n_cams: int = 8,
    radius: float = 4.0,
    height: float = 2.5,
    width: int = 1920,
    image_height: int = 1080,
    focal: float = 1400.0,
    target_height: float = 1.0,
) -> list[Camera]:
    """Cameras evenly spaced on a circle around the origin, looking at the volume centre (TotalCapture-like)."""
    cams = []
    for i in range(n_cams):
        a = 2.0 * np.pi * i / max(n_cams, 1)
        pos = np.array([radius * np.sin(a), height, radius * np.cos(a)])
        cams.append(look_at(f"cam{i}", pos, np.array([0.0, target_height, 0.0]), width, image_height, focal))
    return cams


# Joint-angle amplitudes (radians) per bone for the synthetic walk-like motion: (x, y, z) of the local
# rotation vector. Legs swing about X, arms hang down (rotation about Z) and swing, spine sways.
_AMPLITUDES: dict[str, tuple[float, float, float]] = {
    "Hips": (0.05, 0.3, 0.03), "Spine": (0.05, 0.05, 0.03), "Spine1": (0.05, 0.05, 0.03),
    "Spine2": (0.03, 0.05, 0.02), "Spine3": (0.03, 0.05, 0.02), "Neck": (0.1, 0.2, 0.05),
    "Head": (0.1, 0.3, 0.05),
    "LeftUpperArm": (0.4, 0.2, 0.3), "LeftLowerArm": (0.1, 0.6, 0.1), "LeftHand": (0.2, 0.2, 0.2),
    "RightUpperArm": (0.4, 0.2, 0.3), "RightLowerArm": (0.1, 0.6, 0.1), "RightHand": (0.2, 0.2, 0.2),
    "LeftUpperLeg": (0.5, 0.1, 0.1), "LeftLowerLeg": (0.6, 0.02, 0.02), "LeftFoot": (0.3, 0.05, 0.05),
    "LeftToes": (0.2, 0.0, 0.0),
    "RightUpperLeg": (0.5, 0.1, 0.1), "RightLowerLeg": (0.6, 0.02, 0.02), "RightFoot": (0.3, 0.05, 0.05),
    "RightToes": (0.2, 0.0, 0.0),
}  # fmt: skip
_BIAS: dict[str, tuple[float, float, float]] = {
    "LeftUpperArm": (0.0, 0.0, -1.2), "RightUpperArm": (0.0, 0.0, 1.2),
    "LeftLowerArm": (0.0, 0.4, 0.0), "RightLowerArm": (0.0, -0.4, 0.0),
    "LeftLowerLeg": (0.4, 0.0, 0.0), "RightLowerLeg": (0.4, 0.0, 0.0),
    "LeftUpperLeg": (-0.2, 0.0, 0.0), "RightUpperLeg": (-0.2, 0.0, 0.0),
}  # fmt: skip


_N_LATENT = 8
_MIXING_SEED = 1234  # fixed: every sequence shares the same joint coordination, as real motion does


def moving_sequence(
    skeleton: Skeleton,
    n_frames: int,
    fps: float = 60.0,
    seed: int = 0,
    speed: float = 1.0,
    amplitude: float = 1.0,
) -> FloatArray:
    """A smooth, human-scaled motion with coordinated joints, the root walking a circle.

    Joint angles are driven by a few latent oscillations through a fixed mixing matrix (shared by all seeds,
    like the coordination of real movement, so a PCA prior fitted on one seed describes another), plus a
    small independent jitter per joint. The seed picks the latent frequencies and phases; ``amplitude``
    scales all joint excursions (e.g. to sample a broad pose pool for a prior).

    Returns
    -------
    array, shape (n_frames, 66)
    """
    rng = np.random.default_rng(seed)
    mix_rng = np.random.default_rng(_MIXING_SEED)
    t = np.arange(n_frames)[:, None] / fps * speed
    amp = np.array([_AMPLITUDES[n] for n in BONE_INDEX]).reshape(-1)
    bias = np.array([_BIAS.get(n, (0.0, 0.0, 0.0)) for n in BONE_INDEX]).reshape(-1)
    mixing = mix_rng.normal(size=(3 * N_BONES, _N_LATENT))
    mixing /= np.linalg.norm(mixing, axis=1, keepdims=True)
    freq = rng.uniform(0.3, 1.5, size=_N_LATENT)
    phase = rng.uniform(0, 2 * np.pi, size=_N_LATENT)
    latent = np.sin(2 * np.pi * freq * t + phase)  # (n_frames, n_latent)
    jf = rng.uniform(0.5, 2.5, size=3 * N_BONES)
    jp = rng.uniform(0, 2 * np.pi, size=3 * N_BONES)
    jitter = 0.1 * np.sin(2 * np.pi * jf * t + jp)
    rot = bias + amplitude * amp * (latent @ mixing.T + jitter)
    theta = np.zeros((n_frames, POSE_DIM))
    theta[:, 3:] = rot
    heading = 0.25 * 2 * np.pi * t[:, 0]
    theta[:, 0] = 1.0 * np.sin(heading)
    theta[:, 2] = 1.0 * np.cos(heading) - 1.0
    theta[:, 1] = skeleton.root_height + 0.03 * np.sin(2 * np.pi * 1.8 * t[:, 0])
    return theta


def perturb_pose(theta: FloatArray, rng: np.random.Generator, degrees: float) -> FloatArray:
    """θ with each joint rotated by ``degrees`` about a random axis (the root translation unchanged)."""
    out = np.array(theta, dtype=np.float64)
    axes = rng.normal(size=(N_BONES, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    out[3:] += (axes * np.deg2rad(degrees)).reshape(-1)
    return out


def exact_observations(
    skeleton: Skeleton,
    cameras: list[Camera],
    targets: TrackTargets,
    imus: tuple[ImuMount, ...],
    thetas: FloatArray,
    fps: float = 60.0,
) -> list[Observations]:
    """Noise-free observations of a pose sequence.

    Keypoints are the projections of the targets (confidence 1, or 0 when behind a camera or outside the
    image); IMU orientations are the bones' global orientations rotated by the mounts (Eq. 8 inverted with
    R_ig = I, so measured = solved exactly); accelerations at t-1 are central differences of the IMU sites.

    Parameters
    ----------
    thetas : array, shape (n_frames, 66)
    """
    kin = Kinematics(skeleton)
    fk = kin.forward(thetas)
    n = thetas.shape[0]
    bones = np.array([m.bone_index for m in imus], dtype=np.intp)
    offs = np.array([m.t_ib for m in imus]).reshape(-1, 3)
    sites = kin.targets(fk, bones, offs) if imus else np.zeros((n, 0, 3))
    q_bone = quat_from_matrix(fk.rotations[:, bones]) if imus else np.zeros((n, 0, 4))
    pts = kin.targets(fk, targets.bones, targets.offsets)
    K, dist, R, t = stack_cameras(cameras)
    dt = 1.0 / fps
    out = []
    for i in range(n):
        if cameras:
            uv, _, valid = project_points(K, dist, R, t, pts[i], jacobian=False)
            w = np.array([c.width for c in cameras])[:, None]
            h = np.array([c.height for c in cameras])[:, None]
            inside = valid & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
            conf = inside.astype(np.float64)
        else:
            uv = np.zeros((0, len(targets), 2))
            conf = np.zeros((0, len(targets)))
        acc = None
        if imus and i >= 2:
            acc = (sites[i] - 2 * sites[i - 1] + sites[i - 2]) / (dt * dt)
        out.append(
            Observations(
                keypoints=uv,
                confidences=conf,
                imu_orientations=q_bone[i] if imus else None,
                imu_accelerations=acc,
                dt=dt,
            )
        )
    return out

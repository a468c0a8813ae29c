"""Synthetic rigs, motion and exact observations for solver tests, benchmarks and the offline demo.

This is not the accuracy harness's sensor simulator (that one adds documented noise models to real recorded
motion); it produces *exact* measurements of a known pose so a solver's behaviour can be checked in isolation.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera, look_at, project_points, stack_cameras
from mocapd.core.imu import ImuMount
from mocapd.core.keypoints import TrackTargets, coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import quat_from_matrix, quat_from_rotvec, quat_multiply
from mocapd.core.skeleton import BONE_INDEX, N_BONES, POSE_DIM, Skeleton
from mocapd.core.solver import Observations
from mocapd.core.sorting import Detections2D
from mocapd.core.suit_binding import LIMBS

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


def named_ring_rig(names: Sequence[str]) -> list[Camera]:
    """The ring rig of ``len(names)`` cameras (defaults of :func:`ring_rig`), named ``names`` in order (the
    simulated rig of ``source = "synthetic"`` cameras and of synthetic camera hosts)."""
    return [dataclasses.replace(c, name=n) for c, n in zip(ring_rig(len(names)), names, strict=True)]


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
    start_still_s: float = 0.0,
) -> FloatArray:
    """A smooth, human-scaled motion with coordinated joints, the root walking a circle.

    Joint angles are driven by a few latent oscillations through a fixed mixing matrix (shared by all seeds,
    like the coordination of real movement, so a PCA prior fitted on one seed describes another), plus a
    small independent jitter per joint. The seed picks the latent frequencies and phases; ``amplitude``
    scales all joint excursions (e.g. to sample a broad pose pool for a prior). With ``start_still_s > 0`` time
    is warped as ``τ = t²/(2R)`` for ``t < R`` so the motion starts at rest and reaches full speed after R
    seconds, like a capture that begins from a calibration pose (IMU-only tracking needs a known start
    velocity).

    Returns
    -------
    array, shape (n_frames, 66)
    """
    rng = np.random.default_rng(seed)
    mix_rng = np.random.default_rng(_MIXING_SEED)
    t = np.arange(n_frames)[:, None] / fps
    if start_still_s > 0.0:
        t = np.where(t < start_still_s, t * t / (2.0 * start_still_s), t - 0.5 * start_still_s)
    t = t * speed
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


def scene_detections(
    cameras: list[Camera],
    targets: TrackTargets | Sequence[TrackTargets],
    skeleton: Skeleton | Sequence[Skeleton],
    people: list[FloatArray],
    rng: np.random.Generator,
    noise_px: float = 0.0,
) -> tuple[list[list[Detections2D]], list[list[NDArray[np.intp]]]]:
    """Per frame and camera, the 2D people as a detector would report them: unordered, labels kept apart.

    Parameters
    ----------
    targets, skeleton : one for everybody, or one per person.
    people : list of arrays, shape (n_frames, 66)
        Each person's pose sequence (same length).

    Returns
    -------
    detections : [frame][camera] Detections2D, people in a random order per camera and frame; keypoints outside
        the image or behind the camera have confidence 0, people with fewer than 5 visible keypoints are omitted.
    labels : [frame][camera] int array mapping each detection index to its person index in ``people``.
    """
    sks = [skeleton] * len(people) if isinstance(skeleton, Skeleton) else list(skeleton)
    tgs = [targets] * len(people) if isinstance(targets, TrackTargets) else list(targets)
    pts = []
    for p, theta in enumerate(people):  # (n_frames, n_kp, 3) per person
        kin = Kinematics(sks[p])
        pts.append(kin.targets(kin.forward(theta), tgs[p].bones, tgs[p].offsets))
    n_kp = len(tgs[0])
    K, dist, R, t = stack_cameras(cameras)
    n_frames = people[0].shape[0]
    dets: list[list[Detections2D]] = []
    labels: list[list[NDArray[np.intp]]] = []
    w = np.array([c.width for c in cameras])[:, None]
    h = np.array([c.height for c in cameras])[:, None]
    for f in range(n_frames):
        per_cam_kp: list[list[FloatArray]] = [[] for _ in cameras]
        per_cam_cf: list[list[FloatArray]] = [[] for _ in cameras]
        per_cam_lb: list[list[int]] = [[] for _ in cameras]
        for p, X in enumerate(pts):
            uv, _, valid = project_points(K, dist, R, t, X[f], jacobian=False)
            uv = uv + rng.normal(scale=noise_px, size=uv.shape) if noise_px > 0 else uv
            inside = valid & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
            for c in range(len(cameras)):
                if inside[c].sum() >= 5:
                    per_cam_kp[c].append(np.where(inside[c][:, None], uv[c], 0.0))
                    per_cam_cf[c].append(inside[c].astype(np.float64) * 0.9)
                    per_cam_lb[c].append(p)
        frame_dets, frame_labels = [], []
        for c in range(len(cameras)):
            order = rng.permutation(len(per_cam_lb[c]))
            kp = np.array(per_cam_kp[c]).reshape(-1, n_kp, 2)[order]
            cf = np.array(per_cam_cf[c]).reshape(-1, n_kp)[order]
            frame_dets.append(Detections2D(kp, cf))
            frame_labels.append(np.array(per_cam_lb[c], dtype=np.intp).reshape(-1)[order])
        dets.append(frame_dets)
        labels.append(frame_labels)
    return dets, labels


def walking_path(
    skeleton: Skeleton,
    n_frames: int,
    start: tuple[float, float],
    end: tuple[float, float],
    seed: int,
    fps: float = 60.0,
) -> FloatArray:
    """A person moving (limbs as :func:`moving_sequence`) in a straight line from ``start`` to ``end`` (x, z)."""
    theta = moving_sequence(skeleton, n_frames, fps=fps, seed=seed)
    s = np.linspace(0.0, 1.0, n_frames)[:, None]
    xz = (1 - s) * np.asarray(start) + s * np.asarray(end)
    theta[:, 0] = xz[:, 0]
    theta[:, 2] = xz[:, 1]
    return theta


def waypoint_path(
    skeleton: Skeleton, n_frames: int, waypoints: list[tuple[float, float, float]], seed: int, fps: float = 60.0
) -> FloatArray:
    """A person moving through ``(time fraction, x, z)`` waypoints (piecewise linear), limbs moving throughout."""
    theta = moving_sequence(skeleton, n_frames, fps=fps, seed=seed)
    w = np.asarray(waypoints, dtype=np.float64)
    s = np.linspace(0.0, 1.0, n_frames)
    theta[:, 0] = np.interp(s, w[:, 0], w[:, 1])
    theta[:, 2] = np.interp(s, w[:, 0], w[:, 2])
    return theta


def suit_orientations(
    skeleton: Skeleton, theta: FloatArray, yaw_deg: float, rng: np.random.Generator, noise_deg: float = 2.0
) -> dict[str, FloatArray]:
    """A simulated IMU suit: measured global orientations of the limb bones of ``theta`` (66,).

    Each limb bone of :data:`mocapd.core.suit_binding.LIMBS` gets its solved orientation, rotated by a heading
    misalignment of ``yaw_deg`` about +Y (an uncalibrated R_ig) and by ``noise_deg`` RMS-per-axis random rotation.
    """
    R = Kinematics(skeleton).forward(theta).rotations
    q_ig = quat_from_rotvec(np.array([0.0, np.radians(yaw_deg), 0.0]))
    out = {}
    for bone, _, _, _ in LIMBS:
        noise = quat_from_rotvec(rng.normal(scale=np.radians(noise_deg), size=3))
        out[bone] = quat_multiply(noise, quat_multiply(q_ig, quat_from_matrix(R[BONE_INDEX[bone]])))
    return out


def detector_like(
    detections: list[list[Detections2D]],
    rng: np.random.Generator,
    sigma_height: float = 0.015,
    outlier: float = 0.05,
    swap: float = 0.02,
) -> list[list[Detections2D]]:
    """Exact detections (:func:`scene_detections`) made as noisy as a real detector's, with the noise model of
    :mod:`mocapd.eval.simulate` applied per detected person: Gaussian noise of σ = ``sigma_height`` of the person's
    height in the image (the keypoints' vertical extent), a share ``outlier`` of keypoints thrown up to 30 % of that
    height away, in a share ``swap`` of people one limb's left and right keypoints exchanged, and a confidence that
    falls with the error (``c = 0.9 / (1 + (e / 4σ)²)``)."""
    out = []
    for row in detections:
        new_row = []
        for det in row:
            kp, cf = det.keypoints.copy(), det.confidences.copy()
            for p in range(len(kp)):
                seen = cf[p] > 0
                if seen.sum() < 2:
                    continue
                h = float(np.ptp(kp[p, seen, 1])) or 1.0
                sigma = sigma_height * h
                noise = rng.normal(scale=sigma, size=kp[p].shape)
                bad = rng.uniform(size=len(kp[p])) < outlier
                ang = rng.uniform(0.0, 2.0 * np.pi, size=len(kp[p]))
                rad = 0.3 * h * np.sqrt(rng.uniform(size=len(kp[p])))
                noise[bad] = np.stack((np.cos(ang), np.sin(ang)), axis=1)[bad] * rad[bad, None]
                kp[p] += noise
                err = np.linalg.norm(noise, axis=1)
                cf[p] = np.where(seen, 0.9 / (1.0 + (err / (4.0 * sigma)) ** 2), 0.0)
                if rng.uniform() < swap:
                    limb = ((5, 6), (7, 8), (9, 10)) if rng.uniform() < 0.5 else ((11, 12), (13, 14), (15, 16))
                    for left, right in limb:
                        kp[p, [left, right]] = kp[p, [right, left]]
                        cf[p, [left, right]] = cf[p, [right, left]]
            new_row.append(Detections2D(kp, cf))
        out.append(new_row)
    return out


def people_walking(
    cameras: list[Camera],
    heights: Sequence[float],
    seconds: float,
    rng: np.random.Generator,
    fps: float = 10.0,
    still_s: float = 1.0,
    extent: float = 1.5,
) -> tuple[list[list[Detections2D]], list[FloatArray]]:
    """People of ``heights`` walking through the rig for ``seconds`` (a self-calibration take): the first one
    stands at the origin facing +Z for ``still_s`` (limbs moving, feet on the floor), then walks a square of side
    2 ``extent`` around the centre; the others walk random waypoints inside ± ``extent``. Exact detections
    (:func:`scene_detections`) at ``fps`` moments a second.

    Returns
    -------
    detections : [moment][camera] Detections2D
    poses : list of arrays, shape (n_moments, 66), one per person
    """
    n = round(seconds * fps)
    still = round(still_s * fps)
    sks = [Skeleton.from_height(h) for h in heights]
    people = []
    for p, sk in enumerate(sks):
        if p == 0:
            e = extent
            square = [(0.3, e, -e), (0.5, -e, -e), (0.7, -e, e), (0.9, e, e), (1.0, e, -e)]
            theta = waypoint_path(sk, n, [(0.0, 0.0, 0.0), (still / n, 0.0, 0.0), *square], seed=p, fps=fps)
            theta[:still, 3:6] = 0.0  # facing +Z, upright
            theta[:still, 1] = sk.root_height
        else:
            pts = rng.uniform(-extent, extent, size=(6, 2))
            theta = waypoint_path(sk, n, [(k / 5, x, z) for k, (x, z) in enumerate(pts)], seed=p, fps=fps)
        people.append(theta)
    targets = [coco17_targets(sk) for sk in sks]
    dets, _ = scene_detections(cameras, targets, sks, people, rng)
    return dets, people

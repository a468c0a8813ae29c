"""Simulated inputs of the learned-fusion streams (issue 30; seed 001), for training and for the accuracy harness.

One :class:`~mocapd.eval.harness.Sequence` (the harness's simulated detections and IMU readings of a real clip)
gives everything the learned method reads, so the learned rows of ``mocapd eval accuracy`` and the LM solver see
the very same detections and IMUs:

- the **vision stream's** input per frame: the two-channel PVH (:mod:`mocapd.core.pvh`) of the cameras of a rig,
  carved around the grid centre triangulated from the detections (held from the previous frame when too few views
  see the hips), from rendered proxy mattes with :class:`~mocapd.sim.silhouettes.MatteNoise` and joint channels
  rendered from the detections;
- the **solved-IMU stream's** input: mocapd's own IMU-only solve (:class:`~mocapd.core.solver.PoseSolver` without
  cameras, with the pose prior and the foot-contact root) of the 6 or 13 IMUs, as joints relative to its root;
- the **raw-IMU** input: the measured bone orientations (rotation matrices' first two columns, 6 numbers per IMU,
  zero for an absent IMU, and a presence flag).

Training uses the CMU clips that the evaluation split does not hold (:func:`training_clips`): the Bandai clips of the
development split are CC BY-NC and the weights ship (MANIFEST.md).
"""

from __future__ import annotations

import time
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera, look_at
from mocapd.core.imu import IMU_SET_13
from mocapd.core.keypoints import coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.prior import PcaPrior
from mocapd.core.pvh import PvhGrid, carve, joint_map, joint_sigma, log_channels, person_centre, scaled_pixels
from mocapd.core.retarget import Retargeted
from mocapd.core.rotations import matrix_from_quat, matrix_from_rotvec, rotvec_from_matrix
from mocapd.core.terms import CostOptions
from mocapd.errors import ConfigError
from mocapd.eval.data import load_splits
from mocapd.eval.harness import IMU_SETS, RunConfig, Sequence, run_solver
from mocapd.eval.simulate import DetectionNoise, simulate_detections, totalcapture_ring
from mocapd.sim.silhouettes import MatteNoise, simulated_matte

FloatArray = NDArray[np.float64]
U8Array = NDArray[np.uint8]

N_JOINTS = 21
RAW_IMU_FEATURES = 13 * 7
"""Raw-IMU input per frame: 6 rotation numbers + 1 presence flag per slot of the 13-IMU set."""


def training_clips(data_root: Path | None = None) -> tuple[tuple[Path, ...], tuple[Path, ...]]:
    """(training, validation) clip files: CMU clips of the ``prior`` split train, the ``development`` split's CMU
    clip validates; no clip of the ``evaluation`` split, no Bandai clip (its licence forbids a shipped artefact)."""
    sp = load_splits(data_root)
    train = tuple(p for p in sp["prior"] if "cmu" in p.parts)
    val = tuple(p for p in sp["development"] if "cmu" in p.parts)
    if set(train + val) & set(sp["evaluation"]):
        raise ConfigError("the learned-fusion training clips overlap the evaluation split")
    if not train or not val:
        raise ConfigError("no CMU clips in the prior/development splits to train the learned fusion on")
    return train, val


def rotate_clip(clip: Retargeted, yaw: float, shift: FloatArray) -> Retargeted:
    """The clip turned by ``yaw`` (radians) about the vertical axis through the origin, then moved by ``shift``
    (x, z; metres): seed 001's augmentation (random rotation about the vertical), and a place in the volume."""
    Ry = matrix_from_rotvec(np.array([0.0, yaw, 0.0]))
    d = np.array([shift[0], 0.0, shift[1]])
    theta = clip.theta.copy()
    theta[:, :3] = clip.theta[:, :3] @ Ry.T + d
    theta[:, 3:6] = rotvec_from_matrix(Ry @ matrix_from_rotvec(clip.theta[:, 3:6]))
    fk = Kinematics(clip.skeleton).forward(theta)
    return replace(
        clip,
        theta=theta,
        positions=fk.positions,
        rotations=fk.rotations,
        source_positions=clip.source_positions @ Ry.T + d,
    )


@dataclass
class VisionInputs:
    """The vision stream's input for a run of frames of one rig.

    Attributes
    ----------
    pvh : uint8 array, shape (n, 2, S, S, S)
        Probabilities × 255 (matte, joints).
    centre : array, shape (n, 3)
        World grid centre of each frame.
    views : array, shape (n,)
        Cameras that see the person (any keypoint with confidence > 0).
    frames : int array, shape (n,)
        The sequence's frame of each row.
    seconds : float
        Time spent on what the daemon does per learned frame (grid centre, joint channels, carving), without
        the simulation of the mattes (a live rig's come from the cameras).
    """

    pvh: U8Array
    centre: FloatArray
    views: FloatArray
    frames: NDArray[np.intp]
    seconds: float = 0.0


def frame_channels(
    grid: PvhGrid,
    cams: list[Camera],
    centre: FloatArray,
    joints: FloatArray,
    height: float,
    uv: FloatArray,
    conf: FloatArray,
    noise: MatteNoise,
    rng: np.random.Generator,
) -> tuple[list[NDArray[np.float32]], NDArray[np.bool_], float]:
    """Log channel images of every camera for one frame, which are valid (simulated matte, detections' joints), and
    the seconds spent on what the daemon does (the joint channels and logarithms, not the matte simulation).

    Parameters
    ----------
    joints : (21, 3) the true pose the mattes are rendered from; uv : (n_cams, 17, 2); conf : (n_cams, 17).
    """
    imgs = []
    valid = np.ones((len(cams), 2), dtype=bool)
    mattes = [simulated_matte(cam, [(joints, height)], grid.scale, noise, rng) for cam in cams]
    t0 = time.perf_counter()
    for c, cam in enumerate(cams):
        m = mattes[c]
        seen = bool(np.any(conf[c] > 0))
        valid[c, 1] = seen
        jm = (
            joint_map(scaled_pixels(uv[c], grid.scale), conf[c], m.shape, joint_sigma(cam, centre, grid.scale))
            if seen
            else np.ones_like(m)
        )
        imgs.append(log_channels(np.stack((m, jm))))
    return imgs, valid, time.perf_counter() - t0


def vision_inputs(
    clip: Retargeted,
    cams: list[Camera],
    uv: FloatArray,
    conf: FloatArray,
    grid: PvhGrid,
    noise: MatteNoise,
    rng: np.random.Generator,
    frames: NDArray[np.intp] | None = None,
) -> VisionInputs:
    """PVHs of the frames (all by default) of a clip seen by ``cams``.

    Parameters
    ----------
    uv : (f, n_cams, 17, 2) and conf : (f, n_cams, 17): the detections of exactly these cameras.
    """
    idx = np.arange(clip.n_frames) if frames is None else np.asarray(frames, dtype=np.intp)
    s = grid.size
    out = np.zeros((len(idx), 2, s, s, s), dtype=np.uint8)
    centres = np.zeros((len(idx), 3))
    views = np.zeros(len(idx))
    prev = clip.positions[0, 0]  # the harness's solves also start from the known first pose
    seconds = 0.0
    for i, t in enumerate(idx):
        t0 = time.perf_counter()
        c = person_centre(cams, uv[t], conf[t], fallback=prev)
        assert c is not None
        prev = c
        t1 = time.perf_counter()
        imgs, valid, t_ch = frame_channels(
            grid, cams, c, clip.positions[t], clip.skeleton.height, uv[t], conf[t], noise, rng
        )
        t2 = time.perf_counter()
        out[i] = np.rint(255.0 * carve(grid, c, cams, imgs, valid)).astype(np.uint8)
        seconds += (t1 - t0) + t_ch + (time.perf_counter() - t2)
        centres[i] = c
        views[i] = np.count_nonzero(np.any(conf[t] > 0, axis=1))
    return VisionInputs(out, centres, views, idx, seconds)


def random_rig(rng: np.random.Generator, n_cams: int) -> list[Camera]:
    """A random rig of ``n_cams`` cameras around the volume, for training: ring radius 3.5–6 m, height 1.6–3 m,
    60 % of the time landscape 1920×1080 (25 % portrait 1080×1920, 15 % 1280×720), 50–75° across the long side,
    looking 0.8–1.2 m above the floor; the cameras adjacent on a ring of 8 (half of the rigs) or anywhere on it
    (a network trained on one rig alone would learn that rig's hull shapes)."""
    radius = float(rng.uniform(3.5, 6.0))
    height = float(rng.uniform(1.6, 3.0))
    u = rng.uniform()
    w, h = (1920, 1080) if u < 0.6 else (1080, 1920) if u < 0.85 else (1280, 720)
    fov = np.deg2rad(rng.uniform(50.0, 75.0))
    focal = 0.5 * max(w, h) / np.tan(fov / 2.0)
    start = rng.uniform(0, 2 * np.pi)
    if rng.uniform() < 0.5:
        angles = start + 2 * np.pi * np.arange(n_cams) / 8.0
    else:
        angles = start + np.sort(rng.uniform(0, 2 * np.pi, n_cams))
    angles = angles + rng.normal(scale=np.deg2rad(5.0), size=n_cams)
    target = np.array([0.0, float(rng.uniform(0.8, 1.2)), 0.0])
    return [
        look_at(f"rig{i}", np.array([radius * np.sin(a), height, radius * np.cos(a)]), target, w, h, float(focal))
        for i, a in enumerate(angles)
    ]


def rig_vision(
    seq: Sequence,
    cams: list[Camera],
    grid: PvhGrid,
    noise: MatteNoise,
    rng: np.random.Generator,
    frames: NDArray[np.intp] | None = None,
) -> VisionInputs:
    """:func:`vision_inputs` of a harness sequence's motion seen by another rig (its detections simulated here with
    the harness's realistic detector model)."""
    uv, conf = simulate_detections(seq.clip, cams, coco17_targets(seq.clip.skeleton), DetectionNoise(), rng)
    return vision_inputs(seq.clip, cams, uv, conf, grid, noise, rng, frames)


def ring_subset(n_cams: int, first: int) -> list[int]:
    """Indices of ``n_cams`` adjacent cameras of the 8-camera ring starting at ``first``."""
    return [(first + i) % 8 for i in range(n_cams)]


def sequence_vision(
    seq: Sequence,
    n_cams: int,
    grid: PvhGrid,
    noise: MatteNoise,
    seed: int,
    first: int = 0,
    frames: NDArray[np.intp] | None = None,
) -> VisionInputs:
    """:func:`vision_inputs` of a harness sequence on ``n_cams`` adjacent ring cameras (the harness's first N when
    ``first`` is 0), mattes seeded by ``seed`` and the sequence name."""
    idx = ring_subset(n_cams, first)
    ring = totalcapture_ring(8)
    rng = np.random.default_rng(zlib.crc32(f"matte:{seed}:{seq.name}:{n_cams}:{first}".encode()))
    return vision_inputs(seq.clip, [ring[i] for i in idx], seq.uv[:, idx], seq.conf[:, idx], grid, noise, rng, frames)


def solved_imu(seq: Sequence, n_imus: int, prior: PcaPrior | None, cost: CostOptions) -> FloatArray:
    """Joints (f, 21, 3) of mocapd's IMU-only solve of the sequence's ``n_imus`` IMUs (the solved-IMU stream)."""
    theta, _ = run_solver(seq, RunConfig(0, n_imus), prior, cost)
    return np.asarray(Kinematics(seq.clip.skeleton).forward(theta).positions)


def raw_imu(seq: Sequence, n_imus: int) -> FloatArray:
    """Raw-IMU features (f, 91): per slot of the 13-IMU set the measured bone orientation's first two matrix columns
    and a presence flag (zeros for IMUs the set lacks)."""
    f = seq.clip.n_frames
    out = np.zeros((f, 13, 7))
    rows = [IMU_SET_13.index(b) for b in IMU_SETS[n_imus]]
    if rows:
        R = matrix_from_quat(seq.q13[:, rows])  # (f, n, 3, 3)
        out[:, rows, :3] = R[..., :, 0]
        out[:, rows, 3:6] = R[..., :, 1]
        out[:, rows, 6] = 1.0
    return out.reshape(f, RAW_IMU_FEATURES)

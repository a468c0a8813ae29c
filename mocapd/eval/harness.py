"""``mocapd eval accuracy``: the accuracy harness (issue 3 §4).

For every evaluation sequence (a retargeted clip cut into windows that stay inside the capture volume) the
simulator produces one set of detections for the 8-camera ring (and the 120° arc) and one set of 13 IMU readings;
every configuration uses a subset of those same inputs (first N adjacent cameras; the 6-IMU set is a subset of
the 13). The real :class:`PoseSolver` runs online, frame by frame, warm-started, from the clip's first pose (as
after a calibration). The baselines see the same detections and IMU readings.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.imu import IMU_SET_6, IMU_SET_13, default_mounts
from mocapd.core.keypoints import coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.prior import PcaPrior
from mocapd.core.retarget import Retargeted
from mocapd.core.solver import TERM_NAMES, LMOptions, Observations, PoseSolver
from mocapd.core.terms import CostOptions
from mocapd.eval.baselines import imu_only_theta, joints_from_keypoints, robust_triangulate
from mocapd.eval.metrics import orientation_errors, position_errors, stats
from mocapd.eval.simulate import (
    DetectionNoise,
    ImuNoise,
    outdoor_arc,
    simulate_detections,
    simulate_imus,
    totalcapture_ring,
)

FloatArray = NDArray[np.float64]
IMU_SETS: dict[int, tuple[str, ...]] = {0: (), 6: IMU_SET_6, 13: IMU_SET_13}


@dataclass
class Sequence:
    """One evaluation sequence and its simulated inputs."""

    name: str
    clip: Retargeted
    uv: FloatArray  # (f, 8, 17, 2) ring detections
    conf: FloatArray  # (f, 8, 17)
    h_px: FloatArray  # (f, 8) person height in pixels per ring camera
    arc_uv: FloatArray  # (f, 4, 17, 2)
    arc_conf: FloatArray
    arc_h_px: FloatArray
    q13: FloatArray  # (f, 13, 4) measured bone orientations
    acc13: FloatArray  # (f, 13, 3) measured accelerations at t-1 (rows 0, 1 NaN)


def windows(clip: Retargeted, radius: float = 1.75, min_frames: int = 60) -> list[Retargeted]:
    """The clip cut where its root leaves a disc of ``radius`` around the window start, each window recentred.

    Long walks and runs would otherwise leave the ~4×4 m volume the cameras look at.
    """
    xz = clip.theta[:, [0, 2]]
    out: list[Retargeted] = []
    start = 0
    f = clip.n_frames
    while start < f:
        end = start + 1
        while end < f and np.linalg.norm(xz[end] - xz[start]) <= 2 * radius:
            end += 1
        if end - start >= min_frames:
            sl = slice(start, end)
            shift = np.zeros(3)
            shift[[0, 2]] = -xz[sl].mean(axis=0)
            theta = clip.theta[sl].copy()
            theta[:, :3] += shift
            name = clip.name if start == 0 and end == f else f"{clip.name}@{start}"
            out.append(
                replace(
                    clip,
                    name=name,
                    theta=theta,
                    positions=clip.positions[sl] + shift,
                    rotations=clip.rotations[sl],
                    source_positions=clip.source_positions[sl] + shift,
                )
            )
        start = end
    return out


def _height_px(clip: Retargeted, cams: list[Camera]) -> FloatArray:
    root = clip.theta[:, :3]
    out = np.zeros((clip.n_frames, len(cams)))
    for c, cam in enumerate(cams):
        depth = (root @ cam.R.T + cam.t)[:, 2]
        out[:, c] = cam.K[0, 0] * clip.skeleton.height / np.maximum(depth, 0.1)
    return out


def make_sequence(clip: Retargeted, seed: int, det: DetectionNoise, imu: ImuNoise) -> Sequence:
    rng = np.random.default_rng(seed)
    targets = coco17_targets(clip.skeleton)
    ring, arc = totalcapture_ring(), outdoor_arc()
    uv, conf = simulate_detections(clip, ring, targets, det, rng)
    auv, aconf = simulate_detections(clip, arc, targets, det, rng)
    q, acc = simulate_imus(clip, default_mounts(IMU_SET_13, clip.skeleton), imu, rng)
    return Sequence(clip.name, clip, uv, conf, _height_px(clip, ring), auv, aconf, _height_px(clip, arc), q, acc)


@dataclass(frozen=True)
class RunConfig:
    """One solver configuration."""

    n_cams: int
    n_imus: int
    rig: str = "ring"  # "ring" (first n_cams adjacent cameras) or "arc" (the 4-camera arc)
    cost: CostOptions | None = None
    subsample: tuple[int, int] | None = None  # (N_o, N_p): detections on the first N_o of every N_p frames


def _imu_rows(n_imus: int) -> list[int]:
    return [IMU_SET_13.index(b) for b in IMU_SETS[n_imus]]


def _cameras(seq: Sequence, cfg: RunConfig) -> tuple[list[Camera], FloatArray, FloatArray, FloatArray]:
    if cfg.rig == "arc":
        return outdoor_arc()[: cfg.n_cams], seq.arc_uv[:, : cfg.n_cams], seq.arc_conf[:, : cfg.n_cams], seq.arc_h_px
    return totalcapture_ring(cfg.n_cams), seq.uv[:, : cfg.n_cams], seq.conf[:, : cfg.n_cams], seq.h_px


def run_solver(
    seq: Sequence,
    cfg: RunConfig,
    prior: PcaPrior | None,
    cost: CostOptions,
    lm: LMOptions | None = None,
    learned: dict[int, FloatArray] | None = None,
) -> tuple[FloatArray, int]:
    """Solve the sequence online; returns θ (f, 66) and the number of frames whose solve was not finite.

    ``learned`` (issue 30): per frame, learned 3D joints (21, 3) that enter the solve as E_J observations."""
    clip = seq.clip
    cams, uv, conf, _ = _cameras(seq, cfg)
    rows = _imu_rows(cfg.n_imus)
    mounts = default_mounts(IMU_SETS[cfg.n_imus], clip.skeleton)
    solver = PoseSolver(clip.skeleton, cams, coco17_targets(clip.skeleton), mounts, prior, cfg.cost or cost, lm)
    solver.reset(clip.theta[0])
    f = clip.n_frames
    out = np.zeros((f, 66))
    bad = 0
    dt = 1.0 / clip.fps
    for t in range(f):
        detect = cfg.subsample is None or (t % cfg.subsample[1]) < cfg.subsample[0]
        c = conf[t] if detect else np.zeros_like(conf[t])
        obs = Observations(
            keypoints=uv[t] if cams else None,
            confidences=c if cams else None,
            imu_orientations=seq.q13[t, rows] if rows else None,
            imu_accelerations=seq.acc13[t, rows] if rows and t >= 2 else None,
            joint_positions=learned.get(t) if learned is not None else None,
            dt=dt,
        )
        theta = solver.solve(obs).theta
        if not np.all(np.isfinite(theta)):
            bad += 1
        out[t] = theta
    return out, bad


def run_triangulation(seq: Sequence, n_cams: int, rig: str = "ring") -> FloatArray:
    """Baseline (i): joints (f, 21, 3) from robust per-frame triangulation (previous value where missing).

    Frames are independent for the triangulation itself, so all of them go through one vectorised call; only
    the carry-forward of joints not seen in a frame runs in time order.
    """
    cams, uv, conf, hpx = _cameras(seq, RunConfig(n_cams, 0, rig))
    clip = seq.clip
    f, _, k = conf.shape
    flat_uv = np.swapaxes(uv, 0, 1).reshape(n_cams, f * k, 2)
    flat_w = np.swapaxes(conf, 0, 1).reshape(n_cams, f * k)
    flat_h = np.repeat(hpx[:, :n_cams].T, k, axis=1)  # (n_cams, f * k)
    kp, ok = robust_triangulate(cams, flat_uv, flat_w, flat_h)
    kp, ok = kp.reshape(f, k, 3), ok.reshape(f, k)
    prev = clip.positions[0].copy()  # the same known start as the solver
    out = np.zeros((f, 21, 3))
    for t in range(f):
        prev = joints_from_keypoints(kp[t], ok[t], clip.skeleton, prev)
        out[t] = prev
    return out


def run_imu_only(seq: Sequence, n_imus: int) -> FloatArray:
    """Baseline (ii): θ (f, 66) of IMU-only forward kinematics, root held at its start."""
    rows = _imu_rows(n_imus)
    bones = [IMU_SET_13.index(b) for b in IMU_SETS[n_imus]]
    from mocapd.core.skeleton import BONE_INDEX

    bone_idx = [BONE_INDEX[IMU_SET_13[i]] for i in bones]
    root = np.broadcast_to(seq.clip.theta[0, :3], (seq.clip.n_frames, 3))
    return imu_only_theta(seq.clip.skeleton, bone_idx, seq.q13[:, rows], root)


@dataclass
class Errors:
    """Per-frame, per-joint errors of one method over several sequences (concatenated)."""

    global_mm: list[FloatArray]
    root_mm: list[FloatArray]
    procrustes_mm: list[FloatArray]
    orient_deg: list[FloatArray]
    nonfinite: int = 0
    frames: int = 0

    @classmethod
    def empty(cls) -> Errors:
        return cls([], [], [], [])

    def add(self, pos: FloatArray, truth: Retargeted, rot: FloatArray | None, nonfinite: int = 0) -> None:
        e = position_errors(pos, truth.positions)
        self.global_mm.append(e["global"])
        self.root_mm.append(e["root_relative"])
        self.procrustes_mm.append(e["procrustes"])
        if rot is not None:
            self.orient_deg.append(orientation_errors(rot, truth.rotations))
        self.nonfinite += nonfinite
        self.frames += pos.shape[0]

    def table(self, joints: tuple[int, ...] | None = None) -> dict[str, Any]:
        def cat(xs: list[FloatArray]) -> FloatArray:
            a = np.concatenate(xs) if xs else np.zeros((0, 21))
            return a[:, list(joints)] if joints is not None else a

        return {
            "global_mm": stats(cat(self.global_mm)),
            "root_relative_mm": stats(cat(self.root_mm)),
            "procrustes_mm": stats(cat(self.procrustes_mm)),
            "orientation_deg": stats(cat(self.orient_deg)) if self.orient_deg else None,
            "frames": self.frames,
            "nonfinite_frames": self.nonfinite,
        }


def solver_errors(
    seqs: list[Sequence],
    cfg: RunConfig,
    prior: PcaPrior | None,
    cost: CostOptions,
    tick: Callable[[int], None],
    per_sequence: dict[str, Any] | None = None,
) -> Errors:
    err = Errors.empty()
    for s in seqs:
        theta, bad = run_solver(s, cfg, prior, cost)
        fk = Kinematics(s.clip.skeleton).forward(theta)
        err.add(fk.positions, s.clip, fk.rotations, bad)
        if per_sequence is not None:
            one = Errors.empty()
            one.add(fk.positions, s.clip, fk.rotations, bad)
            per_sequence[s.name] = one.table()
        tick(s.clip.n_frames)
    return err


def iterate_terms() -> Iterator[str]:
    yield from TERM_NAMES

"""Finger accuracy on simulated hands: ``python -m mocapd.eval.hands`` prints JSON.

A person walks the synthetic motion of :func:`mocapd.core.synthetic.moving_sequence` inside the ring rig of
:func:`mocapd.core.synthetic.ring_rig` (8 cameras on a 4 m circle, 1400 px focal length, 1920x1080: the hand is
about 65 px long in each view). Both hands, hanging from the body's hand bones, run a few seconds of finger
motion (:func:`hand_motion`): fists made and opened in a wave across the fingers, the fingers spread and closed,
and the thumb opposed to the fingertips and back. Each frame:

1. the body's COCO-17 keypoints and the hands' 21 landmarks are projected into every view with detector-like
   noise (:class:`HandNoise`: Gaussian pixels, a few outliers, points and whole hands dropped per view);
2. the body is solved (:class:`~mocapd.core.solver.PoseSolver`, warm-started, no prior), as in the daemon;
3. each hand is solved (:class:`~mocapd.core.hand_solver.HandSolver`) from its keypoints, starting from the body
   solve's hand bone and wrist, warm-started from its previous frame.

Reported: the flexion error of every finger joint (the angle of the hinge that flexes each of the 15 bones, solved
against true; degrees, mean and p90 over frames and hands), per finger and overall, the abduction error, and the
CPU time of a hand solve against the body solve's in the same run (thread CPU time; medians). Self-occlusion of
the fingers is not simulated: the noise stands in for it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera, project_points, stack_cameras
from mocapd.core.hand_skeleton import FINGER_BONES, FINGERS, HAND_BONES, SIDES, HandSkeleton
from mocapd.core.hand_solver import (
    FLEXION_HINGES,
    HINGE_NAMES,
    LOWER,
    N_HINGES,
    PRIOR_MEAN,
    UPPER,
    HandResult,
    HandSolver,
    hand_fk,
)
from mocapd.core.keypoints import coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.core.solver import Observations, PoseSolver
from mocapd.core.synthetic import moving_sequence, ring_rig

FloatArray = NDArray[np.float64]
_DEG = np.pi / 180.0


@dataclass(frozen=True)
class HandNoise:
    """Detector-like noise on the hand keypoints of one view."""

    sigma_px: float = 2.5
    """Gaussian noise per coordinate (pixels)."""
    outlier: float = 0.02
    """Share of points thrown up to ``outlier_px`` away."""
    outlier_px: float = 25.0
    dropout: float = 0.05
    """Share of points not found (confidence 0)."""
    hand_dropout: float = 0.1
    """Share of views in which a hand is not found at all."""


def hand_motion(seconds: float, fps: float = 60.0, phase: float = 0.0) -> FloatArray:
    """True hinge angles (n_frames, 21) of one hand: fists in a wave, spreading and thumb opposition.

    Three overlapping movements at their own rates, so a few seconds cover their combinations:

    * flexion: each finger's MCP 0-80°, PIP 0-95°, DIP 2/3 of PIP (± 6°) at 0.45 Hz, each finger a quarter of a
      radian behind the one before (a wave from the index to the little finger);
    * spreading: the MCPs' abduction ±15° (little finger 0-25°) at 0.3 Hz;
    * opposition: the thumb's CMC palmar abduction 5-60°, adduction 0-35°, roll 0-45°, MCP 5-40°, IP 5-55° at
      0.25 Hz (the thumb's tip sweeps across toward the fingertips and back).
    """
    t = np.arange(round(seconds * fps)) / fps + phase
    out = np.zeros((len(t), N_HINGES))
    idx = {n: i for i, n in enumerate(HINGE_NAMES)}
    for f, finger in enumerate(("index", "middle", "ring", "little")):
        close = 0.5 - 0.5 * np.cos(2 * np.pi * 0.45 * t - 0.25 * f)  # 0 open .. 1 fist
        out[:, idx[f"{finger}_mcp_flexion"]] = 80.0 * close
        out[:, idx[f"{finger}_pip_flexion"]] = 95.0 * close
        out[:, idx[f"{finger}_dip_flexion"]] = 95.0 * close * 2 / 3 + 6.0 * np.sin(2 * np.pi * 0.7 * t + f)
        spread = np.sin(2 * np.pi * 0.3 * t)
        out[:, idx[f"{finger}_mcp_abduction"]] = (12.5 + 12.5 * spread) if finger == "little" else 15.0 * spread
    oppose = 0.5 - 0.5 * np.cos(2 * np.pi * 0.25 * t)
    for name, lo, hi in (("thumb_cmc_palmar", 5, 60), ("thumb_cmc_adduction", 0, 35), ("thumb_cmc_roll", 0, 45),
                         ("thumb_mcp_flexion", 5, 40), ("thumb_ip_flexion", 5, 55)):  # fmt: skip
        out[:, idx[name]] = lo + (hi - lo) * oppose
    return np.clip(out * _DEG, LOWER, UPPER)


def _project(cameras: list[Camera], points: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Pixels (n_cams, n, 2) of world points (n, 3) and whether each lands in front of and inside the image."""
    K, dist, R, t = stack_cameras(cameras)
    uv, _, valid = project_points(K, dist, R, t, points, jacobian=False)
    w = np.array([c.width for c in cameras])[:, None]
    h = np.array([c.height for c in cameras])[:, None]
    inside = valid & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
    return uv, inside


def _noisy(uv: FloatArray, seen: NDArray[np.bool_], noise: HandNoise, rng: np.random.Generator) -> tuple[
    FloatArray, FloatArray]:  # fmt: skip
    """Detector-like hand keypoints (n_cams, 21, 2) and confidences (n_cams, 21)."""
    out = uv + rng.normal(scale=noise.sigma_px, size=uv.shape)
    bad = rng.uniform(size=seen.shape) < noise.outlier
    ang = rng.uniform(0.0, 2 * np.pi, size=seen.shape)
    rad = noise.outlier_px * np.sqrt(rng.uniform(size=seen.shape))
    out[bad] = uv[bad] + np.stack((np.cos(ang), np.sin(ang)), axis=-1)[bad] * rad[bad, None]
    conf = rng.uniform(0.6, 1.0, size=seen.shape) * seen
    conf[bad] *= 0.5
    conf[rng.uniform(size=seen.shape) < noise.dropout] = 0.0
    conf[rng.uniform(size=seen.shape[0]) < noise.hand_dropout] = 0.0
    return out, conf


def run(seconds: float = 4.0, seed: int = 0, n_cams: int = 8, radius: float = 4.0,
        noise: HandNoise | None = None) -> dict[str, Any]:  # fmt: skip
    """The evaluation (see the module docstring); returns the report."""
    noise = noise if noise is not None else HandNoise()
    rng = np.random.default_rng(seed)
    fps = 60.0
    skeleton = Skeleton.from_height(1.75)
    hands = HandSkeleton.from_body(skeleton)
    cameras = ring_rig(n_cams, radius=radius)
    P = np.stack([c.projection_matrix for c in cameras])
    targets = coco17_targets(skeleton)
    n = round(seconds * fps)
    thetas = moving_sequence(skeleton, n, fps=fps, seed=seed, amplitude=0.6)
    kin = Kinematics(skeleton)
    fk = kin.forward(thetas)
    body_pts = kin.targets(fk, targets.bones, targets.offsets)
    truth = np.stack([hand_motion(seconds, fps, phase=0.0), hand_motion(seconds, fps, phase=1.3)], axis=1)
    body = PoseSolver(skeleton, cameras, targets)
    body.reset(thetas[0])
    solvers = [HandSolver(hands, side) for side in (0, 1)]
    previous: list[HandResult | None] = [None, None]
    bone = [BONE_INDEX[HAND_BONES[s]] for s in SIDES]
    err_flex, err_abd, body_cpu, hand_cpu, solved, frames = [], [], [], [], 0, 0
    for i in range(n):
        uv_b, in_b = _project(cameras, body_pts[i])
        uv_b = uv_b + rng.normal(scale=2.0, size=uv_b.shape)
        c0 = time.thread_time_ns()
        result = body.solve(Observations(keypoints=uv_b, confidences=in_b.astype(np.float64), dt=1 / fps))
        c1 = time.thread_time_ns()
        body_cpu.append(c1 - c0)
        solved_fk = kin.forward(result.theta)
        for side in (0, 1):
            b = bone[side]
            true_lm = hand_fk(hands, side, truth[i, side], fk.rotations[i, b], fk.positions[i, b]).landmarks
            uv, seen = _project(cameras, true_lm)
            uv_n, conf = _noisy(uv, seen, noise, rng)
            c2 = time.thread_time_ns()
            res = solvers[side].solve(P, uv_n, conf, solved_fk.rotations[b], solved_fk.positions[b], previous[side])
            hand_cpu.append(time.thread_time_ns() - c2)
            frames += 1
            if res is None:
                continue  # not seen well enough this frame: the previous solve stays the warm start
            previous[side] = res
            solved += 1
            d = (res.angles - truth[i, side]) / _DEG
            err_flex.append(np.abs(d[list(FLEXION_HINGES)]))
            err_abd.append(np.abs(d[[HINGE_NAMES.index(f"{f}_mcp_abduction") for f in ("index", "middle", "ring",
                                                                                         "little")]]))  # fmt: skip
    flex = np.array(err_flex)  # (n_solved, 15)
    abd = np.array(err_abd)
    per_joint = {FINGER_BONES[b]: _stats(flex[:, b]) for b in range(len(FINGER_BONES))}
    per_finger = {f: _stats(flex[:, 3 * k : 3 * k + 3].reshape(-1)) for k, f in enumerate(FINGERS)}
    prior_only = np.abs(truth.reshape(-1, N_HINGES) - PRIOR_MEAN)[:, list(FLEXION_HINGES)] / _DEG
    hand_ms = np.array(hand_cpu) / 1e6
    body_ms = np.array(body_cpu) / 1e6
    return {
        "eval": "hands",
        "setup": {
            "seconds": seconds,
            "fps": fps,
            "seed": seed,
            "cameras": n_cams,
            "radius_m": radius,
            "hand_length_m": round(hands.length(0), 4),
            "hand_px": round(_hand_px(cameras, hands), 1),
            "noise": noise.__dict__,
        },
        "flexion_error_deg": {"overall": _stats(flex.reshape(-1)), "per_finger": per_finger, "per_joint": per_joint},
        "abduction_error_deg": _stats(abd.reshape(-1)),
        "prior_mean_error_deg": _stats(prior_only.reshape(-1)),
        "hands_solved": solved,
        "hand_frames": frames,
        "cpu": {
            "model": _cpu_model(),
            "hand_solve_ms_median": round(float(np.median(hand_ms)), 3),
            "hand_solve_ms_p90": round(float(np.percentile(hand_ms, 90)), 3),
            "body_solve_ms_median": round(float(np.median(body_ms)), 3),
            "hand_per_body": round(float(np.median(hand_ms) / np.median(body_ms)), 2),
            "loadavg": [round(x, 2) for x in os.getloadavg()],
        },
    }


def _stats(x: FloatArray) -> dict[str, float]:
    return {"mean": round(float(np.mean(x)), 2), "median": round(float(np.median(x)), 2),
            "p90": round(float(np.percentile(x, 90)), 2)}  # fmt: skip


def _hand_px(cameras: list[Camera], hands: HandSkeleton) -> float:
    """A hand's length in pixels at the rig's centre (focal length · length / distance), the views' median."""
    distances = [float(np.linalg.norm(c.center - np.array([0.0, 1.0, 0.0]))) for c in cameras]
    return float(np.median([c.K[0, 0] * hands.length(0) / d for c, d in zip(cameras, distances, strict=True)]))


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.partition(":")[2].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mocapd.eval.hands", description=__doc__.split("\n")[0])
    p.add_argument("--seconds", type=float, default=4.0, help="length of the run (default 4)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cameras", type=int, default=8, help="cameras in the ring (default 8)")
    p.add_argument("--radius", type=float, default=4.0, help="the ring's radius, metres (default 4)")
    p.add_argument("--sigma-px", type=float, default=2.5, help="keypoint noise, pixels (default 2.5)")
    args = p.parse_args(argv)
    report = run(args.seconds, args.seed, args.cameras, args.radius, HandNoise(sigma_px=args.sigma_px))
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

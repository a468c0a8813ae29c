"""Root drift without cameras (issue 14): ``mocapd eval ground`` → JSON.

Four measurements, each with foot contacts on (:mod:`mocapd.core.ground`, the default) and off (the LM's root: the
behaviour before issue 14 minus the velocity feedback of its warm start):

``synthetic``
    The synthetic rig's recorded motion (:class:`~mocapd.sim.world.SyntheticWorld`'s CMU clips, 12 s each, at
    60 Hz) with 0 cameras and 13 IMUs, IMU noise of :class:`~mocapd.eval.simulate.ImuNoise` (5° mounting
    calibration error, 1° per-sample orientation noise, a 1°/√min heading random walk, 0.2 m/s² acceleration
    noise), the solver started at the true first pose. Per clip: the root height error (p95, max) and the
    horizontal drift at the end and at its worst, also as a fraction of the distance walked (the root's
    horizontal path sampled every 0.5 s, so that the sway of a step is not counted as walking).
``walking``
    The same on the evaluation split's walking, running and dashing clips (``mocapd/data/eval_splits.toml``; the
    rig's clips are fighting moves that step about in place).
``standing``
    60 s of standing still (the rig's first clip's first pose held) with the same noise: root drift.
``cameras_back``
    The rig's first clip with 4 cameras (simulated detections, 1 px noise) that see nothing from 2 s to 8 s: the
    published root's largest jump per frame beyond the true motion's, and the error 1 s after they return.
``mtw``
    The real Xsens MTw recording (``imu/opensense_mtw``, 8 sensors on the lower body and the back, 24 s: standing,
    then walking), imported, calibrated from its stillest standing second and solved IMU-only. There is no position
    truth: the root height (which the standing posture fixes at the start) and its range over the recording, and
    the horizontal drift in the still first seconds.
``mvnx``
    The MVNX upper-body recording (11 sensors, 1.9 s) against MVN's own pelvis trajectory.
``optical`` (not in the default parts: its data are not shipped)
    A real walk of a 7-sensor lower-body suit against Vicon, beside Xsens MVN's own solve
    (:mod:`mocapd.eval.ground_optical`).

Every IMU-only part reports the root's path length against the truth's (``path_error_pct``): an avatar's steps
must cover the floor its body covers (issue 28).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.ground import GroundOptions
from mocapd.core.imu import IMU_SET_13, ImuMount, default_mounts
from mocapd.core.keypoints import TrackTargets, coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.motion import resample_poses
from mocapd.core.observations import Observations
from mocapd.core.prior import PcaPrior
from mocapd.core.retarget import Retargeted
from mocapd.core.rotations import matrix_from_rotvec, rotvec_from_matrix
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.core.solver import PoseSolver
from mocapd.core.terms import CostOptions
from mocapd.eval.simulate import ImuNoise, simulate_imus
from mocapd.sim.world import TRUTH_FPS, SyntheticWorld, load_demo_motion

FloatArray = NDArray[np.float64]
FPS = 60.0
WALK_WINDOW_S = 0.5


def make_clip(name: str, skeleton: Skeleton, theta: FloatArray, fps: float) -> Retargeted:
    """A pose sequence as a :class:`Retargeted` clip (its joints and rotations by forward kinematics)."""
    fk = Kinematics(skeleton).forward(theta)
    return Retargeted(name, skeleton, theta, fk.positions, fk.rotations, fk.positions, fps)


FLAT_SPEED = 0.05
"""m/s: a foot whose ankle and toe joints both move slower than this, at the lower end of their heights, stands
flat (for :func:`standing_feet`)."""


FLAT_FRAMES = 10
"""A clip with fewer frames of a foot standing flat (a run, a dash) does not tell that foot's flat pitch."""


def flat_pitches(skeleton: Skeleton, theta: FloatArray, fps: float) -> tuple[float | None, float | None]:
    """Each foot's pitch (radians, toe down positive) where it stands flat in a clip: the median over the frames where
    its ankle and toe joints both move slower than :data:`FLAT_SPEED` at the lower end of their heights; None with
    fewer than :data:`FLAT_FRAMES` such frames."""
    fk = Kinematics(skeleton).forward(theta)
    out: list[float | None] = []
    for foot, toes in (("LeftFoot", "LeftToes"), ("RightFoot", "RightToes")):
        f, t = BONE_INDEX[foot], BONE_INDEX[toes]
        pts = fk.positions[:, [f, t]]
        if len(pts) < 2:
            out.append(None)
            continue
        speed = np.linalg.norm(np.gradient(pts, 1.0 / fps, axis=0), axis=-1).max(axis=1)
        top = pts[:, :, 1].max(axis=1)
        still = (speed < FLAT_SPEED) & (top <= np.percentile(top, 30))
        fwd = fk.rotations[still, f][:, :, 2]  # the foot's forward axis in the world
        out.append(float(np.median(np.arcsin(np.clip(-fwd[:, 1], -1.0, 1.0)))) if still.sum() >= FLAT_FRAMES else None)
    return out[0], out[1]


def standing_feet(
    skeleton: Skeleton, theta: FloatArray, pitches: tuple[float | None, float | None]
) -> tuple[Skeleton, FloatArray]:
    """A clip as a suit calibrated standing sees it: each foot's rest orientation is the one it stands flat in.

    A suit's calibration takes the standing posture for the rest pose (``mocapd calibrate imu``), so a foot standing
    flat on the floor is at its rest orientation, with its sole on the floor. Retargeted recordings do not do that:
    their foot bones point from the source's ankle joint to its toe joint, which stands pitched down by 6-12° (CMU)
    or 31.5° (Bandai, every clip) against the skeleton's rest foot. Here each foot's frame is turned by its flat pitch
    (:func:`flat_pitches`; None: left as it is): its local rotation ``R_f ← R_f · P⁻¹``, its toes' offset
    ``o ← P · o`` and rotation ``R_t ← P · R_t · P⁻¹``, the rest pose put back on the floor. Every joint position of
    every frame is unchanged (forward kinematics gives the same points); only the feet's rest pose, and so their
    bone orientations, now match a calibrated suit.

    Returns
    -------
    skeleton, theta
        The re-expressed skeleton and clip.
    """
    kin = Kinematics(skeleton)
    offsets = skeleton.offsets.copy()
    th = np.array(theta, dtype=np.float64)
    for (foot, toes), pitch in zip((("LeftFoot", "LeftToes"), ("RightFoot", "RightToes")), pitches, strict=True):
        if pitch is None:
            continue
        f, t = BONE_INDEX[foot], BONE_INDEX[toes]
        P = matrix_from_rotvec(np.array([pitch, 0.0, 0.0]))
        sl_f, sl_t = slice(3 + 3 * f, 6 + 3 * f), slice(3 + 3 * t, 6 + 3 * t)
        th[:, sl_f] = rotvec_from_matrix(matrix_from_rotvec(th[:, sl_f]) @ P.T)
        th[:, sl_t] = rotvec_from_matrix(P @ matrix_from_rotvec(th[:, sl_t]) @ P.T)
        offsets[t] = P @ offsets[t]
    # The rest pose stands on the floor as before: its lowest foot joint as high as it was.
    feet = [BONE_INDEX[b] for b in ("LeftFoot", "LeftToes", "RightFoot", "RightToes")]
    low_before = float(kin.forward(skeleton.rest_pose()).positions[feet, 1].min())
    moved = Skeleton(offsets=offsets, root_height=skeleton.root_height, height=skeleton.height)
    low_after = float(Kinematics(moved).forward(moved.rest_pose()).positions[feet, 1].min())
    root_height = skeleton.root_height + low_before - low_after
    return Skeleton(offsets=offsets, root_height=root_height, height=skeleton.height), th


def imu_only_observations(
    clip: Retargeted, mounts: tuple[ImuMount, ...], noise: ImuNoise, rng: np.random.Generator
) -> list[Observations]:
    """0-camera observations of a clip: simulated IMU bone orientations and accelerations, per frame."""
    q, acc = simulate_imus(clip, mounts, noise, rng)
    dt = 1.0 / clip.fps
    return [
        Observations(imu_orientations=q[t], imu_accelerations=acc[t] if t >= 2 else None, dt=dt)
        for t in range(clip.n_frames)
    ]


def walked_distance(root_xz: FloatArray, fps: float) -> float:
    """Horizontal path length (m) of a root trajectory (n, 2) sampled every :data:`WALK_WINDOW_S`."""
    step = max(1, round(WALK_WINDOW_S * fps))
    pts = np.concatenate([root_xz[::step], root_xz[-1:]])
    return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())


def drift_metrics(solved: FloatArray, truth: FloatArray, fps: float) -> dict[str, float]:
    """Root height and horizontal drift of solved θ (n, 66) against the truth (n, 66)."""
    dy = np.abs(solved[:, 1] - truth[:, 1])
    exz = solved[:, [0, 2]] - truth[:, [0, 2]]
    dxz = np.linalg.norm(exz, axis=1)
    walked = walked_distance(truth[:, [0, 2]], fps)
    path = walked_distance(solved[:, [0, 2]], fps)
    n = max(1, round(fps))  # 1 s means: the drift without the per-frame jitter of the orientation noise
    smooth = np.linalg.norm(np.cumsum(exz, axis=0)[n - 1 :] - np.r_[np.zeros((1, 2)), np.cumsum(exz, axis=0)[:-n]],
                            axis=1) / n  # fmt: skip
    return {
        "seconds": round(len(truth) / fps, 1),
        "walked_m": round(walked, 2),
        "solved_path_m": round(path, 2),
        "path_error_pct": round(100 * (path - walked) / max(walked, 1e-9), 1),
        "height_error_p95_cm": round(100 * float(np.percentile(dy, 95)), 1),
        "height_error_max_cm": round(100 * float(dy.max()), 1),
        "horizontal_drift_end_cm": round(100 * float(dxz[-1]), 1),
        "horizontal_drift_max_cm": round(100 * float(dxz.max()), 1),
        "horizontal_drift_max_1s_mean_cm": round(100 * float(smooth.max()), 1) if smooth.size else float("nan"),
        "drift_end_per_walked_pct": round(100 * float(dxz[-1]) / max(walked, 1e-9), 1),
    }


def _solver(
    skeleton: Skeleton,
    prior: PcaPrior | None,
    ground: bool,
    cameras: list[Camera] | None = None,
    targets: TrackTargets | None = None,
) -> PoseSolver:
    return PoseSolver(
        skeleton,
        cameras or [],
        targets,
        default_mounts(IMU_SET_13, skeleton),
        prior,
        CostOptions(),
        ground=GroundOptions(enabled=ground),
    )


def solve_clip(solver: PoseSolver, truth: FloatArray, obs: list[Observations]) -> FloatArray:
    """Solve every frame from the true first pose; θ per frame (n, 66)."""
    solver.reset(truth[0])
    return np.array([solver.solve(o).theta for o in obs])


def imu_only_case(
    name: str,
    skeleton: Skeleton,
    truth: FloatArray,
    prior: PcaPrior | None,
    seed: int,
    noise: ImuNoise,
    pitches: tuple[float | None, float | None] | None = None,
) -> dict[str, Any]:
    """One clip, 0 cameras + 13 IMUs, contacts on and off (the feet as a suit calibrated standing sees them,
    :func:`standing_feet`, at ``pitches``, default the clip's own :func:`flat_pitches`)."""
    skeleton, truth = standing_feet(skeleton, truth, flat_pitches(skeleton, truth, FPS) if pitches is None else pitches)
    clip = make_clip(name, skeleton, truth, FPS)
    obs = imu_only_observations(clip, default_mounts(IMU_SET_13, skeleton), noise, np.random.default_rng(seed))
    out: dict[str, Any] = {"clip": name}
    for label, ground in (("contacts", True), ("no_contacts", False)):
        out[label] = drift_metrics(solve_clip(_solver(skeleton, prior, ground), truth, obs), truth, FPS)
    return out


def synthetic_rig_clips() -> tuple[list[tuple[str, FloatArray]], Skeleton]:
    """The synthetic rig's recorded clips at 60 Hz, named after their source (``mocapd/data/demo_motion_cmu``)."""
    clips, skeleton = load_demo_motion()
    names = ("02_05 punching", "02_07 swordplay", "02_06 punching", "02_08 swordplay")
    return [(names[i], resample_poses(c, TRUTH_FPS, FPS)) for i, c in enumerate(clips)], skeleton


def _summary(rows: list[dict[str, Any]], label: str) -> dict[str, float]:
    vals = [r[label] for r in rows]
    walked = sum(v["walked_m"] for v in vals)
    return {
        "clips": len(vals),
        "walked_m": round(walked, 1),
        "height_error_p95_cm_worst": max(v["height_error_p95_cm"] for v in vals),
        "height_error_p95_cm_median": float(np.median([v["height_error_p95_cm"] for v in vals])),
        "drift_end_per_walked_pct_worst": max(v["drift_end_per_walked_pct"] for v in vals),
        "drift_end_per_walked_pct_median": float(np.median([v["drift_end_per_walked_pct"] for v in vals])),
        "drift_end_sum_per_walked_pct": round(
            100 * sum(v["horizontal_drift_end_cm"] / 100 for v in vals) / max(walked, 1e-9), 1
        ),
        "path_error_pct_median": float(np.median([v["path_error_pct"] for v in vals])),
        "path_error_pct_worst": max((v["path_error_pct"] for v in vals), key=abs),
        "path_error_abs_pct_median": float(np.median([abs(v["path_error_pct"]) for v in vals])),
    }


def run_synthetic(prior: PcaPrior | None, seed: int, noise: ImuNoise) -> dict[str, Any]:
    clips, skeleton = synthetic_rig_clips()
    rows = [imu_only_case(n, skeleton, th, prior, seed + i, noise) for i, (n, th) in enumerate(clips)]
    return {"clips": rows, "summary": {k: _summary(rows, k) for k in ("contacts", "no_contacts")}}


def run_walking(
    prior: PcaPrior | None, seed: int, noise: ImuNoise, split: str, data_root: Path | None
) -> dict[str, Any]:
    from mocapd.eval.data import load_clip, load_splits

    paths = [p for p in load_splits(data_root)[split] if any(w in p.name for w in ("walk", "run", "dash", "131_"))]
    clips = [load_clip(p, FPS) for p in paths]
    # A clip that never stands flat (a run) takes its feet's flat pitch from the other clips of its data set (the
    # same source skeleton's feet: one folder).
    own = [flat_pitches(c.skeleton, c.theta, FPS) for c in clips]

    def pitch(p: Path, f: int) -> float | None:
        kin = [x for q, o in zip(paths, own, strict=True) if q.parent == p.parent and (x := o[f]) is not None]
        return float(np.median(kin)) if kin else None

    pitches = [
        (mine[0] if mine[0] is not None else pitch(p, 0), mine[1] if mine[1] is not None else pitch(p, 1))
        for p, mine in zip(paths, own, strict=True)
    ]
    rows = []
    for i, (p, c) in enumerate(zip(paths, clips, strict=True)):
        rows.append(imu_only_case(p.stem, c.skeleton, c.theta, prior, seed + 100 + i, noise, pitches[i]))
    rows_walk = [r for r in rows if not any(w in r["clip"] for w in ("run", "dash"))]
    rows_run = [r for r in rows if any(w in r["clip"] for w in ("run", "dash"))]
    return {
        "split": split,
        "clips": rows,
        "summary": {k: _summary(rows, k) for k in ("contacts", "no_contacts")},
        "walking_clips": {k: _summary(rows_walk, k) for k in ("contacts", "no_contacts")} if rows_walk else {},
        "running_clips": {k: _summary(rows_run, k) for k in ("contacts", "no_contacts")} if rows_run else {},
    }


def run_standing(prior: PcaPrior | None, seed: int, noise: ImuNoise, seconds: float = 60.0) -> dict[str, Any]:
    clips, skeleton = synthetic_rig_clips()
    pose = clips[0][1][0]
    truth = np.repeat(pose[None], round(seconds * FPS), axis=0)
    out = imu_only_case("standing still (02_05, first pose)", skeleton, truth, prior, seed + 50, noise)
    return out


def run_cameras_back(prior: PcaPrior | None, seed: int, dark: tuple[float, float] = (2.0, 8.0)) -> dict[str, Any]:
    """The rig's first clip, 4 cameras that see nothing during ``dark`` (seconds)."""
    world = SyntheticWorld(n_cams=4, n_people=1, n_suits=1, seed=seed)
    clips, skeleton = synthetic_rig_clips()
    skeleton, truth = standing_feet(skeleton, clips[0][1], flat_pitches(skeleton, clips[0][1], FPS))
    clip = make_clip(clips[0][0], skeleton, truth, FPS)
    rng = np.random.default_rng(seed + 7)
    imu = imu_only_observations(clip, default_mounts(IMU_SET_13, skeleton), ImuNoise(), rng)
    targets = coco17_targets(skeleton)
    kin = Kinematics(skeleton)
    sites = kin.targets(kin.forward(truth), targets.bones, targets.offsets)
    from mocapd.core.camera import project_points, stack_cameras

    K, dist, R, t = stack_cameras(world.cameras)
    solver = _solver(skeleton, prior, True, world.cameras, targets)
    solver.reset(truth[0])
    roots = []
    views = []
    for f, o in enumerate(imu):
        uv, _, valid = project_points(K, dist, R, t, sites[f], jacobian=False)
        uv = uv + rng.normal(scale=1.0, size=uv.shape)
        conf = np.where(valid, 0.9, 0.0)
        if dark[0] <= f / FPS < dark[1]:
            conf = np.zeros_like(conf)
        res = solver.solve(replace(o, keypoints=uv, confidences=conf))
        roots.append(res.theta[:3])
        views.append(int(np.count_nonzero(conf.any(axis=1))))
    r = np.array(roots)
    jump = np.linalg.norm(np.diff(r, axis=0) - np.diff(truth[:, :3], axis=0), axis=1)
    back = round(dark[1] * FPS)
    err = np.linalg.norm(r - truth[:, :3], axis=1)
    return {
        "clip": clips[0][0],
        "cameras": 4,
        "dark_s": list(dark),
        "root_error_when_cameras_return_cm": round(100 * float(err[back - 1]), 1),
        "largest_jump_beyond_true_motion_cm_per_frame": round(100 * float(jump.max()), 2),
        "largest_jump_while_blending_cm_per_frame": round(100 * float(jump[back - 1 : back + round(2 * FPS)].max()), 2),
        "root_error_1s_after_return_cm": round(100 * float(err[min(back + round(FPS), len(err) - 1)]), 1),
        "root_error_3s_after_return_cm": round(100 * float(err[min(back + round(3 * FPS), len(err) - 1)]), 1),
    }


@dataclass(frozen=True)
class GroundEvalOptions:
    seed: int = 0
    split: str = "evaluation"
    parts: tuple[str, ...] = ("synthetic", "walking", "standing", "cameras_back", "mtw", "mvnx")
    standing_s: float = 60.0
    optical_dir: Path | None = None
    """The optical-truth recording for the ``optical`` part (default ``<data root>/imu/gaittoolbox``)."""


def run(opts: GroundEvalOptions, data_root: Path | None = None) -> dict[str, Any]:
    """Every part of the evaluation (see the module docstring); JSON-able."""
    from mocapd.io.prior import resolve_prior

    load0 = os.getloadavg()
    t0 = time.perf_counter()
    prior = resolve_prior("default")  # the shipped prior; CostOptions() are the shipped config's weights
    noise = ImuNoise()
    setup = {"imus": 13, "cameras": 0, "fps": FPS, "imu_noise": noise.__dict__, "seed": opts.seed,
             "solver": "CostOptions() (= the shipped config.toml), the default prior"}  # fmt: skip
    out: dict[str, Any] = {"setup": setup}
    if "synthetic" in opts.parts:
        out["synthetic"] = run_synthetic(prior, opts.seed, noise)
    if "walking" in opts.parts:
        out["walking"] = run_walking(prior, opts.seed, noise, opts.split, data_root)
    if "standing" in opts.parts:
        out["standing"] = run_standing(prior, opts.seed, noise, opts.standing_s)
    if "cameras_back" in opts.parts:
        out["cameras_back"] = run_cameras_back(prior, opts.seed)
    if "mtw" in opts.parts or "mvnx" in opts.parts:
        from mocapd.eval.ground_real import run_mtw, run_mvnx

        if "mtw" in opts.parts:
            out["mtw"] = run_mtw(prior, data_root)
        if "mvnx" in opts.parts:
            out["mvnx"] = run_mvnx(prior, data_root)
    if "optical" in opts.parts:
        from mocapd.eval.data import default_data_root
        from mocapd.eval.ground_optical import default_dir, run_optical

        root = default_data_root() if data_root is None else Path(data_root)
        out["optical"] = run_optical(prior, opts.optical_dir or default_dir(root))
    out["machine"] = {"cpus": os.cpu_count(), "seconds": round(time.perf_counter() - t0, 1),
                      "loadavg_start": [round(x, 2) for x in load0],
                      "loadavg_end": [round(x, 2) for x in os.getloadavg()]}  # fmt: skip
    return out

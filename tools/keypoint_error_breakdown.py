#!/usr/bin/env python3
"""Where mocapd's keypoint error goes on ``mocapd eval keypoints`` (issue 41): per joint, limb and cause, as JSON.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

Reads a finished ``mocapd eval keypoints --out OUT`` run (its ``keypoints.json`` names the scene: people, seconds,
seed), rebuilds the scene's truth and detections (seeded, so the same), and scores on the benchmark's 14 limb
keypoints, each system matched to the actors frame by frame as :func:`mocapd.eval.keypoint_bench.score` matches:

- **systems**: mocapd's forward pass (``OUT/forward.mcs``) and ``resolve`` (the session's resolved stream),
  Pose2Sim's raw triangulation and its filtered output (``OUT/pose2sim/project/result.npz``), the DLT of the
  truth-associated views, and, as what-ifs, Pose2Sim's own filter (Hampel 7 frames, 2 MADs, then a zero-phase
  Butterworth of order 4 at 6 Hz, its Demo_MultiPerson ``Config.toml``) on mocapd's forward keypoints and on the
  DLT's; ``resolve``'s RTS smoother re-run on the forward pass with other noise settings (``--sweep``, ``--rts``);
- per system: MPJPE per joint and per limb (the mean distance of its two ends, as PCP has it), the error of
  each limb's length, and the RMS error split into a constant part per actor and joint (the mean error vector, in
  the frame of the true bone the keypoint rides on: what a wrong skeleton or keypoint offset gives) and the
  zero-mean scatter about it (what a filter can remove): RMS² = bias² + scatter²;
- for mocapd: each person's sized skeleton against their true one (heights; each limb's median length over the
  frames), and what-ifs: the arms and legs rebuilt with the truth's segment lengths along the system's own
  directions, and the MPJPE with the constant part removed (every joint's, or only the trunk's: neck, mid-hip,
  shoulders, which the sized skeleton's spine, neck and hip offsets place).

Usage (after ``mocapd eval keypoints --people 3 --seconds 6 --seed 0 --out /tmp/kb``)::

    MOCAPD_DATA=/work/shared/data python tools/keypoint_error_breakdown.py /tmp/kb --sweep > breakdown-seed0.json
    python tools/keypoint_error_breakdown.py /tmp/kb1 --rts 0.01,3,0.006,2 > breakdown-seed1.json
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.signal import butter, filtfilt

from mocapd.core.keypoints import BODY25_FORMAT
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import Skeleton
from mocapd.eval.keypoint_bench import (
    FPS,
    LIMBS,
    Noise,
    build_scene,
    detect,
    dlt_baseline,
    match_people,
    visible,
)
from mocapd.io.imu_recordings import T0_NS
from mocapd.io.session import RESOLVED, open_session
from mocapd.protocols.session_format import PoseRecord
from mocapd.service.session.solve import ResolveOptions, session_rig, smooth_frames

FloatArray = NDArray[np.float64]
Sized = list[list[Skeleton | None]]
"""Per actor and frame: mocapd's skeleton of the person matched to the actor."""
NAMES = BODY25_FORMAT.keypoints
IDX = {n: i for i, n in enumerate(NAMES)}
USED = sorted({IDX[k] for pair in LIMBS.values() for k in pair})
"""The 14 keypoints the benchmark scores (BODY_25 indices)."""
BUTTER_ORDER, BUTTER_HZ, HAMPEL_WINDOW, HAMPEL_SIGMAS = 4, 6.0, 7, 2.0
"""Pose2Sim 0.10.49's Demo_MultiPerson filtering: Hampel outlier rejection, then a Butterworth low-pass."""


@dataclass
class Truth:
    """Per actor: the true skeleton, θ (frames, 66) and keypoints (frames, 25, 3)."""

    skeletons: list[Skeleton]
    thetas: list[FloatArray]
    keypoints: list[FloatArray]


def build_truth(n_people: int, seconds: float, data_root: Path | None) -> Truth:
    """The scene of :func:`mocapd.eval.keypoint_bench.build_scene`, with each actor's skeleton and θ kept."""
    scene = build_scene(n_people, seconds, data_root)
    return Truth(scene.skeletons, scene.thetas, scene.keypoints)


def keypoints_of(sk: Skeleton, theta: FloatArray) -> FloatArray:
    """BODY_25 keypoints (..., 25, 3) of ``theta`` (..., 66) on ``sk`` with the format's track targets."""
    kin = Kinematics(sk)
    tg = BODY25_FORMAT.track_targets(sk)
    return np.asarray(kin.targets(kin.forward(theta), tg.bones, tg.offsets))


def assign(truth: list[FloatArray], people: list[list[FloatArray]]) -> list[dict[int, int]]:
    """Per actor, frame -> index of the estimate matched to it (:func:`~mocapd.eval.keypoint_bench.match_people`)."""
    out: list[dict[int, int]] = [{} for _ in truth]
    for f, row in enumerate(people):
        for i, a in match_people(row, [g[f] for g in truth], USED).items():
            out[a][f] = i
    return out


def per_actor(truth: list[FloatArray], people: list[list[FloatArray]]) -> list[FloatArray]:
    """A system's people as per-actor (frames, 25, 3) arrays, NaN where none is matched."""
    n = truth[0].shape[0]
    out = [np.full((n, 25, 3), np.nan) for _ in truth]
    for a, match in enumerate(assign(truth, people)):
        for f, i in match.items():
            out[a][f] = people[f][i]
    return out


def mocapd_people(
    frames: list[PoseRecord], n: int, rig: Skeleton
) -> tuple[list[list[FloatArray]], list[list[Skeleton]]]:
    """Per input frame, each person's keypoints (25, 3) and skeleton, as ``mocapd eval keypoints`` reads them."""
    pts: list[list[FloatArray]] = [[] for _ in range(n)]
    extra: list[list[Skeleton]] = [[] for _ in range(n)]
    for r in frames:
        for p in r.people:
            t = (p.t_pose_ns if p.t_pose_ns is not None else r.t_solve_ns) - T0_NS
            f = round(t * FPS / 1e9)
            if 0 <= f < n:
                sk = p.skeleton if p.skeleton is not None else rig
                pts[f].append(keypoints_of(sk, np.asarray(p.theta)))
                extra[f].append(sk)
    return pts, extra


def skeletons_per_actor(truth: list[FloatArray], pts: list[list[FloatArray]], sks: list[list[Skeleton]]) -> Sized:
    """Per actor and frame, the skeleton of mocapd's person matched to the actor (None where none is)."""
    out: Sized = [[None] * truth[0].shape[0] for _ in truth]
    for a, match in enumerate(assign(truth, pts)):
        for f, i in match.items():
            out[a][f] = sks[f][i]
    return out


def pose2sim_people(out: Path, n: int) -> dict[str, list[list[FloatArray]]]:
    """Pose2Sim's raw and filtered people by frame (``OUT/pose2sim/project/result.npz``)."""
    path = out / "pose2sim" / "project" / "result.npz"
    res: dict[str, list[list[FloatArray]]] = {}
    if not path.is_file():
        return res
    with np.load(path) as z:
        for kind in ("raw", "filt"):
            people = [np.asarray(z[k]) for k in sorted(z.files) if k.startswith(f"{kind}_")]
            rows: list[list[FloatArray]] = [[] for _ in range(n)]
            for pts in people:
                for f in range(min(n, len(pts))):
                    if np.isfinite(pts[f]).any():
                        rows[f].append(np.asarray(pts[f]))
            res[kind] = rows
    return res


def hampel(x: FloatArray) -> FloatArray:
    """Pose2Sim's Hampel filter of one channel: a value more than 2 scaled MADs from its window's median replaced."""
    out, h = x.copy(), HAMPEL_WINDOW // 2
    for i in range(h, len(x) - h):
        w = x[i - h : i + h + 1]
        med = np.median(w)
        mad = np.median(np.abs(w - med))
        if mad != 0 and abs(0.6745 * (x[i] - med) / mad) > HAMPEL_SIGMAS:
            out[i] = med
    return out


def pose2sim_filter(track: FloatArray) -> FloatArray:
    """Pose2Sim's filtering (Hampel, then zero-phase Butterworth) of one actor's (frames, 25, 3) points, per
    channel and per run of finite frames (as Pose2Sim splits at gaps)."""
    b, a = butter(BUTTER_ORDER // 2, BUTTER_HZ / (FPS / 2), "low")
    pad = 3 * max(len(a), len(b))
    out = track.copy()
    ok = np.all(np.isfinite(track[:, USED]), axis=(1, 2))
    edges = np.flatnonzero(np.diff(np.r_[0, ok.astype(int), 0]))
    for s, e in zip(edges[::2], edges[1::2], strict=True):
        if e - s <= pad:
            continue
        seg = track[s:e].reshape(e - s, -1)
        filt = np.column_stack([filtfilt(b, a, hampel(c)) if np.all(np.isfinite(c)) else c for c in seg.T])
        out[s:e] = filt.reshape(e - s, 25, 3)
    return out


def bone_frames(truth: Truth) -> list[FloatArray]:
    """Per actor, (frames, 25, 3, 3): the world rotation of the true bone each keypoint rides on."""
    out = []
    for sk, th in zip(truth.skeletons, truth.thetas, strict=True):
        rot = Kinematics(sk).forward(th).rotations
        out.append(np.asarray(rot[:, BODY25_FORMAT.track_targets(sk).bones]))
    return out


LIMB_CHAINS = (("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"), ("right_shoulder", "right_elbow"),
               ("right_elbow", "right_wrist"), ("left_hip", "left_knee"), ("left_knee", "left_ankle"),
               ("right_hip", "right_knee"), ("right_knee", "right_ankle"))  # fmt: skip
"""The arms and legs from the shoulders and hips down (parents first): :func:`true_lengths` keeps each segment's
direction and gives it the truth's length."""
TRUNK = tuple(IDX[k] for k in ("neck", "mid_hip", "left_shoulder", "right_shoulder"))
"""The keypoints the trunk's proportions place (spine, neck and hip-joint offsets of the sized skeleton)."""


def true_lengths(truth: list[FloatArray], est: list[FloatArray]) -> list[FloatArray]:
    """Each system's points with its arms and legs rebuilt down :data:`LIMB_CHAINS` from its own shoulders and hips,
    its own directions and the truth's segment lengths of the same frame: the error left with the limb lengths
    substituted."""
    out = []
    for g, e in zip(truth, est, strict=True):
        x = e.copy()
        for a, b in LIMB_CHAINS:
            i, j = IDX[a], IDX[b]
            d = e[:, j] - e[:, i]
            unit = d / np.linalg.norm(d, axis=1, keepdims=True)
            x[:, j] = x[:, i] + unit * np.linalg.norm(g[:, j] - g[:, i], axis=1, keepdims=True)
        out.append(x)
    return out


def breakdown(truth: Truth, est: list[FloatArray], vis: NDArray[np.bool_], frames: list[FloatArray]) -> dict[str, Any]:
    """MPJPE per joint and limb, limb-length error and the bias/scatter split of one system's per-actor points."""
    errs: dict[str, list[float]] = {n: [] for n in NAMES}
    bias: dict[str, list[float]] = {n: [] for n in NAMES}
    lens: dict[str, list[float]] = {k: [] for k in LIMBS}
    vecs, unbiased, trunk_unbiased, bias2, scatter2 = [], [], [], [], []
    for a, (g, e) in enumerate(zip(truth.keypoints, est, strict=True)):
        f = np.flatnonzero(vis[:, a] & np.all(np.isfinite(e[:, USED]), axis=(1, 2)))
        d = e[f] - g[f]  # (m, 25, 3) world
        local = np.einsum("fkji,fkj->fki", frames[a][f], d)  # in the true bone's frame
        mean = local.mean(axis=0)  # (25, 3): the constant part per joint
        for k in USED:
            errs[NAMES[k]].extend(np.linalg.norm(d[:, k], axis=1).tolist())
            bias[NAMES[k]].append(float(np.linalg.norm(mean[k])))
            bias2.append(float(mean[k] @ mean[k]))
            scatter2.append(float(np.mean(np.sum((local[:, k] - mean[k]) ** 2, axis=1))))
        vecs.append(d[:, USED])
        unbiased.append((d - np.einsum("fkij,kj->fki", frames[a][f], mean))[:, USED])
        trunk = mean.copy()
        trunk[[k for k in range(len(NAMES)) if k not in TRUNK]] = 0.0
        trunk_unbiased.append((d - np.einsum("fkij,kj->fki", frames[a][f], trunk))[:, USED])
        for name, (i, j) in LIMBS.items():
            length = np.linalg.norm(e[f, IDX[i]] - e[f, IDX[j]], axis=1)
            lens[name].extend((length - np.linalg.norm(g[f, IDX[i]] - g[f, IDX[j]], axis=1)).tolist())
    all_d, all_u = np.concatenate(vecs), np.concatenate(unbiased)
    per_joint = {n: round(1e3 * float(np.mean(v)), 1) for n, v in errs.items() if v}
    return {
        "mpjpe_mm": round(1e3 * float(np.mean(np.linalg.norm(all_d, axis=-1))), 2),
        "mpjpe_bias_removed_mm": round(1e3 * float(np.mean(np.linalg.norm(all_u, axis=-1))), 2),
        "mpjpe_trunk_bias_removed_mm": round(
            1e3 * float(np.mean(np.linalg.norm(np.concatenate(trunk_unbiased), axis=-1))), 2
        ),
        "rms_mm": round(1e3 * float(np.sqrt(np.mean(np.sum(all_d**2, axis=-1)))), 2),
        "bias_rms_mm": round(1e3 * float(np.sqrt(np.mean(bias2))), 2),
        "scatter_rms_mm": round(1e3 * float(np.sqrt(np.mean(scatter2))), 2),
        "per_joint_mm": per_joint,
        "per_joint_bias_mm": {n: round(1e3 * float(np.mean(v)), 1) for n, v in bias.items() if v},
        "per_limb_mm": {name: round(0.5 * (per_joint[i] + per_joint[j]), 1) for name, (i, j) in LIMBS.items()},
        "limb_length_error_mm": {
            k: {"mean": round(1e3 * float(np.mean(v)), 1), "mean_abs": round(1e3 * float(np.mean(np.abs(v))), 1)}
            for k, v in lens.items()
        },
        "person_frames": int(all_d.shape[0]),
    }


def sizing(truth: Truth, est: list[FloatArray], sized: Sized) -> list[dict[str, Any]]:
    """Each actor's sized skeleton against the true one: heights, and each limb's median length over the frames."""
    out = []
    for a, (g, e) in enumerate(zip(truth.keypoints, est, strict=True)):
        used = [s for s in sized[a] if s is not None]
        if not used:
            continue
        ok = np.all(np.isfinite(e[:, USED]), axis=(1, 2))

        def median_length(x: FloatArray, i: str, j: str, ok: NDArray[np.bool_] = ok) -> float:
            return float(np.median(np.linalg.norm(x[ok, IDX[i]] - x[ok, IDX[j]], axis=1)))

        out.append({
            "actor": a + 1, "height_true_m": round(truth.skeletons[a].height, 3),
            "height_sized_m": round(used[-1].height, 3), "skeletons": len({s.offsets.tobytes() for s in used}),
            "limb_length_error_mm": {name: round(1e3 * (median_length(e, i, j) - median_length(g, i, j)), 1)
                                     for name, (i, j) in LIMBS.items()},
        })  # fmt: skip
    return out


def rts_options(spec: str) -> ResolveOptions:
    rot_sigma, rot_accel, root_sigma, root_accel = (float(v) for v in spec.split(","))
    return replace(
        ResolveOptions(), rot_sigma=rot_sigma, rot_accel=rot_accel, root_sigma_m=root_sigma, root_accel=root_accel
    )


def pcp(out: Path, truth: Truth, vis: NDArray[np.bool_], rig: Skeleton) -> dict[str, Any]:
    """The benchmark's own PCP and MPJPE of the forward pass and ``resolve`` (as ``mocapd eval keypoints``)."""
    from mocapd.eval.keypoint_bench import score
    from mocapd.service.keypoint_eval import _estimates

    session, n = open_session(out / "session"), truth.thetas[0].shape[0]
    res = {}
    for name, frames in (("mocapd forward", session.require_poses_file(out / "forward.mcs")),
                         ("mocapd resolve", session.require_poses(RESOLVED))):  # fmt: skip
        r = score(truth.keypoints, _estimates(frames, n, rig), vis, NAMES, LIMBS)
        res[name] = {k: r[k] for k in ("pcp_average", "mpjpe_mm", "misses", "identity_switches", "tracks")}
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="a `mocapd eval keypoints --out` directory")
    ap.add_argument("--data-root", type=Path, default=None)
    ap.add_argument("--sweep", action="store_true", help="grid of RTS noise settings on the forward pass")
    ap.add_argument(
        "--rts",
        action="append",
        default=[],
        help="rot_sigma,rot_accel,root_sigma_m,root_accel: the smoother re-run with these",
    )
    args = ap.parse_args(argv)
    bench = json.loads((args.out / "keypoints.json").read_text())["benchmark"]
    truth = build_truth(bench["people"], bench["seconds"], args.data_root)
    n = truth.thetas[0].shape[0]
    from mocapd.eval.keypoint_bench import build_scene

    scene = build_scene(bench["people"], bench["seconds"], args.data_root)
    det = detect(scene, Noise(**bench["noise"]), bench["seed"])
    vis = visible(det, bench["people"])
    frames_rot = bone_frames(truth)
    session = open_session(args.out / "session")
    rig = session_rig(session).skeleton
    forward = session.require_poses_file(args.out / "forward.mcs")
    systems: dict[str, list[FloatArray]] = {}
    fwd_pts, _ = mocapd_people(forward, n, rig)
    systems["mocapd forward"] = per_actor(truth.keypoints, fwd_pts)
    res_pts, res_extra = mocapd_people(session.require_poses(RESOLVED), n, rig)
    systems["mocapd resolve"] = per_actor(truth.keypoints, res_pts)
    for kind, rows in pose2sim_people(args.out, n).items():
        systems[f"Pose2Sim {'raw triangulation' if kind == 'raw' else 'filtered'}"] = per_actor(truth.keypoints, rows)
    if "Pose2Sim raw triangulation" in systems:  # the check that this tool's filter is Pose2Sim's
        systems["Pose2Sim raw + this tool's copy of its filter"] = [
            pose2sim_filter(t) for t in systems["Pose2Sim raw triangulation"]
        ]
    dlt = per_actor(truth.keypoints, [[p for _, p in row] for row in dlt_baseline(scene, det).frames])
    systems["DLT, truth-associated"] = dlt
    systems["DLT + Pose2Sim's filter"] = [pose2sim_filter(t) for t in dlt]
    systems["mocapd forward + Pose2Sim's filter on its keypoints"] = [
        pose2sim_filter(t) for t in systems["mocapd forward"]
    ]
    res_sized = skeletons_per_actor(truth.keypoints, res_pts, res_extra)
    for name in ("mocapd forward", "mocapd resolve", "Pose2Sim filtered"):
        if name in systems:
            systems[f"{name}, the truth's bone lengths"] = true_lengths(truth.keypoints, systems[name])
    specs = list(args.rts)
    if args.sweep:
        specs += [
            f"{s * 0.01:g},{k * 3.0:g},{s * 0.006:g},{k * 2.0:g}"
            for s in (0.5, 1.0, 2.0, 4.0)
            for k in (0.03, 0.1, 0.3, 1.0, 3.0)
        ]
    for spec in specs:
        pts, _ = mocapd_people(smooth_frames(forward, rig, rts_options(spec)), n, rig)
        systems[f"mocapd forward + RTS {spec}"] = per_actor(truth.keypoints, pts)
    report = {
        "benchmark_scores": pcp(args.out, truth, vis, rig),
        "benchmark": {k: bench[k] for k in ("people", "seconds", "seed", "clips")},
        "pose2sim_filter": {
            "hampel_window": HAMPEL_WINDOW,
            "hampel_sigmas": HAMPEL_SIGMAS,
            "butterworth_order": BUTTER_ORDER,
            "cutoff_hz": BUTTER_HZ,
            "zero_phase": True,
        },
        "sizing": sizing(truth, systems["mocapd resolve"], res_sized),
        "systems": {name: breakdown(truth, est, vis, frames_rot) for name, est in systems.items()},
    }
    json.dump(report, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

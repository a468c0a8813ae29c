"""``mocapd eval keypoints``: a multi-person benchmark of real recorded motion seen through a detector's noise.

No public multi-view, multi-person set with 3D truth can be obtained here, so the benchmark builds one the way
Shelf and Campus are built, from recorded motion with known truth:

- **People**: 2 to 4 people of the development split's recorded clips (:data:`CLIPS`: a CMU walk, a wave, a
  guiding gesture, a bow), each looped forwards then backwards (continuous motion) and placed close together in the
  middle of the volume (:data:`PLACES`), so they pass and occlude each other.
- **Rig** (:func:`shelf_rig`): 5 cameras of 1032×776 pixels (f ≈ 1050 px) at the volume's edges, 2.3–2.8 m high,
  looking at the middle, at 25 fps, like Shelf's.
- **Detector** (:func:`detect`): each person's BODY_25 keypoints projected into each camera with the errors of a
  real detector: Gaussian pixel noise scaled by the person's height in the image (:attr:`Noise.sigma_frac`, wrists
  and ankles twice as much), a few outliers, keypoints of a person hidden behind a nearer person dropped or kept at
  low confidence, a whole view of a person flipped left for right now and then, and false-positive people.
- Written as OpenPose BODY_25 JSON folders (one per camera) and a calibration file, so the benchmark runs through
  ``mocapd import keypoints`` and ``mocapd resolve`` as a user runs them (``mocapd.service.keypoint_eval``).

Scores (:func:`score`), per system, on the Shelf/Campus protocol, on the 14 BODY_25 keypoints of its limbs
(:data:`LIMBS`: head as neck to nose, torso, upper/lower arms, upper/lower legs; mocapd's are the keypoints of its
solved pose on the person's own skeleton, the truth's those of the recorded pose): **PCP** (α = 0.5) per actor and
limb (a limb is correct when the mean distance of its two ends to the truth is at most half its true length; a
frame where the actor is visible, in at least two cameras, and has no track counts as wrong), **MPJPE** over those
14 points, **misses** (frames a visible actor has no track; also those after the actor's first 0.2 s, and the time
to the first published frame), **false-positive tracks** (identities that match no actor in most of their frames)
and **identity switches**. The naive baseline is the confidence-weighted DLT of each actor's detections, associated
by the truth (an oracle association, flips and all).
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from mocapd.core.camera import Camera, look_at, project_points, stack_cameras, triangulate
from mocapd.core.keypoints import BODY25_FORMAT
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import Skeleton
from mocapd.errors import InputError
from mocapd.io.calibration_files import CalibrationSet, CameraCalibration, write_mocapd_toml

FloatArray = NDArray[np.float64]
FPS = 25.0
WIDTH, HEIGHT = 1032, 776
CLIPS = ("131_02.bvh", "dataset-1_bye_happy_001.bvh", "dataset-1_guide_normal_001.bvh", "dataset-1_bow_normal_001.bvh")
"""Development-split clips, one per person: a CMU walk (it crosses the others), a wave (fast forearms), a guiding
gesture and a bow."""
PLACES = ((0.0, 0.0), (0.75, 0.35), (-0.7, 0.45), (0.6, -0.9))
"""Where each person's clip is centred on the floor (x, z, m): within arm's reach of the next, never closer than
:data:`MIN_APART_M` (the walk passes 0.59 m from the bow; at (0.1, -0.9) it walked through it: hips down to 0.10 m
apart, under 0.4 m in 89 of 10 s's 250 frames, two bodies in one place that no detector or tracker tells apart)."""
MIN_APART_M = 0.5
"""Closest two people's hips come, horizontally (m): bodies are about 0.3 m deep, so nearer is one inside another."""
EARLY_S = 0.2
"""A miss in an actor's first this many seconds of visibility is allowed (enrolment needs evidence)."""

LIMBS: dict[str, tuple[str, str]] = {
    "head": ("neck", "nose"),
    "torso": ("mid_hip", "neck"),
    "left_upper_arm": ("left_shoulder", "left_elbow"),
    "right_upper_arm": ("right_shoulder", "right_elbow"),
    "left_lower_arm": ("left_elbow", "left_wrist"),
    "right_lower_arm": ("right_elbow", "right_wrist"),
    "left_upper_leg": ("left_hip", "left_knee"),
    "right_upper_leg": ("right_hip", "right_knee"),
    "left_lower_leg": ("left_knee", "left_ankle"),
    "right_lower_leg": ("right_knee", "right_ankle"),
}
"""The Shelf/Campus limbs as BODY_25 keypoints (the head: neck to nose)."""
LIMB_GROUPS = {"head": ("head",), "torso": ("torso",), "upper_arms": ("left_upper_arm", "right_upper_arm"),
               "lower_arms": ("left_lower_arm", "right_lower_arm"), "upper_legs": ("left_upper_leg", "right_upper_leg"),
               "lower_legs": ("left_lower_leg", "right_lower_leg")}  # fmt: skip
MATCH_M = 0.5
"""An estimate is an actor's on a frame when its mean joint distance is below this (Hungarian assignment)."""


@dataclass(frozen=True)
class Noise:
    """The simulated detector's errors."""

    sigma_frac: float = 0.012
    """Pixel noise per keypoint (standard deviation) as a fraction of the person's height in the image."""
    extremity_factor: float = 2.0
    """Wrists and ankles: this many times the noise (they move fastest and blur)."""
    outlier_p: float = 0.02
    """Chance a keypoint is off by 5-15 % of the person's height."""
    occluded_drop_p: float = 0.5
    """A keypoint hidden behind a nearer person: dropped with this chance, else kept at low confidence."""
    flip_p: float = 0.03
    """Chance per view, person and frame that the detector swaps left and right."""
    false_positive_p: float = 0.03
    """Chance per view and frame of a false-positive person."""


@dataclass
class Scene:
    """A benchmark scene: cameras, per-person truth (frames, 21, 3) joints and (frames, 25, 3) keypoints, and each
    person's skeleton and θ (frames, 66) they come from."""

    cameras: list[Camera]
    joints: list[FloatArray]
    keypoints: list[FloatArray]
    clips: list[str]
    skeletons: list[Skeleton]
    thetas: list[FloatArray]

    @property
    def n_frames(self) -> int:
        return int(self.joints[0].shape[0])


@dataclass
class Detected:
    """The simulated detector's output: per frame and camera, people (n, 25, 2), confidences (n, 25), and the
    true person of each (-1: a false positive)."""

    keypoints: list[list[FloatArray]]
    confidences: list[list[FloatArray]]
    labels: list[list[NDArray[np.intp]]]
    flips: int = 0
    occluded: int = 0
    false_positives: int = 0


def shelf_rig() -> list[Camera]:
    """5 cameras of 1032×776 px at the edges of a 5 m × 5 m volume, unevenly spaced (two on one side) as Shelf's."""
    placed = ((0.0, 4.2, 2.6), (60.0, 3.8, 2.3), (130.0, 4.4, 2.8), (215.0, 4.0, 2.5), (290.0, 3.6, 2.4))
    cams = []
    for i, (deg, r, h) in enumerate(placed):
        a = np.deg2rad(deg)
        cams.append(look_at(f"cam{i + 1}", np.array([r * np.sin(a), h, r * np.cos(a)]), np.array([0.0, 0.9, 0.0]),
                            WIDTH, HEIGHT, 1050.0))  # fmt: skip
    return cams


def _ping_pong(theta: FloatArray, n: int) -> FloatArray:
    """The clip forwards then backwards, repeated to ``n`` frames (continuous: no jump at a turn)."""
    loop = np.concatenate([theta, theta[-2:0:-1]]) if len(theta) > 2 else theta
    return np.asarray(loop[np.arange(n) % len(loop)])


def build_scene(n_people: int = 3, seconds: float = 10.0, data_root: Path | None = None) -> Scene:
    """``n_people`` (2-4) of :data:`CLIPS` placed at :data:`PLACES` in :func:`shelf_rig`, ``seconds`` at 25 fps."""
    from mocapd.eval.data import load_clip, load_splits

    if not 2 <= n_people <= len(CLIPS):
        raise InputError(f"--people {n_people}: allowed 2 to {len(CLIPS)}")
    if not 1.0 <= seconds <= 120.0:
        raise InputError(f"--seconds {seconds}: allowed 1 to 120")
    files = {p.name: p for p in load_splits(data_root)["development"]}
    n = round(seconds * FPS)
    joints, keypoints, skeletons, thetas = [], [], [], []
    targets_of = BODY25_FORMAT
    for i in range(n_people):
        clip = load_clip(files[CLIPS[i]], fps=FPS)
        theta = _ping_pong(clip.theta, n).copy()
        theta[:, [0, 2]] += np.asarray(PLACES[i]) - clip.theta[:, [0, 2]].mean(axis=0)
        sk: Skeleton = clip.skeleton
        kin = Kinematics(sk)
        state = kin.forward(theta)
        tg = targets_of.track_targets(sk)
        joints.append(np.asarray(state.positions))
        keypoints.append(np.asarray(kin.targets(state, tg.bones, tg.offsets)))
        skeletons.append(sk)
        thetas.append(theta)
    return Scene(shelf_rig(), joints, keypoints, list(CLIPS[:n_people]), skeletons, thetas)


_SWAP = [BODY25_FORMAT.keypoints.index(k.replace("left_", "@").replace("right_", "left_").replace("@", "right_"))
         for k in BODY25_FORMAT.keypoints]  # fmt: skip
_EXTREMITIES = [BODY25_FORMAT.keypoints.index(k) for k in ("left_wrist", "right_wrist", "left_ankle", "right_ankle")]


def detect(scene: Scene, noise: Noise, seed: int = 0) -> Detected:
    """Every person's keypoints through every camera with ``noise``'s errors (see the module docstring)."""
    rng = np.random.default_rng(seed)
    K, dist, R, t = stack_cameras(scene.cameras)
    n_kp = len(BODY25_FORMAT.keypoints)
    out = Detected([], [], [])
    for f in range(scene.n_frames):
        kf, cf, lf = [], [], []
        for c in range(len(scene.cameras)):
            uvs, depths, inside = [], [], []
            for X in scene.keypoints:
                uv, _, valid = project_points(K[c : c + 1], dist[c : c + 1], R[c : c + 1], t[c : c + 1], X[f],
                                              jacobian=False)  # fmt: skip
                uvs.append(uv[0])
                depths.append(float((R[c] @ X[f].mean(axis=0) + t[c])[2]))
                ok = valid[0] & (uv[0, :, 0] >= 0) & (uv[0, :, 0] < WIDTH) & (uv[0, :, 1] >= 0) & (uv[0, :, 1] < HEIGHT)
                inside.append(ok)
            people, confs, labels = [], [], []
            for p, uv in enumerate(uvs):
                if inside[p].sum() < 5:
                    continue
                size = float(np.ptp(uv[:, 1]))
                sigma = np.full(n_kp, noise.sigma_frac * size)
                sigma[_EXTREMITIES] *= noise.extremity_factor
                kp = uv + rng.normal(size=uv.shape) * sigma[:, None]
                outlier = rng.uniform(size=n_kp) < noise.outlier_p
                kp[outlier] += rng.uniform(0.05, 0.15, (int(outlier.sum()), 1)) * size * _unit(rng, int(outlier.sum()))
                conf = rng.uniform(0.6, 0.95, n_kp)
                hidden = _hidden(uv, p, uvs, depths, inside)
                out.occluded += int(hidden.sum())
                drop = hidden & (rng.uniform(size=n_kp) < noise.occluded_drop_p)
                weak = hidden & ~drop
                kp[weak] += rng.normal(size=(int(weak.sum()), 2)) * 3.0 * sigma[weak, None]
                conf[weak] = rng.uniform(0.1, 0.35, int(weak.sum()))
                conf[drop | ~inside[p]] = 0.0
                if rng.uniform() < noise.flip_p:
                    kp, conf = kp[_SWAP], conf[_SWAP]
                    out.flips += 1
                people.append(kp)
                confs.append(conf)
                labels.append(p)
            if people and rng.uniform() < noise.false_positive_p:  # a person-shaped detection where nobody is
                src = people[int(rng.integers(len(people)))]
                shift = rng.uniform([0.1 * WIDTH, 0.1 * HEIGHT], [0.9 * WIDTH, 0.9 * HEIGHT]) - np.nanmean(src, axis=0)
                people.append(src * rng.uniform(0.6, 1.0) + shift)
                confs.append(rng.uniform(0.2, 0.6, n_kp))
                labels.append(-1)
                out.false_positives += 1
            order = rng.permutation(len(people))
            kf.append(np.array([people[i] for i in order]).reshape(-1, n_kp, 2))
            cf.append(np.array([confs[i] for i in order]).reshape(-1, n_kp))
            lf.append(np.array([labels[i] for i in order], dtype=np.intp))
        out.keypoints.append(kf)
        out.confidences.append(cf)
        out.labels.append(lf)
    return out


def _unit(rng: np.random.Generator, n: int) -> FloatArray:
    a = rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([np.cos(a), np.sin(a)])


def _hidden(uv: FloatArray, p: int, uvs: list[FloatArray], depths: list[float], inside: list[Any]) -> NDArray[np.bool_]:
    """Keypoints of person ``p`` inside the (slightly shrunk) image box of a person nearer the camera."""
    hidden = np.zeros(uv.shape[0], dtype=bool)
    for q, other in enumerate(uvs):
        if q == p or depths[q] >= depths[p] or inside[q].sum() < 5:
            continue
        lo, hi = other[inside[q]].min(axis=0), other[inside[q]].max(axis=0)
        pad = 0.15 * (hi - lo)
        hidden |= np.all((uv >= lo + pad) & (uv <= hi - pad), axis=1)
    return hidden


def visible(det: Detected, n_people: int) -> NDArray[np.bool_]:
    """(frames, people): seen by at least two cameras."""
    return np.array([[sum(int(np.any(lb == p)) for lb in frame) >= 2 for p in range(n_people)]
                     for frame in det.labels])  # fmt: skip


# ---------------------------------------------------------------------------------------------- files
def write_openpose(det: Detected, cameras: list[Camera], folder: Path) -> list[Path]:
    """One OpenPose ``--write_json`` folder per camera (``<camera>_json/<camera>_<frame>_keypoints.json``)."""
    out = []
    for c, cam in enumerate(cameras):
        d = folder / f"{cam.name}_json"
        d.mkdir(parents=True, exist_ok=True)
        for f in range(len(det.keypoints)):
            people = [{"person_id": [-1],
                       "pose_keypoints_2d": np.column_stack([kp, cf]).ravel().round(2).tolist()}
                      for kp, cf in zip(det.keypoints[f][c], det.confidences[f][c], strict=True)]  # fmt: skip
            (d / f"{cam.name}_{f:012d}_keypoints.json").write_text(json.dumps({"version": 1.3, "people": people}))
        out.append(d)
    return out


def write_calibration(cameras: list[Camera], path: Path) -> None:
    calib = CalibrationSet(tuple(CameraCalibration(c.name, (c.width, c.height), c.K, c.dist, c.R, c.t)
                                 for c in cameras), source="mocapd eval keypoints")  # fmt: skip
    write_mocapd_toml(calib, path)


# ---------------------------------------------------------------------------------------------- scoring
@dataclass
class Estimates:
    """A system's output: per frame, (identity, points (n_points, 3)) of each person it gives."""

    frames: list[list[tuple[str, FloatArray]]]


def dlt_baseline(scene: Scene, det: Detected, min_confidence: float = 0.3) -> Estimates:
    """Per frame and actor, the confidence-weighted DLT of the actor's detections (associated by the truth)."""
    frames: list[list[tuple[str, FloatArray]]] = []
    n_kp = len(BODY25_FORMAT.keypoints)
    for f in range(scene.n_frames):
        row = []
        for p in range(len(scene.keypoints)):
            uv = np.full((len(scene.cameras), n_kp, 2), np.nan)
            w = np.zeros((len(scene.cameras), n_kp))
            for c, lb in enumerate(det.labels[f]):
                hit = np.flatnonzero(lb == p)
                if hit.size:
                    uv[c], w[c] = det.keypoints[f][c][hit[0]], det.confidences[f][c][hit[0]]
            w[w < min_confidence] = 0.0
            X, ok = triangulate(scene.cameras, uv, w)
            if np.any(ok):
                row.append((f"dlt{p}", np.where(ok[:, None], X, np.nan)))
        frames.append(row)
    return Estimates(frames)


def match_people(points: list[FloatArray], truth: list[FloatArray], used: list[int]) -> dict[int, int]:
    """One frame's estimates matched to the actors: estimate index -> actor, by the Hungarian method on the mean
    distance of the ``used`` points ``points[i]`` (n_points, 3) and ``truth[a]`` (n_points, 3), under MATCH_M."""
    cost = np.full((len(points), len(truth)), 1e6)
    for i, pts in enumerate(points):
        for a, g in enumerate(truth):
            d = np.linalg.norm(pts[used] - g[used], axis=1)
            if np.any(np.isfinite(d)):
                cost[i, a] = float(np.nanmean(d))
    rows, cols = linear_sum_assignment(cost) if points else ([], [])
    return {int(i): int(a) for i, a in zip(rows, cols, strict=True) if cost[i, a] < MATCH_M}


def score(truth: list[FloatArray], est: Estimates, vis: NDArray[np.bool_], names: tuple[str, ...],
          limbs: dict[str, tuple[str, str]]) -> dict[str, Any]:  # fmt: skip
    """PCP, MPJPE, misses, false-positive tracks and identity switches of ``est`` against ``truth`` (per actor
    (frames, n_points, 3), points named ``names``); ``limbs`` name each limb's two points."""
    idx = {n: i for i, n in enumerate(names)}
    ends = np.array([[idx[a], idx[b]] for a, b in limbs.values()])
    used = sorted(set(ends.ravel().tolist()))
    n_actors, n_frames = len(truth), vis.shape[0]
    matched: dict[tuple[int, int], tuple[str, FloatArray]] = {}  # (frame, actor) -> estimate
    follows: dict[str, list[tuple[int, int | None]]] = {}
    for f in range(n_frames):
        people = est.frames[f] if f < len(est.frames) else []
        taken = match_people([pts for _, pts in people], [t[f] for t in truth], used)
        for i, a in taken.items():
            matched[(f, a)] = people[i]
        for i, (ident, _) in enumerate(people):
            follows.setdefault(ident, []).append((f, taken.get(i)))
    fp_tracks = [ident for ident, seq in follows.items() if sum(a is not None for _, a in seq) < 0.5 * len(seq)]
    actors: list[dict[str, Any]] = []
    for a in range(n_actors):
        frames = np.flatnonzero(vis[:, a])
        first = int(frames[0]) if frames.size else 0
        correct = {name: [] for name in limbs}  # type: dict[str, list[bool]]
        errors, idents = [], []
        misses = late_misses = 0
        first_pub = None
        for f in frames.tolist():
            g = truth[a][f]
            m = matched.get((f, a))
            if m is None:
                misses += 1
                late_misses += int((f - first) / FPS >= EARLY_S)
                for name in limbs:
                    correct[name].append(False)
                continue
            first_pub = f if first_pub is None else first_pub
            idents.append(m[0])
            e = m[1]
            for name, (i, j) in zip(limbs, ends, strict=True):
                length = np.linalg.norm(g[i] - g[j])
                d = 0.5 * (np.linalg.norm(e[i] - g[i]) + np.linalg.norm(e[j] - g[j]))
                correct[name].append(bool(d <= 0.5 * length))
            errors.append(float(np.nanmean(np.linalg.norm(e[used] - g[used], axis=1))))
        pcp = {n: 100.0 * float(np.mean(v)) if v else 0.0 for n, v in correct.items()}
        groups = {g: round(float(np.mean([pcp[n] for n in ns])), 2) for g, ns in LIMB_GROUPS.items()}
        actors.append({
            "actor": a + 1, "visible_frames": int(frames.size),
            "pcp": round(float(np.mean(list(pcp.values()))), 2), "pcp_limbs": groups,
            "mpjpe_mm": round(1e3 * float(np.mean(errors)), 1) if errors else None,
            "misses": misses, "misses_after_first_0.2s": late_misses,
            "first_published_s": round((first_pub - first) / FPS, 3) if first_pub is not None else None,
            "identity_switches": sum(1 for x, y in pairwise(idents) if x != y),
        })  # fmt: skip
    all_err = [x["mpjpe_mm"] for x in actors if x["mpjpe_mm"] is not None]
    owners = Counter(Counter(a for _, a in seq if a is not None).most_common(1)[0][0]
                     for ident, seq in follows.items() if ident not in fp_tracks)  # fmt: skip
    return {
        "pcp_average": round(float(np.mean([x["pcp"] for x in actors])), 2),
        "mpjpe_mm": round(float(np.mean(all_err)), 1) if all_err else None,
        "misses": sum(x["misses"] for x in actors),
        "misses_after_first_0.2s": sum(x["misses_after_first_0.2s"] for x in actors),
        "identity_switches": sum(x["identity_switches"] for x in actors),
        "tracks": len(follows),
        "false_positive_tracks": len(fp_tracks),
        "actors_with_several_tracks": sum(1 for n in owners.values() if n > 1),
        "actors": actors,
    }

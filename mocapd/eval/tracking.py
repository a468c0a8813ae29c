"""``mocapd eval tracking`` and ``mocapd bench sorting``: multi-person tracking on synthetic scenes.

Scenes: people moving through a camera ring, passing close to each other (the seed's failure case), plus
bystanders walking along the edge outside the capture volume. Motion is real by default: recorded clips of the
accuracy harness's evaluation split (CMU, Bandai), retargeted with their own skeletons; the clip gives every joint
rotation and the root height, the scene gives the path on the floor (x, z). ``synthetic`` uses the generator of
``mocapd.core.synthetic`` instead. Detections are projected keypoints with pixel
noise, missed keypoints and random order per camera; suits give measured bone orientations (2° noise, a
heading misalignment per suit). Each scene runs with suits and without.

Metrics per scene and mode:

- ``identity_switches``: times an output identity changes the true person it follows;
- ``correct_fraction``: person-frames (true subject visible in ≥ 2 views) covered by that subject's main identity
  with detections of that subject only;
- ``bystanders_enrolled``: output identities that mainly follow a bystander;
- ``ghost_tracks``: output identities that never follow one person, subject or bystander (the
  detections always come from people here, so these are identities made only of frames mixing people);
- ``first_published_s``: per subject, the time from its first frame in ≥ 2 views to the first frame its main
  identity follows it (the enrolment delay: the evidence rule of ``[tracking.enrolment]`` with 0.1 s, one tracker
  update per frame as here);
- ``joint_error_mm``: per subject, the solver's mean joint error on its sorted detections (+ its suit's IMUs).
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.imu import ImuMount
from mocapd.core.keypoints import coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.observations import Observations
from mocapd.core.people import PeopleTracker
from mocapd.core.skeleton import Skeleton
from mocapd.core.solver import PoseSolver
from mocapd.core.sorting import Detections2D, DetectionSorter
from mocapd.core.suit_binding import LIMBS, SuitBinder
from mocapd.core.synthetic import ring_rig, scene_detections, suit_orientations, walking_path, waypoint_path
from mocapd.core.tracking import SubjectTracker, TrackingOptions
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
FPS = 30.0


Waypoints = list[tuple[float, float, float]]  # (time fraction, x, z)


@dataclass(frozen=True)
class Scene:
    name: str
    n_cams: int
    subjects: list[Waypoints]
    bystanders: list[Waypoints]


def _line(a: tuple[float, float], b: tuple[float, float]) -> Waypoints:
    return [(0.0, *a), (1.0, *b)]


SCENES = (
    Scene("two_passing_close", 4, [_line((-1.6, 0.15), (1.6, 0.15)), _line((1.6, -0.15), (-1.6, -0.15))],
          [_line((3.0, -2.5), (3.0, 2.5))]),
    # The seed's failure case: two people meet, stand 20 cm apart for two seconds, and leave to new sides.
    Scene("close_interaction", 4,
          [[(0.0, -1.6, 0.0), (0.35, -0.1, 0.0), (0.6, -0.1, 0.05), (1.0, 0.6, 1.7)],
           [(0.0, 1.6, 0.0), (0.35, 0.1, 0.0), (0.6, 0.1, -0.05), (1.0, -0.6, 1.7)]],
          [_line((3.0, -2.5), (3.0, 2.5))]),
    Scene("three_crossing", 6,
          [_line((-1.6, 0.2), (1.6, 0.2)), _line((1.6, -0.2), (-1.6, -0.2)), _line((0.8, 1.6), (0.8, -1.6))],
          [_line((-3.0, 2.5), (-3.0, -2.5))]),
    Scene("four_and_two_bystanders", 8,
          [_line((-1.5, -0.5), (1.5, -0.2)), _line((1.5, 0.3), (-1.5, 0.0)), _line((-0.5, 1.5), (-0.3, -1.5)),
           _line((0.6, -1.5), (0.4, 1.5))],
          [_line((3.0, -2.5), (3.0, 2.5)), _line((-2.5, -3.0), (2.5, -3.0))]),
)  # fmt: skip


def _drop_keypoints(dets: list[list[Detections2D]], rng: np.random.Generator, p: float) -> None:
    for frame in dets:
        for d in frame:
            d.confidences[rng.uniform(size=d.confidences.shape) < p] = 0.0


# Evaluation-split clips of at least 8 s (CMU subjects 02 and 131, Bandai walks), one per person of a scene.
REAL_CLIPS = (
    "02_10.amc", "131_03.bvh", "dataset-1_walk_old_001.bvh", "dataset-1_walk-back_old_001.bvh", "02_09.amc",
    "dataset-1_walk_tired_001.bvh", "dataset-1_walk-back_angry_001.bvh",
)  # fmt: skip


def _real_people(paths: list[Waypoints], n: int) -> tuple[list[Skeleton], list[FloatArray]]:
    from mocapd.eval.data import load_clip, load_splits

    files = {p.name: p for p in load_splits()["evaluation"]}
    skeletons, people = [], []
    for i, w in enumerate(paths):
        clip = load_clip(files[REAL_CLIPS[i % len(REAL_CLIPS)]])
        step = round(clip.fps / FPS)
        theta = clip.theta[::step][:n].copy()
        if theta.shape[0] < n:
            raise InputError(f"clip {clip.name} is shorter than {n / FPS:.1f} s at {FPS:.0f} Hz")
        wp = np.asarray(w, dtype=np.float64)
        s = np.linspace(0.0, 1.0, n)
        theta[:, 0] = np.interp(s, wp[:, 0], wp[:, 1])
        theta[:, 2] = np.interp(s, wp[:, 0], wp[:, 2])
        skeletons.append(clip.skeleton)
        people.append(theta)
    return skeletons, people


def run_scene(
    scene: Scene, with_suits: bool, seconds: float = 8.0, seed: int = 0, motion: str = "real"
) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    n = int(seconds * FPS)
    cams = ring_rig(scene.n_cams, radius=4.5)
    paths = scene.subjects + scene.bystanders
    if motion == "real":
        skeletons, people = _real_people(paths, n)
    else:
        sk0 = Skeleton.from_height(1.75)
        skeletons = [sk0] * len(paths)
        people = [waypoint_path(sk0, n, w, seed=seed + 10 + i, fps=FPS) for i, w in enumerate(paths)]
    n_subj = len(scene.subjects)
    targets = [coco17_targets(sk) for sk in skeletons]
    dets, labels = scene_detections(cams, targets, skeletons, people, rng, noise_px=2.0)
    _drop_keypoints(dets, rng, 0.05)
    tracker = PeopleTracker(
        SubjectTracker(DetectionSorter(cams), TrackingOptions(max_subjects=n_subj, enrol_after_s=0.1,
                                                              volume_min=(-2.2, -2.2), volume_max=(2.2, 2.2))),
        SuitBinder(skeletons[0]) if with_suits else None,
    )  # fmt: skip
    yaw = rng.uniform(-90, 90, size=n_subj)
    follows: dict[str, list[tuple[int, int]]] = {}  # identity -> (frame, true person)
    mixed = 0
    published: set[str] = set()
    frames_out = []
    sort_ms = []
    for f in range(n):
        suits = (
            {f"S{p}": suit_orientations(skeletons[p], people[p][f], yaw[p], rng) for p in range(n_subj)}
            if with_suits
            else None
        )
        t0 = time.perf_counter()
        out = tracker.update(int(f * 1e9 / FPS), dets[f], suits)
        sort_ms.append(1e3 * (time.perf_counter() - t0))
        frames_out.append(out)
        published.update(person.identity for person in out.people)
        for person in out.people:
            truth = {int(labels[f][cam][i]) for cam, i in person.detections.items()}
            if len(truth) != 1:
                mixed += 1
                continue
            follows.setdefault(person.identity, []).append((f, truth.pop()))
    main = {ident: Counter(p for _, p in seq).most_common(1)[0][0] for ident, seq in follows.items()}
    switches = sum(sum(1 for (_, a), (_, b) in pairwise(seq) if a != b) for seq in follows.values())
    owner = {}  # true subject -> its main identity (the identity that follows it longest)
    for p in range(n_subj):
        counts = Counter(ident for ident, seq in follows.items() for _, q in seq if q == p)
        owner[p] = counts.most_common(1)[0][0] if counts else None
    visible = correct = 0
    first_seen: dict[int, int] = {}
    first_followed: dict[int, int] = {}
    for f in range(n):
        for p in range(n_subj):
            if sum(int(np.any(lb == p)) for lb in labels[f]) < 2:
                continue
            visible += 1
            first_seen.setdefault(p, f)
            hit = any((f, p) in follows.get(ident, []) and ident == owner[p] for ident in follows)
            correct += hit
            if hit:
                first_followed.setdefault(p, f)
    errors = _solve_errors(skeletons, cams, targets, people, dets, frames_out, owner, with_suits, rng)
    return {
        "scene": scene.name, "motion": motion, "cameras": scene.n_cams, "subjects": n_subj,
        "bystanders": len(scene.bystanders),
        "suits": with_suits, "frames": n,
        "identity_switches": switches,
        "correct_fraction": round(correct / max(visible, 1), 4),
        "bystanders_enrolled": sum(1 for ident, p in main.items() if p >= n_subj),
        "ghost_tracks": len(published - set(main)),
        "first_published_s": {f"subject_{p}": round((first_followed[p] - first_seen[p]) / FPS, 3)
                              if p in first_followed else None for p in range(n_subj)},
        "mixed_assignments": mixed,
        "joint_error_mm": errors,
        "tracking_ms_median": round(float(np.median(sort_ms)), 3),
    }  # fmt: skip


def _solve_errors(
    skeletons: list[Skeleton],
    cams: list[Any],
    targets: list[Any],
    people: list[FloatArray],
    dets: list[list[Detections2D]],
    frames_out: list[Any],
    owner: dict[int, str | None],
    with_suits: bool,
    rng: np.random.Generator,
) -> dict[str, float | None]:
    """Per subject: solve its main identity's sorted detections (and suit IMUs) every frame; mean joint error."""
    imus = tuple(ImuMount(b) for b, _, _, _ in LIMBS) if with_suits else ()
    out: dict[str, float | None] = {}
    for p, ident in owner.items():
        if ident is None:
            out[f"subject_{p}"] = None
            continue
        sk = skeletons[p]
        kin = Kinematics(sk)
        solver = PoseSolver(sk, cams, targets[p], imus)
        errs = []
        started = False
        for f, frame in enumerate(frames_out):
            person = next((x for x in frame.people if x.identity == ident), None)
            if person is None:
                continue
            uv = np.zeros((len(cams), len(targets[p]), 2))
            conf = np.zeros((len(cams), len(targets[p])))
            for cam, i in person.detections.items():
                uv[cam] = dets[f][cam].keypoints[i]
                conf[cam] = dets[f][cam].confidences[i]
            q = None
            if with_suits and person.suit is not None:
                wearer = int(person.suit[1:])
                meas = suit_orientations(skeletons[wearer], people[wearer][f], 0.0, rng)
                q = np.stack([meas[m.bone] for m in imus])
            if not started:  # start from the rest pose at the triangulated position
                theta0 = sk.rest_pose()
                theta0[[0, 2]] = np.nanmean(person.keypoints[[11, 12]], axis=0)[[0, 2]]
                solver.reset(theta0)
                started = True
            res = solver.solve(Observations(keypoints=uv, confidences=conf, imu_orientations=q, dt=1 / FPS))
            e = np.linalg.norm(kin.forward(res.theta).positions - kin.forward(people[p][f]).positions, axis=1)
            errs.append(float(e.mean()))
        # The first second converges from the rest pose; report the steady state.
        out[f"subject_{p}"] = round(1e3 * float(np.mean(errs[int(FPS) :])), 1) if len(errs) > FPS else None
    return out


def evaluate(
    seconds: float = 8.0,
    seed: int = 0,
    motion: str = "real",
    scenes: list[str] | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Every scene (or those named in ``scenes``), with and without suits; ``progress`` is called with 1 after each
    run (``2 * len(scenes)``)."""
    known = [s.name for s in SCENES]
    unknown = sorted(set(scenes or []) - set(known))
    if unknown:
        raise InputError(f"unknown tracking scene(s) {unknown}; the scenes are {known}")
    chosen = [s for s in SCENES if scenes is None or s.name in scenes]
    results = []
    for s in chosen:
        for suits in (True, False):
            results.append(run_scene(s, suits, seconds, seed, motion))
            if progress is not None:
                progress(1)
    return {"scenes": results}


def bench_sorting(frames: int = 60, seed: int = 0) -> dict[str, Any]:
    """Median time of detection sorting (candidates + assignment) per frame: 4 cameras × 3 people, 8 × 10."""
    sk = Skeleton.from_height(1.75)
    out: dict[str, Any] = {}
    for n_cams, n_people in ((4, 3), (8, 10)):
        cams = ring_rig(n_cams, radius=5.0)
        rng = np.random.default_rng(seed)
        people = []
        for p in range(n_people):
            a, r = 2 * np.pi * p / n_people, 0.5 + 1.5 * (p % 2)
            start = (r * np.cos(a), r * np.sin(a))
            people.append(walking_path(sk, frames, start, (start[0] + 0.3, start[1]), seed=p, fps=FPS))
        dets, _ = scene_detections(cams, coco17_targets(sk), sk, people, rng, 2.0)
        sorter = DetectionSorter(cams)
        sorter.assign(sorter.candidates(dets[0]), [None] * n_people)  # compile / load the kernel
        times = []
        found = []
        for f in range(frames):
            t0 = time.perf_counter()
            cands = sorter.candidates(dets[f])
            sorter.assign(cands, [None] * n_people)
            times.append(1e3 * (time.perf_counter() - t0))
            found.append(len(cands))
        out[f"{n_cams}cam_{n_people}people"] = {"median_ms": round(float(np.median(times)), 3),
                                                 "p90_ms": round(float(np.percentile(times, 90)), 3),
                                                 "frames": frames,
                                                 "candidates_median": float(np.median(found))}  # fmt: skip
    return out

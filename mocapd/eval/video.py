"""``mocapd eval video``: accuracy on real multi-view footage, mocapd beside Pose2Sim on the same detections.

For each take (the Pose2Sim demos: :func:`~mocapd.eval.video_input.pose2sim_take`): mocapd's detector runs once on
every frame and camera (cached, :mod:`mocapd.eval.video_input`); then every system reconstructs the take from those
detections five times: with all cameras, and with each camera held out. Systems (:data:`SYSTEMS`):

* ``mocapd live``: the daemon's per-frame solve (:func:`mocapd.service.video_systems.run_live`);
* ``mocapd resolve``: ``mocapd resolve`` of the session the live run recorded (offline, smoothed);
* ``naive DLT``: confidence-weighted DLT of the keypoints the live tracker assigned, nothing rejected;
* ``Pose2Sim`` and ``Pose2Sim filtered``: Pose2Sim's own person association and triangulation, then its
  filtering (:mod:`mocapd.eval.pose2sim_system`).

Metrics (:mod:`mocapd.eval.heldout`, :mod:`mocapd.eval.video_metrics`): held-out-view error (each held-out run
projected into its held-out camera; median and p90 px per joint group and per camera, over each system's own
comparisons and over the comparisons every system has: the *common* set, which the targets use), joint jitter and
bone-length variation of the all-camera run, people (identities, frames, identity switches, bystanders) and
left/right flips accepted per camera. This module turns the systems' reconstructions into those numbers; the
systems are run by :mod:`mocapd.service.video_eval` (they are the daemon's own parts), which also writes
``results.json``, ``report.md`` and the pictures (:mod:`mocapd.eval.video_report`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.skeleton import Skeleton
from mocapd.eval.heldout import COCO17_COMPARED, COCO17_GROUPS, held_out_errors, summarize
from mocapd.eval.video_input import Take, TakeDetections
from mocapd.eval.video_metrics import (
    accepted_flips,
    bone_cv,
    identity_switches,
    jitter,
    matched_detections,
    track_2d,
)

FloatArray = NDArray[np.float64]

LIVE, RESOLVE, DLT, P2S, P2S_FILT = "mocapd live", "mocapd resolve", "naive DLT", "Pose2Sim", "Pose2Sim filtered"
SYSTEMS = (LIVE, RESOLVE, DLT, P2S, P2S_FILT)
MOCAPD = (LIVE, RESOLVE)
FILTERED = {LIVE: RESOLVE, DLT: DLT, P2S: P2S_FILT}
"""Each system's own filtered output (the DLT has none)."""

ALL = "all"
AREA = ((-2.5, -2.5), (2.5, 2.5))
"""The demos' performance area (floor x, z in metres, the shipped capture volume): a person whose median position
lies outside it is a bystander (the Pose2Sim demos' bystanders stand 4.5 m from the centre)."""

HELD_OUT_TARGET = 0.8
"""Target: mocapd's held-out median at most this fraction of Pose2Sim's (the better of its two outputs)."""


@dataclass
class TakeRun:
    """Every system's people per variant (``all`` or ``no_<camera>``): identity -> (n_frames, 17, 3)."""

    take: Take
    detections: TakeDetections
    people: dict[str, dict[str, dict[str, FloatArray]]] = field(default_factory=dict)
    skeletons: dict[str, Skeleton] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)


def variant_names(take: Take) -> dict[str, list[int]]:
    """``all`` and one held-out variant per camera: name -> indices of the cameras used."""
    n = len(take.cameras)
    return {ALL: list(range(n))} | {f"no_{name}": [c for c in range(n) if c != k] for k, name in
                                    enumerate(take.camera_names)}  # fmt: skip


def _stack(people: dict[str, FloatArray], n_frames: int) -> FloatArray:
    if not people:
        return np.full((n_frames, 0, 17, 3), np.nan)
    return np.stack(list(people.values()), axis=1)


def held_out(run: TakeRun) -> dict[str, Any]:
    """Held-out-view errors of every system: own and common sets, per group and per camera."""
    take, dets = run.take, run.detections
    systems = [s for s in SYSTEMS if run.people.get(s)]
    n, n_cams = dets.n_frames, len(take.cameras)
    max_det = max((len(d) for row in dets.frames for d in row), default=0)
    # Per system: errors placed at (camera, frame, detection, keypoint) so that systems can be intersected.
    grid = {s: np.full((n_cams, n, max_det, 17), np.nan) for s in systems}
    for s in systems:
        for k, name in enumerate(take.camera_names):
            pts = _stack(run.people[s].get(f"no_{name}", {}), n)
            res = held_out_errors(take.cameras[k], [row[k] for row in dets.frames], pts)
            for f, p in zip(*np.nonzero(res.matched >= 0), strict=True):
                grid[s][k, f, res.matched[f, p]] = res.errors[f, p]
    common = np.logical_and.reduce([np.isfinite(grid[s]) for s in systems]) if systems else np.zeros(0, bool)
    out: dict[str, Any] = {}
    for s in systems:
        g = grid[s]
        out[s] = {
            "own": summarize(g),
            "common": summarize(np.where(common, g, np.nan)),
            "per_camera": {name: summarize(g[k])[ALL] for k, name in enumerate(take.camera_names)},
            "per_camera_common": {
                name: summarize(np.where(common[k], g[k], np.nan))[ALL] for k, name in enumerate(take.camera_names)
            },
        }
    return out


def _median_floor(points: FloatArray) -> FloatArray:
    hips = points[:, [11, 12]]
    return np.asarray(np.nanmedian(hips.reshape(-1, 3)[:, [0, 2]], axis=0))


def people_metrics(run: TakeRun, system: str) -> dict[str, Any]:
    """The all-camera run's people: performers and bystanders, frames each, identity switches, flips accepted."""
    take, dets = run.take, run.detections
    people = run.people[system].get(ALL, {})
    ids = list(people)
    arrays = [people[i] for i in ids]
    (x0, z0), (x1, z1) = AREA
    inside = []
    for a in arrays:
        xz = _median_floor(a) if np.isfinite(a[:, [11, 12]]).any() else np.array([np.nan, np.nan])
        inside.append(bool(x0 <= xz[0] <= x1 and z0 <= xz[1] <= z1))
    matched = matched_detections(take.cameras, dets.frames, arrays)
    tracks = [track_2d([row[c] for row in dets.frames]) for c in range(len(take.cameras))]
    switches = identity_switches(matched, tracks)
    found, accepted = accepted_flips(take.cameras, dets.frames, arrays, matched)
    frames = {i: int(np.count_nonzero(np.isfinite(a[:, COCO17_COMPARED]).all(axis=-1).any(axis=-1)))
              for i, a in zip(ids, arrays, strict=True)}  # fmt: skip
    return {
        "identities": len(ids),
        "performers": [i for i, ins in zip(ids, inside, strict=True) if ins],
        "bystanders_enrolled": sum(1 for ins in inside if not ins),
        "frames": frames,
        "identity_switches": int(sum(switches)),
        "switches_per_identity": dict(zip(ids, switches, strict=True)),
        "flips_found": {n: int(v) for n, v in zip(take.camera_names, found, strict=True)},
        "flips_accepted": {n: int(v) for n, v in zip(take.camera_names, accepted, strict=True)},
    }


def segment_lengths(skeletons: dict[str, Skeleton]) -> dict[str, dict[str, float]]:
    """The segment lengths mocapd estimated per identity (m)."""
    out = {}
    for identity, sk in skeletons.items():
        out[identity] = {
            "height": round(sk.height, 3),
            "upper_arm": round(sk.bone_length("LeftLowerArm"), 3),
            "forearm": round(sk.bone_length("LeftHand"), 3),
            "thigh": round(sk.bone_length("LeftLowerLeg"), 3),
            "shank": round(sk.bone_length("LeftFoot"), 3),
        }
    return out


def take_results(run: TakeRun) -> dict[str, Any]:
    """Every metric of one take."""
    take = run.take
    systems = [s for s in SYSTEMS if run.people.get(s)]
    ho = held_out(run)
    res: dict[str, Any] = {"take": take.name, "frames": run.detections.n_frames, "cameras": take.camera_names,
                           "fps": take.fps, "source": take.source, "systems": {}}  # fmt: skip
    for s in systems:
        people = people_metrics(run, s)
        performers = [run.people[s][ALL][i] for i in people["performers"]]
        res["systems"][s] = {
            "held_out": ho[s],
            "jitter": jitter(performers, take.fps),
            "bone_cv": bone_cv(performers),
            "people": people,
        }
    res["segment_lengths"] = segment_lengths(run.skeletons)
    res["notes"] = dict(run.notes)
    res["targets"] = targets(res)
    return res


def targets(res: dict[str, Any]) -> dict[str, Any]:
    """The issue's targets on one take (NaN/False where Pose2Sim did not run)."""
    sy = res["systems"]
    out: dict[str, Any] = {}
    p2s = [sy[s]["held_out"]["common"][ALL]["median"] for s in (P2S, P2S_FILT) if s in sy]
    best = min(p2s) if p2s else float("nan")
    for s in MOCAPD:
        if s in sy:
            m = sy[s]["held_out"]["common"][ALL]["median"]
            out[f"{s} held-out / Pose2Sim"] = round(m / best, 3) if p2s else None
            out[f"{s} held-out <= {HELD_OUT_TARGET} x Pose2Sim"] = bool(p2s and m <= HELD_OUT_TARGET * best)
    if P2S_FILT in sy:
        ref = sy[P2S_FILT]["jitter"]["median"]
        for s in MOCAPD:
            if s in sy:
                out[f"{s} jitter <= Pose2Sim filtered"] = bool(sy[s]["jitter"]["median"] <= ref)
    for s in MOCAPD:
        if s in sy:
            out[f"{s} identity switches == 0"] = sy[s]["people"]["identity_switches"] == 0
            out[f"{s} bystanders enrolled == 0"] = sy[s]["people"]["bystanders_enrolled"] == 0
    return out


def groups() -> tuple[str, ...]:
    """The joint groups of the held-out tables, ``all`` first."""
    return (ALL, *COCO17_GROUPS)

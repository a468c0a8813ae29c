"""Error of a synthetic session's poses against the synthetic world's known truth (resolve measurement).

The error is the mean 3D distance of the 17 COCO keypoint sites (what the cameras observe), like the synthetic
demo's: with per-person body sizing a person's skeleton differs from the world's, and joints no camera sees sit
at different places on two skeletons by definition.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mocapd.errors import InputError
from mocapd.io.session import MANIFEST, Session
from mocapd.protocols.session_format import PoseRecord
from mocapd.sim.world import SyntheticWorld

MAX_SYNTHETIC_CAMERAS = 64
"""The most cameras a daemon runs (``MAX_CAMERAS`` of the config)."""
MAX_SYNTHETIC_PEOPLE = 4
"""The most people and suits ``[synthetic]`` allows."""


def synthetic_of(session: Session) -> dict[str, Any] | None:
    """The manifest's ``extra.synthetic`` table (None for a session of real cameras), its values checked: a
    damaged or hand-edited one is an InputError naming the manifest, not a traceback or a world of a million
    people built from it."""
    extra = session.manifest.get("extra")
    if not isinstance(extra, dict) or "synthetic" not in extra:
        return None
    where = f"{session.path / MANIFEST}: damaged: extra.synthetic"
    s = extra["synthetic"]
    if not isinstance(s, dict):
        raise InputError(f"{where} is not a table")
    ranges = {"cameras": (1, MAX_SYNTHETIC_CAMERAS), "people": (1, MAX_SYNTHETIC_PEOPLE),
              "suits": (0, MAX_SYNTHETIC_PEOPLE), "seed": (0, 2**31), "epoch_ns": (-(2**62), 2**62)}  # fmt: skip
    for key, (lo, hi) in ranges.items():
        v = s.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise InputError(f"{where}.{key} = {v!r}; allowed: an integer in [{lo}, {hi}]")
    if s.get("motion", "procedural") not in ("recorded", "procedural"):
        raise InputError(f'{where}.motion = {s.get("motion")!r}; allowed: "recorded" or "procedural"')
    names = s.get("camera_names")
    if names is not None and (
        not isinstance(names, list) or len(names) != s["cameras"] or not all(isinstance(n, str) for n in names)
    ):
        raise InputError(f"{where}.camera_names is not a list of {s['cameras']} camera names")
    return s


def world_of(session: Session) -> tuple[SyntheticWorld, int]:
    """The synthetic world a session was recorded in, and its epoch (host ns of world time 0)."""
    s = synthetic_of(session)
    if s is None:
        raise InputError(f"{session.path / MANIFEST}: not a session of the synthetic rig (no extra.synthetic)")
    world = SyntheticWorld(
        s["cameras"],
        s["people"],
        s["suits"],
        seed=s["seed"],
        motion=str(s.get("motion", "procedural")),  # sessions before the recorded motion
        camera_names=s.get("camera_names"),  # sessions before named synthetic cameras: cam0, cam1, ...
    )
    return world, int(s["epoch_ns"])


def person_errors(world: SyntheticWorld, epoch_ns: int, frames: list[PoseRecord]) -> dict[tuple[int, int], float]:
    """Mean keypoint-site error (m) of every solved person against the nearest true person, keyed by (solve
    time, index of that true person), so that streams whose people come in another order compare on the same
    people."""
    out: dict[tuple[int, int], float] = {}
    for f in frames:
        for p in f.people:  # against the truth at the pose's own instant (later than the solve when predicted)
            t = ((f.t_solve_ns if p.t_pose_ns is None else p.t_pose_ns) - epoch_ns) / 1e9
            e, k = world.nearest_site_error(p.theta, p.skeleton, t)
            out[(f.t_solve_ns, k)] = min(e, out.get((f.t_solve_ns, k), np.inf))
    return out


def truth_report(
    session: Session, streams: dict[str, list[PoseRecord]], skip_s: float = 1.0, from_ns: int | None = None
) -> dict[str, Any]:
    """Median, mean and p95 keypoint-site error (mm) of each pose stream, over the person-frames that every stream
    solved after the first ``skip_s`` of the session (start-up: enrolment and convergence), or after the solve
    time ``from_ns`` when given."""
    world, epoch = world_of(session)
    starts = [f[0].t_solve_ns for f in streams.values() if f]
    t0 = from_ns if from_ns is not None else min(starts) if starts else 0
    skip_s = 0.0 if from_ns is not None else skip_s
    errs = {
        name: {k: v for k, v in person_errors(world, epoch, frames).items() if k[0] - t0 >= skip_s * 1e9}
        for name, frames in streams.items()
    }
    common = sorted(set.intersection(*(set(e) for e in errs.values()))) if errs else []
    out: dict[str, Any] = {"person_frames": len(common)}
    for name, e in errs.items():
        v = np.array([e[k] for k in common]) * 1e3
        out[name] = {"median": round(float(np.median(v)), 2), "mean": round(float(v.mean()), 2),
                     "p95": round(float(np.percentile(v, 95)), 2)} if v.size else None  # fmt: skip
    return out

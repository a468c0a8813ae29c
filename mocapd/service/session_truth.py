"""Joint error of a synthetic session's poses against the synthetic world's known truth (resolve measurement)."""

from __future__ import annotations

from typing import Any

import numpy as np

from mocapd.io.session import Session
from mocapd.protocols.session_format import PoseRecord
from mocapd.service.synthetic_rig import SyntheticWorld


def world_of(session: Session) -> tuple[SyntheticWorld, int]:
    """The synthetic world a session was recorded in, and its epoch (host ns of world time 0)."""
    s = session.manifest["extra"]["synthetic"]
    return SyntheticWorld(int(s["cameras"]), int(s["people"]), int(s["suits"]), seed=int(s["seed"])), int(s["epoch_ns"])


def person_errors(world: SyntheticWorld, epoch_ns: int, frames: list[PoseRecord]) -> dict[int, float]:
    """Per (frame index, person) — keyed ``frame_index * 16 + person`` — the mean joint error (m) against the
    nearest true person."""
    out = {}
    for i, f in enumerate(frames):
        if not f.people:
            continue
        t = (f.t_solve_ns - epoch_ns) / 1e9
        truth = [world.joints_at(p, t) for p in range(len(world.truth))]
        for j, p in enumerate(f.people):
            out[i * 16 + j] = min(float(np.linalg.norm(p.joints - x, axis=1).mean()) for x in truth)
    return out


def truth_report(session: Session, streams: dict[str, list[PoseRecord]], skip_s: float = 1.0) -> dict[str, Any]:
    """Median, mean and p95 joint error (mm) of each pose stream, over the frames after the first ``skip_s``
    (start-up: enrolment and convergence) in which every stream solved someone."""
    world, epoch = world_of(session)
    errs = {}
    for name, frames in streams.items():
        t0 = frames[0].t_solve_ns if frames else 0
        keep = [f for f in frames if f.t_solve_ns - t0 >= skip_s * 1e9]
        e = person_errors(world, epoch, keep)
        errs[name] = {keep[k // 16].t_solve_ns * 16 + k % 16: v for k, v in e.items()}
    common = set.intersection(*(set(e) for e in errs.values())) if errs else set()
    out: dict[str, Any] = {"person_frames": len(common)}
    for name, e in errs.items():
        v = np.array([e[k] for k in sorted(common)]) * 1e3
        out[name] = {"median": round(float(np.median(v)), 2), "mean": round(float(v.mean()), 2),
                     "p95": round(float(np.percentile(v, 95)), 2)} if v.size else None  # fmt: skip
    return out

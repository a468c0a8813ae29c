"""A recorded session's keypoint sets through the daemon's people sorting, as the live daemon saw them: at each
recorded output tick, only the sets that had *arrived* by the tick's wall time are in the cameras' timelines
(:class:`~mocapd.pipeline.keypoint_timeline.DetectionTimeline`, the session's own hold and gap limits), sampled at
the tick's solve time, sorted and enrolled (:class:`~mocapd.core.people.PeopleTracker`, the session's
``[tracking]``). No pose is solved, so it runs in seconds and reproduces the live person count (to ~0.01 a tick on
the camera demo) -- what to replay when people are lost: which cameras had people, which candidates the sorting
made, and with which sorting thresholds (``--set``) the same keypoints would have kept them.

    mocapd demo --seconds 60 --record /tmp/s          # (in a private network namespace, docs/daemon.md)
    .venv/bin/python tools/replay_people.py /tmp/s
    .venv/bin/python tools/replay_people.py /tmp/s --set min_shared_keypoints=3

Prints one JSON object: person solves a tick (replayed and recorded), enrolments and releases, the timelines'
sample statuses, and the ticks with fewer people than subjects by cameras with people and candidates' views.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from mocapd.core.people import PeopleTracker
from mocapd.core.sorting import Detections2D, DetectionSorter
from mocapd.core.tracking import SubjectTracker
from mocapd.io.session import open_session
from mocapd.pipeline.keypoint_timeline import USABLE, DetectionTimeline
from mocapd.service.session.solve import session_rig

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

Options = TypeVar("Options", bound="DataclassInstance")


def with_settings(base: Options, settings: list[str], what: str) -> Options:
    """``base`` (a dataclass of options) with ``name=value`` settings, each in its field's own type; an unknown name
    stops the tool, naming it as one of ``what``'s."""
    out = base
    for kv in settings:
        name, _, value = kv.partition("=")
        if name not in {f.name for f in dataclasses.fields(base)}:
            raise SystemExit(f"unknown {what} option {name!r}")
        kind = type(getattr(base, name))
        out = dataclasses.replace(out, **{name: value == "true" if kind is bool else kind(float(value))})
    return out


def replay(path: str, settings: list[str]) -> dict[str, Any]:
    session = open_session(path)
    rig = session_rig(session)
    cfg, o = rig.config, rig.options
    # Every recorded column, as the live daemon sampled and sorted them: the targets', then both hands' when the
    # rig detected hands (the manifest's keypoint_columns; the sorter pairs left and right by these names).
    columns = rig.keypoint_columns or rig.targets.names
    options = with_settings(cfg.tracking.sorting.options(), settings, "sorting")
    sorter = DetectionSorter(rig.cameras, options, keypoint_names=columns)
    people = PeopleTracker(SubjectTracker(sorter, cfg.tracking.enrolment.options()))
    n_kp = len(columns)
    timelines = [DetectionTimeline(n_kp, max_age_ns=o.keypoint_max_age_ns, max_gap_ns=o.keypoint_max_gap_ns,
                                   match_px=o.match_px) for _ in rig.cameras]  # fmt: skip
    sets = sorted(session.keypoints(), key=lambda k: (k.arrival_ns, k.camera))
    poses = session.poses()
    statuses: collections.Counter[str] = collections.Counter()
    short: collections.Counter[str] = collections.Counter()
    events: list[tuple[float, str, int]] = []
    counts = []
    i = 0
    for frame in poses:
        while i < len(sets) and sets[i].arrival_ns <= frame.tick_ns:
            k = sets[i]
            timelines[k.camera].push(k.capture_ns, Detections2D(k.keypoints, k.confidences))
            i += 1
        detections, frames = [], []
        for tl in timelines:
            s = tl.sample(frame.t_solve_ns)
            statuses[s.status.value] += 1
            detections.append(s.detections if s.status in USABLE else Detections2D.empty(n_kp))
            frames.append(s.frame_ns)
        found = people.update(frame.t_solve_ns, detections, frames=frames)
        counts.append(len(found.people))
        events += [(round((e.t_ns - poses[0].t_solve_ns) / 1e9, 2), e.kind, e.subject) for e in found.tracking_events]
        if len(found.people) < len(people.tracker.subjects):
            views = [len(d) for d in detections]
            cands = sorted(len(c.sources) for c in sorter.candidates(detections))
            short[f"people by camera {views}, candidates' views {cands}"] += 1
    recorded = [len(f.people) for f in poses]
    return {
        "session": path, "ticks": len(poses),
        "person_solves_per_tick": round(float(np.mean(counts)), 3) if counts else None,
        "recorded_person_solves_per_tick": round(float(np.mean(recorded)), 3) if recorded else None,
        "identities_recorded": sorted({p.identity for f in poses for p in f.people}),
        "tracking_events": events, "sample_statuses": dict(statuses),
        "ticks_short_of_subjects": dict(short.most_common(12)),
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("session", help="a recorded session directory")
    ap.add_argument("--set", nargs="*", default=[], metavar="NAME=VALUE", help="[tracking.sorting] options")
    args = ap.parse_args()
    print(json.dumps(replay(args.session, args.set), indent=1))


if __name__ == "__main__":
    main()

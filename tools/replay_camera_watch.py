"""The bumped-camera watch replayed over recorded sessions' real detections (issue 43): does it name a camera that
never moved?

Developer tool. Two steps, the first slow, the second instant:

1. **Observations.** A recorded session's keypoint sets through the daemon's scheduler as the live daemon saw them
   (at each recorded output tick, only the sets that had *arrived* by the tick's wall time, as
   ``tools/replay_people.py`` does; people sorted, enrolled and solved with the live LM budget), every solved
   person's undistorted keypoints and confidences *as the watch is handed them* (after the left/right flips were
   undone, :attr:`~mocapd.pipeline.scheduler.FixedLatencyScheduler.observation_hook`) kept, with their solve time.
   The watch is not in that loop (nobody is down-weighted: the observations are the session's, not one watch
   setting's). About a minute of CPU for a minute of the camera demo; kept in ``--cache DIR`` as ``NAME.npz``.
2. **The watch** (:class:`~mocapd.core.camera_watch.CameraWatch`, the session's ``[calibration.watch]`` unless
   ``--set``) fed those observations in order; its re-estimates that pass are applied (``apply`` on, whatever the
   session had: the question is what applying would have done). What it said is printed: the cameras named, the
   re-estimates and their verdicts, the cameras' residual levels.

    mocapd demo --seconds 60 --record /tmp/s     # a camera-demo session (cameras that never moved)
    python -m tools.replay_camera_watch /tmp/s /tmp/other --cache /tmp/obs
    python -m tools.replay_camera_watch /tmp/s --cache /tmp/obs --set ratio=0.5

Prints one JSON object per session (one a line); a camera named in a session whose cameras never moved is a false
naming.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.camera_watch import CameraWatch, WatchOptions
from mocapd.core.sorting import Detections2D
from mocapd.io.session import open_session
from mocapd.service.session.solve import ResolveOptions, session_rig, session_scheduler
from tools.replay_people import with_settings

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Observations:
    """Every solved person the watch would have been handed, in order.

    Attributes
    ----------
    t_ns : array, shape (n,)
        Solve times.
    uv : array, shape (n, n_cams, n_kp, 2)
        Undistorted keypoints, flips undone.
    conf : array, shape (n, n_cams, n_kp)
        Their confidences (0: not seen by that camera).
    """

    t_ns: NDArray[np.int64]
    uv: FloatArray
    conf: FloatArray


def observe(path: str | Path) -> Observations:
    """Step 1 (module docstring): the session's keypoints through the live scheduler, the watch's input kept."""
    session = open_session(path)
    rig = session_rig(session)
    lm = rig.config.solver.lm
    sched, _ = session_scheduler(rig, ResolveOptions(max_iterations=lm.max_iterations,
                                                     tolerance=lm.function_tolerance))  # fmt: skip
    kept: list[tuple[int, FloatArray, FloatArray]] = []

    def hook(t: int, uv: FloatArray, conf: FloatArray, person: str) -> FloatArray:
        kept.append((t, uv.copy(), conf.copy()))
        return conf

    sched.observation_hook = hook
    sets = sorted(session.keypoints(), key=lambda k: (k.arrival_ns, k.camera))
    i = 0
    for frame in session.poses():
        while i < len(sets) and sets[i].arrival_ns <= frame.tick_ns:
            k = sets[i]
            sched.add_detections(k.camera, k.capture_ns, Detections2D(k.keypoints, k.confidences), k.arrival_ns)
            i += 1
        sched.tick(frame.tick_ns)
    n_cams, n_kp = len(rig.cameras), len(rig.targets)
    if not kept:
        return Observations(np.zeros(0, np.int64), np.zeros((0, n_cams, n_kp, 2)), np.zeros((0, n_cams, n_kp)))
    return Observations(np.array([k[0] for k in kept], np.int64), np.stack([k[1] for k in kept]),
                        np.stack([k[2] for k in kept]))  # fmt: skip


def cached(path: str | Path, cache: Path | None) -> Observations:
    """:func:`observe`, kept in ``cache`` (a directory) under the session directory's name."""
    if cache is None:
        return observe(path)
    f = cache / f"{Path(path).resolve().as_posix().strip('/').replace('/', '_')}.npz"
    if f.exists():
        with np.load(f) as z:
            return Observations(z["t_ns"], z["uv"], z["conf"])
    obs = observe(path)
    cache.mkdir(parents=True, exist_ok=True)
    part = f.with_suffix(".part.npz")
    np.savez_compressed(part, t_ns=obs.t_ns, uv=obs.uv, conf=obs.conf)
    part.replace(f)  # whole or absent: a run stopped while writing leaves no torn cache
    return obs


def watch_over(cameras: list[Camera], obs: Observations, options: WatchOptions) -> CameraWatch:
    """Step 2: the watch fed ``obs`` in order, its passing re-estimates applied at once (as the daemon does on its
    next status pass)."""
    watch = CameraWatch(cameras, options)
    for t, uv, conf in zip(obs.t_ns, obs.uv, obs.conf, strict=True):
        watch.observe(int(t), uv, conf)
        for index, p in watch.pending():
            watch.apply(index, p.camera)
    return watch


def replay(path: str, cache: Path | None, settings: list[str]) -> dict[str, Any]:
    session = open_session(path)
    rig = session_rig(session)
    obs = cached(path, cache)
    options = with_settings(dataclasses.replace(rig.config.calibration.watch.options(), apply=True), settings, "watch")
    watch = watch_over(rig.cameras, obs, options)
    t0 = int(obs.t_ns[0]) if len(obs.t_ns) else 0
    events = [{"t_s": round((t - t0) / 1e9, 2), "camera": cam, "what": what,
               **{k: v for k, v in d.items() if k not in ("R", "t")}}
              for t, cam, what, d in watch.events]  # fmt: skip
    return {
        "session": path,
        "seconds": round((int(obs.t_ns[-1]) - t0) / 1e9, 1) if len(obs.t_ns) else 0.0,
        "person_solves": len(obs.t_ns),
        "named": sorted({e["camera"] for e in events if e["what"] == "bumped"}),
        "applied": sum(c["applied"] for c in watch.status().values()),
        "events": events,
        "baseline_px": {name: s["baseline_px"] for name, s in watch.status().items()},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sessions", nargs="+", help="recorded session directories")
    ap.add_argument("--cache", type=Path, help="a directory keeping each session's observations (step 1)")
    ap.add_argument("--set", nargs="*", default=[], metavar="NAME=VALUE", help="[calibration.watch] options")
    args = ap.parse_args()
    for path in args.sessions:
        print(json.dumps(replay(path, args.cache, args.set)), flush=True)


if __name__ == "__main__":
    main()

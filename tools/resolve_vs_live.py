"""Where ``mocapd resolve`` differs from the live solve on the Pose2Sim demos, per joint group and per performer.

Reads the live sessions a ``mocapd eval video`` run recorded (``OUT/work/sessions/<take>/no_<camera>``), re-solves
each with ``mocapd resolve``'s passes one at a time (the forward re-solve at the live LM budget, which must give the
live poses back; at resolve's budget; then smoothed) and scores every stream by the held-out-view error of
``mocapd eval video`` (docs/accuracy-video.md), on the keypoints every stream was compared on: median / p90 px per
joint group, and elbows and wrists per performer (the live run's identities). ``--skip-collapsed`` leaves out
held-out detections whose left/right elbows, wrists, knees or ankles lie within 15 % of the person's size of each
other (the detector put both on one limb: no solve can match both).

Then each stream against live: the difference of the median and of the p90 per joint group with its 95 % interval
over the take's frames (:func:`~mocapd.eval.heldout.quantile_difference`; ``worse`` where the whole interval is
above zero). ``--frames A:B`` scores frames A to B-1 only: issue 41's split of the demos (which are not a
held-back set) by take halves, frames 0-49 for development and 50-99 for evaluation (docs/accuracy-video.md).

    PYTHONPATH=$PWD .venv/bin/mocapd eval video --config presets/eval-video.toml --no-pose2sim --images 0 --out R
    PYTHONPATH=$PWD .venv/bin/python tools/resolve_vs_live.py R --frames 0:50
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mocapd.core.kinematics import Kinematics
from mocapd.core.per_skeleton import PerSkeleton
from mocapd.eval.heldout import COCO17_GROUPS, Difference, held_out_errors, quantile_difference
from mocapd.eval.video_input import Take, TakeDetections, detect_take, eval_detector_config, pose2sim_take
from mocapd.io.pose2sim_demo import DEMOS
from mocapd.io.session import Session
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.protocols.session_format import PoseRecord
from mocapd.service.config import load_config
from mocapd.service.session.solve import ResolveOptions, manifest_skeleton, resolve
from mocapd.service.video_systems import _keypoints

FloatArray = NDArray[np.float64]
T0_NS = 1_000_000_000  # the first frame's capture time in the eval's lockstep replay (video_systems.run_live)
LIVE_LM = ResolveOptions(smooth=False, max_iterations=20, tolerance=1e-6)
STREAMS: dict[str, ResolveOptions | None] = {
    "live (recorded)": None,
    "forward, live LM budget": LIVE_LM,
    "forward, resolve's LM budget": ResolveOptions(smooth=False),
    "resolve (forward + RTS)": ResolveOptions(),
}
PAIRS = ((7, 8), (9, 10), (13, 14), (15, 16))


def _points(frames: list[PoseRecord], session: Session, n: int, fps: float) -> dict[str, FloatArray]:
    skeleton, targets = manifest_skeleton(session.manifest)
    kins = PerSkeleton(Kinematics(skeleton), Kinematics)
    out: dict[str, FloatArray] = {}
    for fr in frames:
        f = round((fr.t_solve_ns - T0_NS) * fps / 1e9)
        if 0 <= f < n:
            for p in fr.people:
                arr = out.setdefault(p.identity, np.full((n, len(targets), 3), np.nan))
                arr[f] = _keypoints(kins, targets, p.theta, p.skeleton)
    return out


def _grid(
    take: Take, dets: TakeDetections, people: dict[str, dict[str, FloatArray]], skip_collapsed: bool
) -> tuple[FloatArray, NDArray[np.object_]]:
    """Held-out errors (camera, frame, detection, keypoint) and the identity compared there."""
    n = dets.n_frames
    width = max((len(d) for row in dets.frames for d in row), default=0)
    g = np.full((len(take.cameras), n, width, 17), np.nan)
    who = np.full((len(take.cameras), n, width), "", dtype=object)
    for k, name in enumerate(take.camera_names):
        ids = list(people[name])
        pts = np.stack([people[name][i] for i in ids], axis=1) if ids else np.full((n, 0, 17, 3), np.nan)
        res = held_out_errors(take.cameras[k], [row[k] for row in dets.frames], pts)
        for f, p in zip(*np.nonzero(res.matched >= 0), strict=True):
            i = int(res.matched[f, p])
            g[k, f, i] = res.errors[f, p]
            who[k, f, i] = ids[p]
            if skip_collapsed:
                det = dets.frames[f][k]
                ok = det.confidences[i] >= 0.3
                size = float(np.ptp(det.keypoints[i][ok], axis=0).max()) if np.count_nonzero(ok) >= 4 else 0.0
                for a, b in PAIRS:
                    if size and np.linalg.norm(det.keypoints[i, a] - det.keypoints[i, b]) < 0.15 * size:
                        g[k, f, i, [a, b]] = np.nan
    return g, who


def _cell(values: FloatArray) -> str:
    return f"{np.median(values):.1f} / {np.percentile(values, 90):.0f}" if values.size else "-"


def _diff(d: Difference) -> str:
    return f"{d.value:+.1f} [{d.low:+.1f}, {d.high:+.1f}]{' worse' if d.worse else ''}" if d.n else "-"


def _frames(text: str) -> slice:
    a, _, b = text.partition(":")
    return slice(int(a) if a else None, int(b) if b else None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", type=Path, help="a `mocapd eval video` results directory (its work/ sessions)")
    ap.add_argument("--config", type=Path, default=Path("presets/eval-video.toml"), help="the run's config")
    ap.add_argument("--take", action="append", choices=DEMOS, help="default: both")
    ap.add_argument("--skip-collapsed", action="store_true", help="see the module docstring")
    ap.add_argument("--frames", type=_frames, default=slice(None), help="A:B, frames A to B-1 only (default: all)")
    args = ap.parse_args()
    cfg = load_config(args.config)
    detector: list[OnnxPoseDetector] = []

    def make_detector() -> OnnxPoseDetector:  # only to fingerprint the cached detections
        if not detector:
            detector.append(OnnxPoseDetector.from_config(eval_detector_config(cfg.detector.options(), "fp32")))
        return detector[0]

    groups = ("all", *COCO17_GROUPS)
    cols = {g: list(COCO17_GROUPS[g]) if g != "all" else [i for v in COCO17_GROUPS.values() for i in v]
            for g in groups}  # fmt: skip
    for name in args.take or DEMOS:
        take = pose2sim_take(name)
        dets = detect_take(take, make_detector)
        n = dets.n_frames
        sessions = {c: Session(args.results / "work" / "sessions" / name / f"no_{c}") for c in take.camera_names}
        grids = {}
        for stream, opts in STREAMS.items():
            people = {c: _points(list(s.poses()) if opts is None else resolve(s, opts)[0], s, n, take.fps)
                      for c, s in sessions.items()}  # fmt: skip
            g, who = _grid(take, dets, people, args.skip_collapsed)
            grids[stream] = (g[:, args.frames], who[:, args.frames])
        common = np.logical_and.reduce([np.isfinite(g) for g, _ in grids.values()])
        print(f"\n{name}: held-out median / p90 px (keypoints every stream was compared on)\n")
        print("| stream | " + " | ".join(groups) + " |\n|---|" + "---|" * len(groups))
        for stream, (g, _) in grids.items():
            print(f"| {stream} | " + " | ".join(_cell(g[..., cols[gr]][common[..., cols[gr]]]) for gr in groups) + " |")
        who = next(iter(grids.values()))[1]
        print("\n| stream | " + " | ".join(f"{i} elbows | {i} wrists" for i in sorted(set(who[who != ""]))) + " |")
        print("|---|" + "---|---|" * len(set(who[who != ""])))
        for stream, (g, _) in grids.items():
            cells = []
            for ident in sorted(set(who[who != ""])):
                sel = who == ident
                for gr in ("elbows", "wrists"):
                    cells.append(_cell(g[..., cols[gr]][sel][common[..., cols[gr]][sel]]))
            print(f"| {stream} | " + " | ".join(cells) + " |")
        base = next(iter(grids.values()))[0]
        for q in (50.0, 90.0):
            print(f"\n{'median' if q == 50 else 'p90'} minus live's, px [95 % interval over frames]\n")
            print("| stream | " + " | ".join(groups) + " |\n|---|" + "---|" * len(groups))
            for stream, (g, _) in list(grids.items())[1:]:
                cells = [
                    _diff(quantile_difference(
                        np.moveaxis(np.where(common, base, np.nan)[..., cols[gr]], 1, 0),
                        np.moveaxis(np.where(common, g, np.nan)[..., cols[gr]], 1, 0), q))
                    for gr in groups
                ]  # fmt: skip
                print(f"| {stream} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()

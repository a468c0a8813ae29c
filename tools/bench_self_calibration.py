"""Developer benchmark: self-calibration from people (issue 43), measured (docs/cameras.md).

Synthetic rig: known cameras, people of known height walking, detector-like noise; prints rotation, centre, scale
and up errors against the truth::

    python -m tools.bench_self_calibration [--cameras 4 8] [--seconds 60] [--seed 0]

Held-out-view error on a Pose2Sim demo take with each calibration file given (the board's and the self-calibration's):
for each camera k, the people mocapd's association (``DetectionSorter``) triangulates from the other cameras are
projected into k and compared with k's detections (``mocapd.eval.heldout``)::

    python -m tools.bench_self_calibration --heldout Demo_SinglePerson board.qca.txt self.toml

A Pose2Sim demo take calibrated from its people with each front end's keypoints (``yolo``: the shipped detector's;
``heavy`` / ``full``: BlazePose's landmarks, ``[detector] landmarks``, issue 40), from nothing and from the board
calibration, against the board calibration (rotation, centre, scale, up, median px per camera)::

    python -m tools.bench_self_calibration --demo Demo_SinglePerson --height 1.61 --keypoints yolo heavy
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from mocapd.core.self_calibration import SelfCalibrationOptions, calibrate_from_people, compare_calibrations
from mocapd.core.synthetic import detector_like, people_walking, ring_rig


def run(n_cams: int, seconds: float, seed: int, height_given: bool) -> str:
    rng = np.random.default_rng(seed)
    truth = ring_rig(n_cams, radius=4.0)
    heights = (1.80, 1.62)
    exact, _ = people_walking(truth, heights, seconds, rng)
    dets = detector_like(exact, rng)
    guess = [replace(c, R=np.eye(3), t=np.zeros(3)) for c in truth]
    opts = SelfCalibrationOptions(height_m=float(np.mean(heights)) if height_given else None, origin="person",
                                  origin_moments=(0, 10), seed=seed)  # fmt: skip
    t0 = time.monotonic()
    res = calibrate_from_people(dets, guess, opts)
    wall = time.monotonic() - t0
    cmp = compare_calibrations(res.cameras, truth)
    # Without alignment: the world itself (origin = person 0's start, facing +Z, floor y = 0).
    direct_deg = max(float(np.degrees(np.arccos(np.clip((np.trace(e.R @ t.R.T) - 1) / 2, -1, 1))))
                     for e, t in zip(res.cameras, truth, strict=True))  # fmt: skip
    direct_mm = max(float(np.linalg.norm(e.center - t.center)) * 1000 for e, t in zip(res.cameras, truth, strict=True))
    med = np.median([q.median_px for q in res.report.cameras])
    return (f"| {n_cams} | {seconds:.0f} s | {'1.71 m given' if height_given else '1.75 m default'} | "
            f"{max(cmp.rotation_deg.values()):.3f} | {max(cmp.centre_mm.values()):.1f} | {cmp.scale_error:+.2%} | "
            f"{cmp.up_deg:.2f} | {direct_deg:.2f} / {direct_mm:.0f} | {med:.1f} | {wall:.0f} s |")  # fmt: skip


def heldout(take: str, files: list[str]) -> None:
    """Median / p90 held-out-view error (px) per calibration file and camera on the demo take's detections."""
    from mocapd.core.sorting import DetectionSorter
    from mocapd.eval.heldout import COCO17_COMPARED, held_out_errors
    from mocapd.io.calibration_files import core_cameras, read_any
    from mocapd.service.people_calibration import load_people

    people = load_people(f"pose2sim:{take}")
    names = [c.name for c in people.cameras]
    print(f"| {take}: calibration | held-out median px (all cameras) | p90 | " + " | ".join(names) + " |")
    print("|---|---|---|" + "---|" * len(names))
    for f in files:
        given = {c.name: c for c in core_cameras(read_any(Path(f)))}
        cams = [given[n] for n in names]
        errs, per = [], []
        for k in range(len(cams)):
            others = [c for i, c in enumerate(cams) if i != k]
            sorter = DetectionSorter(others)
            pts = []
            for row in people.frames:
                cands = sorter.candidates([d for i, d in enumerate(row) if i != k])
                pts.append([c.points for c in cands])
            n_people = max(1, *(len(p) for p in pts))
            arr = np.full((len(pts), n_people, 17, 3), np.nan)
            for i, p in enumerate(pts):
                for j, x in enumerate(p):
                    arr[i, j] = x
            e = held_out_errors(cams[k], [row[k] for row in people.frames], arr).errors[..., list(COCO17_COMPARED)]
            errs.append(e[np.isfinite(e)])
            per.append(float(np.median(errs[-1])))
        a = np.concatenate(errs)
        print(f"| {Path(f).name} | {np.median(a):.1f} | {np.percentile(a, 90):.1f} | "
              + " | ".join(f"{m:.1f}" for m in per) + " |")  # fmt: skip


def demo(take: str, keypoints: list[str], height: float | None) -> None:
    """Rows of the docs/cameras.md demo table: per front end, the self-calibration from nothing and from the board."""
    import tempfile

    from mocapd.core.self_calibration import compare_calibrations
    from mocapd.service.people_calibration import load_people

    print("| take | keypoints | start | height | rotation deg per camera | centre mm per camera | scale | up deg | "
          "median px per camera | wall |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|")
    for kind in keypoints:
        with tempfile.TemporaryDirectory() as tmp:
            config = None
            if kind != "yolo":
                config = Path(tmp) / "landmarks.toml"
                config.write_text(f'[detector]\nlandmarks = "{kind}"\n', encoding="utf-8")
            people = load_people(f"pose2sim:{take}", config=config)
        assert people.reference is not None
        for start in ("nothing", "board"):
            opts = SelfCalibrationOptions(height_m=height, origin="people")
            t0 = time.monotonic()
            res = calibrate_from_people(people.frames, people.cameras, opts,
                                        initial=people.reference if start == "board" else None)  # fmt: skip
            wall = time.monotonic() - t0
            cmp = compare_calibrations(res.cameras, people.reference)
            names = [c.name for c in people.cameras]
            print(f"| {take} | {kind} | {start} | {height if height else '1.75 default'} | "
                  + " / ".join(f"{cmp.rotation_deg[n]:.2f}" for n in names) + " | "
                  + " / ".join(f"{cmp.centre_mm[n]:.0f}" for n in names)
                  + f" | {cmp.scale_error:+.2%} | {cmp.up_deg:.2f} | "
                  + " / ".join(f"{q.median_px:.1f}" for q in res.report.cameras) + f" | {wall:.0f} s |",
                  flush=True)  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, nargs="+", default=[4, 8])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--heldout", nargs="+", metavar=("TAKE", "CALIBRATION"), help="take, then calibration files")
    ap.add_argument("--demo", metavar="TAKE", help="a Pose2Sim demo take calibrated from its people")
    ap.add_argument("--keypoints", nargs="+", choices=["yolo", "full", "heavy"], default=["yolo", "heavy"])
    ap.add_argument("--height", type=float, default=None, help="the people's mean height (m) for --demo")
    args = ap.parse_args()
    if args.demo:
        demo(args.demo, args.keypoints, args.height)
        return
    if args.heldout:
        heldout(args.heldout[0], args.heldout[1:])
        return
    print("| cameras | take | height | rotation deg (worst) | centre mm (worst) | scale | up deg | "
          "world as is: deg / mm | median px | wall |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|")
    for n in args.cameras:
        for given in (True, False):
            print(run(n, args.seconds, args.seed, given), flush=True)


if __name__ == "__main__":
    main()

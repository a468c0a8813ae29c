"""Self-calibration from people on the synthetic rig (issue 43): known cameras, people of known height walking,
detector-like noise; prints rotation, centre, scale and up errors against the truth (docs/cameras.md).

    python -m tools.bench_self_calibration [--cameras 4 8] [--seconds 60] [--seed 0]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, nargs="+", default=[4, 8])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print("| cameras | take | height | rotation deg (worst) | centre mm (worst) | scale | up deg | "
          "world as is: deg / mm | median px | wall |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|")
    for n in args.cameras:
        for given in (True, False):
            print(run(n, args.seconds, args.seed, given), flush=True)


if __name__ == "__main__":
    main()

"""Camera-only orientation error of Foot, Toes and Hand on the synthetic rig, COCO-17 against BlazePose's 33 points
(issue 40; :mod:`mocapd.eval.extremities`). Prints JSON (with the CPU and the load) on stdout, a summary on stderr.

    MOCAPD_DATA=/work/shared/data PYTHONPATH=$PWD nice -n 19 .venv/bin/python tools/extremity_orientation.py \\
        --split evaluation --frames 600 --sequences 100 > docs/accuracy/extremities.json
"""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict

from mocapd.eval.extremities import TARGET_DEG, ExtremityOptions, extremity_orientation
from mocapd.io.prior import resolve_prior
from mocapd.service.bench.machine import emit


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--split", default="evaluation", help="clips of mocapd/data/eval_splits.toml (default evaluation)")
    p.add_argument("--frames", type=int, default=300, help="frames per sequence (default 300)")
    p.add_argument("--sequences", type=int, default=6, help="sequences (default 6)")
    p.add_argument("--cameras", type=int, default=8, help="first N cameras of the 8-camera ring (default 8)")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    opts = ExtremityOptions(split=a.split, n_cams=a.cameras, max_frames=a.frames, max_sequences=a.sequences,
                            seed=a.seed)  # fmt: skip
    t0 = time.perf_counter()
    result = extremity_orientation(opts, resolve_prior("default"))
    setup = {k: v for k, v in asdict(opts).items() if k != "detections"}
    report = {"setup": {**setup, "detections": "realistic", "target_median_deg": TARGET_DEG,
                        "wall_s": round(time.perf_counter() - t0, 1)}, **result}  # fmt: skip
    bp = result["blazepose33"]
    summary = ", ".join(f"{part} {bp[part]['median']:.1f}/{bp[part]['p90']:.1f}" for part in ("Foot", "Toes", "Hand"))
    emit(report, f"blazepose33 camera-only median/p90 deg: {summary}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

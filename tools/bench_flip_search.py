"""What the left/right flip search costs a person a tick: thread CPU of ``choose_swaps`` (a developer tool).

Developer benchmark, not a ``mocapd bench`` verb. The inputs are real: the Pose2Sim demos' detections (both takes,
the first ``--frames`` frames; cached by ``mocapd eval video``, detected otherwise), per frame the most confident
person of each of the 4 views, as detected and with views flipped at random, with the previous frame's
triangulated keypoints as the previous pose on most calls. Each input is decided ``--repeats`` times; the median
and mean thread CPU per call are printed as JSON, for the compiled decision, the compiled decision with a memo that
holds the same inputs (a held frame: only the mirror choice runs) and the numpy reference. Run it in an old
checkout too (``PYTHONPATH=<old checkout> python tools/bench_flip_search.py --compiled-only``) to compare the
code before a change on the same inputs.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable

import numpy as np

from mocapd.core import lr_flips
from mocapd.core.camera import triangulate_projections
from mocapd.eval.video_input import detect_take, pose2sim_take
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import ModelSpec
from mocapd.service.bench.machine import machine

Call = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]


def inputs(frames: int, seed: int = 0) -> list[Call]:
    """(P, undistorted pixels, confidences, previous pose) per call, two per demo frame (as detected, flipped)."""
    rng = np.random.default_rng(seed)
    out: list[Call] = []
    for demo in ("Demo_SinglePerson", "Demo_MultiPerson"):
        take = pose2sim_take(demo)
        dets = detect_take(take, lambda: OnnxPoseDetector(ModelSpec(), intra_op_threads=2), n_frames=frames)
        P = np.stack([c.projection_matrix for c in take.cameras])
        previous = None
        for kp, cf in dets.most_confident():
            _, und = lr_flips.undistorted(take.cameras, kp)
            und = np.where(np.isfinite(kp), und, np.nan)
            out.append((P, und, cf, previous))
            flipped = und.copy()
            for view in range(len(kp)):
                if rng.random() < 0.3:
                    for left, right in lr_flips.COCO17_LR_PAIRS:
                        flipped[view, [left, right]] = und[view, [right, left]]
            out.append((P, flipped, cf, None if rng.random() < 0.3 else previous))
            previous, _ = triangulate_projections(P, und, np.where(cf >= 0.3, cf, 0.0))
    return out


def thread_cpu_us(calls: list[Call], decide: Callable[[Call], object], repeats: int) -> dict[str, float]:
    """Median and mean thread CPU (µs) of ``decide`` over every call, each repeated."""
    decide(calls[0])  # compiled, loaded
    times = []
    for _ in range(repeats):
        for call in calls:
            t0 = time.thread_time_ns()
            decide(call)
            times.append(time.thread_time_ns() - t0)
    return {"median_us": round(float(np.median(times)) / 1e3, 1), "mean_us": round(float(np.mean(times)) / 1e3, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40, help="frames of each demo take")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--compiled-only", action="store_true", help="time the compiled decision alone")
    args = ap.parse_args()
    calls = inputs(args.frames)
    pairs = lr_flips.COCO17_LR_PAIRS
    result: dict[str, object] = {"calls": len(calls), "repeats": args.repeats, "machine": machine()}
    result["compiled"] = thread_cpu_us(
        calls, lambda c: lr_flips.choose_swaps(c[0], c[1], c[2], pairs, c[3]), args.repeats
    )
    if not args.compiled_only:
        memo = lr_flips.FlipMemo(4, len(pairs))

        def held(c: Call) -> int:
            lr_flips.choose_swaps(c[0], c[1], c[2], pairs, c[3], memo=memo)  # fills the memo: not timed below
            t0 = time.thread_time_ns()
            lr_flips.choose_swaps(c[0], c[1], c[2], pairs, c[3], memo=memo)
            return time.thread_time_ns() - t0

        held_ns = [held(c) for c in calls]
        result["compiled_held_frame"] = {"median_us": round(float(np.median(held_ns)) / 1e3, 1)}
        result["numpy_reference"] = thread_cpu_us(
            calls, lambda c: lr_flips.choose_swaps(c[0], c[1], c[2], pairs, c[3], compiled=False), 1
        )
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()

"""Benchmark: execution provider x precision x (whole, fitted, packed) detection on the Pose2Sim 4-camera demo.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

Prints one JSON object. For each provider (``--providers``, config names: cpu, openvino, cuda, tensorrt) and
precision (``--precision``: fp32, int8, bf16 = the FP32 model computed in BF16, OpenVINO only) it times
whole-frame detection (each camera frame letterboxed alone into the square input: the naive way), whole frames
at the camera's aspect (``fitted``: the 384x640 export for these portrait cameras, ``[detector]
fitted_inputs``) and packed detection (the ROIs of 4 cameras x 2 consecutive frames on shared canvases, as
``mocapd bench detector``). All configurations run in the same process on the same frame pairs, their order
rotating from pair to pair, and every rate is a median over pairs, so that the other work on this shared machine
hits all alike. ``disagreement_px`` compares each configuration's keypoints
with those of FP32 CPU whole-frame detection (the reference, always run): distance between keypoints both found
with confidence >= 0.5 on the same person in the same camera frame, in source pixels (median and p90).

    .venv/bin/python tools/bench_providers.py --providers cpu --precision fp32 int8 --pairs 20 --threads 2
    python tools/bench_providers.py --providers cpu openvino --precision fp32 int8 bf16 --threads 2  # openvino extra
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from mocapd.core.pose2d import PoseDetections
from mocapd.core.roi_packing import match_people
from mocapd.errors import MocapdError
from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.pipeline.detector import Image, OnnxPoseDetector
from mocapd.pipeline.detector_config import ModelSpec, PackingConfig
from mocapd.pipeline.packing import PackedDetector

MODES = ["whole", "fitted", "packed", "packed-square"]


def disagreements(a: PoseDetections, b: PoseDetections, conf: float = 0.5) -> list[float]:
    """Distances (source px) between keypoints of matched people both found with confidence >= ``conf``."""
    out: list[float] = []
    for i, j in match_people(a, b):
        ka, kb = a.keypoints[i], b.keypoints[j]
        ok = (ka[:, 2] >= conf) & (kb[:, 2] >= conf)
        out.extend(np.linalg.norm(ka[ok, :2] - kb[ok, :2], axis=1).tolist())
    return out


@dataclass
class _Run:
    """One provider x precision x mode under test, and what it measured."""

    name: str
    provider: str
    precision: str
    mode: str
    detector: OnnxPoseDetector
    packer: PackedDetector | None
    seconds: list[float] = field(default_factory=list)
    dis: list[float] = field(default_factory=list)
    people: int = 0

    def detect(self, pair: list[list[Image]]) -> list[list[PoseDetections]]:
        if self.packer is not None:
            return self.packer.detect(pair)
        return [[self.detector.detect(img) for img in cams] for cams in pair]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--demo", default="Demo_MultiPerson", help="Demo_SinglePerson or Demo_MultiPerson")
    ap.add_argument("--providers", nargs="+", default=["cpu"], help="config provider names (cpu, openvino, ...)")
    ap.add_argument("--precision", nargs="+", default=["fp32", "int8"], choices=["fp32", "int8", "bf16"])
    ap.add_argument("--modes", nargs="+", default=["whole", "fitted", "packed"], choices=MODES,
                    help="whole: frames letterboxed into the square input (naive); fitted: whole frames at the "
                    "camera's aspect; packed: ROIs on canvases, cropped to their tiles where an export fits "
                    "(both [detector] fitted_inputs); packed-square: packed at the model's own input only")  # fmt: skip
    ap.add_argument("--pairs", type=int, default=20, help="frame pairs to time (each: 8 camera frames)")
    ap.add_argument("--skip", type=int, default=0, help="frames to skip at the start of the videos")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    ap.add_argument("--scale-ratio", type=float, default=1.0,
                    help="packed tiles' scale / the whole frame's letterbox scale (1: as large; < 1: smaller tiles, "
                    "fewer canvases, coarser keypoints; [detector.packing] min/max_scale_ratio)")  # fmt: skip
    ap.add_argument("--align-stride", type=int, default=32,
                    help="[detector.packing] align_stride: > 0 aligned tiles at the whole frame's scale (the scale "
                    "ratio is then unused), 0 common-scale packing")  # fmt: skip
    args = ap.parse_args(argv)

    caps = [cv2.VideoCapture(str(demo_video(args.demo, c))) for c in CAMERAS]
    for cap in caps:
        cap.set(cv2.CAP_PROP_POS_FRAMES, args.skip)

    def read() -> list[Image] | None:
        imgs = []
        for cap in caps:
            ok, img = cap.read()
            if not ok:
                return None
            imgs.append(np.asarray(img, dtype=np.uint8))
        return imgs

    first = read()
    if first is None:
        raise SystemExit("cannot read the demo videos")
    sizes = [(im.shape[1], im.shape[0]) for im in first]
    packing = PackingConfig(align_stride=args.align_stride, min_scale_ratio=args.scale_ratio,
                            max_scale_ratio=args.scale_ratio, n_o=2, n_p=2)  # fmt: skip

    def detector(provider: str, precision: str, fit: bool) -> OnnxPoseDetector:
        d = OnnxPoseDetector(ModelSpec(), providers=[provider], precision=precision, intra_op_threads=args.threads,
                             inter_op_threads=1, fitted_inputs=fit)  # fmt: skip
        d.detect(first[0])  # warm-up: the first run allocates (and OpenVINO compiles)
        return d

    try:
        reference = detector("cpu", "fp32", False)
    except MocapdError as exc:
        raise SystemExit(f"bench_providers: {exc}") from None
    runs: list[_Run] = []
    skipped: dict[str, str] = {}  # provider/precision that cannot run here (BF16 off OpenVINO), and why
    for provider in args.providers:
        for precision in args.precision:
            try:
                square = reference if (provider, precision) == ("cpu", "fp32") else detector(provider, precision, False)
                fitted = detector(provider, precision, True) if {"fitted", "packed"} & set(args.modes) else square
            except MocapdError as exc:
                skipped[f"{provider}/{precision}"] = str(exc)
                print(f"bench_providers: {provider}/{precision} skipped: {exc}", file=sys.stderr)
                continue
            for mode in args.modes:
                det = square if mode in ("whole", "packed-square") else fitted
                packer = PackedDetector(det, sizes, packing) if mode.startswith("packed") else None
                runs.append(_Run(f"{provider}/{precision}/{mode}", provider, precision, mode, det, packer))
    if not any(r.name == "cpu/fp32/whole" for r in runs):
        runs.append(_Run("cpu/fp32/whole", "cpu", "fp32", "whole", reference, None))

    frame: list[Image] | None = first
    pairs = 0
    for k in range(args.pairs):
        nxt = read()
        if frame is None or nxt is None:
            break
        pair = [frame, nxt]
        results: dict[str, list[list[PoseDetections]]] = {}
        shift = k % len(runs)
        for r in runs[shift:] + runs[:shift]:
            t0 = time.perf_counter()
            results[r.name] = r.detect(pair)
            r.seconds.append(time.perf_counter() - t0)
        ref = results["cpu/fp32/whole"]
        for r in runs:
            for s in range(2):
                for c in range(len(CAMERAS)):
                    r.dis.extend(disagreements(ref[s][c], results[r.name][s][c]))
                    r.people += len(results[r.name][s][c])
        pairs += 1
        frame = read()

    n_cf = 2 * len(CAMERAS)
    base = float(np.median(n_cf / np.array(next(r for r in runs if r.name == "cpu/fp32/whole").seconds)))
    table = {}
    for r in runs:
        rate = float(np.median(n_cf / np.array(r.seconds)))
        table[r.name] = {
            "provider": r.detector.session.get_providers()[0],  # what the session runs, not what was asked
            "precision": r.precision,
            "mode": r.mode,
            "camera_frames_per_s_median": round(rate, 2),
            "x_fp32_cpu_whole": round(rate / base, 2),
            "disagreement_px_median": round(float(np.median(r.dis)), 2) if r.dis else None,
            "disagreement_px_p90": round(float(np.percentile(r.dis, 90)), 2) if r.dis else None,
            "keypoint_pairs_compared": len(r.dis),
            "people": r.people,
        }
    import onnxruntime as ort

    result = {
        "demo": args.demo,
        "frame_pairs": pairs,
        "camera_frames_per_pair": n_cf,
        "image_size": sizes[0],
        "model_input": list(reference.input_size),
        "intra_op_threads": args.threads,
        "packed_scale_ratio": args.scale_ratio,
        "packed_align_stride": args.align_stride,
        "onnxruntime": ort.__version__,
        "available_providers": ort.get_available_providers(),
        "reference": "cpu/fp32/whole",
        "results": table,
        "skipped": skipped,
    }
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())

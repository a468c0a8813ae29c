"""``mocapd model fetch``: build the default pose model (YOLO11n-pose → ONNX, and with ``--int8`` its INT8
quantization) into the cache; with ``--landmarks`` the BlazePose landmark models (heavy, full) from
``@mediapipe/pose`` too, with ``--hands`` the hand landmark models (full, lite) from ``@mediapipe/hands``."""

from __future__ import annotations

import argparse
from typing import Any

from mocapd.errors import MocapdError

# The square input (packed canvases, square cameras) and the whole-frame inputs of 9:16 portrait and 16:9
# landscape cameras ([detector] fitted_inputs).
DEFAULT_SIZES = ((640, 640), (384, 640), (640, 384))


def _parse_size(text: str) -> tuple[int, int]:
    try:
        if "x" in text:
            w, h = (int(v) for v in text.split("x", 1))
        else:
            w = h = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be N or WxH, got {text!r}") from None
    if w % 32 or h % 32 or w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"size must be positive multiples of 32 (the network stride), got {text!r}")
    return w, h


def _fetch(args: argparse.Namespace) -> int:
    from mocapd.io import lifecycle
    from mocapd.io.model_build import build_default_model
    from mocapd.io.progress import Progress

    sizes = args.size or list(DEFAULT_SIZES)
    # A stop signal unwinds the build (its temporary venv removed, its pip or export process killed) and leaves
    # the cache as it was: a model file is current only once its sidecar's checksum matches.
    lifecycle.enter_phase("building the model")
    try:
        with Progress(1, "model fetch") as bar:
            build_default_model(sizes, force=args.force, steps=bar.update)
        if args.int8:
            from mocapd.io.model_quant import build_int8_model

            build_int8_model(sizes, force=args.force)
        if args.landmarks:
            from mocapd.io.landmark_build import build_landmark_models

            build_landmark_models(force=args.force)
        if args.hands:
            from mocapd.io.hand_model_build import build_hand_models

            build_hand_models(force=args.force)
    except MocapdError as exc:
        print(f"mocapd model fetch: {exc}")
        return 1
    return 0


def register(subparsers: Any) -> None:
    """Add ``model fetch`` to the CLI's subcommands."""
    p = subparsers.add_parser("model", help="detector models")
    sub = p.add_subparsers(dest="model_command", metavar="ACTION", required=True)
    f = sub.add_parser("fetch", help="build the default YOLO11n-pose ONNX model into the cache (AGPL-3.0 weights)")
    f.add_argument(
        "--size",
        type=_parse_size,
        action="append",
        help="input size N or WxH (repeatable; default 640, 384x640, 640x384)",
    )
    f.add_argument("--force", action="store_true", help="rebuild even when the cached model is current")
    f.add_argument(
        "--int8",
        action="store_true",
        help="also build the INT8 model beside each FP32 one (static quantization calibrated on the Pose2Sim demo)",
    )
    f.add_argument(
        "--landmarks",
        action="store_true",
        help="also fetch the BlazePose landmark models (heavy, full; Apache-2.0) from the npm package @mediapipe/pose",
    )
    f.add_argument(
        "--hands",
        action="store_true",
        help="also fetch the hand landmark models (full, lite; Apache-2.0) from the npm package @mediapipe/hands",
    )
    f.set_defaults(func=_fetch)

"""Calibrate keypoint track-target offsets t_pb (seed 003 §3.3.2) and write the offsets file the solver reads.

Input: one ``.npz`` file with

==============  ==============================  =================================================
array           shape                           meaning
==============  ==============================  =================================================
``P``           (n_cams, 3, 4)                  projection matrices (undistorted pixels)
``keypoints``   (n_frames, n_cams, n_kp, 3)     the subject's detections: x, y (px), confidence
``bone_rot``    (n_frames, 21, 3, 3)            reference bone rotations (bone → world)
``bone_pos``    (n_frames, 21, 3)               reference bone origins (metres, world)
==============  ==============================  =================================================

Bones are in DESIGN.md's order; ``n_kp`` must match ``--format``. Output: the JSON offsets file described in
:mod:`mocapd.core.offset_calibration`; a summary (per keypoint: frames used, offset, MAD) goes to stdout.

    .venv/bin/python tools/calibrate_offsets.py session.npz --format coco17 --out offsets.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from mocapd.core.keypoints import keypoint_format
from mocapd.core.offset_calibration import calibrate_offsets, offsets_to_json
from mocapd.core.skeleton import BONE_INDEX
from mocapd.errors import MocapdError


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("inputs", type=Path, help=".npz with P, keypoints, bone_rot, bone_pos")
    ap.add_argument("--format", default="coco17", help="keypoint format of the detections")
    ap.add_argument("--out", type=Path, required=True, help="offsets JSON file to write")
    ap.add_argument("--min-confidence", type=float, default=0.3)
    args = ap.parse_args(argv)
    try:
        fmt = keypoint_format(args.format)
        with np.load(args.inputs) as data:
            missing = {"P", "keypoints", "bone_rot", "bone_pos"} - set(data.files)
            if missing:
                raise MocapdError(f"{args.inputs} lacks arrays {sorted(missing)}")
            bones = [BONE_INDEX[fmt.targets[k].bone] if k in fmt.targets else -1 for k in fmt.keypoints]
            est = calibrate_offsets(
                data["P"], data["keypoints"], data["bone_rot"], data["bone_pos"], bones,
                min_confidence=args.min_confidence,
            )  # fmt: skip
    except (MocapdError, OSError, ValueError) as exc:
        print(f"calibrate_offsets: {exc}", file=sys.stderr)
        return 1
    args.out.write_text(offsets_to_json(fmt, est), encoding="utf-8")
    summary = {
        name: {
            "frames": int(est.frames[k]),
            "offset_m": est.offsets[k].round(4).tolist(),
            "mad_m": est.mad[k].round(4).tolist(),
        }
        for k, name in enumerate(fmt.keypoints)
    }
    json.dump({"written": str(args.out), "keypoints": summary}, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())

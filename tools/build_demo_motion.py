#!/usr/bin/env python3
"""Build the recorded motion the synthetic rig plays (``mocapd/data/demo_motion_cmu.npz`` + ``.json``).

The synthetic rig of ``mocapd demo --synthetic`` and ``mocapd bench latency`` moves its people with real recorded
motion: CMU subject 02 clips of the ``prior`` split (``mocapd/data/eval_splits.toml``; CMU's terms allow shipping a
derived artefact, MANIFEST.md), retargeted onto the 21-bone skeleton at 60 Hz. Only in-place clips are used
(punching, swordplay, jumping: the root stays within ~0.4 m) so people placed around the volume never walk into
each other; each clip is turned to face +Z on average and centred on the origin. The demo's joint error is not an
accuracy measurement (the prior was trained on these clips; ``mocapd eval accuracy`` is).

Usage: ``.venv/bin/python tools/build_demo_motion.py [--data-root ../shared/data] [--seconds 12]``
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np

from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import matrix_from_rotvec, rotvec_from_matrix
from mocapd.eval.data import default_data_root, load_clip

#: (clip, what it is) — in the order people are assigned to them.
CLIPS = (
    ("mocap/cmu/asfamc/02_05.amc", "punching, boxing"),
    ("mocap/cmu/asfamc/02_07.amc", "swordplay"),
    ("mocap/cmu/asfamc/02_06.amc", "punching, boxing"),
    ("mocap/cmu/asfamc/02_08.amc", "swordplay"),
)
OUT = Path(__file__).resolve().parents[1] / "mocapd/data/demo_motion_cmu.npz"


def _face_forward(theta: np.ndarray) -> np.ndarray:
    """Turn the clip about +Y so its mean heading is +Z and centre its root on the origin (x, z)."""
    R0 = matrix_from_rotvec(theta[:, 3:6])
    fwd = R0[:, :, 2]  # the root's +Z axis (the rest pose faces +Z)
    heading = float(np.arctan2(fwd[:, 0].mean(), fwd[:, 2].mean()))
    c, s = np.cos(-heading), np.sin(-heading)
    Ry = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    out = theta.copy()
    out[:, 3:6] = rotvec_from_matrix(Ry @ R0)
    out[:, :3] = theta[:, :3] @ Ry.T
    out[:, [0, 2]] -= out[:, [0, 2]].mean(axis=0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data-root", type=Path, default=None)
    ap.add_argument("--seconds", type=float, default=12.0, help="length kept of each clip")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    root = args.data_root or default_data_root()
    arrays: dict[str, np.ndarray] = {}
    sources = []
    skeleton = None
    for i, (rel, what) in enumerate(CLIPS):
        clip = load_clip(root / rel)  # 60 Hz
        n = min(clip.n_frames, int(args.seconds * clip.fps) + 1)
        theta = _face_forward(clip.theta[:n])
        angle = np.linalg.norm(theta[:, 3:6], axis=1)
        if angle.max() > 0.9 * np.pi:  # the world interpolates rotation vectors: keep away from the π flip
            raise SystemExit(f"{rel}: root turns to {np.degrees(angle.max()):.0f}°, too close to 180°")
        if skeleton is None:
            skeleton = clip.skeleton
        arrays[f"theta_{i}"] = theta.astype(np.float32)
        pos = Kinematics(clip.skeleton).forward(theta).positions
        digest = hashlib.sha256((root / rel).read_bytes()).hexdigest()
        sources.append({
            "path": rel, "what": what, "frames": int(n), "sha256": digest,
            "root_travel_m": [round(float(v), 3) for v in np.ptp(theta[:, [0, 2]], axis=0)],
            "lowest_joint_m": round(float(pos[..., 1].min()), 3),
        })  # fmt: skip
    assert skeleton is not None
    arrays["offsets"] = skeleton.offsets
    arrays["root_height"] = np.array(skeleton.root_height)
    arrays["fps"] = np.array(60.0)
    np.savez_compressed(args.out, allow_pickle=False, **arrays)
    meta = {
        "what": "recorded motion for the synthetic rig (θ at 60 Hz on the 21-bone skeleton, float32)",
        "licence": "CMU Graphics Lab Motion Capture Database terms: free for research and commercial use",
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "tool": "tools/build_demo_motion.py",
        "sources": sources,
    }
    args.out.with_suffix(".json").write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    print(json.dumps({"out": str(args.out), "bytes": args.out.stat().st_size, "sources": sources}, indent=2))


if __name__ == "__main__":
    main()

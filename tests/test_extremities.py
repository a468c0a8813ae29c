"""Camera-only orientation of the feet, toes and hands on the synthetic rig (issue 40): BlazePose's heel, toe,
pinky, index and thumb points observe them (at most 15° median), COCO-17's do not."""

from __future__ import annotations

import numpy as np

from mocapd.core.keypoints import BLAZEPOSE33_FORMAT, keypoint_format
from mocapd.eval.data import default_data_root, load_clip
from mocapd.eval.extremities import TARGET_DEG, ExtremityOptions, extremity_orientation
from mocapd.eval.harness import windows
from mocapd.eval.simulate import DetectionNoise, simulate_detections, totalcapture_ring
from mocapd.io.prior import resolve_prior


def test_blazepose_points_bound_the_foot_and_hand_orientation_camera_only() -> None:
    opts = ExtremityOptions(split="quick", max_frames=90, max_sequences=2)
    out = extremity_orientation(opts, resolve_prior("default"))
    bp, coco = out["blazepose33"], out["coco17"]
    assert out["frames"] > 150
    for part in ("Foot", "Hand"):
        assert bp[part]["median"] <= TARGET_DEG, (part, bp[part])
        assert coco[part]["median"] > 1.3 * bp[part]["median"], (part, coco[part], bp[part])  # unobserved there
    assert bp["Toes"]["median"] <= 20.0  # the toe's twist has no point: a little above


def test_a_simulated_swap_exchanges_a_whole_limb_of_any_keypoint_set() -> None:
    # The swap model once took COCO-17's columns for every set: in BlazePose's 33 it swapped eye corners.
    clip = windows(load_clip(default_data_root() / "mocap/cmu/131_03.bvh"))[0]
    targets = keypoint_format("blazepose33").track_targets(clip.skeleton)
    cams = totalcapture_ring(1)
    clean = DetectionNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, False, False)
    swapped = DetectionNoise(0.0, 0.0, 0.0, 0.0, 1.0, 0.0, False, False)
    uv0, _ = simulate_detections(clip, cams, targets, clean, np.random.default_rng(1))
    uv1, _ = simulate_detections(clip, cams, targets, swapped, np.random.default_rng(1))
    names = targets.names
    moved = {names[k] for k in np.flatnonzero(np.any(np.abs(uv1 - uv0) > 1e-9, axis=(0, 1, 3)))}
    arm = {f"{s}_{p}" for s in ("left", "right") for p in ("shoulder", "elbow", "wrist", "pinky", "index", "thumb")}
    leg = {f"{s}_{p}" for s in ("left", "right") for p in ("hip", "knee", "ankle", "heel", "foot_index")}
    assert moved == arm | leg
    assert set(BLAZEPOSE33_FORMAT.keypoints) - moved >= {"nose", "left_eye_inner", "right_eye_outer"}

"""Keypoint offset calibration (seed 003 §3.3.2) on synthetic scenes with known offsets."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.camera import look_at, triangulate_projections
from mocapd.core.keypoints import COCO17_FORMAT as COCO17
from mocapd.core.offset_calibration import (
    calibrate_offsets,
    offsets_from_json,
    offsets_to_json,
    project,
    to_bone_space,
)
from mocapd.core.rotations import matrix_from_rotvec, random_rotvec
from mocapd.core.skeleton import BONE_NAMES
from mocapd.errors import CalibrationError, InputError


def _rig(n: int = 4) -> np.ndarray:
    Ps = []
    for k in range(n):
        a = 2 * np.pi * k / n + 0.3
        cam = look_at(f"c{k}", np.array([4 * np.sin(a), 1.8, 4 * np.cos(a)]), np.array([0, 1.0, 0]), 1088, 1920, 1600)
        Ps.append(cam.K @ np.hstack([cam.R, cam.t[:, None]]))
    return np.stack(Ps)


def triangulate_weighted(P: np.ndarray, uv: np.ndarray, w: np.ndarray) -> np.ndarray:
    """One point through the core DLT the calibration uses: uv (n_cams, 2), w (n_cams,) → (3,)."""
    X, _ = triangulate_projections(P, uv[:, None], w[:, None])
    point: np.ndarray = X[0]
    return point


def test_triangulate_weighted_is_exact_on_clean_views_and_ignores_zero_weight() -> None:
    P = _rig()
    X = np.array([0.2, 1.3, -0.1])
    uv = project(P, X)
    np.testing.assert_allclose(triangulate_weighted(P, uv, np.ones(4)), X, atol=1e-9)
    bad = uv.copy()
    bad[2] += 300.0  # a wild view with zero confidence must not matter
    np.testing.assert_allclose(triangulate_weighted(P, bad, np.array([1, 1, 0, 1.0])), X, atol=1e-9)
    # A low-weight outlier pulls the point much less than a full-weight one.
    lo = np.linalg.norm(triangulate_weighted(P, bad, np.array([1, 1, 0.05, 1.0])) - X)
    hi = np.linalg.norm(triangulate_weighted(P, bad, np.ones(4)) - X)
    assert lo < 0.2 * hi
    assert np.all(np.isnan(triangulate_weighted(P, uv, np.array([1.0, 0, 0, 0]))))
    with pytest.raises(InputError):
        triangulate_weighted(P, uv[:3], np.ones(4))


def test_to_bone_space_inverts_the_bone_pose() -> None:
    rng = np.random.default_rng(0)
    R = matrix_from_rotvec(random_rotvec(rng, (5,)))
    p = rng.normal(size=(5, 3))
    local = rng.normal(size=(5, 3)) * 0.1
    world = np.einsum("nij,nj->ni", R, local) + p
    np.testing.assert_allclose(to_bone_space(world, R, p), local, atol=1e-12)


def _scene(rng: np.random.Generator, n_frames: int, outlier_rate: float) -> tuple[np.ndarray, ...]:
    P = _rig()
    n_b = len(BONE_NAMES)
    bones = [BONE_NAMES.index(COCO17.targets[k].bone) for k in COCO17.keypoints]
    true_off = rng.uniform(-0.06, 0.06, (17, 3))
    R = matrix_from_rotvec(random_rotvec(rng, (n_frames, n_b)))
    pos = rng.uniform([-0.5, 0.2, -0.5], [0.5, 1.7, 0.5], (n_frames, n_b, 3))
    kp = np.zeros((n_frames, 4, 17, 3))
    for f in range(n_frames):
        X = np.einsum("kij,kj->ki", R[f, bones], true_off) + pos[f, bones]
        uv = project(P, X)  # (4, 17, 2)
        kp[f, :, :, :2] = uv + rng.normal(0, 2.0, uv.shape)
        kp[f, :, :, 2] = rng.uniform(0.5, 1.0, (4, 17))
        wild = rng.uniform(size=(4, 17)) < outlier_rate
        kp[f, :, :, :2][wild] += rng.uniform(-400, 400, (int(wild.sum()), 2))
    kp[0, :, 3, 2] = 0.0  # left ear unseen in frame 0
    kp[1, 1:, 4, 2] = 0.1  # right ear seen by one camera only (others below threshold) in frame 1
    return P, kp, R, pos, np.array(bones), true_off


def test_calibrate_offsets_recovers_known_offsets_despite_outliers() -> None:
    rng = np.random.default_rng(7)
    P, kp, R, pos, bones, true_off = _scene(rng, 60, outlier_rate=0.08)
    est = calibrate_offsets(P, kp, R, pos, bones.tolist(), min_confidence=0.3)
    np.testing.assert_allclose(est.offsets, true_off, atol=0.012)  # 2 px noise at ~4 m, 8 % wild views
    assert est.frames[3] == 59 and est.frames[4] == 59 and est.frames[0] == 60
    assert np.all(est.mad < 0.05)


def test_calibrate_offsets_skips_unattached_keypoints_and_checks_shapes() -> None:
    rng = np.random.default_rng(8)
    P, kp, R, pos, bones, _ = _scene(rng, 5, outlier_rate=0.0)
    skip = bones.tolist()
    skip[0] = -1
    est = calibrate_offsets(P, kp, R, pos, skip)
    assert est.frames[0] == 0 and np.all(np.isnan(est.offsets[0]))
    with pytest.raises(InputError):
        calibrate_offsets(P, kp[:, :3], R, pos, bones.tolist())
    with pytest.raises(InputError):
        calibrate_offsets(P, kp, R[:4], pos, bones.tolist())
    with pytest.raises(InputError):
        calibrate_offsets(P, kp, R, pos, bones.tolist()[:16])


def test_offsets_file_round_trip_and_validation() -> None:
    rng = np.random.default_rng(9)
    P, kp, R, pos, bones, _ = _scene(rng, 10, outlier_rate=0.0)
    est = calibrate_offsets(P, kp, R, pos, bones.tolist())
    text = offsets_to_json(COCO17, est)
    targets = offsets_from_json(text, COCO17)
    assert set(targets) == set(COCO17.keypoints)
    for k, name in enumerate(COCO17.keypoints):
        assert targets[name].bone == COCO17.targets[name].bone
        np.testing.assert_allclose(targets[name].offset, est.offsets[k], atol=1e-5)
    doc = json.loads(text)
    assert doc["format"] == "mocapd-keypoint-offsets" and doc["version"] == 1 and doc["units"] == "m"
    for bad, msg in [
        ("not json", "not JSON"),
        (json.dumps({**doc, "format": "x"}), "not a"),
        (json.dumps({**doc, "version": 2}), "version"),
        (json.dumps({**doc, "keypoint_format": "body25"}), "body25"),
        (json.dumps({**doc, "targets": {"tail": doc["targets"]["nose"]}}), "tail"),
        (json.dumps({**doc, "targets": {"nose": {**doc["targets"]["nose"], "bone": "Tail"}}}), "bone"),
        (json.dumps({**doc, "targets": {"nose": {**doc["targets"]["nose"], "offset": [0, "a", 0]}}}), "offset"),
    ]:
        with pytest.raises(CalibrationError, match=msg):
            offsets_from_json(bad, COCO17)


def test_calibrate_offsets_tool_writes_the_offsets_file(tmp_path: Path) -> None:
    rng = np.random.default_rng(10)
    P, kp, R, pos, _, true_off = _scene(rng, 30, outlier_rate=0.05)
    npz = tmp_path / "session.npz"
    np.savez(npz, P=P, keypoints=kp, bone_rot=R, bone_pos=pos)
    out = tmp_path / "offsets.json"
    tool = Path(__file__).resolve().parents[1] / "tools" / "calibrate_offsets.py"
    proc = subprocess.run(
        [sys.executable, str(tool), str(npz), "--out", str(out)], capture_output=True, text=True, check=False
    )
    assert proc.returncode == 0, proc.stderr
    targets = offsets_from_json(out.read_text(), COCO17)
    for k, name in enumerate(COCO17.keypoints):
        np.testing.assert_allclose(targets[name].offset, true_off[k], atol=0.015)
    assert json.loads(proc.stdout)["keypoints"]["nose"]["frames"] == 30
    bad = tmp_path / "bad.npz"
    np.savez(bad, P=P)
    proc = subprocess.run(
        [sys.executable, str(tool), str(bad), "--out", str(out)], capture_output=True, text=True, check=False
    )
    assert proc.returncode == 1 and "lacks arrays" in proc.stderr

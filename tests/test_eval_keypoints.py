"""``mocapd eval keypoints``: the multi-person benchmark (recorded motion, a Shelf-like rig, a detector's errors)
through ``import keypoints`` and ``resolve``, and its scoring."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.keypoints import BODY25_FORMAT
from mocapd.eval.keypoint_bench import LIMBS, MIN_APART_M, Estimates, Noise, build_scene, detect, score, visible
from mocapd.service.cli import main

NAMES = BODY25_FORMAT.keypoints


def _truth(n_frames: int) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [np.add(rng.uniform(-1, 1, (n_frames, len(NAMES), 3)), (2.0 * a, 1.0, 0.0)) for a in range(2)]


def test_scoring_counts_what_the_protocol_says() -> None:
    """A perfect track scores 100 PCP and 0 mm; a missing frame is a miss and every limb wrong; an identity that
    follows nobody is a false-positive track; a second identity on the same actor is a switch."""
    truth = _truth(10)
    vis = np.ones((10, 2), dtype=bool)
    frames = [[("a", truth[0][f]), ("b", truth[1][f] + 0.01)] for f in range(10)]
    s = score(truth, Estimates(frames), vis, NAMES, LIMBS)
    assert s["pcp_average"] == 100.0 and s["misses"] == 0 and s["false_positive_tracks"] == 0
    assert s["actors"][0]["mpjpe_mm"] == 0.0 and s["actors"][1]["mpjpe_mm"] == pytest.approx(17.3, abs=0.1)
    frames[0] = [("b", truth[1][0])]  # actor 1 missed in its first frame
    frames[9] = [("a", truth[0][9] + 5.0), ("b", truth[1][9])]  # 5 m away: no match
    for f in range(5, 9):
        frames[f] = [("c", truth[0][f]), ("b", truth[1][f]), ("ghost", truth[0][f] + 3.0)]
    s = score(truth, Estimates(frames), vis, NAMES, LIMBS)
    a1 = s["actors"][0]
    assert a1["misses"] == 2 and a1["misses_after_first_0.2s"] == 1 and a1["pcp"] == 80.0
    assert a1["first_published_s"] == pytest.approx(0.04) and a1["identity_switches"] == 1  # a -> c
    assert s["tracks"] == 4 and s["false_positive_tracks"] == 1  # "ghost"; "a" matched 4 of its 5 frames
    s = score(truth, Estimates(frames), np.zeros((10, 2), dtype=bool), NAMES, LIMBS)
    assert s["misses"] == 0  # an actor seen by fewer than 2 cameras is not to be found


def test_detector_errors_are_there() -> None:
    """The simulated detector flips views, hides keypoints behind nearer people and adds false positives."""
    scene = build_scene(3, 2.0)
    det = detect(scene, Noise(flip_p=0.1, false_positive_p=0.3), seed=1)
    assert det.flips > 0 and det.occluded > 0 and det.false_positives > 0
    labels = [lb for frame in det.labels for lb in frame]
    assert sum(int(np.sum(lb == -1)) for lb in labels) == det.false_positives
    assert visible(det, 3).mean() > 0.9


def test_eval_keypoints_through_import_and_resolve(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two people, 2 s: OpenPose folders + calibration -> ``import keypoints`` -> ``resolve``. Each person is one
    track published within 0.2 s (the evidence rule of ``[tracking.enrolment]``; the former fixed second missed every
    frame of a person's first second), no false-positive track, no identity switch; Pose2Sim scored beside them on
    the same files (the old evaluation had no Pose2Sim row)."""
    out = tmp_path / "bench"
    assert main(["eval", "keypoints", "--people", "2", "--seconds", "2", "--out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    report = json.loads((out / "keypoints.json").read_text())
    assert printed["systems"]["mocapd resolve"]["pcp_average"] == report["systems"]["mocapd resolve"]["pcp_average"]
    assert printed["commands"] == report["commands"] and printed["commands"][0].startswith("mocapd import keypoints")
    assert sorted(p.name for p in (out / "input" / "openpose").iterdir()) == [f"cam{i}_json" for i in range(1, 6)]
    assert "| mocapd resolve |" in (out / "keypoints.md").read_text()
    for name in ("mocapd forward (live scheduler)", "mocapd resolve"):
        s = report["systems"][name]
        assert s["tracks"] == 2 and s["false_positive_tracks"] == 0 and s["identity_switches"] == 0, s
        assert s["misses_after_first_0.2s"] == 0, s
        assert all(a["first_published_s"] <= 0.2 for a in s["actors"]), s
        assert s["pcp_average"] >= 85.0 and s["mpjpe_mm"] < 45.0, s
    assert report["systems"]["DLT, truth-associated views"]["misses"] == 0
    # Pose2Sim (installed by the set-up, never skipped) on the same OpenPose folders and calibration: its own
    # association finds both people, in mocapd's world (a wrong axis or unit would put every limb off).
    assert report["benchmark"]["pose2sim"] == "0.10.49" and printed["pose2sim"] == "0.10.49"
    p2s = report["systems"]["Pose2Sim (its association, triangulation, filter)"]
    assert p2s["tracks"] >= 2 and p2s["pcp_average"] >= 80.0 and p2s["mpjpe_mm"] < 60.0, p2s
    assert (out / "pose2sim" / "Calib.toml").is_file() and "| Pose2Sim (its association" in (
        out / "keypoints.md"
    ).read_text()
    assert main(["eval", "keypoints", "--people", "5", "--out", str(tmp_path / "x")]) == 2
    assert "--people 5" in capsys.readouterr().err


def test_people_never_stand_inside_each_other() -> None:
    """Every pair of the 4 people keeps its hips at least MIN_APART_M apart in every frame (at the former fourth
    place the walk went through the bow: hips 0.10 m apart, two bodies in one place, and the 4-person run's identity
    switches were all there)."""
    scene = build_scene(4, 10.0)
    hips = [np.asarray(j)[:, 0][:, [0, 2]] for j in scene.joints]
    for a in range(4):
        for b in range(a + 1, 4):
            closest = float(np.linalg.norm(hips[a] - hips[b], axis=1).min())
            assert closest >= MIN_APART_M, (a + 1, b + 1, closest)

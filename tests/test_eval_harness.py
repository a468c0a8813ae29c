"""The accuracy harness end to end on a few short sequences (a smaller `mocapd eval accuracy --quick`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.imu import IMU_SET_13
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import BONE_INDEX
from mocapd.core.terms import CostOptions
from mocapd.eval.baselines import robust_triangulate
from mocapd.eval.data import default_data_root, load_clip
from mocapd.eval.harness import RunConfig, make_sequence, run_imu_only, run_solver, windows
from mocapd.eval.simulate import DetectionNoise, ImuNoise, totalcapture_ring
from mocapd.io.prior import load_default_prior
from mocapd.service.cli import main
from mocapd.service.config import load_config


def test_windows_stay_in_the_volume() -> None:
    clip = load_clip(default_data_root() / "mocap/bandai/dataset-1_walk_angry_001.bvh")
    ws = windows(clip)
    assert len(ws) >= 2
    for w in ws:
        r = np.linalg.norm(w.theta[:, [0, 2]], axis=1)
        assert r.max() < 2.0
        assert w.n_frames >= 60
        np.testing.assert_allclose(Kinematics(w.skeleton).forward(w.theta[:3]).positions, w.positions[:3], atol=1e-9)


def test_robust_triangulation_rejects_an_outlier_view() -> None:
    cams = totalcapture_ring()
    X = np.array([[0.1, 1.2, 0.3], [0.0, 0.5, 0.0]])
    uv = np.stack([c.project(X) for c in cams])
    uv[2, 0] += [200.0, -150.0]  # one gross outlier
    kp, ok = robust_triangulate(cams, uv, np.ones((8, 2)), np.full(8, 500.0))
    assert ok.all()
    np.testing.assert_allclose(kp, X, atol=1e-6)


def test_clean_inputs_solve_accurately_and_imu_fk_is_exact() -> None:
    clip = windows(load_clip(default_data_root() / "mocap/cmu/131_03.bvh"))[0]
    seq = make_sequence(clip, 0, DetectionNoise.clean(), ImuNoise.clean())
    theta, bad = run_solver(seq, RunConfig(8, 13), load_default_prior(), CostOptions())
    assert bad == 0
    err = np.linalg.norm(Kinematics(clip.skeleton).forward(theta).positions - clip.positions, axis=-1)
    assert err.mean() < 0.015
    imu = Kinematics(clip.skeleton).forward(run_imu_only(seq, 13))
    b = [BONE_INDEX[n] for n in IMU_SET_13]  # the bones with an IMU take its (clean) orientation exactly
    np.testing.assert_allclose(imu.rotations[:, b], clip.rotations[:, b], atol=1e-6)


# The quick split with the shipped config.toml weights (what `mocapd eval accuracy --quick` runs), through the
# command line. Its main table is the whole quick run's (--sweep-frames only shortens the sweep, ablation and
# sub-sampling); measured over noise seeds 0-4 (docs/accuracy.md, "What CI asserts"): ratio to triangulation
# 0.29-0.34 (8 cams + 13 IMUs) and 0.38-0.42 (4 cams + 6 IMUs), orientation 6.6-7.1 deg.
QUICK_RATIO_MAX = 0.5
QUICK_ORIENTATION_MAX_DEG = 8.0


def test_quick_run_with_the_shipped_weights_beats_triangulation(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "quick"
    assert main(["eval", "accuracy", "--quick", "--sweep-frames", "20", "--no-progress", "--out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    for name in ("results.json", "tables.md", "sweep.png", "subsampling.png"):
        assert (out / name).stat().st_size > 100
    data = json.loads((out / "results.json").read_text())
    assert printed["targets"] == data["targets"] and printed["setup"]["split"] == data["setup"]["split"] == "quick"
    assert data["setup"]["cost"] == "[solver] of the shipped config.toml" and len(data["setup"]["sequences"]) == 4
    assert load_config().solver.cost != CostOptions.seed_003()  # the shipped weights, not the seed's (which lose)
    t = data["targets"]
    assert t["8c13i_vs_triangulation_8c_global_mean_ratio"] <= QUICK_RATIO_MAX, t
    assert t["4c6i_vs_triangulation_4c_global_mean_ratio"] <= QUICK_RATIO_MAX, t
    assert t["8c13i_orientation_mean_deg"] <= QUICK_ORIENTATION_MAX_DEG, t
    assert all(t["met"].values()), t
    main_ = data["main"]
    assert all(r["nonfinite_frames"] == 0 for r in main_.values())
    # Every sweep configuration returns finite poses on every frame, monocular and IMU-only included.
    assert len(data["sweep"]) == 15 and all(r["nonfinite_frames"] == 0 for r in data["sweep"].values())
    # Without the position term the global position is lost.
    assert data["ablation"]["relative"]["without position"]["global_mm"]["mean"] > 2.0


def test_cli_has_eval(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["eval", "accuracy", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "usage: mocapd eval accuracy" in text and "--quick" in text and "--config" in text

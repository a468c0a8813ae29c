"""The accuracy harness end to end on a few short sequences (a smaller `mocapd eval accuracy --quick`)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from mocapd.core.imu import IMU_SET_13
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import BONE_INDEX
from mocapd.core.terms import CostOptions
from mocapd.eval.baselines import robust_triangulate
from mocapd.eval.data import default_data_root, load_clip
from mocapd.eval.harness import RunConfig, make_sequence, run_imu_only, run_solver, windows
from mocapd.eval.runner import EvalOptions, run_eval
from mocapd.eval.simulate import DetectionNoise, ImuNoise, totalcapture_ring
from mocapd.io.prior import load_default_prior
from mocapd.service.cli import main


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


def test_quick_run_writes_results(tmp_path: Path) -> None:
    opts = replace(
        EvalOptions.quick(),
        max_frames=100,
        sweep_frames=40,
        sweep_cams=(0, 1, 2, 8),
        max_sequences=2,
        progress=False,
    )
    res = run_eval(opts, tmp_path)
    for name in ("results.json", "tables.md", "sweep.png", "subsampling.png"):
        assert (tmp_path / name).stat().st_size > 100
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["setup"]["split"] == "quick"
    # Every configuration returns finite poses on every frame, monocular and IMU-only included.
    assert all(r["nonfinite_frames"] == 0 for r in data["sweep"].values())
    assert len(data["sweep"]) == 12
    main_ = res["main"]
    assert main_["solver 8 cams + 13 IMUs"]["global_mm"]["mean"] < 150
    # Without the position term the global position is lost.
    assert res["ablation"]["relative"]["without position"]["global_mm"]["mean"] > 2.0


def test_cli_has_eval() -> None:
    try:
        main(["eval", "accuracy", "--help"])
    except SystemExit as exc:
        assert exc.code == 0

"""The learned fusion (issue 30): the PVH and its channels, the mattes, a small training run through the simulator,
its ONNX export run by onnxruntime, the runtime's streaming windows against the training's, and the shipped
networks' provenance."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.fusion_features import imu_windows, vision_windows, window_index
from mocapd.core.keypoints import coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.pvh import MATTE, PvhGrid, carve, joint_map, log_channels, person_centre, scaled_pixels
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.errors import ModelError
from mocapd.eval.data import load_splits
from mocapd.eval.fusion_data import training_clips
from mocapd.eval.simulate import totalcapture_ring
from mocapd.pipeline.frame_ring import FrameRing
from mocapd.pipeline.fusion import (
    PROVENANCE_FILE,
    FusionModels,
    PersonFusion,
    available_variants,
    reference_provenance,
)
from mocapd.pipeline.mattes import BackgroundMatte, FrameMattes, RingMattes
from mocapd.sim.silhouettes import MatteNoise, proxy_shapes, render_silhouette, simulated_matte


def _pose() -> tuple[Skeleton, np.ndarray]:
    """A standing person at (0.3, _, -0.2), arms down-ish (rest pose turned a little)."""
    sk = Skeleton.from_height(1.75)
    theta = sk.rest_pose()
    theta[0], theta[2] = 0.3, -0.2
    theta[3:6] = [0.0, 0.4, 0.0]
    return sk, Kinematics(sk).forward(theta).positions


def _hull(cams_idx: list[int], grid: PvhGrid, drop_view: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    sk, joints = _pose()
    ring = totalcapture_ring(8)
    cams = [ring[i] for i in cams_idx]
    targets = coco17_targets(sk)
    kin = Kinematics(sk)
    theta = sk.rest_pose()
    theta[0], theta[2] = 0.3, -0.2
    theta[3:6] = [0.0, 0.4, 0.0]
    kp = kin.targets(kin.forward(theta), targets.bones, targets.offsets)
    centre = person_centre(cams, np.stack([c.project(kp) for c in cams]), np.ones((len(cams), 17)), fallback=None)
    assert centre is not None
    imgs = []
    valid = np.ones((len(cams), 2), dtype=bool)
    for c, cam in enumerate(cams):
        m = simulated_matte(cam, [(joints, sk.height)], grid.scale, MatteNoise.clean(), np.random.default_rng(0))
        if c == drop_view:
            m = np.zeros_like(m)  # a failed matte: marked invalid below, it must not carve
            valid[c, MATTE] = False
        jm = joint_map(scaled_pixels(cam.project(kp), grid.scale), np.ones(17), m.shape, 1.5)
        imgs.append(log_channels(np.stack((m, jm))))
    return carve(grid, centre, cams, imgs, valid), centre


def _voxel(grid: PvhGrid, centre: np.ndarray, x: np.ndarray) -> tuple[int, int, int]:
    i = np.floor((x - centre + grid.extent / 2) / grid.voxel).astype(int)
    return int(i[0]), int(i[1]), int(i[2])


def test_pvh_carves_the_body_and_marks_its_joints() -> None:
    grid = PvhGrid()
    vol, centre = _hull(list(range(8)), grid)
    assert vol.shape == (2, 30, 30, 30) and vol.dtype == np.float32
    _, joints = _pose()
    chest = joints[BONE_INDEX["Spine2"]]
    assert vol[MATTE][_voxel(grid, centre, chest)] > 0.9
    beside = chest + np.array([0.6, 0.0, 0.6])  # beside the body: carved away by the views that see it
    assert vol[MATTE][_voxel(grid, centre, beside)] < 0.1
    # Occupied volume of a 1.75 m person: tens of litres, not the cube's 8 m³.
    occupied = float((vol[MATTE] > 0.5).sum()) * grid.voxel**3
    assert 0.04 < occupied < 0.25, occupied
    # Joint channel: a keypoint's voxel (the left wrist is a keypoint with no offset) is high, the chest is not.
    # (The voxel centres lie up to half a 67 mm voxel from the keypoint: the neighbourhood's peak.)
    i, j, k = _voxel(grid, centre, joints[BONE_INDEX["LeftHand"]])
    assert vol[1][i - 1 : i + 2, j - 1 : j + 2, k - 1 : k + 2].max() > 0.5
    assert vol[1][_voxel(grid, centre, chest)] < 0.3


def test_pvh_geometric_mean_keeps_camera_counts_comparable_and_skips_invalid_views() -> None:
    grid = PvhGrid()
    v8, _ = _hull(list(range(8)), grid)
    v4, _ = _hull([0, 1, 2, 3], grid)
    body = v8[MATTE] > 0.9
    assert np.all(v4[MATTE][body] > 0.8)  # the body stays as strong with half the views
    dropped, _ = _hull(list(range(8)), grid, drop_view=3)
    assert np.all(dropped[MATTE][body] > 0.8)  # an invalid (zero) matte is left out, not multiplied in


def test_supersampled_carving_averages_fine_voxels() -> None:
    coarse, _ = _hull(list(range(8)), PvhGrid(size=15, extent=2.0, supersample=1))
    fine, _ = _hull(list(range(8)), PvhGrid(size=15, extent=2.0, supersample=2))
    assert coarse.shape == fine.shape == (2, 15, 15, 15)
    # Averaging 8 fine voxels softens the boundary: fewer voxels at exactly 0 or 1, same occupied volume.
    assert abs(float(fine[MATTE].sum()) - float(coarse[MATTE].sum())) < 0.25 * float(coarse[MATTE].sum())


def test_joint_map_renders_confidences_over_a_floor() -> None:
    uv = np.array([[10.0, 20.0], [40.0, 5.0], [np.nan, np.nan]])
    m = joint_map(uv, np.array([0.8, 0.0, 1.0]), (30, 60), 1.5, floor=0.1)
    assert m.shape == (30, 60)
    assert m[20, 10] == pytest.approx(0.1 + 0.9 * 0.8, abs=1e-5)
    assert m[5, 40] == pytest.approx(0.1)  # confidence 0: not rendered
    assert m.min() == pytest.approx(0.1)


def test_person_centre_is_the_triangulated_hip_midpoint() -> None:
    sk, _ = _pose()
    cams = totalcapture_ring(4)
    targets = coco17_targets(sk)
    kin = Kinematics(sk)
    theta = sk.rest_pose()
    theta[0], theta[2] = 0.3, -0.2
    kp = kin.targets(kin.forward(theta), targets.bones, targets.offsets)
    uv = np.stack([c.project(kp) for c in cams])
    c = person_centre(cams, uv, np.ones((4, 17)))
    assert c is not None
    assert np.linalg.norm(c - kp[[11, 12]].mean(axis=0)) < 1e-6
    fallback = np.array([1.0, 1.0, 1.0])
    held = person_centre(cams, uv, np.zeros((4, 17)), fallback)
    assert held is not None and np.array_equal(held, fallback)
    assert person_centre(cams, uv, np.zeros((4, 17))) is None


def test_proxy_silhouette_covers_the_body_not_the_background() -> None:
    sk, joints = _pose()
    cam = totalcapture_ring(8)[2]
    sil = render_silhouette(cam, [proxy_shapes(joints, sk.height)], 8)
    assert sil.shape == (135, 240)
    u, v = scaled_pixels(cam.project(joints[BONE_INDEX["Spine2"]][None])[0], 8)
    assert sil[round(v), round(u)] == 1.0
    assert 0.005 < sil.mean() < 0.1  # a person 4.5 m away: a few percent of the frame
    noisy = simulated_matte(cam, [(joints, sk.height)], 8, MatteNoise(), np.random.default_rng(1))
    assert noisy.shape == sil.shape and noisy.min() >= 0.0 and noisy.max() <= 1.0


def test_background_matte_finds_a_moving_object() -> None:
    rng = np.random.default_rng(0)
    bg = rng.integers(60, 90, size=(240, 320, 3), dtype=np.uint8)
    bm = BackgroundMatte(scale=4)
    for _ in range(30):
        bm.apply(np.clip(bg + rng.integers(-3, 4, size=bg.shape), 0, 255).astype(np.uint8))
    frame = bg.copy()
    frame[80:160, 120:200] = 230  # a bright object walks in
    m = bm.apply(frame)
    assert m.shape == (60, 80)
    assert m[25:35, 35:45].mean() > 0.9 and m[:10, :20].mean() < 0.05

    fm = FrameMattes(1, scale=4, max_age_ns=50)
    fm.push(0, 1000, frame)
    fm.push(0, 2000, bg)
    assert fm.mattes(1010)[0] is not None and fm.mattes(1010)[0].mean() > fm.mattes(1990)[0].mean()  # type: ignore[union-attr]
    assert fm.mattes(5000) == [None]  # nothing within max_age


def test_ring_mattes_subtract_the_background_of_each_cameras_newest_frame() -> None:
    """The daemon's matte source on real frame rings: each poll takes every ring's newest frame once."""
    rng = np.random.default_rng(3)
    rings = [FrameRing(f"cam{i}", 4, 240, 320, 3) for i in range(2)]
    rm = RingMattes([*rings, None], scale=4)
    bg = rng.integers(60, 90, size=(240, 320, 3), dtype=np.uint8)
    for k in range(20):
        for ring in rings:
            ring.next_slot()[:] = bg
            ring.publish(1_000 * k, 0, k)
        assert rm.poll() == 2 and rm.poll() == 0  # a frame is subtracted once
    rings[0].next_slot()[:] = bg
    rings[0].next_slot()[80:160, 120:200] = 230
    rings[0].publish(50_000, 0, 20)
    assert rm.poll() == 1
    m = rm.mattes(50_000)
    assert m[1] is not None and m[2] is None  # camera 2 has no frames; camera 1's last frame is old but in range
    m0 = m[0]
    assert m0 is not None and m0.shape == (60, 80) and m0[25:35, 35:45].mean() > 0.9 and m0[:10, :20].mean() < 0.05


def test_clean_plate_mattes_find_a_subject_present_in_every_frame() -> None:
    """The real-footage evaluation's mattes: a subject in every frame of a short take (where MOG2 absorbs it into
    the background) stands out against the plate estimated from the frames where it is elsewhere."""
    from mocapd.eval.fusion_video import clean_plate_mattes

    rng = np.random.default_rng(4)
    scale = 4
    bg = rng.integers(40, 200, size=(60, 80, 3), dtype=np.uint8)  # textured background at the matte's scale
    n = 12
    frames = np.repeat(bg[None], n, axis=0)
    uv = np.full((n, 17, 2), np.nan)
    conf = np.zeros((n, 17))
    for t in range(n):
        x0 = 4 + 5 * t  # the subject walks across the frame; always in view
        frames[t, 20:44, x0 : x0 + 12] = (20, 220, 240)
        corners = {5: (x0, 20), 6: (x0 + 11, 20), 11: (x0, 43), 12: (x0 + 11, 43)}  # shoulders and hips
        for k, (x, y) in corners.items():
            uv[t, k] = ((x + 0.5) * scale - 0.5, (y + 0.5) * scale - 0.5)  # full-resolution pixels
            conf[t, k] = 0.9
    m = clean_plate_mattes(frames, uv, conf, scale)
    assert m.shape == (n, 60, 80) and m.dtype == np.float32 and m.min() >= 0.0 and m.max() <= 1.0
    for t in (0, n // 2, n - 1):
        x0 = 4 + 5 * t
        assert m[t, 24:40, x0 + 2 : x0 + 10].mean() > 0.9  # the subject
        off = np.ones((60, 80), dtype=bool)
        off[16:48, max(0, x0 - 4) : x0 + 16] = False
        assert m[t][off].mean() < 0.02  # the background, including where the subject stands in other frames


def test_window_index_with_stride_repeats_the_phase_start() -> None:
    w = window_index(8, look_back=3, stride=3)
    assert w[0].tolist() == [0, 0, 0]
    assert w[4].tolist() == [1, 1, 4]
    assert w[7].tolist() == [1, 4, 7]
    assert window_index(3, 2).tolist() == [[0, 0], [0, 1], [1, 2]]


# ---------------------------------------------------------------------------------------- training and export
@pytest.fixture(scope="module")
def tiny_models(tiny_fusion_models: Path) -> Path:
    """A seconds-long training run of the whole recipe and its ONNX export (conftest)."""
    return tiny_fusion_models


def test_training_exports_networks_that_onnxruntime_runs_as_torch_does(tiny_models: Path) -> None:
    prov = json.loads((tiny_models / PROVENANCE_FILE).read_text())
    assert set(prov["files"]) == {
        "fusion_cnn.onnx", "fusion_cnn_matte.onnx", "fusion_cnn_joints.onnx", "fusion_temporal.onnx",
        "fusion_raw_imu.onnx",
    }  # fmt: skip
    for name, sha in prov["files"].items():
        assert hashlib.sha256((tiny_models / name).read_bytes()).hexdigest() == sha
    assert max(prov["onnx_max_abs_diff_vs_torch"].values()) < 1e-4
    assert all(e["train_rms_mm"] > 0 for h in prov["history"].values() for e in h)
    assert {s["use"] for s in prov["source_files"]} == {"train", "validation"}
    assert available_variants(tiny_models) == ("both", "matte", "joints")
    models = FusionModels(tiny_models, variants=("both", "matte"), raw_imu=True)
    out = models.cnn(np.random.default_rng(0).uniform(size=(3, 2, 30, 30, 30)).astype(np.float32))
    assert out.shape == (3, 63) and np.all(np.isfinite(out))
    assert models.cnn(np.zeros((1, 1, 30, 30, 30), np.float32), "matte").shape == (1, 63)
    assert models.raw_imu(np.zeros((2, 5, 91), np.float32)).shape == (2, 63)


def test_runtime_streaming_windows_equal_the_training_windows(tiny_models: Path) -> None:
    """PersonFusion (the daemon's frame-by-frame path) gives what the batch windows of training and evaluation
    give on the same sequence of learned frames."""
    models = FusionModels(tiny_models)
    rng = np.random.default_rng(2)
    n = 9
    pvh = rng.uniform(size=(n, 2, 30, 30, 30)).astype(np.float32)
    up = np.array([0.0, 0.9, 0.0])
    centres = np.cumsum(rng.normal(scale=0.02, size=(n, 3)), axis=0) + up
    imu = rng.normal(scale=0.3, size=(n, 21, 3)) + up
    views = np.full(n, 7.0)
    pf = PersonFusion(models)
    streamed = [pf.step(pvh[k], centres[k], 7, imu[k]) for k in range(n)]
    rel = models.cnn(pvh).astype(np.float64).reshape(n, 21, 3)
    v, _, f = models.temporal(
        vision_windows(rel + centres[:, None], centres, models.look_back).astype(np.float32),
        imu_windows(imu, models.look_back).astype(np.float32),
        views[:, None].astype(np.float32),
    )
    for k in range(n):
        np.testing.assert_allclose(streamed[k].vision, v[k].reshape(21, 3) + centres[k], atol=1e-5)
        fused = streamed[k].fused
        assert fused is not None
        np.testing.assert_allclose(fused, f[k].reshape(21, 3) + centres[k], atol=1e-5)
    alone = PersonFusion(models).step(pvh[0], centres[0], 7, None)
    assert alone.fused is None and np.array_equal(alone.joints, alone.vision)


def test_the_recipe_reproduces_what_it_recorded_beside_the_reference_networks(tiny_models: Path) -> None:
    """The reference training's provenance records the CI recipe's validation errors as run when it trained;
    the same recipe run now (the fixture) must give them again. A change to the recipe's code, the simulator or
    a library under them shows here (retraining the reference networks themselves takes most of an hour)."""
    shipped = reference_provenance()["reproduction_check"]
    now = json.loads((tiny_models / PROVENANCE_FILE).read_text())["validation_mean_mm"]
    assert now.keys() == shipped["validation_mean_mm"].keys()
    for k, v in shipped["validation_mean_mm"].items():
        assert now[k] == pytest.approx(v, rel=0.02), f"{k}: {now[k]} mm now, {v} mm recorded"


# ---------------------------------------------------------------------------------------- the reference training
def test_the_reference_training_used_development_cmu_motion_only(tiny_models: Path) -> None:
    prov = reference_provenance()
    # Trained on CMU motion only (the only licence here that allows a shipped artefact), none of it evaluated on.
    evaluation = {str(p) for p in load_splits()["evaluation"]}
    train, val = training_clips()
    assert {s["path"] for s in prov["source_files"]} == {
        str(p.relative_to(p.parents[3] if "asfamc" in p.parts else p.parents[2])) for p in (*train, *val)
    }
    assert all("cmu" in s["path"] for s in prov["source_files"])
    assert not {str(p) for p in (*train, *val)} & evaluation
    tiny = json.loads((tiny_models / PROVENANCE_FILE).read_text())
    models = FusionModels(tiny_models)  # a folder's recipe sets the runtime's grid and stride
    assert models.stride == tiny["recipe"]["stride"] and models.grid.size == tiny["recipe"]["grid_size"]
    with pytest.raises(ModelError, match=r"tools/train_fusion\.py --out"):
        FusionModels(tiny_models / "nowhere")


def test_eval_accuracy_gains_table_6(tmp_path: Path, capsys: pytest.CaptureFixture[str], tiny_models: Path) -> None:
    """``mocapd eval accuracy --only-fusion`` on a few frames of the quick split: every Table 6 row for every camera ×
    IMU configuration, finite, with its cost per frame; the markdown has the table."""
    from mocapd.eval.fusion_eval import NETWORK_ROWS, SOLVE_ROWS
    from mocapd.service.cli import main

    out = tmp_path / "t6"
    args = ["eval", "accuracy", "--quick", "--only-fusion", "--fusion-frames", "24", "--no-scenarios",
            "--fusion-model", str(tiny_models)]  # fmt: skip
    assert main([*args, "--no-progress", "--out", str(out)]) == 0
    capsys.readouterr()
    data = json.loads((out / "results.json").read_text())
    t6 = data["fusion"]["table6"]
    assert set(t6) == {f"{c}c{i}i" for c in (4, 8) for i in (0, 6, 13)}
    for cfg, rows in t6.items():
        want = set(SOLVE_ROWS) | {"two-channel PVH", "+ LSTM"}
        if not cfg.endswith("c0i"):
            want |= set(NETWORK_ROWS) - {"matte PVH", "joint-channel PVH"}
        assert want <= set(rows), (cfg, want - set(rows))
        for name, r in rows.items():
            assert r["nonfinite_frames"] == 0 and np.isfinite(r["global_mm"]["mean"]), (cfg, name)
            assert r["ms_per_frame"] > 0 or name == "raw-IMU LSTM", (cfg, name)
        assert rows["LM solver"]["orientation_deg"] is not None and rows["both"]["orientation_deg"] is not None
    assert "seed 001 Table 6" in (out / "tables.md").read_text()


def test_real_footage_errors_are_issue_29s_held_out_view_metric() -> None:
    """tools/eval_fusion_video.py scores with mocapd.eval.heldout (docs/accuracy-video.md): a method's person is
    matched to one of the held-out camera's detections, one far from every detection is not compared at all, and
    only the 12 limb keypoints the learned joints sit on are compared; the input is each view's largest person."""
    from mocapd.core.sorting import Detections2D
    from mocapd.core.synthetic import moving_sequence, ring_rig
    from mocapd.eval.fusion_video import LIMB_KEYPOINTS, held_out_grid, subject_keypoints

    sk = Skeleton.from_height(1.7)
    kin, tg = Kinematics(sk), coco17_targets(sk)
    thetas = moving_sequence(sk, 6, fps=60.0, seed=3)

    def person(dx: float, dz: float) -> np.ndarray:
        th = thetas.copy()
        th[:, 0] += dx
        th[:, 2] += dz  # y is up
        return np.stack([kin.targets(kin.forward(t), tg.bones, tg.offsets) for t in th])  # (6, 17, 3)

    cam = ring_rig(4, radius=4.5)[0]
    subject, bystander = person(0.0, 0.0), person(0.5, 3.0)  # the bystander further from this camera: smaller
    if np.linalg.norm(cam.t + cam.R @ bystander[0, 0]) < np.linalg.norm(cam.t + cam.R @ subject[0, 0]):
        subject, bystander = person(0.0, 0.0), person(0.5, -3.0)
    dets = []
    for f in range(6):
        uv = np.stack([cam.project(bystander[f]), cam.project(subject[f])])  # the bystander first
        conf = np.full((2, 17), 0.9)
        uv[1, 9] += (6.0, 8.0)  # the subject's left wrist detected 10 px off
        dets.append(Detections2D(uv, conf))
    uv_s, conf_s = subject_keypoints([[d] for d in dets])
    assert np.allclose(uv_s[:, 0], np.stack([d.keypoints[1] for d in dets]))  # the largest person
    assert conf_s.shape == (6, 1, 17)

    limbs = list(LIMB_KEYPOINTS)
    g = held_out_grid(subject[:, limbs], cam, dets, 3)
    assert g.shape == (6, 3, 17)
    assert np.all(np.isnan(g[:, [0, 2]]))  # matched to the subject's detection only
    assert np.allclose(g[:, 1, 9], 10.0) and np.nanmax(np.delete(g[:, 1], 9, axis=1)) < 1e-6
    assert np.all(np.isnan(g[:, 1, :5]))  # nose, eyes, ears: not joints the learned stream has
    assert np.count_nonzero(np.isfinite(g)) == 6 * 12
    # A reconstruction of the bystander is compared with the bystander's detection, not with the subject's.
    assert np.nanmax(held_out_grid(bystander[:, limbs], cam, dets, 3)[:, 0]) < 1e-6
    # One 3 m from everybody is not compared (the old own metric counted it as a large error).
    assert np.all(np.isnan(held_out_grid(subject[:, limbs] + (3.0, 3.0, 0.0), cam, dets, 3)))


def test_eval_accuracy_without_trained_networks_says_how_to_train_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The networks are trained by the user (no weights are committed): without them the Table 6 evaluation stops
    before its work with one line naming the command."""
    from mocapd.service.cli import main

    args = ["eval", "accuracy", "--quick", "--only-fusion", "--no-scenarios", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "t6"), "--fusion-model", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: learned fusion: cannot read") and "tools/train_fusion.py --out" in err, err
    assert not (tmp_path / "t6").exists()

"""Rig extrinsics + bundle adjustment on the real Pose2Sim demo rig geometry (cameras from Calib.qca.txt),
observing a synthetic board with 0.3 px corner noise; recovered poses are compared with the truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapd.core.rotations import matrix_from_rotvec
from mocapd.errors import CalibrationError
from mocapd.io.board_calibration import Board, Detection
from mocapd.io.calibration_files import CalibrationSet, read_qca
from mocapd.io.rig_calibration import Intrinsics, Observation, calibrate_rig
from tests.pose2sim_data import demo_root


@pytest.fixture(scope="module")
def pose2sim_demo() -> Path:
    return demo_root()


BOARD = Board("checkerboard", 5, 8, 0.1)
FLOOR = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # board z points down into the floor


def _observe(truth: CalibrationSet, seed: int, n_frames: int = 15) -> list[Observation]:
    rng = np.random.default_rng(seed)
    obj = BOARD.object_points()
    poses = {"f00": (FLOOR, np.zeros(3))}
    for i in range(1, n_frames):
        R = matrix_from_rotvec(rng.normal(0, 0.6, 3)) @ FLOOR
        poses[f"f{i:02d}"] = (R, np.array([rng.uniform(-1, 1), rng.uniform(0.5, 1.5), rng.uniform(-1, 1)]))
    obs = []
    for frame, (R, t) in poses.items():
        Xw = obj @ R.T + t
        for cam in truth.cameras:
            if ((Xw @ cam.R.T + cam.t)[:, 2] <= 0.1).any():
                continue
            px = cam.project(Xw)
            if (px < 0).any() or (px[:, 0] >= cam.size[0]).any() or (px[:, 1] >= cam.size[1]).any():
                continue
            noisy = px + rng.normal(0, 0.3, px.shape)
            obs.append(
                Observation(cam.name, frame, Detection(f"{cam.name}/{frame}", np.arange(len(obj)), noisy, cam.size))
            )
    return obs


@pytest.fixture()
def truth(pose2sim_demo: Path) -> CalibrationSet:
    return read_qca(pose2sim_demo / "Demo_SinglePerson" / "calibration" / "Calib.qca.txt")


def test_recovers_the_demo_rig(truth: CalibrationSet) -> None:
    obs = _observe(truth, 0)
    intr = {c.name: Intrinsics(c.K, c.dist, c.size) for c in truth.cameras}
    result = calibrate_rig(intr, obs, BOARD, origin_frame="f00")
    for cam in truth.cameras:
        est = result.calibration[cam.name]
        angle = np.degrees(np.arccos(np.clip((np.trace(est.R.T @ cam.R) - 1) / 2, -1, 1)))
        assert angle < 0.1, cam.name
        assert np.linalg.norm(est.center - cam.center) < 0.005, cam.name
        # Bundle adjustment brings every camera down to the noise level (0.3 px per axis -> 0.42 px RMS).
        assert result.rms_after_px[cam.name] < 0.5
        assert est.center[1] > 1.5  # +Y up: cameras above the floor
    # One camera may end slightly worse, the rig as a whole better (the PnP chain accumulates errors).
    assert sum(result.rms_after_px.values()) < sum(result.rms_before_px.values())
    # The floor board lies in y = 0.
    R0, t0 = result.board_poses["f00"]
    assert np.allclose((BOARD.object_points() @ R0.T + t0)[:, 1], 0.0)


def test_unlinked_camera_and_bad_input(truth: CalibrationSet) -> None:
    obs = _observe(truth, 1)
    intr = {c.name: Intrinsics(c.K, c.dist, c.size) for c in truth.cameras}
    # cam03 only sees frames nobody else sees: it cannot be placed.
    shared = {o.frame for o in obs if o.camera != "cam03"}
    lonely = [o for o in obs if o.camera != "cam03" or o.frame not in shared]
    lonely = [o if o.camera != "cam03" else Observation("cam03", "alone-" + o.frame, o.detection) for o in lonely]
    with pytest.raises(CalibrationError, match=r"\['cam03'\] never see the board"):
        calibrate_rig(intr, lonely, BOARD, origin_frame="f00")
    with pytest.raises(CalibrationError, match="no board observation"):
        calibrate_rig(intr, [], BOARD)
    with pytest.raises(CalibrationError, match="no intrinsics"):
        calibrate_rig({"cam01": intr["cam01"]}, obs, BOARD)

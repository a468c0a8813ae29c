"""Intrinsic calibration: the four Pose2Sim demo cameras from their checkerboard pictures, compared with the
shipped Calib.qca.txt; ChArUco on rendered views; rejection of bad views; clear errors on bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from mocapd.core.rotations import matrix_from_rotvec
from mocapd.errors import CalibrationError
from mocapd.io.board_calibration import Board, Detection, calibrate_intrinsics, detect_board, detect_in_files
from mocapd.io.calibration_files import read_qca
from tests.pose2sim_data import demo_root


@pytest.fixture(scope="module")
def pose2sim_demo() -> Path:
    return demo_root()


DEMO_BOARD = Board("checkerboard", 4, 7, 0.060)  # Pose2Sim demo Config.toml: corners_nb [4, 7], 60 mm


@pytest.mark.parametrize("cam", ["cam01", "cam02", "cam03", "cam04"])
def test_demo_intrinsics_agree_with_qualisys(pose2sim_demo: Path, cam: str) -> None:
    calib_dir = pose2sim_demo / "Demo_SinglePerson" / "calibration"
    dets, missed = detect_in_files((calib_dir / "intrinsics" / f"int_{cam}_img").glob("*.jpg"), DEMO_BOARD)
    assert len(dets) >= 5 and len(missed) <= 2
    result = calibrate_intrinsics(dets, DEMO_BOARD, rational_k3=False)
    ref = read_qca(calib_dir / "Calib.qca.txt")[cam]
    assert result.size == ref.size == (1088, 1920)
    assert result.rms_px < 0.5
    assert all(e < 1.0 for e in result.view_errors_px.values())
    # Focal lengths within 1 %; principal points within 45 px (7 pictures, board mostly in the image centre).
    assert result.K[0, 0] == pytest.approx(ref.K[0, 0], rel=0.01)
    assert result.K[1, 1] == pytest.approx(ref.K[1, 1], rel=0.01)
    assert abs(result.K[0, 2] - ref.K[0, 2]) < 45 and abs(result.K[1, 2] - ref.K[1, 2]) < 45
    # Radial distortion has the file's sign and magnitude (it is not in 1/64 units).
    assert -0.07 < result.dist[0] < -0.02 and ref.dist[0] < 0


def test_bad_view_is_rejected(pose2sim_demo: Path) -> None:
    folder = pose2sim_demo / "Demo_SinglePerson" / "calibration" / "intrinsics" / "int_cam01_img"
    dets, _ = detect_in_files(folder.glob("*.jpg"), DEMO_BOARD)
    bad = dets[0]
    # Swap two corner rows: a typical mis-ordered detection.
    pixels = bad.pixels.copy()
    pixels[[0, 1, 2, 3]] = pixels[[4, 5, 6, 7]]
    dets[0] = Detection("mis-detected.jpg", bad.ids, pixels, bad.size)
    result = calibrate_intrinsics(dets, DEMO_BOARD, rational_k3=False)
    assert "mis-detected.jpg" in result.rejected
    assert "mis-detected.jpg" not in result.view_errors_px
    assert result.rms_px < 0.5


def test_too_few_views_and_no_board(pose2sim_demo: Path) -> None:
    folder = pose2sim_demo / "Demo_SinglePerson" / "calibration" / "intrinsics" / "int_cam02_img"
    dets, _ = detect_in_files(folder.glob("*.jpg"), DEMO_BOARD)
    with pytest.raises(CalibrationError, match="take more pictures"):
        calibrate_intrinsics(dets[:2], DEMO_BOARD)
    wrong = Board("checkerboard", 5, 9, 0.06)
    dets, missed = detect_in_files(list(folder.glob("*.jpg"))[:2], wrong)
    assert dets == [] and len(missed) == 2


def _render_charuco(board: Board, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    ppm = 2000  # board image pixels per metre
    w, h = round(board.cols * board.square_m * ppm), round(board.rows * board.square_m * ppm)
    flat = board.charuco().generateImage((w, h), marginSize=0)
    # Homography board plane (metres) -> image, through the flat image's pixel grid.
    R = matrix_from_rotvec(rvec)
    H = K @ np.column_stack([R[:, 0], R[:, 1], tvec])
    S = np.diag([1.0 / ppm, 1.0 / ppm, 1.0])
    img = cv2.warpPerspective(flat, H @ S, (1280, 960), borderValue=255, flags=cv2.INTER_AREA)
    return np.asarray(img, np.uint8)


def test_charuco_on_rendered_views() -> None:
    board = Board("charuco", 7, 5, 0.04, 0.03, "DICT_4X4_50")
    K = np.array([[1100.0, 0, 640], [0, 1100.0, 480], [0, 0, 1]])
    rng = np.random.default_rng(1)
    dets = []
    for i in range(8):
        rvec = rng.normal(0, 0.35, 3)
        tvec = np.array([-0.14 + rng.normal(0, 0.03), -0.1 + rng.normal(0, 0.03), 0.55 + rng.uniform(0, 0.15)])
        det = detect_board(_render_charuco(board, K, rvec, tvec), board, f"v{i}")
        if det is not None:
            dets.append(det)
    assert len(dets) >= 6
    result = calibrate_intrinsics(dets, board, rational_k3=False)
    assert result.rms_px < 1.0
    assert result.K[0, 0] == pytest.approx(1100, rel=0.02) and result.K[1, 1] == pytest.approx(1100, rel=0.02)
    assert abs(result.K[0, 2] - 640) < 15 and abs(result.K[1, 2] - 480) < 15


def test_degenerate_views_are_refused(pose2sim_demo: Path) -> None:
    folder = pose2sim_demo / "Demo_SinglePerson" / "calibration" / "intrinsics" / "int_cam03_img"
    dets, _ = detect_in_files(folder.glob("*.jpg"), DEMO_BOARD)
    # The same picture five times: the board has a single orientation.
    same = [Detection(f"copy{i}", dets[0].ids, dets[0].pixels, dets[0].size) for i in range(5)]
    with pytest.raises(CalibrationError, match="tilt it"):
        calibrate_intrinsics(same, DEMO_BOARD)
    mixed = [*dets[:3], Detection("small", dets[0].ids, dets[0].pixels, (640, 480))]
    with pytest.raises(CalibrationError, match="different image sizes"):
        calibrate_intrinsics(mixed, DEMO_BOARD)

"""`mocapd calibrate cameras` and `mocapd calibrate convert` on the Pose2Sim demo data."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from mocapd.core.rotations import matrix_from_rotvec
from mocapd.io.board_calibration import Board
from mocapd.io.calibration_files import (
    CalibrationSet,
    read_mocapd_toml,
    read_pose2sim_toml,
    read_qca,
    write_mocapd_toml,
)
from mocapd.service.cli import main
from tests.pose2sim_data import demo_root


@pytest.fixture(scope="module")
def pose2sim_demo() -> Path:
    return demo_root()


def test_calibrate_intrinsics_of_demo(pose2sim_demo: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    intr = pose2sim_demo / "Demo_SinglePerson" / "calibration" / "intrinsics"
    out = tmp_path / "calib.toml"
    code = main(
        [
            "calibrate",
            "cameras",
            "--cols",
            "4",
            "--rows",
            "7",
            "--square-mm",
            "60",
            "--intrinsics",
            str(intr),
            "--fix-k3",
            "--output",
            str(out),
        ]
    )
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert sorted(report["intrinsics"]) == ["cam01", "cam02", "cam03", "cam04"]
    assert all(r["rms_px"] < 0.5 for r in report["intrinsics"].values())
    calib = read_mocapd_toml(out)
    assert calib.names == ["cam01", "cam02", "cam03", "cam04"]


def test_no_board_found_says_what_to_do(
    pose2sim_demo: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = pose2sim_demo / "Demo_SinglePerson" / "calibration" / "intrinsics" / "int_cam01_img"
    shutil.copytree(src, tmp_path / "imgs" / "int_cam01_img")
    code = main(
        [
            "calibrate",
            "cameras",
            "--cols",
            "6",
            "--rows",
            "9",
            "--square-mm",
            "60",
            "--intrinsics",
            str(tmp_path / "imgs"),
            "--output",
            str(tmp_path / "c.toml"),
        ]
    )
    assert code == 1
    err = capsys.readouterr().err
    assert "cam01" in err and "found in none" in err and "--cols/--rows" in err


def test_convert_qca(pose2sim_demo: Path, tmp_path: Path) -> None:
    qca = pose2sim_demo / "Demo_SinglePerson" / "calibration" / "Calib.qca.txt"
    assert main(["calibrate", "convert", str(qca), str(tmp_path / "c.toml")]) == 0
    assert main(["calibrate", "convert", str(qca), str(tmp_path / "p.toml"), "--to", "pose2sim"]) == 0
    assert main(["calibrate", "convert", str(qca), str(tmp_path / "c.yml")]) == 0
    ours, theirs = read_mocapd_toml(tmp_path / "c.toml"), read_pose2sim_toml(tmp_path / "p.toml")
    assert ours.cameras[0].center == pytest.approx(theirs.cameras[0].center)
    assert main(["calibrate", "convert", str(tmp_path / "missing.toml"), str(tmp_path / "x.toml")]) == 2


def _render_rig_views(truth: CalibrationSet, board: Board, out: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Render the ChArUco board into each demo camera (no distortion) for a floor pose and 8 upright poses."""
    ppm = 1000  # pixels per metre of the flat board image
    flat = board.charuco().generateImage(
        (round(board.cols * board.square_m * ppm), round(board.rows * board.square_m * ppm)), marginSize=0
    )
    S = np.diag([1 / ppm, 1 / ppm, 1.0])
    floor = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # board x -> X, board y -> Z, board z -> -Y
    rng = np.random.default_rng(3)
    poses = {"f00": (floor, np.array([-0.4, 0.0, -0.5]))}
    for i in range(1, 9):
        R = matrix_from_rotvec(np.array([0, rng.uniform(-np.pi, np.pi), 0])) @ matrix_from_rotvec(
            np.array([np.pi + rng.normal(0, 0.2), 0, 0])
        )
        poses[f"f{i:02d}"] = (R, np.array([rng.uniform(-0.5, 0.5), rng.uniform(0.6, 1.0), rng.uniform(-0.5, 0.5)]))
    for cam in truth.cameras:
        (out / cam.name).mkdir(parents=True)
        for frame, (Rb, tb) in poses.items():
            Rcb, tcb = cam.R @ Rb, cam.R @ tb + cam.t
            if ((board.object_points() @ Rcb.T + tcb)[:, 2] < 0.5).any():
                continue
            if Rcb[:, 2] @ tcb <= 0.2 * np.linalg.norm(tcb):  # printed side only, not grazing
                continue
            H = cam.K @ np.column_stack([Rcb[:, 0], Rcb[:, 1], tcb]) @ S
            image = cv2.warpPerspective(flat, H, cam.size, borderValue=128, flags=cv2.INTER_AREA)
            cv2.imwrite(str(out / cam.name / f"{frame}.png"), image)
    return poses


def test_extrinsics_from_rendered_board_views(
    pose2sim_demo: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The demo rig's real geometry (Calib.qca.txt), without distortion so that a homography renders the board.
    qca = read_qca(pose2sim_demo / "Demo_SinglePerson" / "calibration" / "Calib.qca.txt")
    truth = CalibrationSet(tuple(replace(c, dist=np.zeros(5)) for c in qca.cameras))
    write_mocapd_toml(truth, tmp_path / "intrinsics.toml")
    board = Board("charuco", 5, 7, 0.15, 0.11, "DICT_4X4_50")
    poses = _render_rig_views(truth, board, tmp_path / "extrinsics")
    code = main(
        [
            "calibrate",
            "cameras",
            "--board",
            "charuco",
            "--cols",
            "5",
            "--rows",
            "7",
            "--square-mm",
            "150",
            "--marker-mm",
            "110",
            "--intrinsics-from",
            str(tmp_path / "intrinsics.toml"),
            "--extrinsics",
            str(tmp_path / "extrinsics"),
            "--origin-frame",
            "f00",
            "--output",
            str(tmp_path / "rig.toml"),
        ]
    )
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert all(v < 1.5 for v in report["extrinsics"]["rms_after_px"].values())
    est = read_mocapd_toml(tmp_path / "rig.toml")
    # World = the floor board: origin at its corner, so true centres shift by minus the board's position.
    origin = poses["f00"][1]
    for cam in truth.cameras:
        e = est[cam.name]
        angle = np.degrees(np.arccos(np.clip((np.trace(e.R.T @ cam.R) - 1) / 2, -1, 1)))
        assert angle < 0.2, cam.name
        assert np.linalg.norm(e.center - (cam.center - origin)) < 0.01, cam.name

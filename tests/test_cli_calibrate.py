"""`mocapd calibrate cameras` and `mocapd calibrate convert` on the Pose2Sim demo data."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from mocapd.io.calibration_files import read_mocapd_toml, read_pose2sim_toml
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
    assert main(["calibrate", "convert", str(tmp_path / "missing.toml"), str(tmp_path / "x.toml")]) == 1

"""Hostile input, round three (issue 45): the low findings of the probe beyond the web surface, each refused or
made harmless where it starts (the larger ones have tests beside their doors: test_fuzz_media.py,
test_fuzz_streams.py, test_log_throttle.py, test_native_logs.py, test_session_format.py, test_blender_export.py)."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from mocapd.core.skeleton import Skeleton
from mocapd.io.calibration_files import read_any
from mocapd.io.session_export import SubjectTrack, write_csv
from mocapd.service.cli import main
from mocapd.service.config import load_config
from mocapd.sim.camera_hosts import toml_tables, write_ring_calibration


@pytest.mark.parametrize(
    ("argv", "problem"),
    [
        (["eval", "video", "--max-frames", "0"], "--max-frames: '0'; allowed: an integer from 1"),  # was an IndexError
        (["eval", "video", "--images", "-1"], "--images: '-1'; allowed: an integer from 0"),
    ],
)
def test_eval_video_numbers_are_checked(argv: list[str], problem: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and problem in err.strip().splitlines()[-1], err


def test_eval_video_argument_errors_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An unknown --take and a FIFO as --config exited 1, the status of a failed evaluation, not of bad arguments."""
    os.mkfifo(tmp_path / "fifo.toml")
    for argv, problem in ((["--take", "nope"], "unknown Pose2Sim demo 'nope'"),
                          (["--config", str(tmp_path / "fifo.toml")], "not a regular file")):  # fmt: skip
        code = main(["eval", "video", "--out", str(tmp_path / "out"), "--no-pose2sim", *argv])
        err = capsys.readouterr().err
        assert code == 2 and problem in err and len(err.strip().splitlines()) == 1, (argv, code, err)


def _rig(tmp_path: Path, cameras: int, **detector_model: str) -> Path:
    folder = tmp_path / "pictures"
    folder.mkdir(exist_ok=True)
    assert cv2.imwrite(str(folder / "0001.png"), np.zeros((1080, 1920, 3), np.uint8))
    names = [f"cam{i}" for i in range(cameras)]
    write_ring_calibration(names, tmp_path / "calibration.toml")
    tables: dict[str, dict[str, object]] = {"calibration": {"file": str(tmp_path / "calibration.toml")}}
    if detector_model:
        tables["detector"] = {"model": detector_model}
    path = tmp_path / "rig.toml"
    path.write_text(toml_tables(tables, [{"name": n, "source": "images", "path": str(folder)} for n in names]),
                    encoding="utf-8")  # fmt: skip
    return path


def test_check_config_says_what_run_says_of_a_one_camera_rig(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """check-config said ok; `run` loaded the models, then refused: detection sorting needs two cameras."""
    assert main(["check-config", str(_rig(tmp_path, 1))]) == 2
    err = capsys.readouterr().err
    assert "one camera (cam0): detection sorting needs at least two cameras" in err and len(err.splitlines()) == 1
    assert main(["check-config", str(_rig(tmp_path, 2))]) == 0


@pytest.mark.parametrize("kind", ["fifo", "device", "directory"])
def test_check_config_refuses_a_model_path_that_is_no_file(
    kind: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """check-config passed a FIFO, a device or a folder as detector.model.path; `run` said "not found"."""
    model = tmp_path / "model.onnx"
    if kind == "fifo":
        os.mkfifo(model)
    elif kind == "device":
        model.symlink_to("/dev/null")
    else:
        model.mkdir()
    assert main(["check-config", str(_rig(tmp_path, 2, path=str(model)))]) == 2
    err = capsys.readouterr().err
    assert "detector.model.path" in err and "not a regular file" in err, err


def test_a_config_with_a_byte_order_mark_is_read(tmp_path: Path) -> None:
    """Windows Notepad's UTF-8 byte order mark: the error was TOML's "invalid statement (at line 1, column 1)"."""
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf[daemon]\noutput_rate_hz = 30\n")
    assert load_config(path).daemon.output_rate_hz == 30


def test_subject_names_are_spreadsheet_safe_in_csv(tmp_path: Path) -> None:
    """A subject named `=HYPERLINK(...)` went into the CSV verbatim: a formula where the file is opened (OWASP's CSV
    injection). Cells starting with = + - @, a tab or a carriage return get a leading quote; others are untouched."""
    sk = Skeleton.from_height(1.75)
    names = ['=HYPERLINK("http://x.example","y")', "+1", "-cmd", "@SUM(A1)", "\tx", "\rx", "suit:suit0", "Ann"]
    for k, name in enumerate(names):
        path = tmp_path / f"{k}.csv"
        write_csv(path, sk, SubjectTrack(name, np.array([0, 1_000_000]), np.zeros((2, 66))))
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
        cell = rows[1][rows[0].index("subject")]
        assert cell == (name if k >= 6 else f"'{name}"), (name, cell)


def test_a_huge_image_size_in_a_pose2sim_calibration_is_one_short_line(tmp_path: Path) -> None:
    """`size = [1e308, 1080]` in a Pose2Sim calibration printed a 309-digit integer in the error."""
    path = tmp_path / "Calib.toml"
    path.write_text(
        '[cam_01]\nname = "cam_01"\nsize = [1e308, 1080.0]\nmatrix = [[1000.0, 0.0, 960.0], [0.0, 1000.0, 540.0], '
        "[0.0, 0.0, 1.0]]\ndistortions = [0.0, 0.0, 0.0, 0.0]\nrotation = [0.0, 0.0, 0.0]\n"
        "translation = [0.0, 0.0, 3.0]\nfisheye = false\n\n[metadata]\nadjusted = false\nerror = 0.0\n",
        encoding="utf-8",
    )
    with pytest.raises(Exception, match=r"image size about 1e30\dx1080; allowed") as exc:
        read_any(path)
    assert len(str(exc.value)) < 300, str(exc.value)

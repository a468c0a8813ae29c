"""Calibration files: Qualisys qca axis conventions on the Pose2Sim demo rig, round trips of every format."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapd.errors import CalibrationError
from mocapd.io.calibration_files import (
    CalibrationSet,
    CameraCalibration,
    core_cameras,
    read_any,
    read_mocapd_toml,
    read_opencv_yaml,
    read_pose2sim_toml,
    read_qca,
    write_mocapd_toml,
    write_opencv_yaml,
    write_pose2sim_toml,
)
from tests.pose2sim_data import demo_root


@pytest.fixture(scope="module")
def pose2sim_demo() -> Path:
    return demo_root()


@pytest.fixture()
def demo_qca(pose2sim_demo: Path) -> CalibrationSet:
    return read_qca(pose2sim_demo / "Demo_SinglePerson" / "calibration" / "Calib.qca.txt")


def test_qca_values_and_units(demo_qca: CalibrationSet, pose2sim_demo: Path) -> None:
    cam = demo_qca["cam01"]
    assert cam.size == (1088, 1920)
    # 1/64 px: focalLengthU = 107599.671875 -> 1681.24 px; centre minus the video fov offset (0 here).
    assert cam.K[0, 0] == pytest.approx(107599.671875 / 64)
    assert cam.K[1, 2] == pytest.approx(60680.792969 / 64)
    # Distortion is dimensionless: kept as in the file (Pose2Sim's /64 only on request).
    assert cam.dist[:2] == pytest.approx([-0.046183, 0.139983])
    p2s = read_qca(pose2sim_demo / "Demo_SinglePerson" / "calibration" / "Calib.qca.txt", pose2sim_distortion=True)
    assert p2s["cam01"].dist[0] == pytest.approx(-0.046183 / 64)
    # Position in mm -> metres, Z-up -> Y-up: file (1460.2, -1909.2, 1896.5) mm is (1.460, 1.897, 1.909) m.
    assert cam.center == pytest.approx([1.4602324, 1.8965059, 1.9091590], abs=1e-6)


def test_qca_axis_conventions_put_the_capture_area_in_view(demo_qca: CalibrationSet) -> None:
    for cam in demo_qca.cameras:
        # Cameras stand 1.6-2.2 m above the floor (y up), around the capture area.
        assert 1.6 < cam.center[1] < 2.2, cam.name
        # The world origin is in front of every camera and inside its image...
        depth = (cam.R @ np.zeros(3) + cam.t)[2]
        assert depth > 2.0, cam.name
        u, v = cam.project(np.zeros((1, 3)))[0]
        assert 0 < u < cam.size[0] and 0 < v < cam.size[1], cam.name
        # ...and world +Y (up) goes up in the image (v decreases).
        up = cam.project(np.array([[0.0, 1.0, 0.0]]))[0]
        assert up[1] < v - 200, cam.name


def test_round_trips(demo_qca: CalibrationSet, tmp_path: Path) -> None:
    write_mocapd_toml(demo_qca, tmp_path / "c.toml")
    write_pose2sim_toml(demo_qca, tmp_path / "p2s.toml")
    write_opencv_yaml(demo_qca, tmp_path / "c.yml")
    for back in (
        read_mocapd_toml(tmp_path / "c.toml"),
        read_any(tmp_path / "c.toml"),
        read_pose2sim_toml(tmp_path / "p2s.toml"),
        read_any(tmp_path / "p2s.toml"),
        read_opencv_yaml(tmp_path / "c.yml"),
    ):
        assert back.names == demo_qca.names
        for a, b in zip(demo_qca.cameras, back.cameras, strict=True):
            assert a.size == b.size
            np.testing.assert_allclose(b.K, a.K, atol=1e-9)
            np.testing.assert_allclose(b.R, a.R, atol=1e-9)
            np.testing.assert_allclose(b.t, a.t, atol=1e-9)
            np.testing.assert_allclose(b.dist[:4], a.dist[:4], atol=1e-12)


def test_pose2sim_world_is_z_up(demo_qca: CalibrationSet, tmp_path: Path) -> None:
    write_pose2sim_toml(demo_qca, tmp_path / "p2s.toml")
    z_up = read_pose2sim_toml(tmp_path / "p2s.toml", world_up="y")  # read without conversion
    assert z_up["cam01"].center == pytest.approx([1.4602324, -1.9091590, 1.8965059], abs=1e-6)


def test_bad_files(tmp_path: Path) -> None:
    (tmp_path / "x.toml").write_text('format = "other"\n')
    with pytest.raises(CalibrationError, match="holds no camera"):
        read_any(tmp_path / "x.toml")
    (tmp_path / "y.toml").write_text('format = "mocapd-calibration"\nversion = 9\n')
    with pytest.raises(CalibrationError, match="version"):
        read_any(tmp_path / "y.toml")
    (tmp_path / "z.qca.txt").write_text("<calibration><cameras><camera serial='a'/></cameras></calibration>")
    with pytest.raises(CalibrationError, match="lacks"):
        read_any(tmp_path / "z.qca.txt")
    with pytest.raises(CalibrationError, match="unknown calibration format"):
        read_any(tmp_path / "c.csv")  # (.json is the K/R/t calibrations: tests/test_calibration_json.py)
    with pytest.raises(CalibrationError, match="not a rotation"):
        CameraCalibration("c", (10, 10), np.eye(3), R=np.diag([1.0, 1.0, -1.0]))


def test_core_cameras_scaled_to_resized_images(pose2sim_demo: Path) -> None:
    calib = read_qca(pose2sim_demo / "Demo_MultiPerson" / "calibration" / "Calib.qca.txt")
    full, half = core_cameras(calib), core_cameras(calib, 0.5)
    assert [c.name for c in half] == calib.names
    assert (half[0].width, half[0].height) == (round(calib.cameras[0].size[0] / 2), round(calib.cameras[0].size[1] / 2))
    X = np.array([[0.3, 1.0, 0.5], [-0.5, 1.5, -0.2]])
    for f, h, c in zip(full, half, calib.cameras, strict=True):
        assert np.allclose(f.project(X), c.project(X), atol=1e-6)  # same camera as the calibration's own projection
        # A pixel centre u of the full image lies at (u + 0.5) / 2 - 0.5 in the half-size one (cv2.resize).
        assert np.allclose(h.project(X), (f.project(X) + 0.5) * 0.5 - 0.5, atol=1e-6)
    with pytest.raises(CalibrationError):
        core_cameras(calib, 0.0)

"""Calibration files of public multi-view datasets and tools, written here in each one's layout and conventions
from known cameras: 4D association's and VoxelPose's Shelf/Campus JSON, CMU Panoptic's JSON, EasyMocap's
intri/extri YAML, Anipose's and caliscope's TOML; every one must read back as the same cameras in mocapd's +Y-up
world (metres)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from mocapd.core.synthetic import ring_rig
from mocapd.errors import CalibrationError
from mocapd.io.calibration_files import Z_TO_Y, CalibrationSet, on_floor, read_any

RNG = np.random.default_rng(5)
POINTS_Y_UP = np.column_stack([RNG.uniform(-1, 1, 20), RNG.uniform(0, 1.8, 20), RNG.uniform(-1, 1, 20)])
DIST = np.array([-0.21, 0.09, 0.0012, -0.0008, -0.02])


def _cams() -> list:  # type: ignore[type-arg]
    return ring_rig(3)


def _same(calib: CalibrationSet, names: list[str], atol: float = 1e-9) -> None:
    """The calibration's cameras are the ring's (in mocapd's world): same pixels for the same world points."""
    assert calib.names == names
    for cam, ref in zip(calib.cameras, _cams(), strict=True):
        np.testing.assert_allclose(cam.K, ref.K, atol=1e-9)
        np.testing.assert_allclose(cam.R, ref.R, atol=atol)
        np.testing.assert_allclose(cam.t, ref.t, atol=atol)
        assert cam.size == (ref.width, ref.height)


def _z_up(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A camera's extrinsics in a Z-up world (X_y = Z_TO_Y X_z)."""
    return R @ Z_TO_Y, t


def test_4d_association_json(tmp_path: Path) -> None:
    """Per camera K (9), RT (3x4 flat) or R (Rodrigues) + T, imgSize, distCoeff; metres, world Z-up."""
    doc = {}
    for i, c in enumerate(_cams()):
        R, t = _z_up(c.R, c.t)
        if i == 0:
            pose = {"RT": np.column_stack([R, t]).ravel().tolist()}
        else:
            pose = {"R": cv2.Rodrigues(R)[0].ravel().tolist(), "T": t.tolist()}
        doc[str(i)] = {"K": c.K.ravel().tolist(), **pose, "imgSize": [c.width, c.height], "distCoeff": DIST.tolist()}
    (tmp_path / "calibration.json").write_text(json.dumps(doc))
    calib = read_any(tmp_path / "calibration.json")
    _same(calib, ["0", "1", "2"])
    np.testing.assert_allclose(calib.cameras[1].dist, DIST)


def _voxelpose_project(X_mm: np.ndarray, cam: dict) -> np.ndarray:  # type: ignore[type-arg]
    """VoxelPose's own projection (``lib/utils/cameras_cpu.py``, re-derived): x_cam = R (X - T), then radial k1..k3 and
    tangential p = (p1, p2) as Human3.6M's code applies them."""
    R, T = np.array(cam["R"]), np.array(cam["T"])
    xc = R @ (X_mm.T - T)
    y = xc[:2] / xc[2]
    k, p = np.array(cam["k"]).ravel(), np.array(cam["p"]).ravel()
    r2 = np.sum(y**2, axis=0)
    radial = 1 + k[0] * r2 + k[1] * r2**2 + k[2] * r2**3
    tan = p[0] * y[1] + p[1] * y[0]
    y = y * (radial + 2 * tan) + np.outer([p[1], p[0]], r2)
    pixels: np.ndarray = (np.array([[cam["fx"]], [cam["fy"]]]) * y + np.array([[cam["cx"]], [cam["cy"]]])).T
    return pixels


def test_voxelpose_json_projects_as_voxelpose_does(tmp_path: Path) -> None:
    """fx fy cx cy, R, T = the camera centre in mm, k (3x1) and p (2x1): the pixels mocapd projects are the ones
    VoxelPose's formula gives (the tangential terms' order included), the world turned +Y up and in metres."""
    doc = {}
    for i, c in enumerate(_cams()):
        R, t = _z_up(c.R, c.t)
        centre_mm = (-R.T @ t) * 1000.0
        doc[str(i)] = {"R": R.tolist(), "T": centre_mm.reshape(3, 1).tolist(), "fx": c.K[0, 0], "fy": c.K[1, 1],
                       "cx": c.K[0, 2], "cy": c.K[1, 2], "k": [[DIST[0]], [DIST[1]], [DIST[4]]],
                       "p": [[DIST[2]], [DIST[3]]]}  # fmt: skip
    (tmp_path / "calibration_shelf.json").write_text(json.dumps(doc))
    calib = read_any(tmp_path / "calibration_shelf.json")
    assert calib.names == ["0", "1", "2"]
    for name, cam in zip(calib.names, calib.cameras, strict=True):
        np.testing.assert_allclose(cam.t, _cams()[int(name)].t, atol=1e-9)  # mm -> m, centre -> translation
        X_z_mm = (Z_TO_Y.T @ POINTS_Y_UP.T).T * 1000.0
        np.testing.assert_allclose(cam.project(POINTS_Y_UP), _voxelpose_project(X_z_mm, doc[name]), atol=1e-6)
        c = _cams()[int(name)]
        assert cam.size == (round(2 * c.K[0, 2]), round(2 * c.K[1, 2]))  # no size in the file: twice the centre


def test_panoptic_json(tmp_path: Path) -> None:
    """cameras[] with type/resolution/K/distCoef/R/t (cm, world Y-down): HD cameras only, turned +Y up."""
    cams = []
    for i, c in enumerate(_cams()):
        R, t = c.R @ np.diag([1.0, -1.0, -1.0]), c.t * 100.0  # X_down = diag(1, -1, -1) X_up
        cams.append(
            {
                "name": f"00_{i:02d}",
                "type": "hd",
                "resolution": [c.width, c.height],
                "panel": 0,
                "node": i,
                "K": c.K.tolist(),
                "distCoef": DIST.tolist(),
                "R": R.tolist(),
                "t": t.reshape(3, 1).tolist(),
            }
        )
    cams.append({**cams[0], "name": "01_01", "type": "vga", "resolution": [640, 480]})
    untyped = {k: v for k, v in cams[0].items() if k != "type"}
    cams.append({**untyped, "name": "50_01", "panel": 50})  # no type: a panel other than 0 is no HD camera
    (tmp_path / "calibration_171204_pose1.json").write_text(json.dumps({"calibDataSource": "x", "cameras": cams}))
    _same(read_any(tmp_path / "calibration_171204_pose1.json"), ["00_00", "00_01", "00_02"])


def test_easymocap_yaml(tmp_path: Path) -> None:
    """intri.yml (names, K_, dist_) beside extri.yml (R_ Rodrigues, Rot_, T_); world Z-up; either file named."""
    intri = cv2.FileStorage(str(tmp_path / "intri.yml"), cv2.FILE_STORAGE_WRITE)
    extri = cv2.FileStorage(str(tmp_path / "extri.yml"), cv2.FILE_STORAGE_WRITE)
    names = ["01", "02", "03"]
    intri.write("names", names)
    extri.write("names", names)
    for n, c in zip(names, _cams(), strict=True):
        R, t = _z_up(c.R, c.t)
        intri.write(f"K_{n}", c.K)
        intri.write(f"dist_{n}", DIST.reshape(1, 5))
        intri.write(f"W_{n}", c.width)
        intri.write(f"H_{n}", c.height)
        extri.write(f"R_{n}", cv2.Rodrigues(R)[0])
        extri.write(f"Rot_{n}", R)
        extri.write(f"T_{n}", t.reshape(3, 1))
    intri.release()
    extri.release()
    _same(read_any(tmp_path / "extri.yml"), names)
    _same(read_any(tmp_path / "intri.yml"), names)


def test_anipose_toml_in_mm(tmp_path: Path) -> None:
    """Anipose's calibration.toml ([cam_N] name/size/matrix/distortions/rotation/translation, [metadata]): the
    translations in the board's unit (mm here: --units mm), world Z-up as Pose2Sim's."""
    lines = []
    for i, c in enumerate(_cams()):
        R, t = _z_up(c.R, c.t)
        lines += [
            f"[cam_{i}]",
            f'name = "{chr(65 + i)}"',
            f"size = [{c.width}, {c.height}]",
            f"matrix = {c.K.tolist()}",
            f"distortions = {DIST.tolist()}",
            f"rotation = {cv2.Rodrigues(R)[0].ravel().tolist()}",
            f"translation = {(t * 1000).tolist()}",
            "",
        ]
    lines += ["[metadata]", "adjusted = false", "error = 0.4"]
    (tmp_path / "calibration.toml").write_text("\n".join(lines) + "\n")
    _same(read_any(tmp_path / "calibration.toml", units="mm"), ["A", "B", "C"], atol=1e-9)


def _caliscope_camera(c: Any, rotation: list[Any], **extra: object) -> list[str]:
    _, t = _z_up(c.R, c.t)
    rows = [f"size = [{c.width}, {c.height}]", "rotation_count = 0", "error = 0.4", f"matrix = {c.K.tolist()}",
            f"distortions = {DIST.tolist()}", f"translation = {t.tolist()}", f"rotation = {rotation}",
            "exposure = -6", "grid_count = 30", "verified_resolutions = [[640, 480], [1280, 720]]"]  # fmt: skip
    return rows + [f"{k} = {str(v).lower() if isinstance(v, bool) else v}" for k, v in extra.items()]


def test_caliscope_toml(tmp_path: Path) -> None:
    """caliscope's camera_array.toml ([cameras.N], the rotation a 3x3 matrix in files before 2025, a Rodrigues vector
    since) and its older config.toml ([cam_N] with port, beside its [charuco] board and [capture_volume]): cameras
    named cam_N as its own Anipose export names them, an ignored or unposed camera left out, world Z-up, metres.
    The old reader refused the 3x3 rotation ("K and R must be 3x3") and named the cameras 0, 1, 2."""
    cams = _cams()
    lines = []
    for i, c in enumerate(cams):
        R, _ = _z_up(c.R, c.t)
        rotation = R.tolist() if i != 1 else cv2.Rodrigues(R)[0].ravel().tolist()
        lines += [f"[cameras.{i}]", f"cam_id = {i}", *_caliscope_camera(c, rotation, ignore=False), ""]
    # camera 3 has intrinsics only (not posed), camera 4 is ignored
    lines += ["[cameras.3]", "cam_id = 3", "size = [640, 480]", f"matrix = {cams[0].K.tolist()}",
              f"distortions = {DIST.tolist()}", "ignore = false", ""]  # fmt: skip
    lines += ["[cameras.4]", "cam_id = 4", *_caliscope_camera(cams[0], cv2.Rodrigues(cams[0].R)[0].ravel().tolist(),
              ignore=True), ""]  # fmt: skip
    (tmp_path / "camera_array.toml").write_text("\n".join(lines))
    calib = read_any(tmp_path / "camera_array.toml")
    _same(calib, ["cam_0", "cam_1", "cam_2"])
    np.testing.assert_allclose(calib.cameras[2].dist, DIST)
    lines = ["CreationDate = 2023-05-06T11:12:27.631355", "fps_recording = 24", ""]
    for i, c in enumerate(cams):
        R, _ = _z_up(c.R, c.t)
        lines += [f"[cam_{i}]", f"port = {i}", *_caliscope_camera(c, R.tolist(), ignore=False), ""]
    lines += ["[capture_volume]", "stage = 2", "", "[charuco]", "columns = 4", "rows = 5", 'units = "inch"', ""]
    (tmp_path / "config.toml").write_text("\n".join(lines))
    _same(read_any(tmp_path / "config.toml"), ["cam_0", "cam_1", "cam_2"])
    (tmp_path / "none.toml").write_text(
        "[cameras.0]\ncam_id = 0\nsize = [640, 480]\nmatrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n"
    )
    with pytest.raises(CalibrationError, match="no camera table with a posed camera"):
        read_any(tmp_path / "none.toml")
    bad = (
        "[cam_0]\nname = 'a'\nsize = [640, 480]\nmatrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n"
        "distortions = [0, 0, 0, 0]\nrotation = [1, 2]\ntranslation = [0, 0, 1]\n"
    )
    (tmp_path / "bad.toml").write_text(bad)
    with pytest.raises(CalibrationError, match="Rodrigues vector"):
        read_any(tmp_path / "bad.toml")


def test_floor_and_refusals(tmp_path: Path) -> None:
    doc = {"0": {"K": _cams()[0].K.ravel().tolist(), "RT": np.column_stack([*_z_up(_cams()[0].R, _cams()[0].t)])
                 .ravel().tolist(), "imgSize": [640, 480]}}  # fmt: skip
    (tmp_path / "c.json").write_text(json.dumps(doc))
    calib = read_any(tmp_path / "c.json")
    lifted = on_floor(calib, 0.9)  # a floor 0.9 m up: the same pixels once the world moves down by 0.9 m
    np.testing.assert_allclose(
        lifted.cameras[0].project(POINTS_Y_UP - [0.0, 0.9, 0.0]), calib.cameras[0].project(POINTS_Y_UP), atol=1e-6
    )
    (tmp_path / "bad.json").write_text('{"0": {"R": [1, 2, 3]}}')
    with pytest.raises(CalibrationError, match="no intrinsics"):
        read_any(tmp_path / "bad.json")
    (tmp_path / "nan.json").write_text('{"0": {"K": [1, 0, 0, 0, 1, 0, 0, 0, NaN], "RT": [0]}}')
    with pytest.raises(CalibrationError, match="non-finite"):
        read_any(tmp_path / "nan.json")
    (tmp_path / "empty.json").write_text("[]")
    with pytest.raises(CalibrationError, match="no cameras"):
        read_any(tmp_path / "empty.json")
    (tmp_path / "text.json").write_text("{")
    with pytest.raises(CalibrationError, match="not JSON"):
        read_any(tmp_path / "text.json")

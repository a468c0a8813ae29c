"""Camera calibration files: mocapd's own TOML, Pose2Sim/OpenCV TOML, Qualisys ``Calib.qca.txt``, OpenCV YAML.

Everything is read into a :class:`CalibrationSet` in mocapd's conventions (DESIGN.md): world right-handed, +Y up,
metres; per camera ``x_cam = R @ X_world + t`` (world→camera, OpenCV camera axes: x right, y down, z forward),
pixel intrinsics ``K`` and OpenCV distortion ``(k1, k2, p1, p2, k3)``.

mocapd calibration TOML (``format = "mocapd-calibration"``, ``version = 1``)::

    format = "mocapd-calibration"
    version = 1
    world = "right-handed, +Y up, metres, floor y=0"

    [[camera]]
    name = "cam01"
    size = [1088, 1920]                  # width, height in pixels
    K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
    dist = [k1, k2, p1, p2, k3]          # OpenCV model
    R = [[...], [...], [...]]            # world -> camera rotation
    t = [tx, ty, tz]                     # world -> camera translation, metres
    reprojection_error_px = 0.41         # optional: RMS from the calibration that produced it
    time_offset_s = 0.067                # optional: frames this late, s ([daemon.offsets] cameras convention)

Foreign conventions handled on import/export:

* Pose2Sim TOML: one table per camera with ``size``, ``matrix``, ``distortions`` (k1 k2 p1 p2), ``rotation``
  (Rodrigues vector, world→camera), ``translation`` (metres); its world is Z-up.
* Qualisys ``.qca.txt`` (as shipped with Pose2Sim): focal lengths and principal points in 1/64 pixel, principal
  point relative to the sensor (minus the video field-of-view offset), camera position in mm and camera
  orientation (rows: the camera's axes in the world) with the camera looking along -Z and +Y up in the image;
  world Z-up.
  Converted as Pose2Sim's ``calib_qca_fun`` does (world→camera, then rotate by π about the camera's x axis), except
  for the distortion coefficients: Pose2Sim divides them by 64 like the pixel values, but they are dimensionless.
  Calibrating the four demo cameras from their own checkerboard images gives k1 ≈ -0.03…-0.05, k2 ≈ 0.01…0.15,
  the file holds k1 ≈ -0.047, k2 ≈ 0.137 (``tests/test_board_calibration.py``). Pass
  ``pose2sim_distortion=True`` to reproduce Pose2Sim's numbers.
* OpenCV YAML (``cv2.FileStorage``): Pose2Sim's ``names`` + ``K_<name>``, ``dist_<name>``, ``R_<name>``
  (Rodrigues), ``T_<name>`` layout, or a single camera as ``camera_matrix``, ``distortion_coefficients``,
  ``image_width``, ``image_height`` (+ optional ``rvec``/``tvec``).

* K/R/t JSON (``.json``) of the multi-view benchmarks and their code bases, told apart by their keys:

  - 4D association's ``calibration.json`` (Shelf, Campus as its repository ships them): per camera name ``K`` (9
    numbers), ``R`` (3: Rodrigues, or 9) and ``T`` (3), or ``RT`` (3x4), ``imgSize`` [w, h], ``distCoeff``;
    world→camera, metres, world Z-up;
  - VoxelPose's ``calibration_shelf.json`` / ``calibration_campus.json``: per camera ``fx fy cx cy``, ``R`` (3x3),
    ``T`` the camera's **centre** in the world (``x_cam = R (X - T)``), ``k`` (k1 k2 k3) and ``p`` (p1 p2),
    millimetres, world Z-up, no image size (twice the principal point, as Pose2Sim does);
  - CMU Panoptic's ``calibration_<sequence>.json``: ``cameras[]`` with ``name``, ``type``, ``resolution``, ``K``,
    ``distCoef``, ``R``, ``t`` (world→camera, centimetres); its world is Y-down (the people stand towards -y); its
    HD cameras only (``type = "hd"``: the 480 VGA and 10 Kinect cameras are left out);
  - any list ``[{"name", "K", "R", "t", "dist", "size"}, ...]`` or object of such cameras (metres, +Y up).

* caliscope's ``camera_array.toml`` (``[cameras.N]``) or ``config.toml`` (``[cam_N]`` with ``port``, beside its
  board's tables): Pose2Sim's keys without ``name``, the rotation a 3x3 matrix (files before 2025) or a Rodrigues
  vector, metres, world Z-up; cameras named ``cam_N``, ignored and unposed ones left out.

* EasyMocap's ``intri.yml`` + ``extri.yml`` (OpenCV YAML, one beside the other; either may be named): ``names``,
  ``K_<name>``, ``dist_<name>`` and ``Rot_<name>`` (3x3) or ``R_<name>`` (Rodrigues), ``T_<name>``; metres, world
  Z-up (a board on the floor).

Z-up worlds are turned +Y up by ``X_y = (x, z, -y)`` of ``X_z = (x, y, z)`` (a rotation, so handedness is kept);
Y-down worlds by ``(x, -y, -z)``. :func:`read_any` takes the world's up axis, the translations' unit and the floor's
height from the caller where a file's own convention is not the one wanted (``mocapd import keypoints --up z
--units mm --floor M``).
"""

from __future__ import annotations

import json
import math
import tomllib
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.names import check_name
from mocapd.errors import CalibrationError
from mocapd.io.calibration_units import UNITS
from mocapd.io.input_files import open_input, read_input_bytes
from mocapd.io.output_files import atomic_path, write_text_atomic

FloatArray = NDArray[np.float64]
WorldUp = Literal["y", "z", "-y"]

# Z-up world -> mocapd's Y-up world: X_y = Z_TO_Y @ X_z.
Z_TO_Y: FloatArray = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


MAX_CAMERAS = 256
"""Most cameras one calibration file may hold."""
MAX_FILE_BYTES = 16 << 20
"""Largest calibration file read (a calibration of 256 cameras is ~200 KB of text)."""
MAX_IMAGE_PX = 65535
"""Largest image side a calibration may give (the session format's 16-bit sizes)."""


def _side(v: object) -> str:
    """An image side for a message: a huge one by its magnitude (``size = [1e308, ...]`` in a Pose2Sim file, rounded
    to an integer, printed 309 digits, issue 45)."""
    if isinstance(v, int) and abs(v) >= 10**9:
        return f"about 1e{int(abs(v).bit_length() * 0.30103)}"
    return f"{v:g}" if isinstance(v, float) else str(v)


@dataclass(frozen=True)
class CameraCalibration:
    """One calibrated camera in mocapd's conventions.

    Attributes
    ----------
    name : str
    size : (width, height)
        Image size in pixels.
    K : ndarray, shape (3, 3)
        Intrinsic matrix (pixels).
    dist : ndarray, shape (5,)
        OpenCV distortion (k1, k2, p1, p2, k3).
    R : ndarray, shape (3, 3)
        World→camera rotation.
    t : ndarray, shape (3,)
        World→camera translation in metres.
    error_px : float or None
        RMS reprojection error of the calibration that produced it.
    time_offset_s : float or None
        How far the camera's time stamps run ahead of the rig's (its frames show the scene this late), seconds, in
        the convention of ``[daemon.offsets] cameras``; where a calibration estimated it (``mocapd calibrate
        cameras --from-people``), None where nothing did. The daemon applies only the config's offsets.
    """

    name: str
    size: tuple[int, int]
    K: FloatArray
    dist: FloatArray = field(default_factory=lambda: np.zeros(5))
    R: FloatArray = field(default_factory=lambda: np.eye(3))
    t: FloatArray = field(default_factory=lambda: np.zeros(3))
    error_px: float | None = None
    time_offset_s: float | None = None

    def __post_init__(self) -> None:
        check_name(self.name, "camera name", CalibrationError)  # the config's rule: the name must match one there
        K = np.asarray(self.K, np.float64)
        dist = np.zeros(5)
        d = np.asarray(self.dist, np.float64).reshape(-1)[:5]
        dist[: d.size] = d
        R = np.asarray(self.R, np.float64)
        t = np.asarray(self.t, np.float64).reshape(-1)
        if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
            raise CalibrationError(
                f"camera {self.name!r}: K and R must be 3x3 and t has 3 values (got {K.shape}, {R.shape}, {t.shape})"
            )
        if not (
            np.all(np.isfinite(K)) and np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and np.all(np.isfinite(dist))
        ):
            raise CalibrationError(f"camera {self.name!r}: non-finite calibration values")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise CalibrationError(f"camera {self.name!r}: focal lengths must be positive, got K={K.tolist()}")
        width, height = self.size
        if not all(isinstance(v, int | float) and math.isfinite(v) and 1 <= v <= MAX_IMAGE_PX for v in (width, height)):
            raise CalibrationError(
                f"camera {self.name!r}: image size {_side(width)}x{_side(height)}; allowed: 1..{MAX_IMAGE_PX} px"
            )
        if self.error_px is not None and not (math.isfinite(self.error_px) and self.error_px >= 0):
            raise CalibrationError(f"camera {self.name!r}: reprojection error {self.error_px!r}; allowed: >= 0 px")
        if self.time_offset_s is not None and not (
            isinstance(self.time_offset_s, int | float) and math.isfinite(self.time_offset_s)
            and abs(self.time_offset_s) <= 1.0
        ):  # fmt: skip
            raise CalibrationError(f"camera {self.name!r}: time offset {self.time_offset_s!r}; allowed: -1..1 s")
        if abs(np.linalg.det(R) - 1.0) > 1e-3 or not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
            raise CalibrationError(f"camera {self.name!r}: R is not a rotation matrix (det={np.linalg.det(R):.4f})")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "size", (int(self.size[0]), int(self.size[1])))

    @property
    def center(self) -> FloatArray:
        """Camera centre in world coordinates, shape (3,), metres."""
        return -self.R.T @ self.t

    def project(self, points: FloatArray) -> FloatArray:
        """Project world points, shape (n, 3), to pixels, shape (n, 2), with distortion."""
        rvec, _ = cv2.Rodrigues(self.R)
        pixels, _ = cv2.projectPoints(np.asarray(points, np.float64).reshape(-1, 1, 3), rvec, self.t, self.K, self.dist)
        return np.asarray(pixels, np.float64).reshape(-1, 2)


@dataclass(frozen=True)
class CalibrationSet:
    """The calibration of a camera rig, world right-handed, +Y up, metres."""

    cameras: tuple[CameraCalibration, ...]
    source: str = ""

    def __post_init__(self) -> None:
        names = [c.name for c in self.cameras]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:  # which one would a camera of the config get?
            raise CalibrationError(f"camera(s) {twice} appear more than once in the calibration")
        if len(names) > MAX_CAMERAS:
            raise CalibrationError(f"{len(names)} cameras; a calibration holds at most {MAX_CAMERAS}")

    def __getitem__(self, name: str) -> CameraCalibration:
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise KeyError(name)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]


def world_z_up_to_y_up(cam: CameraCalibration) -> CameraCalibration:
    """Re-express a camera calibrated in a Z-up world in mocapd's Y-up world (same camera, same pixels)."""
    return replace(cam, R=cam.R @ Z_TO_Y.T)


def world_y_up_to_z_up(cam: CameraCalibration) -> CameraCalibration:
    """Inverse of :func:`world_z_up_to_y_up`."""
    return replace(cam, R=cam.R @ Z_TO_Y)


# Y-down world (CMU Panoptic's) -> mocapd's Y-up world: half a turn about x (y and z negated; handedness kept).
Y_DOWN_TO_Y: FloatArray = np.diag([1.0, -1.0, -1.0])


def _to_y_up(cams: Sequence[CameraCalibration], world_up: WorldUp) -> tuple[CameraCalibration, ...]:
    if world_up not in ("y", "z", "-y"):
        raise CalibrationError(f"world_up must be 'y', 'z' or '-y', got {world_up!r}")
    if world_up == "-y":
        return tuple(replace(c, R=c.R @ Y_DOWN_TO_Y.T) for c in cams)
    return tuple(world_z_up_to_y_up(c) if world_up == "z" else c for c in cams)


# -- mocapd TOML -------------------------------------------------------------------------------------------------


def _fmt(values: Any) -> str:
    arr = np.asarray(values, np.float64)
    if arr.ndim == 1:
        return "[" + ", ".join(repr(float(v)) for v in arr) + "]"
    return "[" + ", ".join(_fmt(row) for row in arr) + "]"


def write_mocapd_toml(calib: CalibrationSet, path: Path) -> None:
    """Write ``calib`` as mocapd's calibration TOML (see module docstring)."""
    lines = [
        'format = "mocapd-calibration"',
        "version = 1",
        'world = "right-handed, +Y up, metres, floor y=0"',
        f"source = {_quote(calib.source)}",
    ]
    for cam in calib.cameras:
        lines += [
            "",
            "[[camera]]",
            f"name = {_quote(cam.name)}",
            f"size = [{cam.size[0]}, {cam.size[1]}]  # width, height in pixels",
            f"K = {_fmt(cam.K)}",
            f"dist = {_fmt(cam.dist)}  # k1, k2, p1, p2, k3",
            f"R = {_fmt(cam.R)}  # world -> camera",
            f"t = {_fmt(cam.t)}  # world -> camera, metres",
        ]
        if cam.error_px is not None:
            lines.append(f"reprojection_error_px = {cam.error_px!r}")
        if cam.time_offset_s is not None:
            lines.append(f"time_offset_s = {cam.time_offset_s!r}  # as [daemon.offsets] cameras: frames this late")
    write_text_atomic(path, "\n".join(lines) + "\n")


def _quote(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _read(path: Path) -> bytes:
    """A calibration file's bytes: a regular file of at most :data:`MAX_FILE_BYTES` (a FIFO or a device is
    refused, not waited on or read without end)."""
    return read_input_bytes(path, "calibration file", max_bytes=MAX_FILE_BYTES, error=CalibrationError)


def _load_toml(path: Path) -> dict[str, Any]:
    data = _read(path)
    try:
        return tomllib.loads(data.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"cannot read calibration {path}: {exc}") from exc


def read_mocapd_toml(path: Path) -> CalibrationSet:
    """Read mocapd's calibration TOML.

    Raises
    ------
    CalibrationError
        If the file is not a mocapd calibration, has an unknown version or a malformed camera.
    """
    data = _load_toml(path)
    if data.get("format") != "mocapd-calibration":
        raise CalibrationError(f"{path} is not a mocapd calibration (format = {data.get('format')!r})")
    if data.get("version") != 1:
        raise CalibrationError(f"{path}: calibration version {data.get('version')!r} is not supported (1 is)")
    cams = []
    for i, c in enumerate(data.get("camera", [])):
        try:
            cams.append(
                CameraCalibration(
                    c["name"],
                    tuple(c["size"]),
                    np.array(c["K"]),
                    np.array(c["dist"]),
                    np.array(c["R"]),
                    np.array(c["t"]),
                    c.get("reprojection_error_px"),
                    c.get("time_offset_s"),
                )
            )
        except KeyError as exc:
            raise CalibrationError(f"{path}: camera #{i} lacks key {exc}") from exc
    if not cams:
        raise CalibrationError(f"{path} holds no [[camera]]")
    return CalibrationSet(tuple(cams), str(data.get("source", "")))


# -- Pose2Sim TOML ------------------------------------------------------------------------------------------------


_CALISCOPE_KEYS = frozenset({"port", "cam_id", "grid_count", "rotation_count", "verified_resolutions"})
"""Keys only caliscope writes in a camera's table (its ``camera_array.toml`` / ``config.toml``)."""


def _rotation(value: object) -> FloatArray:
    """A world->camera rotation given as a Rodrigues vector (Pose2Sim, Anipose, caliscope since 2025) or as a 3x3
    matrix (caliscope's ``config.toml`` and older ``camera_array.toml``)."""
    r = np.array(value, np.float64)
    if r.shape == (3, 3):
        return r
    if r.size != 3:
        raise CalibrationError(f"rotation: a Rodrigues vector (3) or a 3x3 matrix expected, got shape {r.shape}")
    R, _ = cv2.Rodrigues(r.reshape(3))
    return np.asarray(R, np.float64)


def _toml_cameras(data: dict[str, Any]) -> tuple[list[tuple[str, dict[str, Any]]], bool]:
    """The camera tables of a Pose2Sim/Anipose or caliscope TOML (name, table) and whether it is caliscope's.

    caliscope keeps its cameras under ``[cameras.N]`` (``camera_array.toml``) or as ``[cam_N]`` beside its charuco
    board and capture-volume tables (``config.toml``), named by number: they are named ``cam_N`` here, as caliscope's
    own Anipose export names them; a camera it marks ``ignore`` or has not posed (no rotation) is left out."""
    nested = isinstance(data.get("cameras"), dict)
    tables = data["cameras"] if nested else data
    caliscope = nested or any(isinstance(c, dict) and _CALISCOPE_KEYS & set(c) for c in tables.values())
    out = []
    for key, c in tables.items():
        if key == "metadata" or not isinstance(c, dict):
            continue
        if caliscope:
            if "matrix" not in c or c.get("ignore") is True or "rotation" not in c or "translation" not in c:
                continue  # the board, the capture volume, an ignored or unposed camera
            name = f"cam_{key}" if nested else str(key)
        else:
            name = str(c.get("name", key))
        out.append((name, c))
    return out, caliscope


def read_pose2sim_toml(path: Path, world_up: WorldUp = "z") -> CalibrationSet:
    """Read a Pose2Sim, Anipose or caliscope (OpenCV convention) calibration TOML; its world is Z-up unless
    ``world_up`` says otherwise."""
    data = _load_toml(path)
    tables, caliscope = _toml_cameras(data)
    cams = []
    for key, c in tables:
        try:
            R = _rotation(c["rotation"])
            cams.append(
                CameraCalibration(
                    key,
                    (round(c["size"][0]), round(c["size"][1])),
                    np.array(c["matrix"], np.float64),
                    np.array(c["distortions"], np.float64),
                    np.asarray(R, np.float64),
                    np.array(c["translation"], np.float64),
                )
            )
        except KeyError as exc:
            raise CalibrationError(f"{path}: camera [{key}] lacks key {exc}") from exc
    if not cams:
        raise CalibrationError(f"{path} holds no camera table" + (" with a posed camera" if caliscope else ""))
    kind = "caliscope-toml" if caliscope else "pose2sim-toml"
    return CalibrationSet(_to_y_up(cams, world_up), f"{kind}:{Path(path).name}")


def write_pose2sim_toml(calib: CalibrationSet, path: Path, world_up: WorldUp = "z") -> None:
    """Write ``calib`` as Pose2Sim TOML (world Z-up by default; k3 is dropped, Pose2Sim keeps four terms)."""
    lines = []
    for cam in calib.cameras:
        c = world_y_up_to_z_up(cam) if world_up == "z" else cam
        rvec = cv2.Rodrigues(c.R)[0].reshape(3)
        lines += [
            f"[{c.name}]",
            f"name = {_quote(c.name)}",
            f"size = [{float(c.size[0])}, {float(c.size[1])}]",
            f"matrix = {_fmt(c.K)}",
            f"distortions = {_fmt(c.dist[:4])}",
            f"rotation = {_fmt(rvec)}",
            f"translation = {_fmt(c.t)}",
            "fisheye = false",
            "",
        ]
    lines += ["[metadata]", "adjusted = false", "error = 0.0", ""]
    write_text_atomic(path, "\n".join(lines))


# -- Qualisys .qca.txt ----------------------------------------------------------------------------------------------


def _rot_x(angle: float) -> FloatArray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def read_qca(
    path: Path, binning_factor: int = 1, world_up: WorldUp = "z", *, pose2sim_distortion: bool = False
) -> CalibrationSet:
    """Read a Qualisys ``Calib.qca.txt`` (world Z-up in Qualisys/Pose2Sim practice).

    Parameters
    ----------
    path : Path
    binning_factor : int
        1, or 2 when the videos were filmed binned (Pose2Sim's ``binning_factor``).
    world_up : {'z', 'y'}
        Up axis of the file's world.
    pose2sim_distortion : bool
        Divide the distortion coefficients by 64 (and the binning factor) as Pose2Sim does.
    """
    data = _read(path)
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise CalibrationError(f"cannot read Qualisys calibration {path}: {exc}") from exc
    cams: list[CameraCalibration] = []
    for node in root.findall("cameras/camera"):
        name = node.get("serial", f"cam{len(cams) + 1}")
        fov, intr, tr = node.find("fov_video"), node.find("intrinsic"), node.find("transform")
        if fov is None or intr is None or tr is None:
            raise CalibrationError(f"{path}: camera {name} lacks fov_video, intrinsic or transform")
        try:
            g = {k: float(v) for k, v in {**fov.attrib, **intr.attrib, **tr.attrib}.items() if _is_float(v)}
            b = binning_factor
            size = (
                round((g["right"] - g["left"] + 1) / b),
                round((g["bottom"] - g["top"] + 1) / b),
            )
            K = np.array(
                [
                    [g["focalLengthU"] / 64 / b, 0.0, g["centerPointU"] / 64 / b - g["left"]],
                    [0.0, g["focalLengthV"] / 64 / b, g["centerPointV"] / 64 / b - g["top"]],
                    [0.0, 0.0, 1.0],
                ]
            )
            dist = np.array(
                [
                    g["radialDistortion1"],
                    g["radialDistortion2"],
                    g["tangentalDistortion1"],
                    g["tangentalDistortion2"],
                    0.0,
                ]
            ) / (64 * b if pose2sim_distortion else 1.0)
            # r11..r33 read row by row: the camera's axes in world coordinates are the rows; position in mm.
            R_file = np.array([[g[f"r{i}{j}"] for j in (1, 2, 3)] for i in (1, 2, 3)])
            position = np.array([g["x"], g["y"], g["z"]]) / 1000.0
        except KeyError as exc:
            raise CalibrationError(f"{path}: camera {name} lacks attribute {exc}") from exc
        # Same steps as Pose2Sim: world->camera, then turn the Qualisys camera (looking along -Z, image +Y up)
        # into an OpenCV camera (looking along +Z, image +Y down) by a rotation of pi about its x axis.
        R = R_file
        t = -R @ position
        flip = _rot_x(math.pi)
        cams.append(CameraCalibration(name, size, K, dist, flip @ R, flip @ t, None))
    if not cams:
        raise CalibrationError(f"{path} holds no camera")
    return CalibrationSet(_to_y_up(cams, world_up), f"qca:{Path(path).name}")


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


# -- OpenCV YAML --------------------------------------------------------------------------------------------------


MAX_MATRIX_SIDE = 16
"""Largest row or column count of a matrix in a calibration (3x3 K, up to 14 distortion coefficients)."""


def _mat(fs: Any, key: str, path: Path) -> Any:
    """The matrix ``key`` of an open FileStorage, or None when absent; its header checked first.

    OpenCV's ``FileNode.mat()`` trusts ``rows``/``cols``/``sizes`` and ``dt``: a damaged header (``cols: -1``, a
    count that disagrees with ``data``) corrupts the heap and aborts the whole process (``malloc(): invalid
    size``), past any ``except``. So the header is read as plain nodes and checked against ``data`` before it.
    """
    node = fs.getNode(key)
    if node.empty():
        return None
    if not node.isMap():
        raise CalibrationError(f"{path}: {key} is not an OpenCV matrix")
    data = node.getNode("data")
    dt = node.getNode("dt")
    if not data.isSeq() or not dt.isString() or dt.string() not in ("d", "f"):
        raise CalibrationError(f"{path}: {key}: an OpenCV matrix of 'd' or 'f' numbers with a 'data' list expected")
    sizes_node = node.getNode("sizes")
    if not sizes_node.empty():  # !!opencv-nd-matrix
        sizes = [sizes_node.at(i) for i in range(sizes_node.size())] if sizes_node.isSeq() else []
        dims = [int(n.real()) if n.isInt() else -1 for n in sizes]
    else:  # !!opencv-matrix
        rows, cols = node.getNode("rows"), node.getNode("cols")
        dims = [int(n.real()) if n.isInt() else -1 for n in (rows, cols)]
    if not dims or not all(1 <= d <= MAX_MATRIX_SIDE for d in dims) or math.prod(dims) != data.size():
        raise CalibrationError(
            f"{path}: {key}: matrix dimensions {dims} do not match its {data.size()} values "
            f"(each dimension 1..{MAX_MATRIX_SIDE})"
        )
    if not all(data.at(i).isReal() or data.at(i).isInt() for i in range(data.size())):
        raise CalibrationError(f"{path}: {key}: a value of its data is not a number")
    return node.mat()


EASYMOCAP_FILES = ("intri.yml", "extri.yml")


def _open_yaml(path: Path) -> Any:
    with open_input(path, "calibration file", max_bytes=MAX_FILE_BYTES, error=CalibrationError):
        pass  # a regular file of a sane size: OpenCV opens it by name (and would wait on a FIFO)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise CalibrationError(f"cannot open OpenCV YAML {path}")
    return fs


def read_easymocap(path: Path, world_up: WorldUp = "z") -> CalibrationSet:
    """EasyMocap's ``intri.yml`` and ``extri.yml``, from the folder of ``path`` (either of them)."""
    folder = Path(path).parent
    intri, extri = (_open_yaml(folder / n) for n in EASYMOCAP_FILES)
    try:
        names_node = intri.getNode("names")
        if names_node.empty() or not names_node.isSeq():
            raise CalibrationError(f"{folder / 'intri.yml'}: no 'names' list")
        cams = []
        for i in range(names_node.size()):
            name = names_node.at(i).string()
            K, dist = _mat(intri, f"K_{name}", folder / "intri.yml"), _mat(intri, f"dist_{name}", folder / "intri.yml")
            rot, rvec = _mat(extri, f"Rot_{name}", folder / "extri.yml"), _mat(extri, f"R_{name}", folder / "extri.yml")
            tvec = _mat(extri, f"T_{name}", folder / "extri.yml")
            if K is None or dist is None or tvec is None or (rot is None and rvec is None):
                raise CalibrationError(f"{folder}: camera {name} lacks K_, dist_ (intri.yml), Rot_ or R_, or T_ "
                                       "(extri.yml)")  # fmt: skip
            R = rot.reshape(3, 3) if rot is not None else cv2.Rodrigues(rvec.reshape(3))[0]
            w, h = intri.getNode(f"W_{name}"), intri.getNode(f"H_{name}")
            size = (
                (int(w.real()), int(h.real()))
                if w.isInt() or w.isReal()
                else (round(2 * K[0, 2]), round(2 * K[1, 2]))  # as Pose2Sim: twice the principal point
            )
            cams.append(CameraCalibration(name, size, K, dist.reshape(-1), R, tvec.reshape(3)))
    finally:
        intri.release()
        extri.release()
    return CalibrationSet(_to_y_up(cams, world_up), f"easymocap:{folder.name}")


def read_opencv_yaml(path: Path, world_up: WorldUp = "y") -> CalibrationSet:
    """Read OpenCV ``FileStorage`` YAML (Pose2Sim multi-camera layout or one camera); see module docstring."""
    with open_input(path, "calibration file", max_bytes=MAX_FILE_BYTES, error=CalibrationError):
        pass  # a regular file of a sane size: OpenCV opens it by name (and would wait on a FIFO)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise CalibrationError(f"cannot open OpenCV YAML {path}")
    try:
        names_node = fs.getNode("names")
        cams = []
        if not names_node.empty():
            for i in range(names_node.size()):
                name = names_node.at(i).string()
                K = _mat(fs, f"K_{name}", path)
                dist = _mat(fs, f"dist_{name}", path)
                rvec, tvec = _mat(fs, f"R_{name}", path), _mat(fs, f"T_{name}", path)
                size_mat = _mat(fs, f"size_{name}", path)
                if K is None or dist is None:
                    raise CalibrationError(f"{path}: camera {name} lacks K_{name} or dist_{name}")
                size = (
                    tuple(int(v) for v in size_mat.reshape(-1)[:2])
                    if size_mat is not None
                    else (round(2 * K[0, 2]), round(2 * K[1, 2]))  # as Pose2Sim: twice the principal point
                )
                R = cv2.Rodrigues(rvec.reshape(3))[0] if rvec is not None else np.eye(3)
                t = tvec.reshape(3) if tvec is not None else np.zeros(3)
                cams.append(CameraCalibration(name, size, K, dist.reshape(-1), R, t))  # type: ignore[arg-type]
        else:
            K = _mat(fs, "camera_matrix", path)
            dist = _mat(fs, "distortion_coefficients", path)
            if K is None or dist is None:
                raise CalibrationError(
                    f"{path}: neither a Pose2Sim 'names' list nor camera_matrix/distortion_coefficients found"
                )
            w, h = fs.getNode("image_width").real(), fs.getNode("image_height").real()
            rvec, tvec = _mat(fs, "rvec", path), _mat(fs, "tvec", path)
            R = cv2.Rodrigues(rvec.reshape(3))[0] if rvec is not None else np.eye(3)
            t = tvec.reshape(3) if tvec is not None else np.zeros(3)
            cams.append(
                CameraCalibration(
                    Path(path).stem,
                    (int(w), int(h)),
                    np.asarray(K, np.float64),
                    np.asarray(dist, np.float64),
                    np.asarray(R, np.float64),
                    np.asarray(t, np.float64),
                )
            )
    finally:
        fs.release()
    return CalibrationSet(_to_y_up(cams, world_up), f"opencv-yaml:{Path(path).name}")


def write_opencv_yaml(calib: CalibrationSet, path: Path, world_up: WorldUp = "y") -> None:
    """Write ``calib`` in the Pose2Sim multi-camera OpenCV YAML layout (plus ``size_<name>``)."""
    with atomic_path(path) as tmp:  # OpenCV writes the file itself: into a temporary one of the same suffix
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        try:
            fs.write("names", calib.names)
            for cam in calib.cameras:
                c = world_y_up_to_z_up(cam) if world_up == "z" else cam
                fs.write(f"size_{c.name}", np.array(c.size, np.float64))
                fs.write(f"K_{c.name}", c.K)
                fs.write(f"dist_{c.name}", c.dist.reshape(1, 5))
                fs.write(f"R_{c.name}", cv2.Rodrigues(c.R)[0])
                fs.write(f"T_{c.name}", c.t.reshape(3, 1))
        finally:
            fs.release()


# -- K/R/t JSON ---------------------------------------------------------------------------------------------------

JSON_DEFAULTS: dict[str, tuple[WorldUp, str]] = {
    "4d-association": ("z", "m"),
    "voxelpose": ("z", "mm"),
    "panoptic": ("-y", "cm"),
    "krt": ("y", "m"),
}
"""Each K/R/t JSON flavour's world up axis and translation unit (module docstring)."""


def _array(value: object, what: str) -> FloatArray:
    arr = np.asarray(value, dtype=np.float64)  # a ragged or non-numeric value raises ValueError (read_any says so)
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{what}: non-finite values")
    return arr


def _json_camera(name: str, c: dict[str, Any], flavour: str, where: str) -> CameraCalibration:
    """One camera of a K/R/t JSON file, in the file's units and world."""
    if "K" in c:
        K = _array(c["K"], f"{where} K").reshape(3, 3)
    elif all(k in c for k in ("fx", "fy", "cx", "cy")):
        fx, fy, cx, cy = (float(np.asarray(c[k], np.float64).reshape(-1)[0]) for k in ("fx", "fy", "cx", "cy"))
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    else:
        raise CalibrationError(f"{where}: no intrinsics (K, or fx fy cx cy)")
    R: FloatArray
    if "RT" in c:
        rt = _array(c["RT"], f"{where} RT").reshape(3, 4)
        R, t = rt[:, :3], rt[:, 3]
    else:
        r = _array(c.get("R", c.get("rvec", np.eye(3))), f"{where} R").reshape(-1)
        R = np.asarray(cv2.Rodrigues(r)[0], np.float64) if r.size == 3 else r.reshape(3, 3)
        t = _array(c.get("t", c.get("T", np.zeros(3))), f"{where} t").reshape(3)
        if flavour == "voxelpose":
            t = -R @ t  # VoxelPose's T is the camera's centre: x_cam = R (X - T)
    if "k" in c or "p" in c:
        k = _array(c.get("k", [0.0, 0.0, 0.0]), f"{where} k").reshape(-1)
        p = _array(c.get("p", [0.0, 0.0]), f"{where} p").reshape(-1)
        k = np.r_[k, np.zeros(3)][:3]
        p = np.r_[p, np.zeros(2)][:2]
        dist = np.array([k[0], k[1], p[0], p[1], k[2]])
    else:
        d: object = next((c[k] for k in ("distCoef", "distCoeff", "dist", "distortion") if k in c), [])
        dist = _array(d, f"{where} distortion").reshape(-1)
    size_value = next((c[k] for k in ("imgSize", "size", "resolution") if k in c), None)
    if size_value is not None:
        size = tuple(round(float(v)) for v in np.asarray(size_value, np.float64).reshape(-1)[:2])
    elif "width" in c and "height" in c:
        size = (int(c["width"]), int(c["height"]))
    else:
        size = (round(2 * K[0, 2]), round(2 * K[1, 2]))  # as Pose2Sim: twice the principal point
    if len(size) != 2:
        raise CalibrationError(f"{where}: the image size needs a width and a height")
    return CameraCalibration(str(c.get("name", name)), (size[0], size[1]), K, dist, R, t)


def _json_flavour(doc: object) -> str:
    if isinstance(doc, dict) and isinstance(doc.get("cameras"), list):
        return "panoptic" if any(isinstance(c, dict) and "distCoef" in c for c in doc["cameras"]) else "krt"
    cams = list(doc.values()) if isinstance(doc, dict) else doc if isinstance(doc, list) else []
    first = next((c for c in cams if isinstance(c, dict)), {})
    if "fx" in first and ("k" in first or "p" in first):
        return "voxelpose"
    if "imgSize" in first or "RT" in first:
        return "4d-association"
    return "krt"


def read_json_calibration(path: Path, world_up: WorldUp | None = None, units: str | None = None) -> CalibrationSet:
    """A K/R/t JSON calibration (module docstring); ``world_up`` and ``units`` override the flavour's own."""
    data = _read(path)
    try:
        doc = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise CalibrationError(f"cannot read calibration {path}: not JSON: {exc}") from None
    flavour = _json_flavour(doc)
    if isinstance(doc, dict) and isinstance(doc.get("cameras"), list):
        items = [(str(c.get("name", i)), c) for i, c in enumerate(doc["cameras"]) if isinstance(c, dict)]
        if flavour == "panoptic":
            # HD cameras: type "hd" (panel 0 in files without types); VGA panels 1-20, Kinects panel 50
            items = [(n, c) for n, c in items if c.get("type", "hd" if c.get("panel", 0) == 0 else "other") == "hd"]
    elif isinstance(doc, dict):
        items = [(str(k), c) for k, c in doc.items() if isinstance(c, dict)]
    elif isinstance(doc, list):
        items = [(str(c.get("name", i)), c) for i, c in enumerate(doc) if isinstance(c, dict)]
    else:
        items = []
    if not items:
        raise CalibrationError(f"{path}: no cameras (a K/R/t JSON calibration: see docs/cameras.md)")
    if len(items) > MAX_CAMERAS:
        raise CalibrationError(f"{path}: {len(items)} cameras; a calibration holds at most {MAX_CAMERAS}")
    cams = [_json_camera(name, c, flavour, f"{path}: camera {name}") for name, c in items]
    up, unit = JSON_DEFAULTS[flavour]
    calib = CalibrationSet(_to_y_up(cams, world_up or up), f"{flavour}-json:{Path(path).name}")
    return in_metres(calib, units or unit)


def on_floor(calib: CalibrationSet, floor_m: float) -> CalibrationSet:
    """The world moved down so that a floor ``floor_m`` metres up the (+Y) axis becomes y = 0."""
    if not math.isfinite(floor_m):
        raise CalibrationError(f"floor height {floor_m!r}: a finite number of metres expected")
    if floor_m == 0:
        return calib
    lift = np.array([0.0, floor_m, 0.0])
    cams = tuple(replace(c, t=c.t + c.R @ lift) for c in calib.cameras)  # X_new = X - lift
    return CalibrationSet(cams, source=f"{calib.source} (floor at {floor_m:g} m)" if calib.source else "")


def turned(calib: CalibrationSet, rotation: FloatArray) -> CalibrationSet:
    """The same cameras in a world turned by ``rotation`` (3x3): a point ``X`` of the old world is ``rotation @ X``
    in the new one (``mocapd import keypoints --up auto`` levels the world with it)."""
    rot = np.asarray(rotation, dtype=np.float64)
    cams = tuple(replace(c, R=c.R @ rot.T) for c in calib.cameras)
    return CalibrationSet(cams, source=f"{calib.source} (levelled)" if calib.source else "")


def read_any(path: Path, world_up: WorldUp | None = None, units: str | None = None) -> CalibrationSet:
    """Read a calibration in any supported format, chosen from its name and content.

    ``world_up`` overrides the format's default world up axis (Z for Qualisys/Pose2Sim/EasyMocap and the benchmarks'
    JSON, -Y for CMU Panoptic, Y for mocapd/OpenCV YAML), ``units`` the unit of its translations (metres, except
    VoxelPose's millimetres and Panoptic's centimetres; Qualisys files say theirs).

    Raises
    ------
    CalibrationError
        The file cannot be read, or is not a valid calibration of its format: damaged syntax (OpenCV's YAML
        parser raises ``cv2.error``), a value of the wrong type or shape, a missing key.
    """
    try:
        return _read_any(Path(path), world_up, units)
    except CalibrationError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, AttributeError, OverflowError, cv2.error, SystemError) as exc:
        # A file door: whatever the format's reader trips over in a damaged file is the file's fault, said once.
        raise CalibrationError(f"{path}: not a valid calibration file: {type(exc).__name__}: {exc}") from None


def _read_any(path: Path, world_up: WorldUp | None, units: str | None) -> CalibrationSet:
    name = path.name.lower()
    if name.endswith(".json"):
        return read_json_calibration(path, world_up, units)
    if name.endswith(".qca.txt") or name.endswith(".qca"):
        calib = read_qca(path, world_up=world_up or "z")
    elif name in EASYMOCAP_FILES and all((path.parent / n).is_file() for n in EASYMOCAP_FILES):
        calib = read_easymocap(path, world_up=world_up or "z")
    elif name.endswith((".yml", ".yaml")):
        calib = read_opencv_yaml(path, world_up=world_up or "y")
    elif name.endswith(".toml"):
        data = _load_toml(path)
        if data.get("format") == "mocapd-calibration":
            calib = read_mocapd_toml(path)
        else:
            calib = read_pose2sim_toml(path, world_up=world_up or "z")
    else:
        raise CalibrationError(f"{path}: unknown calibration format (use .toml, .qca.txt, .yml, .yaml or .json)")
    return in_metres(calib, units or "m")


def scale_calibration(calib: CalibrationSet, scale: float) -> CalibrationSet:
    """The rig's calibration for images resized by ``scale`` (0.5: half-size images, as ``cv2.resize`` or 2x2
    binning makes them): focal lengths scale by it and the principal point follows pixel centres,
    ``c' = (c + 0.5) * scale - 0.5``; the size is rounded. Extrinsics and distortion are unchanged.

    Raises
    ------
    CalibrationError
        ``scale`` is not positive.
    """
    if not scale > 0:
        raise CalibrationError(f"image scale must be positive, got {scale}")
    out = []
    for c in calib.cameras:
        K = c.K.copy()
        K[0, 0] *= scale
        K[1, 1] *= scale
        K[0, 2] = (K[0, 2] + 0.5) * scale - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * scale - 0.5
        size = (round(c.size[0] * scale), round(c.size[1] * scale))
        out.append(CameraCalibration(c.name, size, K, c.dist, c.R, c.t, c.error_px))
    source = f"{calib.source} scaled by {scale:g}" if calib.source else f"scaled by {scale:g}"
    return CalibrationSet(tuple(out), source=source)


def in_metres(calib: CalibrationSet, unit: str) -> CalibrationSet:
    """A calibration whose translations are in ``unit`` (:data:`UNITS`), re-expressed in metres (a camera's centre
    scales with its translation; rotations, intrinsics and distortion are unit-free)."""
    if unit not in UNITS:
        raise CalibrationError(f"length unit {unit!r}; choose from {', '.join(UNITS)}")
    if unit == "m":
        return calib
    s = UNITS[unit]
    cams = tuple(replace(c, t=c.t * s) for c in calib.cameras)
    return CalibrationSet(cams, source=f"{calib.source} (translations in {unit})" if calib.source else "")


def core_cameras(calib: CalibrationSet, scale: float = 1.0) -> list[Camera]:
    """The rig as the solver's :class:`~mocapd.core.camera.Camera` objects, for images resized by ``scale``
    (:func:`scale_calibration`), in the calibration's order."""
    scaled = scale_calibration(calib, scale) if scale != 1.0 else calib
    return [Camera(c.name, c.size[0], c.size[1], c.K, c.R, c.t, c.dist) for c in scaled.cameras]

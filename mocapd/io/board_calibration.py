"""Calibration boards (checkerboard, ChArUco), their detection in images, and intrinsic calibration.

Intrinsics come from ``cv2.calibrateCamera`` on the board corners of several views. Each view gets its own RMS
reprojection error; views worse than ``max(max_view_error_px, 3 x median)`` are rejected one at a time (worst
first) and the calibration is redone, so one blurred or mis-detected image cannot spoil the result. Bad input
raises :class:`~mocapd.errors.CalibrationError` with what to do: no board found, too few views, or views too
alike (the board must be tilted in different directions for the focal length to be observable).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.errors import CalibrationError
from mocapd.io.media_files import read_image

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Board:
    """A planar calibration target. Board coordinates: x along columns, y along rows, z = 0 on the board, metres.

    Attributes
    ----------
    kind : {'checkerboard', 'charuco'}
    cols, rows : int
        Checkerboard: inner corners per row and per column (Pose2Sim's ``corners_nb`` order). ChArUco: squares in
        x and in y.
    square_m : float
        Square side in metres.
    marker_m : float
        ChArUco marker side in metres (ignored for checkerboards).
    dictionary : str
        ChArUco ArUco dictionary name, e.g. ``DICT_4X4_50``.
    """

    kind: Literal["checkerboard", "charuco"]
    cols: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self) -> None:
        if self.kind not in ("checkerboard", "charuco"):
            raise CalibrationError(f"board kind must be 'checkerboard' or 'charuco', got {self.kind!r}")
        if self.cols < 2 or self.rows < 2 or self.square_m <= 0:
            raise CalibrationError(f"board needs >= 2x2 corners and a positive square size, got {self}")
        if self.kind == "charuco" and not 0 < self.marker_m < self.square_m:
            raise CalibrationError("a ChArUco board needs 0 < marker_m < square_m")

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows if self.kind == "checkerboard" else (self.cols - 1) * (self.rows - 1)

    def object_points(self) -> FloatArray:
        """Board corners in board coordinates, shape (n_corners, 3), metres, in detection-id order."""
        nx, ny = (self.cols, self.rows) if self.kind == "checkerboard" else (self.cols - 1, self.rows - 1)
        offset = 0.0 if self.kind == "checkerboard" else self.square_m
        grid = np.mgrid[0:nx, 0:ny].T.reshape(-1, 2).astype(np.float64) * self.square_m + offset
        return np.hstack([grid, np.zeros((grid.shape[0], 1))])

    def charuco(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, dictionary)


@dataclass(frozen=True)
class Detection:
    """Board corners found in one image.

    Attributes
    ----------
    view : str
        Name of the image (file name).
    ids : ndarray, shape (n,), int
        Indices into :meth:`Board.object_points`.
    pixels : ndarray, shape (n, 2)
        Sub-pixel corner positions.
    size : (width, height)
        Image size.
    """

    view: str
    ids: NDArray[np.int64]
    pixels: FloatArray
    size: tuple[int, int]


def detect_board(image: NDArray[np.uint8], board: Board, view: str = "") -> Detection | None:
    """Find the board's corners in an image (BGR/RGB or gray), or None if it is not (fully) seen.

    Checkerboards must be seen whole; ChArUco boards need at least 6 corners.
    """
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    size = (gray.shape[1], gray.shape[0])
    if board.kind == "checkerboard":
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(gray, (board.cols, board.rows), flags=flags)
        if not found:
            return None
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
        corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), criteria)
        pixels = corners.reshape(-1, 2).astype(np.float64)
        return Detection(view, np.arange(len(pixels), dtype=np.int64), pixels, size)
    detector = cv2.aruco.CharucoDetector(board.charuco())
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < 6:
        return None
    return Detection(view, ids.reshape(-1).astype(np.int64), corners.reshape(-1, 2).astype(np.float64), size)


def detect_in_files(paths: Iterable[Path], board: Board) -> tuple[list[Detection], list[str]]:
    """Detect the board in image files. Returns the detections and the names of images without a board.

    Raises
    ------
    InputError
        A file that is not a readable picture (a FIFO, a device, over 512 MiB, not decodable): one line naming it.
    """
    found, missed = [], []
    for path in sorted(paths):
        image = read_image(path, "calibration image")  # a FIFO: InputError, one line, not a wait
        det = detect_board(image, board, Path(path).name)
        if det is None:
            missed.append(Path(path).name)
        else:
            found.append(det)
    return found, missed


@dataclass(frozen=True)
class IntrinsicsResult:
    """Result of an intrinsic calibration.

    Attributes
    ----------
    K : ndarray, shape (3, 3)
    dist : ndarray, shape (5,)
        OpenCV (k1, k2, p1, p2, k3).
    size : (width, height)
    rms_px : float
        RMS reprojection error over the kept views.
    view_errors_px : dict
        RMS reprojection error of each kept view.
    rejected : dict
        Rejected views and why.
    """

    K: FloatArray
    dist: FloatArray
    size: tuple[int, int]
    rms_px: float
    view_errors_px: dict[str, float] = field(default_factory=dict)
    rejected: dict[str, str] = field(default_factory=dict)


def _view_errors(
    dets: list[Detection],
    obj: list[FloatArray],
    K: FloatArray,
    dist: FloatArray,
    rvecs: tuple[FloatArray, ...],
    tvecs: tuple[FloatArray, ...],
) -> list[float]:
    errors = []
    for d, o, r, t in zip(dets, obj, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        errors.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - d.pixels) ** 2, axis=1)))))
    return errors


def _tilt_spread_deg(rvecs: tuple[FloatArray, ...]) -> float:
    """Largest angle between the board normals of two views, in degrees."""
    normals = np.array([cv2.Rodrigues(r)[0][:, 2] for r in rvecs])
    cosines = np.clip(normals @ normals.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosines.min())))


def calibrate_intrinsics(
    detections: list[Detection],
    board: Board,
    *,
    min_views: int = 4,
    max_view_error_px: float = 1.0,
    min_tilt_deg: float = 10.0,
    rational_k3: bool = True,
) -> IntrinsicsResult:
    """Intrinsic calibration from board detections of one camera.

    Parameters
    ----------
    detections : list of Detection
        One per view, all with the same image size.
    board : Board
    min_views : int
        Fewest views to keep after rejection.
    max_view_error_px : float
        Views whose RMS error exceeds ``max(max_view_error_px, 3 * median)`` are rejected.
    min_tilt_deg : float
        The board normals must span at least this angle, otherwise focal length is not observable.
    rational_k3 : bool
        Estimate k3 (else fixed to 0, as Qualisys/Pose2Sim do).

    Raises
    ------
    CalibrationError
        Too few views, mixed image sizes, or degenerate geometry; the message says what to do.
    """
    if len(detections) < min_views:
        raise CalibrationError(
            f"only {len(detections)} view(s) with the board found, {min_views} needed: take more pictures of the "
            "board, whole and sharp, tilted differently in each"
        )
    sizes = {d.size for d in detections}
    if len(sizes) != 1:
        raise CalibrationError(f"views have different image sizes {sorted(sizes)}: calibrate each camera mode apart")
    size = sizes.pop()
    all_obj = board.object_points()
    dets = list(detections)
    rejected: dict[str, str] = {}
    flags = 0 if rational_k3 else cv2.CALIB_FIX_K3
    while True:
        obj = [all_obj[d.ids].astype(np.float32) for d in dets]
        img = [d.pixels.astype(np.float32) for d in dets]
        rms, K_cv, dist_cv, rvecs_cv, tvecs_cv = cv2.calibrateCamera(obj, img, size, None, None, flags=flags)
        K, dist = np.asarray(K_cv, np.float64), np.asarray(dist_cv, np.float64)
        rvecs = tuple(np.asarray(r, np.float64) for r in rvecs_cv)
        tvecs = tuple(np.asarray(t, np.float64) for t in tvecs_cv)
        errors = _view_errors(dets, [o.astype(np.float64) for o in obj], K, dist, rvecs, tvecs)
        worst = int(np.argmax(errors))
        limit = max(max_view_error_px, 3.0 * float(np.median(errors)))
        if errors[worst] <= limit or len(dets) <= min_views:
            break
        rejected[dets[worst].view] = f"reprojection error {errors[worst]:.2f} px > {limit:.2f} px"
        del dets[worst]
    spread = _tilt_spread_deg(rvecs)
    if spread < min_tilt_deg:
        raise CalibrationError(
            f"the board has nearly the same orientation in every view (normals within {spread:.1f} deg): tilt it "
            f"by at least {min_tilt_deg:.0f} deg in different directions across the pictures"
        )
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError("calibration diverged: check the board dimensions and use sharper pictures")
    return IntrinsicsResult(
        K=np.asarray(K, np.float64),
        dist=np.asarray(dist, np.float64).reshape(-1)[:5],
        size=size,
        rms_px=float(rms),
        view_errors_px={d.view: round(e, 4) for d, e in zip(dets, errors, strict=True)},
        rejected=rejected,
    )

"""Extrinsic calibration of a camera rig from a board seen by several cameras, refined by bundle adjustment.

Input: each camera's intrinsics and the board detections of synchronised moments ("frames"): the same board pose
seen by one or more cameras. One frame (``origin_frame``) shows the board lying on the floor; it defines mocapd's
world (DESIGN.md): origin at the board's first corner, X along the board's columns, +Y up (the board normal that
points to the side of the cameras), Z = X × Y, metres, floor at y = 0.

1. Each detection gives the board pose in that camera (``solvePnP``).
2. Poses are chained from the origin frame through the graph camera ↔ frame (breadth first) to initialise every
   camera (world→camera) and every other board pose (board→world).
3. Bundle adjustment refines all of them together (``scipy.optimize.least_squares``, trust-region reflective,
   soft-L1 loss of scale 1 px, sparse Jacobian: a corner's two residuals depend only on its camera's and its
   frame's 6 parameters). The origin frame's board pose stays fixed, which fixes the gauge.

The report gives each camera's RMS reprojection error before and after the refinement.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from mocapd.core.rotations import matrix_from_rotvec, rotvec_from_matrix
from mocapd.errors import CalibrationError
from mocapd.io.board_calibration import Board, Detection
from mocapd.io.calibration_files import CalibrationSet, CameraCalibration

FloatArray = NDArray[np.float64]

# Board frame -> world for a board on the floor: X_w = x_b, Y_w = -z_b or +z_b, Z_w = X_w x Y_w.
_FLOOR_DOWN_NORMAL: FloatArray = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
_FLOOR_UP_NORMAL: FloatArray = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class Intrinsics:
    """Intrinsics of one camera: ``K`` (3, 3), ``dist`` (5,) OpenCV, ``size`` (width, height)."""

    K: FloatArray
    dist: FloatArray
    size: tuple[int, int]


@dataclass(frozen=True)
class Observation:
    """The board seen by ``camera`` at the synchronised moment ``frame``."""

    camera: str
    frame: str
    detection: Detection


@dataclass(frozen=True)
class RigResult:
    """Calibrated rig and its report.

    Attributes
    ----------
    calibration : CalibrationSet
        Cameras in mocapd's world.
    rms_before_px, rms_after_px : dict
        Per-camera RMS reprojection error before / after bundle adjustment.
    n_observations : dict
        Board views used per camera.
    board_poses : dict
        Board→world (R (3, 3), t (3,)) per frame.
    """

    calibration: CalibrationSet
    rms_before_px: dict[str, float]
    rms_after_px: dict[str, float]
    n_observations: dict[str, int]
    board_poses: dict[str, tuple[FloatArray, FloatArray]] = field(default_factory=dict)


def _pnp(intr: Intrinsics, det: Detection, board: Board) -> tuple[FloatArray, FloatArray]:
    obj = board.object_points()[det.ids]
    ok, rvec, tvec = cv2.solvePnP(obj, det.pixels, intr.K, intr.dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError(f"board pose in view {det.view!r} cannot be computed: retake it")
    return np.asarray(cv2.Rodrigues(rvec)[0], np.float64), np.asarray(tvec, np.float64).reshape(3)


def _chain(
    cams: list[str],
    frames: list[str],
    pnp: dict[tuple[str, str], tuple[FloatArray, FloatArray]],
    origin: str,
    floor: FloatArray,
) -> tuple[dict[str, tuple[FloatArray, FloatArray]], dict[str, tuple[FloatArray, FloatArray]]]:
    """Initial world→camera and board→world poses by breadth-first chaining from the origin frame."""
    board_to_world: dict[str, tuple[FloatArray, FloatArray]] = {origin: (floor, np.zeros(3))}
    world_to_cam: dict[str, tuple[FloatArray, FloatArray]] = {}
    queue: deque[tuple[str, str]] = deque([("frame", origin)])
    while queue:
        kind, key = queue.popleft()
        if kind == "frame":
            Rf, tf = board_to_world[key]
            for c in cams:
                if c not in world_to_cam and (c, key) in pnp:
                    Rcb, tcb = pnp[(c, key)]  # board -> camera
                    R = Rcb @ Rf.T  # world -> camera = (board -> camera) o (world -> board)
                    world_to_cam[c] = (R, tcb - R @ tf)
                    queue.append(("camera", c))
        else:
            Rc, tc = world_to_cam[key]
            for f in frames:
                if f not in board_to_world and (key, f) in pnp:
                    Rcb, tcb = pnp[(key, f)]
                    board_to_world[f] = (Rc.T @ Rcb, Rc.T @ (tcb - tc))
                    queue.append(("frame", f))
    return world_to_cam, board_to_world


def _project(
    params: FloatArray, n_cams: int, fixed_frame: tuple[FloatArray, FloatArray], data: dict[str, Any]
) -> FloatArray:
    """Residuals (projected - detected), shape (2 * n_points,), for the stacked parameters."""
    cam_p = params[: 6 * n_cams].reshape(n_cams, 6)
    frame_p = params[6 * n_cams :].reshape(-1, 6)
    Rc, tc = matrix_from_rotvec(cam_p[:, :3]), cam_p[:, 3:]
    Rf = np.concatenate([fixed_frame[0][None], matrix_from_rotvec(frame_p[:, :3])])
    tf = np.concatenate([fixed_frame[1][None], frame_p[:, 3:]])
    ci, fi = data["cam"], data["frame"]
    Xw = np.einsum("nij,nj->ni", Rf[fi], data["obj"]) + tf[fi]
    Xc = np.einsum("nij,nj->ni", Rc[ci], Xw) + tc[ci]
    z = np.where(np.abs(Xc[:, 2]) < 1e-9, 1e-9, Xc[:, 2])
    x, y = Xc[:, 0] / z, Xc[:, 1] / z
    k1, k2, p1, p2, k3 = data["dist"].T
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    u = data["fx"] * xd + data["cx"]
    v = data["fy"] * yd + data["cy"]
    return np.stack([u - data["px"][:, 0], v - data["px"][:, 1]], axis=1).reshape(-1)


def _rms_per_camera(residuals: FloatArray, cam_index: NDArray[np.int64], cams: list[str]) -> dict[str, float]:
    sq = residuals.reshape(-1, 2) ** 2
    return {c: round(float(np.sqrt(sq[cam_index == i].sum(axis=1).mean())), 4) for i, c in enumerate(cams)}


def calibrate_rig(
    intrinsics: dict[str, Intrinsics],
    observations: list[Observation],
    board: Board,
    *,
    origin_frame: str | None = None,
    refine: bool = True,
) -> RigResult:
    """Extrinsics of every camera in mocapd's world from board observations (see module docstring).

    Parameters
    ----------
    intrinsics : dict
        Camera name → :class:`Intrinsics`.
    observations : list of Observation
    board : Board
    origin_frame : str or None
        Frame in which the board lies on the floor at the world origin; default: the frame seen by the most
        cameras.
    refine : bool
        Run the bundle adjustment.

    Raises
    ------
    CalibrationError
        No observation, a camera without intrinsics, cameras not linked to the others by common board views, or
        an origin frame nobody saw.
    """
    if not observations:
        raise CalibrationError("no board observation: film the board so that each camera sees it")
    cams = sorted(intrinsics)
    unknown = sorted({o.camera for o in observations} - set(cams))
    if unknown:
        raise CalibrationError(f"no intrinsics for camera(s) {unknown}: calibrate their intrinsics first")
    frames = sorted({o.frame for o in observations})
    seen_by = {f: sorted({o.camera for o in observations if o.frame == f}) for f in frames}
    if origin_frame is None:
        origin_frame = max(frames, key=lambda f: (len(seen_by[f]), f))
    if origin_frame not in seen_by:
        raise CalibrationError(f"origin frame {origin_frame!r} was not seen by any camera")
    pnp = {(o.camera, o.frame): _pnp(intrinsics[o.camera], o.detection, board) for o in observations}
    floor = _floor_rotation(pnp, origin_frame, seen_by[origin_frame])
    world_to_cam, board_to_world = _chain(cams, frames, pnp, origin_frame, floor)
    missing = [c for c in cams if c not in world_to_cam]
    if missing:
        raise CalibrationError(
            f"camera(s) {missing} never see the board at the same moment as the calibrated ones: film the board "
            "where they overlap with at least one other camera"
        )
    used = [o for o in observations if o.frame in board_to_world]
    free_frames = [f for f in frames if f != origin_frame and f in board_to_world]
    data = _stack(used, cams, [origin_frame, *free_frames], intrinsics, board)
    x0 = np.concatenate(
        [np.concatenate([rotvec_from_matrix(world_to_cam[c][0]), world_to_cam[c][1]]) for c in cams]
        + [np.concatenate([rotvec_from_matrix(board_to_world[f][0]), board_to_world[f][1]]) for f in free_frames]
    )
    fixed = board_to_world[origin_frame]
    r0 = _project(x0, len(cams), fixed, data)
    before = _rms_per_camera(r0, data["cam"], cams)
    x = x0
    if refine:
        sol = least_squares(
            _project,
            x0,
            jac_sparsity=_sparsity(data, len(cams), len(free_frames)),
            method="trf",
            x_scale="jac",
            loss="soft_l1",
            f_scale=1.0,
            args=(len(cams), fixed, data),
            max_nfev=200,
        )
        x = sol.x
    after = _rms_per_camera(_project(x, len(cams), fixed, data), data["cam"], cams)
    cam_p = x[: 6 * len(cams)].reshape(-1, 6)
    calib = CalibrationSet(
        tuple(
            CameraCalibration(
                c,
                intrinsics[c].size,
                intrinsics[c].K,
                intrinsics[c].dist,
                matrix_from_rotvec(cam_p[i, :3]),
                cam_p[i, 3:],
                after[c],
            )
            for i, c in enumerate(cams)
        ),
        "mocapd calibrate cameras",
    )
    frame_p = x[6 * len(cams) :].reshape(-1, 6)
    poses = {origin_frame: fixed} | {
        f: (matrix_from_rotvec(frame_p[i, :3]), frame_p[i, 3:]) for i, f in enumerate(free_frames)
    }
    counts = {c: sum(o.camera == c for o in used) for c in cams}
    return RigResult(calib, before, after, counts, poses)


def _floor_rotation(
    pnp: dict[tuple[str, str], tuple[FloatArray, FloatArray]], origin: str, cams: list[str]
) -> FloatArray:
    """Board→world rotation for the floor board: +Y is the board normal pointing to the cameras' side."""
    votes = 0.0
    for c in cams:
        Rcb, tcb = pnp[(c, origin)]
        centre_in_board = -Rcb.T @ tcb  # camera centre in board coordinates
        votes += np.sign(centre_in_board[2])
    # Cameras on the board's -z side: world +Y = -z_b.
    return _FLOOR_DOWN_NORMAL if votes < 0 else _FLOOR_UP_NORMAL


def _stack(
    obs: list[Observation], cams: list[str], frames: list[str], intr: dict[str, Intrinsics], board: Board
) -> dict[str, Any]:
    obj_all = board.object_points()
    cam_idx, frame_idx, obj, px, K, dist = [], [], [], [], [], []
    for o in obs:
        n = len(o.detection.ids)
        cam_idx.append(np.full(n, cams.index(o.camera)))
        frame_idx.append(np.full(n, frames.index(o.frame)))
        obj.append(obj_all[o.detection.ids])
        px.append(o.detection.pixels)
        K.append(np.repeat(intr[o.camera].K[None], n, axis=0))
        dist.append(np.repeat(intr[o.camera].dist[None], n, axis=0))
    Ks = np.concatenate(K)
    return {
        "cam": np.concatenate(cam_idx),
        "frame": np.concatenate(frame_idx),
        "obj": np.concatenate(obj),
        "px": np.concatenate(px),
        "dist": np.concatenate(dist),
        "fx": Ks[:, 0, 0],
        "fy": Ks[:, 1, 1],
        "cx": Ks[:, 0, 2],
        "cy": Ks[:, 1, 2],
    }


def _sparsity(data: dict[str, Any], n_cams: int, n_free_frames: int) -> lil_matrix:
    """Jacobian structure: residuals of a corner depend on its camera's 6 and its (free) frame's 6 parameters."""
    n_points = len(data["cam"])
    A = lil_matrix((2 * n_points, 6 * (n_cams + n_free_frames)), dtype=np.int8)
    rows = np.arange(n_points)
    for k in range(6):
        for r in (0, 1):
            A[2 * rows + r, 6 * data["cam"] + k] = 1
            free = data["frame"] > 0  # frame 0 is the fixed origin frame
            A[2 * rows[free] + r, 6 * n_cams + 6 * (data["frame"][free] - 1) + k] = 1
    return A

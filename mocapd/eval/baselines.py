"""The baselines a user would otherwise pick, run on the very same simulated inputs as the solver.

(i) **Robust weighted triangulation** per frame, like seed 001's "Tri-CPM": each keypoint is triangulated from
every view with confidence > 0 (confidence-weighted DLT), then the view with the largest reprojection error is
dropped while that error exceeds ``max_reprojection`` (a fraction of the person's height in pixels) and at least
two views remain. Keypoints become joints through the same keypoint-to-joint offsets the solver uses: the 12
limb keypoints have zero offsets (they *are* the shoulder/elbow/wrist/hip/knee/ankle joints); the hips, spine,
neck and head joints follow from them and the head keypoints with the default proportions; toes from the ankle
and the body heading. A joint not triangulated this frame keeps its previous value (online, no look-ahead).

(ii) **IMU-only forward kinematics**: each bone with an IMU takes its measured orientation, the others their
parent's (local identity); the root stays at its start position (no IMU gives position).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera, project_points, stack_cameras, triangulate
from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import matrix_from_quat, rotvec_from_matrix
from mocapd.core.skeleton import _DEFAULT_OFFSETS, BONE_INDEX, N_BONES, POSE_DIM, Skeleton

FloatArray = NDArray[np.float64]

# COCO-17 index -> our bone for the keypoints that sit on a joint (offset zero).
LIMB_KEYPOINTS: dict[int, str] = {
    5: "LeftUpperArm", 6: "RightUpperArm", 7: "LeftLowerArm", 8: "RightLowerArm", 9: "LeftHand", 10: "RightHand",
    11: "LeftUpperLeg", 12: "RightUpperLeg", 13: "LeftLowerLeg", 14: "RightLowerLeg", 15: "LeftFoot", 16: "RightFoot",
}  # fmt: skip
LIMB_JOINTS = tuple(BONE_INDEX[b] for b in LIMB_KEYPOINTS.values())
"""Our joints that a keypoint observes directly (the fairest subset to compare the baseline on)."""


def robust_triangulate(
    cameras: list[Camera], uv: FloatArray, conf: FloatArray, height_px: FloatArray, max_reprojection: float = 0.05
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """One frame: keypoints (n_kp, 3) and which were triangulated.

    Parameters
    ----------
    uv : (n_cams, n_kp, 2); conf : (n_cams, n_kp)
    height_px : (n_cams,) or (n_cams, n_kp)
        Person height in pixels per view (per keypoint when several frames are stacked as keypoints).
    """
    K, dist, R, t = stack_cameras(cameras)
    w = conf.copy()
    h = np.asarray(height_px, dtype=np.float64)
    thr = max_reprojection * (h[:, None] if h.ndim == 1 else h)
    X, ok = triangulate(cameras, uv, w)
    for _ in range(len(cameras)):
        if not np.any(ok):
            break
        Xs = np.where(ok[:, None], X, 0.0)
        proj, _, vis = project_points(K, dist, R, t, Xs, jacobian=False)
        err = np.linalg.norm(proj - np.nan_to_num(uv), axis=-1)
        err = np.where((w > 0) & vis, err / thr, 0.0)
        worst = np.argmax(err, axis=0)
        bad = (err[worst, np.arange(err.shape[1])] > 1.0) & ok & (np.sum(w > 0, axis=0) > 2)
        if not np.any(bad):
            break
        w[worst[bad], np.flatnonzero(bad)] = 0.0
        X2, ok2 = triangulate(cameras, uv, w)
        X = np.where(bad[:, None], X2, X)
        ok = np.where(bad, ok2, ok)
    return X, ok


def joints_from_keypoints(kp: FloatArray, ok: NDArray[np.bool_], skeleton: Skeleton, prev: FloatArray) -> FloatArray:
    """Our 21 joints (21, 3) from triangulated COCO-17 keypoints; joints not derivable keep ``prev``."""
    s = skeleton.height / 1.75
    J = prev.copy()
    for k, bone in LIMB_KEYPOINTS.items():
        if ok[k]:
            J[BONE_INDEX[bone]] = kp[k]
    lh, rh = J[BONE_INDEX["LeftUpperLeg"]], J[BONE_INDEX["RightUpperLeg"]]
    ls, rs = J[BONE_INDEX["LeftUpperArm"]], J[BONE_INDEX["RightUpperArm"]]
    hip_mid, sh_mid = 0.5 * (lh + rh), 0.5 * (ls + rs)
    up = sh_mid - hip_mid
    up /= max(float(np.linalg.norm(up)), 1e-9)
    d = _DEFAULT_OFFSETS
    hips = hip_mid - d["LeftUpperLeg"][1] * s * up
    spine3 = sh_mid - d["LeftUpperArm"][1] * s * up
    J[BONE_INDEX["Hips"]] = hips
    lens = np.array([np.linalg.norm(d[n]) for n in ("Spine", "Spine1", "Spine2", "Spine3")])
    fr = np.cumsum(lens) / lens.sum()
    for name, a in zip(("Spine", "Spine1", "Spine2"), fr[:3], strict=True):
        J[BONE_INDEX[name]] = (1 - a) * hips + a * spine3
    J[BONE_INDEX["Spine3"]] = spine3
    J[BONE_INDEX["Neck"]] = spine3 + np.linalg.norm(d["Neck"]) * s * up
    head_kp = [k for k in range(5) if ok[k]]
    if head_kp:  # the head keypoints' centre sits ~7 cm above the head joint (default offsets, upright head)
        offs = np.array(
            [[0.0, 0.06, 0.10], [0.035, 0.09, 0.08], [-0.035, 0.09, 0.08], [0.075, 0.07, 0.0], [-0.075, 0.07, 0.0]]
        )
        J[BONE_INDEX["Head"]] = kp[head_kp].mean(axis=0) - offs[head_kp, 1].mean() * s * np.array([0.0, 1.0, 0.0])
    left = lh - rh
    left[1] = 0.0
    fwd = np.cross(left, np.array([0.0, 1.0, 0.0]))
    fwd /= max(float(np.linalg.norm(fwd)), 1e-9)
    for foot, toes in (("LeftFoot", "LeftToes"), ("RightFoot", "RightToes")):
        o = d[toes]
        J[BONE_INDEX[toes]] = J[BONE_INDEX[foot]] + s * (o[1] * np.array([0.0, 1.0, 0.0]) + o[2] * fwd)
    return J


def imu_only_theta(skeleton: Skeleton, imu_bones: list[int], q_meas: FloatArray, root: FloatArray) -> FloatArray:
    """θ (f, 66) from measured bone orientations (f, n_imu, 4): bones without an IMU copy their parent."""
    f = q_meas.shape[0]
    Q = np.tile(np.eye(3), (f, N_BONES, 1, 1))
    meas = matrix_from_quat(q_meas) if q_meas.shape[1] else np.zeros((f, 0, 3, 3))
    have = {b: i for i, b in enumerate(imu_bones)}
    parents = skeleton.parents
    for b in range(N_BONES):
        if b in have:
            Q[:, b] = meas[:, have[b]]
        elif parents[b] >= 0:
            Q[:, b] = Q[:, parents[b]]
    theta = np.zeros((f, POSE_DIM))
    theta[:, 0:3] = root
    local = Q.copy()
    for b in range(1, N_BONES):
        local[:, b] = np.swapaxes(Q[:, parents[b]], -1, -2) @ Q[:, b]
    theta[:, 3:] = rotvec_from_matrix(local).reshape(f, -1)
    return theta


__all__ = ["LIMB_JOINTS", "Kinematics", "imu_only_theta", "joints_from_keypoints", "robust_triangulate"]

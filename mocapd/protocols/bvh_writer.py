"""BVH text of the 21-bone skeleton (pure: arrays in, text out).

Hierarchy: the 21 bones of DESIGN.md with their names and parents, each ``OFFSET`` the bone's rest offset in its
parent's frame (centimetres by default, ``unit_scale`` = 100 file units per metre), so the BVH semantics
(``x_j = x_p + G_p · offset_j``, ``G_j = G_p · L_j``) are exactly mocapd's forward kinematics. The five leaf bones
(Head, both hands, both toes) end in an ``End Site`` at half their own offset further along.

Channels (the common MotionBuilder order):

- Hips: ``Xposition Yposition Zposition Zrotation Xrotation Yrotation`` — root translation (θ[0:3]) in file units,
  then its rotation;
- every other bone: ``Zrotation Xrotation Yrotation``.

Rotations are intrinsic Euler angles in degrees, applied in channel order: ``L = Rz(z) · Rx(x) · Ry(y)`` (the
rotation of θ's rotation vector). Values are written with ``decimals`` decimals (6: 1e-8 m, 1e-6°). World frame:
mocapd's (+Y up, T-pose facing +Z, right-handed), which is also BVH's usual frame.

Fingers (issue 44): with ``hands`` each hand ``JOINT`` holds its 15 finger joints (``LeftThumbProximal`` ...,
:mod:`mocapd.protocols.fingers`), three per finger, each ``OFFSET`` its rest offset and ``CHANNELS 3 Zrotation
Xrotation Yrotation``; the hands are then no leaves and each distal bone ends in an ``End Site`` at its fingertip.
Without fingers the file is exactly as above.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core.hand_skeleton import N_FINGER_BONES, HandSkeleton
from mocapd.core.rotations import matrix_from_quat, matrix_from_rotvec
from mocapd.core.skeleton import BONE_NAMES, N_BONES, PARENTS, POSE_DIM
from mocapd.errors import InputError
from mocapd.protocols.fingers import EXTENDED_BONE_NAMES, EXTENDED_PARENTS, extended_offsets, leaf_ends

FloatArray = NDArray[np.float64]

ROOT_CHANNELS = ("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation")
JOINT_CHANNELS = ("Zrotation", "Xrotation", "Yrotation")
END_SITE_FRACTION = 0.5


def euler_zxy_from_matrix(R: FloatArray) -> FloatArray:
    """Angles (z, x, y) in degrees with ``R = Rz(z) · Rx(x) · Ry(y)``.

    Parameters
    ----------
    R : array, shape (..., 3, 3)

    Returns
    -------
    array, shape (..., 3)
        (z, x, y); x in [-90, 90]. At x = ±90° (gimbal lock) y is set to 0 and z carries the rotation.
    """
    R = np.asarray(R, dtype=np.float64)
    sx = np.clip(R[..., 2, 1], -1.0, 1.0)
    x = np.arcsin(sx)
    locked = np.abs(sx) > 1.0 - 1e-12
    z = np.where(locked, np.arctan2(R[..., 1, 0], R[..., 0, 0]), np.arctan2(-R[..., 0, 1], R[..., 1, 1]))
    y = np.where(locked, 0.0, np.arctan2(-R[..., 2, 0], R[..., 2, 2]))
    out: FloatArray = np.degrees(np.stack([z, x, y], axis=-1))
    return out


def _hierarchy(
    offsets: FloatArray,
    scale: float,
    fmt: str,
    names: tuple[str, ...] = BONE_NAMES,
    parents: tuple[int, ...] = PARENTS,
    ends: dict[int, FloatArray] | None = None,
) -> tuple[list[str], list[int]]:
    """The HIERARCHY lines and the bones in the order their channels appear (depth first); ``ends``: each leaf's
    End Site (default: :data:`END_SITE_FRACTION` of its own offset)."""
    children: dict[int, list[int]] = {i: [] for i in range(len(parents))}
    for i, p in enumerate(parents):
        if p >= 0:
            children[p].append(i)
    lines = ["HIERARCHY"]
    order: list[int] = []

    def vec(v: FloatArray) -> str:
        return " ".join(fmt % (float(c) * scale) for c in v)

    def emit(b: int, depth: int) -> None:
        pad = "\t" * depth
        kind = "ROOT" if parents[b] < 0 else "JOINT"
        channels = ROOT_CHANNELS if parents[b] < 0 else JOINT_CHANNELS
        order.append(b)
        lines.extend([f"{pad}{kind} {names[b]}", f"{pad}{{", f"{pad}\tOFFSET {vec(offsets[b])}",
                      f"{pad}\tCHANNELS {len(channels)} {' '.join(channels)}"])  # fmt: skip
        for c in children[b]:
            emit(c, depth + 1)
        if not children[b]:
            end = END_SITE_FRACTION * offsets[b] if ends is None else ends[b]
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {vec(end)}", f"{pad}\t}}"])
        lines.append(f"{pad}}}")

    emit(0, 0)
    return lines, order


def bvh_text(
    offsets: FloatArray,
    thetas: FloatArray,
    fps: float,
    unit_scale: float = 100.0,
    decimals: int = 6,
    hands: FloatArray | None = None,
    hand_skeleton: HandSkeleton | None = None,
) -> str:
    """A BVH file of a pose sequence.

    Parameters
    ----------
    offsets : array, shape (21, 3)
        The skeleton's rest offsets (metres), e.g. ``Skeleton.offsets``.
    thetas : array, shape (n_frames, 66)
        Pose vectors (root translation in metres + 21 local rotation vectors).
    fps : float
        Frame rate (``Frame Time`` = 1/fps).
    unit_scale : float
        File units per metre (100: centimetres).
    decimals : int
        Decimals of every number written.
    hands : array, shape (n_frames, 2, 15, 4), optional
        The fingers' local rotations (w, x, y, z) on ``hand_skeleton`` (module doc); None: no finger joints.
    """
    offsets = np.asarray(offsets, dtype=np.float64)
    thetas = np.asarray(thetas, dtype=np.float64)
    if offsets.shape != (N_BONES, 3):
        raise InputError(f"BVH offsets must have shape ({N_BONES}, 3), got {offsets.shape}")
    if thetas.ndim != 2 or thetas.shape[1] != POSE_DIM or thetas.shape[0] < 1:
        raise InputError(f"BVH poses must have shape (n >= 1, {POSE_DIM}), got {thetas.shape}")
    if not (np.all(np.isfinite(thetas)) and np.isfinite(fps) and fps > 0):
        raise InputError("BVH poses must be finite and the frame rate positive")
    fmt = f"%.{decimals}f"
    n = thetas.shape[0]
    R = matrix_from_rotvec(thetas[:, 3:].reshape(n, N_BONES, 3))
    if hands is None or hand_skeleton is None:
        lines, order = _hierarchy(offsets, unit_scale, fmt)
    else:
        if np.shape(hands) != (n, 2, N_FINGER_BONES, 4) or not np.all(np.isfinite(hands)):
            raise InputError(f"BVH fingers must be finite with shape ({n}, 2, {N_FINGER_BONES}, 4)")
        lines, order = _hierarchy(extended_offsets(offsets, hand_skeleton), unit_scale, fmt, EXTENDED_BONE_NAMES,
                                  EXTENDED_PARENTS, leaf_ends(offsets, hand_skeleton, END_SITE_FRACTION))  # fmt: skip
        R = np.concatenate([R, matrix_from_quat(np.asarray(hands, dtype=np.float64)).reshape(n, -1, 3, 3)], axis=1)
    angles = euler_zxy_from_matrix(R)  # (n, 21 or 51, 3)
    values = np.concatenate([thetas[:, 0:3] * unit_scale, angles[:, order].reshape(n, -1)], axis=1)
    lines.extend(["MOTION", f"Frames: {n}", f"Frame Time: {1.0 / fps:.8f}"])
    lines.extend(" ".join(fmt % v for v in row) for row in values)
    return "\n".join(lines) + "\n"

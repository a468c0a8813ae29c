"""A first pose from a suit's orientations alone, for people no camera sees (issue 46).

The solver starts a new person from a warm start. Cameras give one from the triangulated hips
(:func:`mocapd.pipeline.scheduler.initial_pose`); a suit without cameras gave the rest pose, a T-pose, so the first
frames of an IMU-only person were 100–245 mm off while the LM iterations walked the limbs down from it. The measured
bone orientations (Eq. 8 applied) already say where every instrumented bone points: this turns them into θ whose
bones have those global orientations. Bones without a sensor keep their rest orientation relative to their parent
(a head without a sensor follows the neck, a hand its forearm). The root goes above the origin at the height that
puts the lowest foot joint at its rest height above the floor (a standing person: the skeleton's root height; a
crouching one lower); IMUs do not measure where a person stands.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import matrix_from_quat, quat_normalize, rotvec_from_matrix
from mocapd.core.skeleton import BONE_INDEX, N_BONES, POSE_DIM, Skeleton
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: the joints that touch the floor when standing: the root height is chosen to keep the lowest of them at rest height
_FOOT_JOINTS = tuple(BONE_INDEX[b] for b in ("LeftFoot", "RightFoot", "LeftToes", "RightToes"))


def initial_pose_from_imus(
    skeleton: Skeleton,
    bones: Sequence[str],
    orientations: FloatArray,
    mask: BoolArray | None = None,
) -> FloatArray:
    """θ whose instrumented bones have the measured global orientations, standing above the origin.

    Parameters
    ----------
    skeleton : Skeleton
        The person's sized skeleton (the solver's).
    bones : sequence of str, length n
        The bone each orientation belongs to (a suit's mounts, in order).
    orientations : array, shape (n, 4)
        Measured global bone orientations (w, x, y, z): sensor readings with Eq. 8 applied, as the solver takes
        them (``Observations.imu_orientations``).
    mask : bool array, shape (n,), optional
        Which orientations are measured (default: all); the others are ignored and may be non-finite.

    Returns
    -------
    array, shape (66,)
        The rest pose where nothing is measured.

    Raises
    ------
    InputError
        A bone name that is not a bone, a bone named twice, or orientations of the wrong shape or non-finite where
        masked in.
    """
    q = np.asarray(orientations, dtype=np.float64)
    n = len(bones)
    if q.shape != (n, 4):
        raise InputError(f"IMU orientations must have shape ({n}, 4) for {n} bones, got {q.shape}")
    use = np.ones(n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if use.shape != (n,):
        raise InputError(f"IMU mask must have shape ({n},), got {use.shape}")
    unknown = [b for b in bones if b not in BONE_INDEX]
    if unknown:
        raise InputError(f"IMU bones {unknown} are not bones of the skeleton")
    if len(set(bones)) != n:
        raise InputError(f"IMU bones named twice: {sorted(b for b in set(bones) if list(bones).count(b) > 1)}")
    if not np.all(np.isfinite(q[use])) or np.any(np.linalg.norm(q[use], axis=1) < 0.5):
        raise InputError("IMU orientations must be finite unit quaternions where measured")
    measured: dict[int, FloatArray] = {
        BONE_INDEX[b]: matrix_from_quat(quat_normalize(q[i])) for i, b in enumerate(bones) if use[i]
    }
    theta = skeleton.rest_pose()
    if not measured:
        return theta
    children: dict[int, list[int]] = {b: [] for b in range(N_BONES)}
    for b, parent in enumerate(skeleton.parents):
        if parent >= 0:
            children[parent].append(b)
    # Parents before children: the global rotation of each bone is its measured one, else that of the first
    # measured bone down its chain while the chain does not branch (a thigh without a sensor lies along its
    # measured shank: a straight limb is nearer the truth than the rest pose's), else its parent's (the rest pose's
    # identity local rotation); the local rotation is what is left after the parent's.
    glob = np.empty((N_BONES, 3, 3))
    for b in sorted(range(N_BONES), key=lambda i: skeleton.depths[i]):
        parent = skeleton.parents[b]
        above = np.eye(3) if parent < 0 else glob[parent]
        glob[b] = measured.get(b, _down_the_chain(b, children, measured, above))
        theta[3 + 3 * b : 6 + 3 * b] = rotvec_from_matrix(above.T @ glob[b])
    theta[0:3] = 0.0
    fk = Kinematics(skeleton)
    lowest = float(fk.forward(theta).positions[list(_FOOT_JOINTS), 1].min())
    rest_lowest = float(fk.forward(skeleton.rest_pose()).positions[list(_FOOT_JOINTS), 1].min())
    theta[1] = rest_lowest - lowest
    assert theta.shape == (POSE_DIM,)
    return theta


def _down_the_chain(
    bone: int, children: dict[int, list[int]], measured: dict[int, FloatArray], fallback: FloatArray
) -> FloatArray:
    """The measured global rotation (3, 3) nearest below ``bone`` along a chain without branches, else
    ``fallback``."""
    below = children[bone]
    while len(below) == 1:
        found = measured.get(below[0])
        if found is not None:
            return found
        below = children[below[0]]
    return fallback

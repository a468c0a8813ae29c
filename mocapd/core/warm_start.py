"""The first pose of a new person: a warm start for the solver from their triangulated keypoints, any keypoint set.

The pipeline's scheduler places a new person with this; the keypoints are looked up by name, so BODY_25, Halpe-26,
COCO-WholeBody and BlazePose start a person as COCO-17 does.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core.body_size import COCO17_NAMES
from mocapd.core.skeleton import POSE_DIM, Skeleton

FloatArray = NDArray[np.float64]


def initial_pose(
    skeleton: Skeleton, keypoints: FloatArray, names: tuple[str, ...] | list[str] = COCO17_NAMES
) -> FloatArray:
    """A warm start from triangulated keypoints: the rest pose at the mid-hip, facing away from the hip line (the
    solver then converges over the next frames). The rest pose when the hips are not known.

    Parameters
    ----------
    skeleton : Skeleton
    keypoints : array, shape (n_kp, 3)
        World positions (metres), NaN where not triangulated.
    names : sequence of str, length n_kp
        The keypoints' names (COCO-17's by default); ``left_hip`` and ``right_hip`` place the person.

    Returns
    -------
    array, shape (66,)
    """
    theta = skeleton.rest_pose()
    kp = np.asarray(keypoints, dtype=np.float64)
    if kp.shape != (len(names), 3) or "left_hip" not in names or "right_hip" not in names:
        return theta
    left, right = kp[list(names).index("left_hip")], kp[list(names).index("right_hip")]
    if not (np.all(np.isfinite(left)) and np.all(np.isfinite(right))):
        return theta
    theta[0:3] = 0.5 * (left + right)
    d = left - right  # the person's left, +X in the rest pose (facing +Z)
    theta[3:6] = [0.0, float(np.arctan2(-d[2], d[0])), 0.0]
    assert theta.shape == (POSE_DIM,)
    return theta

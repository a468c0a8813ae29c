"""The learned-fusion networks' inputs and outputs as arrays: one definition for training and for the runtime.

Seed 001 §3.5–3.6: each stream's LSTM reads its joint estimates of the current and the ``f - 1`` previous frames
(the seed's look-back f = 5) and predicts the current frame's joints; a dense layer fuses the two streams.

Frames (all positions in metres, joint order = the 21 bones):

- **vision**: the PVH network regresses joints relative to the frame's grid centre; its LSTM reads the window's
  estimates relative to the *current* grid centre (the grid follows the person, so earlier frames are shifted into
  the current frame's coordinates) and predicts the current joints relative to that centre;
- **IMU**: IMUs measure no position, so the IMU streams are root-relative: the solved-IMU LSTM reads the IMU-only
  solve's joints relative to the current frame's solved root and predicts the joints relative to the true root;
  the raw-IMU LSTM reads orientations only;
- **fusion** reads the vision LSTM's joints, the IMU LSTM's joints placed on the vision LSTM's root (both relative
  to the grid centre) and the fraction of cameras that see the person, and predicts the joints relative to the
  grid centre. The "mean of the streams" baseline averages the same two inputs.

Windows at the start of a sequence repeat its first frame (of the window's phase, with a stride). The functions take
whole sequences (training, the accuracy harness: a window per frame); the runtime passes its last f learned frames
and takes the last row, so both build the same windows.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

LOOK_BACK = 5
"""f: frames an LSTM reads (the current one and four before it), seed 001 §4.5.3."""
STRIDE = 3
"""The learned stream runs on every STRIDE-th frame of the 60 Hz output (20 Hz: a person-frame of PVH, network
and IMU-only solve costs ~10 ms on the 2-core CPU, docs/learned-fusion.md); its windows hold the current frame
and the f - 1 frames STRIDE, 2·STRIDE, ... frames before it."""
N_JOINTS = 21
JOINT_DIM = 3 * N_JOINTS
MAX_VIEWS = 8.0
"""The fusion layer reads ``views / MAX_VIEWS``."""


def window_index(n_frames: int, look_back: int = LOOK_BACK, stride: int = 1) -> NDArray[np.intp]:
    """Frame indices of each frame's window, shape (n_frames, look_back), oldest first: ``t - stride·k``, clamped
    at the first frame of the window's phase (``t mod stride``), which repeats."""
    t = np.arange(n_frames)[:, None]
    w = t + stride * np.arange(-look_back + 1, 1)[None, :]
    return np.asarray(np.where(w < 0, t % stride, w), dtype=np.intp)


def vision_windows(joints: FloatArray, centres: FloatArray, look_back: int = LOOK_BACK, stride: int = 1) -> FloatArray:
    """Vision LSTM input (n, look_back, 63): each window's joints relative to its last frame's grid centre.

    Parameters
    ----------
    joints : (n, 21, 3) per-frame world joints of the PVH network; centres : (n, 3) grid centres.
    """
    w = window_index(joints.shape[0], look_back, stride)
    rel = joints[w] - centres[:, None, None, :]
    return np.asarray(rel.reshape(joints.shape[0], look_back, JOINT_DIM))


def imu_windows(joints: FloatArray, look_back: int = LOOK_BACK, stride: int = 1) -> FloatArray:
    """Solved-IMU LSTM input (n, look_back, 63): each window's joints relative to its last frame's root (joint 0).

    Parameters
    ----------
    joints : (n, 21, 3) world joints of the IMU-only solve.
    """
    w = window_index(joints.shape[0], look_back, stride)
    rel = joints[w] - joints[:, None, None, 0, :]
    return np.asarray(rel.reshape(joints.shape[0], look_back, JOINT_DIM))


def feature_windows(features: FloatArray, look_back: int = LOOK_BACK, stride: int = 1) -> FloatArray:
    """Per-frame features (n, d) as windows (n, look_back, d) (raw-IMU LSTM input)."""
    return np.asarray(features[window_index(features.shape[0], look_back, stride)])


def fusion_input(vision: FloatArray, imu_rel: FloatArray, views: FloatArray) -> FloatArray:
    """Fusion layer input (n, 127): vision joints (rel. centre), IMU joints put on the vision root, views / 8.

    Parameters
    ----------
    vision : (n, 21, 3) relative to the grid centre; imu_rel : (n, 21, 3) relative to the root; views : (n,).
    """
    n = vision.shape[0]
    imu = imu_rel - imu_rel[:, :1] + vision[:, :1]
    return np.concatenate(
        (vision.reshape(n, JOINT_DIM), imu.reshape(n, JOINT_DIM), (np.asarray(views) / MAX_VIEWS)[:, None]), axis=1
    )


def mean_of_streams(vision: FloatArray, imu_rel: FloatArray) -> FloatArray:
    """Seed 001's "averaged fused" baseline: the mean of the two streams (IMU joints on the vision root)."""
    return np.asarray(0.5 * (vision + imu_rel - imu_rel[:, :1] + vision[:, :1]))

"""Compile every numba kernel of ``mocapd/core/_*kernel.py`` into numba's on-disk cache, once, before the tests.

On a clean checkout (CI) the cache is empty and each kernel compiled inside whichever test first reached it: a
cold compile of all of them costs 133-141 s of CPU (this script with an empty ``NUMBA_CACHE_DIR``; 2.5 s warm),
spread over the suite on its critical path (tests/test_lr_flips.py, test_hand_solver.py and test_optical_flow.py:
94.9 s of CPU cold, 10.9 s after this script). ``make test`` runs it beside mypy (which uses one core of two) so
the tests only load the compiled code. Each kernel is called
once with small made-up inputs of the dtypes, dimensions, layouts and read-only flags the daemon and the tests pass
(a numba signature differs for each); where a warm-up of the daemon exists it is the one called.
``tests/test_warm_kernels.py`` checks every kernel of those modules gets a signature here.

Usage: ``python tools/warm_kernels.py`` (``NUMBA_CACHE_DIR`` chooses the cache, as for every numba program).
"""

from __future__ import annotations

import time

import numpy as np

from mocapd.core import _flip_kernel, _undistort_kernel, lr_flips
from mocapd.core.hand_skeleton import HandSkeleton
from mocapd.core.hand_solver import N_HINGES, HandSolver
from mocapd.core.imu import IMU_SET_13, default_mounts
from mocapd.core.keypoints import coco17_targets
from mocapd.core.lm import LMOptions
from mocapd.core.observations import Observations
from mocapd.core.prior import PcaPrior
from mocapd.core.skeleton import Skeleton
from mocapd.core.solver import PoseSolver
from mocapd.core.sorting import DetectionSorter
from mocapd.core.synthetic import ring_rig
from mocapd.pipeline import optical_flow


def warm_pose_solver() -> None:
    """The body solve: the compiled LM loop with and without a PCA prior (its mean is read-only: another
    signature), the learned term's Python loop (cost kernel, E_J, LM step) and the skeleton's points."""
    skeleton = Skeleton.from_height()
    cameras = ring_rig(4)
    targets = coco17_targets(skeleton)
    mounts = default_mounts(IMU_SET_13, skeleton)
    # M Fortran-ordered as a fitted or loaded prior's (the transposed SVD factor): its A_pd is C-contiguous
    prior = PcaPrior(M=np.asfortranarray(np.eye(60)[:, :2]), mu=np.zeros(60), sigma=np.ones(2))
    for p in (None, prior):
        solver = PoseSolver(skeleton, cameras, targets, mounts, p, lm=LMOptions(max_iterations=2))
        n_kp = len(targets)
        obs = Observations(keypoints=np.full((4, n_kp, 2), 500.0), confidences=np.ones((4, n_kp)), dt=1 / 60)
        solver.solve(obs, update_state=False)
        joints = solver.kin.forward(solver.theta).positions
        solver.solve(Observations(keypoints=obs.keypoints, confidences=obs.confidences, joint_positions=joints,
                                  dt=1 / 60), update_state=False)  # fmt: skip
        solver.keypoint_positions(solver.theta)


def warm_hands() -> None:
    """The hand solve (its LM loop and the normal equations the tests compare with the numpy reference)."""
    cams = ring_rig(4)
    P = np.stack([c.projection_matrix for c in cams])
    hand = HandSkeleton.reference()
    wrist = np.array([0.3, 1.2, 0.1])
    uv = np.full((4, 21, 2), 500.0)
    conf = np.ones((4, 21))
    for side in (0, 1):
        solver = HandSolver(hand, side)
        solver.solve(P, uv, conf, np.eye(3), wrist)
        solver.normal_equations((np.zeros(N_HINGES), np.eye(3), wrist), P, uv, conf, np.eye(3), wrist)


def warm_tracking() -> None:
    """The daemon's own warm-ups: sorting, flip search, undistortion and optical flow."""
    cameras = ring_rig(4)
    DetectionSorter(cameras).warm_up(17)
    lr_flips.warm_up(cameras, 17)
    _flip_kernel._pairwise_sum(np.ones(3), 0, 3)  # tests/test_lr_flips.py checks the summation order on its own
    _undistort_kernel.warm_up()
    cameras[0].undistort_points(np.zeros((1, 2)))  # a camera's K and dist are read-only: another signature
    optical_flow.warm_up()
    opts = optical_flow.LKOptions(5, 0)
    pyr = optical_flow.build_pyramid(np.zeros((8, 8), np.uint8), opts)
    optical_flow.forward_backward(pyr, pyr, np.full((1, 2), 4.0, np.float32), opts)  # the tracker's check


def main() -> None:
    start = time.perf_counter()
    warm_pose_solver()
    warm_hands()
    warm_tracking()
    print(f"warm_kernels: numba kernels compiled or loaded in {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()

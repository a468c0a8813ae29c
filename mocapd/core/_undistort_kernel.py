"""Compiled (numba) undistortion of pixel coordinates (:func:`mocapd.core.camera.normalized_from_pixels`).

Why compiled. Every keypoint set a camera delivers (60 a second per camera with keypoint tracking) is undistorted
once as it arrives. As numpy, the ten fixed-point iterations were ~150 array calls on a few dozen points each: call
overhead, ~0.3 ms a set, a quarter of the event loop's time on the 2-core camera demo (issue 39's second profile).
Here it is one call, ``nogil``, so the capture threads that produce the sets undistort them in parallel.

The same arithmetic as the numpy reference (:func:`mocapd.core.camera._normalized_from_pixels_numpy`, kept for
the test that compares the two): OpenCV's fixed-point inversion of the Brown-Conrady model, ``k1 k2 p1 p2 k3``.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@nb.njit(cache=True, nogil=True)
def normalize_points(K: FloatArray, dist: FloatArray, uv: FloatArray, iterations: int, out: FloatArray) -> None:
    """Undistorted normalised coordinates of ``uv`` (n, 2) into ``out`` (n, 2); NaN in, NaN out."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for i in range(uv.shape[0]):
        xd = (uv[i, 0] - cx) / fx
        yd = (uv[i, 1] - cy) / fy
        x, y = xd, yd
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            x = (xd - dx) / radial
            y = (yd - dy) / radial
        out[i, 0] = x
        out[i, 1] = y


def warm_up() -> None:
    """Compile (or load from numba's cache) before the first live call."""
    out = np.empty((1, 2))
    normalize_points(np.eye(3), np.zeros(5), np.zeros((1, 2)), 1, out)

"""Compiled (numba) screen of the collapse check (:func:`mocapd.core.lr_collapse.collapsed_pairs`): which keypoints
take part, each view's person size and which (view, pair) are candidates, in one call.

Why compiled. The check runs on every person solve; its screen was ~25 NumPy calls on arrays of a few dozen numbers (the
keypoints' mask, the sizes' masked maxima and minima, the pairs' gaps), each a microsecond or two of interpreter and
wrapper around nanoseconds of arithmetic (issue 39: the collapse check was 12 % of the camera demo's event loop). The
arithmetic is the reference's, operation for operation, so the results are the same to the bit
(``tests/test_lr_collapse_bitwise.py`` compares them with the NumPy screen, kept there as ``view_sizes`` and
``pair_gaps``): maxima and minima and their difference are exact whatever the order; a gap is ``sqrt(x * x + y * y)``
with each product and the sum rounded on its own (numba emits no fused multiply-add without fastmath), the square root
correctly rounded as NumPy's.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]


@nb.njit(cache=True, nogil=True)
def screen(
    uv: FloatArray,
    conf: FloatArray,
    left: IntArray,
    right: IntArray,
    min_confidence: float,
    min_keypoints: int,
    collapsed: float,
    ok: BoolArray,
    size: FloatArray,
    candidate: BoolArray,
) -> bool:  # pragma: no cover - compiled
    """Fill ``ok`` (n_cams, n_kp): confidence at least ``min_confidence`` and a finite pixel; ``size`` (n_cams,): the
    larger extent of the ``ok`` keypoints (0 with fewer than ``min_keypoints``); ``candidate`` (n_cams, n_pairs):
    both keypoints ``ok``, a size, and the pair's gap under ``collapsed`` times it. Returns whether any is a
    candidate. ``uv`` (n_cams, n_kp, 2); ``left``, ``right`` (n_pairs,) keypoint indices."""
    n_cams, n_kp = conf.shape
    found = False
    for c in range(n_cams):
        count = 0
        hi_u, hi_v, lo_u, lo_v = -np.inf, -np.inf, np.inf, np.inf
        for k in range(n_kp):
            u, v = uv[c, k, 0], uv[c, k, 1]
            good = conf[c, k] >= min_confidence and math.isfinite(u) and math.isfinite(v)
            ok[c, k] = good
            if good:
                count += 1
                hi_u, hi_v = max(hi_u, u), max(hi_v, v)
                lo_u, lo_v = min(lo_u, u), min(lo_v, v)
        extent = max(hi_u - lo_u, hi_v - lo_v)
        size[c] = extent if count >= min_keypoints else 0.0
        limit = collapsed * size[c]
        for p in range(left.size):
            a, b = left[p], right[p]
            is_candidate = False
            if ok[c, a] and ok[c, b] and size[c] > 0.0:
                x = uv[c, a, 0] - uv[c, b, 0]
                y = uv[c, a, 1] - uv[c, b, 1]
                is_candidate = math.sqrt(x * x + y * y) < limit
            candidate[c, p] = is_candidate
            found = found or is_candidate
    return found

"""One-to-one assignment of least total cost (the Hungarian method), SciPy's, imported on first use.

``scipy.optimize`` is ~150 modules (its solvers, ``scipy.linalg``, ``scipy.sparse``): imported at the top of the
modules that match people (sorting, the keypoint tracker and timeline, the suit binding) it was part of every
``import mocapd.service.assembly``, seconds of start-up on a loaded 2-core machine for processes that never match
anyone (the camera demo's parent, which re-runs itself in a network namespace; the IMU-only rig; the CLI). The
daemon's warm-up calls :func:`warm_up` before it serves, so the first live match does not pay the import on the
event loop.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def linear_sum_assignment(cost: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """:func:`scipy.optimize.linear_sum_assignment` of ``cost``, shape (R, C): the rows and columns matched, each
    shape (min(R, C),), rows ascending. Raises ValueError (SciPy's) on a NaN or an infeasible matrix."""
    from scipy.optimize import linear_sum_assignment as solve  # here, not at the top: see the module docstring

    rows, cols = solve(cost)
    return rows, cols


def warm_up() -> None:
    """Import SciPy's assignment now (the daemon's warm-up, off the event loop)."""
    linear_sum_assignment(np.zeros((1, 1)))

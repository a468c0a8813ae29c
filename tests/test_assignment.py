"""The Hungarian assignment imported on first use: the daemon's start-up does not load scipy.optimize."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import scipy.optimize

from mocapd.core.assignment import linear_sum_assignment


def test_importing_the_daemons_assembly_leaves_scipy_optimize_unloaded() -> None:
    # A fresh interpreter: this one has imported everything the other tests did.
    code = "import sys, mocapd.service.assembly; print('scipy.optimize' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=600)
    assert out.stdout.strip() == "False"


def test_the_assignment_is_scipys() -> None:
    rng = np.random.default_rng(0)
    for shape in [(1, 1), (3, 3), (2, 5), (6, 4)]:
        cost = rng.uniform(0, 10, shape)
        rows, cols = linear_sum_assignment(cost)
        want_rows, want_cols = scipy.optimize.linear_sum_assignment(cost)
        np.testing.assert_array_equal(rows, want_rows)
        np.testing.assert_array_equal(cols, want_cols)

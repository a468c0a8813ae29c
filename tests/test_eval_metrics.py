"""Seed 003 Table 1 metrics."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.rotations import matrix_from_rotvec
from mocapd.eval.metrics import orientation_errors, position_errors, procrustes_align, stats


def test_stats() -> None:
    s = stats(np.array([1.0, 2.0, 3.0, 10.0, np.nan]))
    assert s == {"mean": 4.0, "std": pytest.approx(3.54, abs=0.01), "median": 2.5, "mad": 1.0, "n": 4}


def test_procrustes_removes_similarity() -> None:
    rng = np.random.default_rng(0)
    T = rng.normal(size=(5, 21, 3))
    R = matrix_from_rotvec(rng.normal(size=(5, 3)))
    P = 1.3 * np.einsum("fij,fnj->fni", R, T) + rng.normal(size=(5, 1, 3))
    np.testing.assert_allclose(procrustes_align(P, T), T, atol=1e-9)
    e = position_errors(P, T)
    assert e["procrustes"].max() < 1e-6 and e["global"].mean() > 100


def test_root_relative_and_orientation() -> None:
    T = np.zeros((1, 21, 3))
    P = T + np.array([0.1, 0.0, 0.0])
    e = position_errors(P, T)
    np.testing.assert_allclose(e["global"], 100.0)
    np.testing.assert_allclose(e["root_relative"], 0.0, atol=1e-12)
    Rt = matrix_from_rotvec(np.zeros((1, 21, 3)))
    Rp = matrix_from_rotvec(np.tile([0.0, np.deg2rad(30.0), 0.0], (1, 21, 1)))
    np.testing.assert_allclose(orientation_errors(Rp, Rt), 30.0)

"""A person solve's observations checked and made dense with fewer NumPy calls (issue 39): what passes, what is
refused and the arrays made are what the old checks gave (kept here verbatim as the oracle)."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.observations import Observations, ValidatedObservations
from mocapd.errors import InputError


def old_confidences_refused(conf: np.ndarray) -> bool:
    """``ValidatedObservations``' confidence check before issue 39, verbatim."""
    return bool(not np.all(np.isfinite(conf)) or np.any(conf < 0) or np.any(conf > 1))


def test_the_same_confidences_are_refused() -> None:
    rng = np.random.default_rng(3)
    kp = rng.uniform(0.0, 1000.0, (4, 17, 2))
    cases = [rng.uniform(0.0, 1.0, (4, 17)), np.zeros((4, 17)), np.ones((4, 17))]
    for bad in (np.nan, np.inf, -np.inf, -1e-300, -0.0, 1.0 + 1e-16, 1.0 + 2.3e-16, 2.0, -0.5):
        c = rng.uniform(0.0, 1.0, (4, 17))
        c[int(rng.integers(0, 4)), int(rng.integers(0, 17))] = bad
        cases.append(c)
    refused = 0
    for conf in cases:
        obs = Observations(keypoints=kp, confidences=conf, dt=1 / 30)
        if old_confidences_refused(conf):
            refused += 1
            with pytest.raises(InputError, match="confidences must be finite and within"):
                ValidatedObservations(obs, 4, 17, 0)
        else:
            v = ValidatedObservations(obs, 4, 17, 0)
            assert v.conf is conf or np.array_equal(v.conf, conf)
    assert refused == 7  # NaN, both infinities, two above 1 (1 + 1e-16 rounds to 1), two below 0 (-0.0 is not)


def test_the_identity_rotations_are_np_tiles() -> None:
    """The IMU orientations default to the identity, as ``np.tile([1, 0, 0, 0], (n_imu, 1))`` made them."""
    for n_imu in (0, 1, 13):
        v = ValidatedObservations(Observations(dt=0.01), 0, 0, n_imu)
        old = np.tile([1.0, 0.0, 0.0, 0.0], (n_imu, 1))
        assert v.q.shape == old.shape and v.q.dtype == old.dtype and v.q.tobytes() == old.tobytes()

"""The PCA pose prior (seed 003 §3.2.4): ``(M, μ, σ)`` over θ̄, the pose without its first six elements.

``M`` (d_p × d_r) has orthonormal columns (principal directions), ``μ`` (d_p,) is the mean pose and ``σ``
(d_r,) the standard deviations along the principal directions. The real default prior is trained from CMU
motion by ``tools/train_prior.py``; :meth:`PcaPrior.fit` is the plain PCA step (no clustering).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mocapd.core.skeleton import POSE_DIM
from mocapd.errors import InputError, ModelError

FloatArray = NDArray[np.float64]

PRIOR_DIM = POSE_DIM - 6
"""d_p = 60: θ without root translation and root rotation (invariant to global position and heading)."""


@dataclass(frozen=True)
class PcaPrior:
    """PCA pose model.

    Attributes
    ----------
    M : array, shape (60, d_r)
        Orthonormal principal directions.
    mu : array, shape (60,)
    sigma : array, shape (d_r,)
        Standard deviations (square roots of the kept eigenvalues), all > 0.
    """

    M: FloatArray
    mu: FloatArray
    sigma: FloatArray

    def __post_init__(self) -> None:
        M = np.array(self.M, dtype=np.float64)
        mu = np.array(self.mu, dtype=np.float64)
        sigma = np.array(self.sigma, dtype=np.float64)
        if M.ndim != 2 or M.shape[0] != PRIOR_DIM or mu.shape != (PRIOR_DIM,) or sigma.shape != (M.shape[1],):
            raise ModelError(
                f"PCA prior must have M ({PRIOR_DIM}, d_r), mu ({PRIOR_DIM},), sigma (d_r,); "
                f"got {M.shape}, {mu.shape}, {sigma.shape}"
            )
        if not (np.all(np.isfinite(M)) and np.all(np.isfinite(mu)) and np.all(np.isfinite(sigma))):
            raise ModelError("PCA prior contains non-finite values")
        if np.any(sigma <= 0):
            raise ModelError("PCA prior standard deviations must be positive")
        if not np.allclose(M.T @ M, np.eye(M.shape[1]), atol=1e-6):
            raise ModelError("PCA prior directions M must be orthonormal")
        for name, a in (("M", M), ("mu", mu), ("sigma", sigma)):
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    @property
    def n_components(self) -> int:
        return int(self.M.shape[1])

    @classmethod
    def fit(cls, poses: FloatArray, variance_kept: float = 0.95) -> PcaPrior:
        """PCA of pose samples keeping ``variance_kept`` of the variance.

        Parameters
        ----------
        poses : array, shape (n, 66) or (n, 60)
            Full θ (its first six elements are dropped) or θ̄ directly.
        """
        X = np.asarray(poses, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] not in (POSE_DIM, PRIOR_DIM) or X.shape[0] < 2:
            raise InputError(f"poses must have shape (n >= 2, {POSE_DIM} or {PRIOR_DIM}), got {X.shape}")
        if X.shape[1] == POSE_DIM:
            X = X[:, 6:]
        if not np.all(np.isfinite(X)):
            raise InputError("poses contain non-finite values")
        if not 0.0 < variance_kept <= 1.0:
            raise InputError(f"variance_kept must be in (0, 1], got {variance_kept}")
        mu = X.mean(axis=0)
        _, s, vt = np.linalg.svd(X - mu, full_matrices=False)
        var = s * s / (X.shape[0] - 1)
        frac = np.cumsum(var) / np.sum(var)
        k = int(np.searchsorted(frac, variance_kept - 1e-12) + 1)
        k = max(1, min(k, int(np.count_nonzero(var > 1e-12 * var[0]))))
        return cls(M=vt[:k].T, mu=mu, sigma=np.sqrt(var[:k]))

    def save(self, path: str | Path) -> None:
        np.savez(Path(path), M=self.M, mu=self.mu, sigma=self.sigma)

    @classmethod
    def load(cls, path: str | Path) -> PcaPrior:
        p = Path(path)
        try:
            with np.load(p) as data:
                return cls(M=data["M"], mu=data["mu"], sigma=data["sigma"])
        except (OSError, KeyError, ValueError) as exc:
            raise ModelError(f"cannot load PCA prior from {p}: {exc}") from exc

"""Robust losses and the Ceres way of applying them to a Gauss–Newton / LM step.

A loss maps the squared norm ``s = ||f||²`` of a residual block to ``ρ(s)`` and returns ``(ρ, ρ', ρ'')``
(Ceres ``LossFunction::Evaluate``). The solver minimises ``½ Σ ρ(||f_i||²)``.

Ceres's ``Corrector`` (internal/ceres/corrector.cc) turns a robustified block into an equivalent least squares
block: with ``α = 1 - sqrt(1 + 2 s ρ''/ρ')`` when ``ρ'' > 0`` (else ``α = 0``)::

    f~ = sqrt(ρ') / (1 - α) f
    J~ = sqrt(ρ') (I - α f fᵀ / s) J

so the normal equations become ``J~ᵀJ~ = ρ' (JᵀJ - β (Jᵀf)(Jᵀf)ᵀ)`` with ``β = (2α - α²)/s`` and
``J~ᵀ f~ = ρ' Jᵀ f`` (the exact gradient of ``½ρ``). For the Cauchy loss ``ρ'' < 0`` always, so α = 0 and only
the first-order ``sqrt(ρ')`` scaling applies — exactly what Ceres does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class Loss(Protocol):
    """A robust loss ρ(s) of a block's squared norm s."""

    def evaluate(self, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(ρ(s), ρ'(s), ρ''(s))``, each with the shape of ``s``."""
        ...


@dataclass(frozen=True)
class TrivialLoss:
    """Plain least squares: ρ(s) = s."""

    def evaluate(self, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        s = np.asarray(s, dtype=np.float64)
        return s, np.ones_like(s), np.zeros_like(s)


@dataclass(frozen=True)
class CauchyLoss:
    """Cauchy loss ``ρ(s) = a² log(1 + s/a²)``; with ``a = 1`` it is the seeds' ``log(1 + x)``."""

    scale: float = 1.0

    def evaluate(self, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        s = np.asarray(s, dtype=np.float64)
        b = self.scale * self.scale
        c = 1.0 / b
        inv = 1.0 / (1.0 + s * c)
        return b * np.log1p(s * c), inv, -c * inv * inv


@dataclass(frozen=True)
class HuberLoss:
    """Huber loss (Ceres form): ``s`` for ``s <= a²``, ``2 a sqrt(s) - a²`` beyond."""

    scale: float = 1.0

    def evaluate(self, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        s = np.asarray(s, dtype=np.float64)
        b = self.scale * self.scale
        r = np.sqrt(np.maximum(s, 1e-300))
        outer = s > b
        rho = np.where(outer, 2.0 * self.scale * r - b, s)
        rho1 = np.where(outer, np.maximum(self.scale / r, np.finfo(float).tiny), 1.0)
        rho2 = np.where(outer, -0.5 * rho1 / np.maximum(s, 1e-300), 0.0)
        return rho, rho1, rho2


def corrector_weights(s: FloatArray, rho1: FloatArray, rho2: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per-block weights of the Ceres correction for the normal equations.

    Parameters
    ----------
    s, rho1, rho2 : arrays of the same shape (n_blocks,)

    Returns
    -------
    w : array (n_blocks,)
        ``ρ'`` — multiplies both ``JᵀJ`` and ``Jᵀf``.
    beta : array (n_blocks,)
        ``(2α - α²)/s`` (0 where Ceres applies no second-order correction); ``J~ᵀJ~ = w (JᵀJ - beta gᵀg)``
        with ``g = Jᵀf``.
    """
    s = np.asarray(s, dtype=np.float64)
    second = (s > 0.0) & (rho2 > 0.0)
    ratio = np.where(second, rho2 / np.where(rho1 > 0, rho1, 1.0), 0.0)
    alpha = np.where(second, 1.0 - np.sqrt(np.maximum(1.0 + 2.0 * s * ratio, 0.0)), 0.0)
    beta = np.where(second, (2.0 * alpha - alpha * alpha) / np.where(s > 0, s, 1.0), 0.0)
    return rho1, beta

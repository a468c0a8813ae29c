"""Seed 003 Table 1 metrics: joint position error (global, root-relative, per-frame Procrustes) and orientation.

Every statistic is over all joints of all frames: mean, standard deviation, median and MAD (median absolute
deviation from the median). Positions in millimetres, orientations in degrees (angle of the relative rotation).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def stats(values: FloatArray) -> dict[str, float]:
    """mean, std, median, MAD of a flat sample (NaN ignored), rounded for reports."""
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"mean": float("nan"), "std": float("nan"), "median": float("nan"), "mad": float("nan"), "n": 0}
    med = float(np.median(v))
    return {
        "mean": round(float(np.mean(v)), 2),
        "std": round(float(np.std(v)), 2),
        "median": round(med, 2),
        "mad": round(float(np.median(np.abs(v - med))), 2),
        "n": int(v.size),
    }


def procrustes_align(pred: FloatArray, truth: FloatArray) -> FloatArray:
    """``pred`` (f, n, 3) aligned per frame to ``truth`` by the best similarity transform (Umeyama)."""
    mp = pred.mean(axis=1, keepdims=True)
    mt = truth.mean(axis=1, keepdims=True)
    P, T = pred - mp, truth - mt
    H = np.einsum("fni,fnj->fij", P, T)
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    D = np.zeros_like(H)
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    var = np.sum(P * P, axis=(1, 2))
    scale = np.einsum("fii->f", _diag(S) @ D) / np.maximum(var, 1e-12)
    return np.asarray(scale[:, None, None] * np.einsum("fij,fnj->fni", R, P) + mt)


def _diag(S: FloatArray) -> FloatArray:
    out = np.zeros((*S.shape, S.shape[-1]))
    idx = np.arange(S.shape[-1])
    out[..., idx, idx] = S
    return out


def position_errors(pred: FloatArray, truth: FloatArray) -> dict[str, FloatArray]:
    """Per-joint errors (mm), shape (f, n), for ``global``, ``root_relative`` and ``procrustes``.

    Parameters
    ----------
    pred, truth : array, shape (f, n, 3), metres; joint 0 is the root. Rows of ``pred`` with NaN give NaN.
    """
    g = np.linalg.norm(pred - truth, axis=-1)
    r = np.linalg.norm((pred - pred[:, :1]) - (truth - truth[:, :1]), axis=-1)
    ok = np.all(np.isfinite(pred), axis=(1, 2))
    pa = np.full_like(g, np.nan)
    if np.any(ok):
        pa[ok] = np.linalg.norm(procrustes_align(pred[ok], truth[ok]) - truth[ok], axis=-1)
    return {"global": 1e3 * g, "root_relative": 1e3 * r, "procrustes": 1e3 * pa}


def orientation_errors(pred: FloatArray, truth: FloatArray) -> FloatArray:
    """Angle (deg) of ``predᵀ truth`` per bone, from rotation matrices (f, n, 3, 3) -> (f, n)."""
    rel = np.swapaxes(pred, -1, -2) @ truth
    c = np.clip((np.einsum("...ii->...", rel) - 1.0) / 2.0, -1.0, 1.0)
    return np.asarray(np.degrees(np.arccos(c)))


def summarize(
    pos: FloatArray, truth_pos: FloatArray, rot: FloatArray | None, truth_rot: FloatArray | None
) -> dict[str, Any]:
    """All Table-1 statistics of one method on one or more concatenated sequences."""
    errs = position_errors(pos, truth_pos)
    out: dict[str, Any] = {k: stats(v) for k, v in errs.items()}
    out["orientation_deg"] = (
        stats(orientation_errors(rot, truth_rot)) if rot is not None and truth_rot is not None else None
    )
    return out

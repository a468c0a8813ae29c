"""The DLT rows, their dehomogenisation and the triangulation written with fewer NumPy temporaries (issue 39: the
collapse check and the camera watch build these on every person solve) give what the old code gave (kept here
verbatim as the oracle): the same rows, weights, points and flags, bit for bit, on rigs of 2 to 8 cameras with
missing, low, negative, NaN and infinite weights, NaN and infinite pixels, points behind a camera, scales near zero
and no points at all."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import dehomogenized, triangulate_arrays, triangulate_projections, weighted_dlt_rows
from mocapd.core.synthetic import ring_rig

FloatArray = NDArray[np.float64]


def old_weighted_dlt_rows(P: FloatArray, uv: FloatArray, weights: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``camera.weighted_dlt_rows`` before this change, verbatim."""
    finite = np.all(np.isfinite(uv), axis=-1) & np.isfinite(weights) & (weights > 0)
    w = np.where(finite, weights, 0.0)
    uv = np.where(finite[..., None], uv, 0.0)
    r1 = uv[..., 0, None] * P[:, None, 2, :] - P[:, None, 0, :]
    r2 = uv[..., 1, None] * P[:, None, 2, :] - P[:, None, 1, :]
    A = np.concatenate((r1, r2), axis=0).transpose(1, 0, 2)
    # Unit-norm rows first (conditioning: pixel-sized rows would dominate), then the confidence weight.
    norms = np.linalg.norm(A, axis=-1, keepdims=True)
    A = A / np.where(norms > 0, norms, 1.0) * np.concatenate((w, w), axis=0).T[..., None]
    return A, w


def old_dehomogenized(h: FloatArray) -> FloatArray:
    """``camera.dehomogenized`` before this change, verbatim."""
    good = np.abs(h[:, 3]) > 1e-12
    X = np.full((h.shape[0], 3), np.nan)
    X[good] = h[good, :3] / h[good, 3:4]
    return X


def old_triangulate_arrays(
    P: FloatArray, uv: FloatArray, w: FloatArray, min_views: int = 2, *, normal_equations: bool = False
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """``camera.triangulate_arrays`` before this change, verbatim (with the old helpers)."""
    A, w = old_weighted_dlt_rows(P, uv, w)
    ok = np.sum(w > 0, axis=0) >= min_views
    X = np.full((uv.shape[1], 3), np.nan)
    if np.any(ok):
        if normal_equations:
            Ao = A[ok]
            h = np.linalg.eigh(Ao.transpose(0, 2, 1) @ Ao)[1][:, :, 0]  # eigenvalues ascending
        else:
            h = np.linalg.svd(A[ok])[2][:, -1, :]
        X[ok] = old_dehomogenized(h)
        ok = ok & np.all(np.isfinite(X), axis=-1)
    return X, ok


def _bits(a: NDArray[np.generic]) -> bytes:
    return np.ascontiguousarray(a).tobytes()


def _same(a: NDArray[np.generic], b: NDArray[np.generic]) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and _bits(a) == _bits(b)


def _scenes(rng: np.random.Generator) -> list[tuple[FloatArray, FloatArray, FloatArray]]:
    """(P, uv, weights) of rigs of 2 to 8 cameras, points near the middle and some behind a camera, with every kind
    of excluded view: weight 0, negative, NaN, inf; a NaN or infinite pixel; a point nobody sees; no points."""
    out = []
    for n_cams in range(2, 9):
        cams = ring_rig(n_cams, radius=4.5)
        P = np.stack([c.projection_matrix for c in cams])
        for n_pts in (0, 1, 2, 6, 17, 40):
            X = rng.normal(0.0, 0.8, (n_pts, 3)) + np.array([0.0, 1.0, 0.0])
            if n_pts > 2:
                X[0] = cams[0].center + 0.5 * (cams[0].center - X[1])  # behind camera 0
            h = P[:, None, :, :3] @ X[None, :, :, None] + P[:, None, :, 3:]
            uv = h[..., :2, 0] / h[..., 2:, 0] + rng.normal(0.0, 1.5, (n_cams, n_pts, 2))
            w = rng.uniform(0.0, 1.0, (n_cams, n_pts))
            w[rng.uniform(size=w.shape) < 0.2] = 0.0
            w[rng.uniform(size=w.shape) < 0.05] = -0.3
            w[rng.uniform(size=w.shape) < 0.03] = np.nan
            w[rng.uniform(size=w.shape) < 0.03] = np.inf
            uv[rng.uniform(size=w.shape) < 0.04] = np.nan
            uv[..., 1][rng.uniform(size=w.shape) < 0.03] = np.inf
            if n_pts > 3:
                w[:, 3] = 0.0  # nobody sees it
            out.append((P, uv, w))
    return out


def test_the_dlt_rows_are_the_old_ones_to_the_bit() -> None:
    for P, uv, w in _scenes(np.random.default_rng(5)):
        A, used = weighted_dlt_rows(P, uv, w)
        A0, used0 = old_weighted_dlt_rows(P, uv, w)
        assert _same(A, A0) and _same(used, used0)


def test_dehomogenized_is_the_old_one_to_the_bit() -> None:
    rng = np.random.default_rng(6)
    h = rng.normal(size=(400, 4))
    h[::7, 3] = rng.choice([0.0, -0.0, 1e-12, -1e-12, 1.1e-12, -3e-13, 5e-300], size=len(h[::7]))
    h[::11, :3] *= 1e300  # overflows to inf for a small scale
    h[::13, 1] = np.nan
    with np.errstate(over="ignore"):
        for rows in (h, h[:0], h[:1], h[::-1]):
            assert _same(dehomogenized(rows), old_dehomogenized(rows))


def test_the_triangulated_points_and_flags_are_the_old_ones_to_the_bit() -> None:
    for P, uv, w in _scenes(np.random.default_rng(7)):
        for min_views in (2, 3):
            for normal in (False, True):
                X, ok = triangulate_arrays(P, uv, w, min_views, normal_equations=normal)
                X0, ok0 = old_triangulate_arrays(P, uv, w, min_views, normal_equations=normal)
                assert _same(X, X0) and _same(ok, ok0)
                X1, ok1 = triangulate_projections(P, uv, w, min_views, normal_equations=normal)
                assert _same(X1, X0) and _same(ok1, ok0)


def test_the_scenes_exercise_every_path() -> None:
    """The oracle is not compared on easy inputs only: many points triangulated, many refused for too few views."""
    triangulated = refused = 0
    for P, uv, w in _scenes(np.random.default_rng(7)):
        _, ok = old_triangulate_arrays(P, uv, w)
        used = old_weighted_dlt_rows(P, uv, w)[1]
        triangulated += int(ok.sum())
        refused += int((np.sum(used > 0, axis=0) < 2).sum())
    assert triangulated > 300 and refused > 50

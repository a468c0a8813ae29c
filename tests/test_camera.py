"""Camera model: checked against OpenCV (an independent implementation) and finite differences."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mocapd.core.camera import (
    Camera,
    _normalized_from_pixels_numpy,
    look_at,
    normalized_from_pixels,
    project_points,
    triangulate,
    triangulate_projections,
)
from mocapd.core.rotations import matrix_from_rotvec, so3_log
from mocapd.errors import InputError

DIST = np.array([-0.21, 0.08, 0.0012, -0.0008, -0.015])


def _camera(dist: np.ndarray = DIST) -> Camera:
    return look_at("c", np.array([3.0, 2.2, 3.5]), np.array([0.0, 1.0, 0.0]), 1280, 720, 900.0, dist=dist)


def _points(rng: np.random.Generator, n: int = 200) -> np.ndarray:
    return rng.uniform([-1.0, 0.0, -1.0], [1.0, 2.0, 1.0], size=(n, 3))


def test_projection_matches_opencv() -> None:
    cam = _camera()
    X = _points(np.random.default_rng(0))
    ref, _ = cv2.projectPoints(X, so3_log(cam.R), cam.t, cam.K, cam.dist)
    np.testing.assert_allclose(cam.project(X), ref[:, 0, :], atol=1e-8)


def test_projection_jacobian_matches_finite_differences() -> None:
    cam = _camera()
    X = _points(np.random.default_rng(1), 50)
    _, J, valid = project_points(cam.K, cam.dist, cam.R, cam.t, X)
    assert J is not None and valid.all()
    eps = 1e-6
    Jn = np.zeros_like(J)
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        Jn[:, :, k] = (cam.project(X + d) - cam.project(X - d)) / (2 * eps)
    assert np.max(np.abs(J - Jn)) / np.max(np.abs(Jn)) < 1e-7


def test_undistortion_matches_opencv_and_inverts_projection() -> None:
    cam = _camera()
    X = _points(np.random.default_rng(2))
    uv = cam.project(X)
    und = cam.undistort_points(uv)
    ref = cv2.undistortPoints(uv[:, None, :], cam.K, cam.dist, P=cam.K)[:, 0, :]
    np.testing.assert_allclose(und, ref, atol=1e-3)
    ideal = Camera("i", cam.width, cam.height, cam.K, cam.R, cam.t).project(X)
    np.testing.assert_allclose(und, ideal, atol=1e-3)


def test_compiled_undistortion_matches_the_numpy_reference() -> None:
    """The compiled kernel (issue 39: the numpy loop was a quarter of the event loop's time) computes exactly the
    reference's fixed-point iteration, shape (..., 2) kept and NaN passed through."""
    K = np.array([[800.0, 0.0, 480.0], [0.0, 790.0, 270.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.28, 0.1, 0.001, -0.002, 0.01])
    uv = np.random.default_rng(3).uniform(0.0, 960.0, (3, 17, 2))
    uv[1, 4] = np.nan
    for iterations in (1, 10):
        got = normalized_from_pixels(K, dist, uv, iterations)
        want = _normalized_from_pixels_numpy(K, dist, uv, iterations)
        assert got.shape == uv.shape
        np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-12, equal_nan=True)
    assert normalized_from_pixels(K, dist, np.zeros((0, 2))).shape == (0, 2)


def test_world_camera_round_trip_and_behind_camera() -> None:
    cam = _camera()
    X = _points(np.random.default_rng(3))
    np.testing.assert_allclose(cam.cam2world(cam.world2cam(X)), X, atol=1e-12)
    behind = cam.center + 2.0 * (cam.center - np.array([0.0, 1.0, 0.0]))
    assert np.all(np.isnan(cam.project(behind[None])))


def test_triangulation_exact_and_confidence_weighted() -> None:
    rng = np.random.default_rng(4)
    cams = [
        look_at(
            f"c{i}",
            np.array([4 * np.sin(a), 2.5, 4 * np.cos(a)]),
            np.array([0.0, 1.0, 0.0]),
            1920,
            1080,
            1400.0,
            dist=DIST * (i % 2),
        )
        for i, a in enumerate(np.linspace(0, 2 * np.pi, 6, False))
    ]
    X = _points(rng, 40)
    uv = np.stack([c.project(X) for c in cams])
    w = np.ones(uv.shape[:2])
    Xt, ok = triangulate(cams, uv, w)
    assert ok.all()
    np.testing.assert_allclose(Xt, X, atol=1e-6)
    # One view grossly wrong: with confidence ~0 it barely matters, with confidence 1 it does.
    bad = uv.copy()
    bad[0] += 150.0
    w_low = w.copy()
    w_low[0] = 1e-4
    err_low = np.linalg.norm(triangulate(cams, bad, w_low)[0] - X, axis=1).max()
    err_high = np.linalg.norm(triangulate(cams, bad, w)[0] - X, axis=1).max()
    assert err_low < 1e-3
    assert err_high > 0.01
    # Fewer than two views: not triangulated.
    w_one = np.zeros_like(w)
    w_one[0] = 1.0
    X1, ok1 = triangulate(cams, uv, w_one)
    assert not ok1.any() and np.all(np.isnan(X1))
    # The normal-equation variant (the left/right flip search's) finds the same points, noise and weights included.
    P = np.stack([c.projection_matrix for c in cams])
    und = np.stack([c.undistort_points(uv[i] + rng.normal(0.0, 2.0, uv[i].shape)) for i, c in enumerate(cams)])
    w_rand = rng.uniform(0.0, 1.0, w.shape)
    w_rand[rng.random(w.shape) < 0.3] = 0.0
    X_svd, ok_svd = triangulate_projections(P, und, w_rand)
    X_ne, ok_ne = triangulate_projections(P, und, w_rand, normal_equations=True)
    assert np.array_equal(ok_svd, ok_ne) and ok_svd.sum() > 30
    np.testing.assert_allclose(X_ne[ok_ne], X_svd[ok_svd], atol=1e-9)


def test_invalid_cameras_and_inputs_raise() -> None:
    K = np.array([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]])
    with pytest.raises(InputError, match="R is not a rotation"):
        Camera("x", 640, 480, K, np.eye(3) * 2, np.zeros(3))
    with pytest.raises(InputError, match="dist must have shape"):
        Camera("x", 640, 480, K, np.eye(3), np.zeros(3), dist=np.zeros(4))
    with pytest.raises(InputError, match="non-finite"):
        Camera("x", 640, 480, K, matrix_from_rotvec(np.array([0.1, 0, 0])), np.array([0, np.nan, 0]))
    with pytest.raises(InputError, match="uv must have shape"):
        triangulate([_camera()], np.zeros((2, 3, 2)), np.ones((2, 3)))

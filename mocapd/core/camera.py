"""Pinhole cameras with OpenCV's 5-parameter distortion, projection Jacobians and triangulation.

Conventions: ``x_cam = R x_world + t`` (world→camera, OpenCV axes: +X right, +Y down, +Z forward), metres;
image coordinates in pixels with the centre of the top-left pixel at (0, 0) as in OpenCV. Distortion
``(k1, k2, p1, p2, k3)`` is OpenCV's radial-tangential model applied to normalised coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core._undistort_kernel import normalize_points
from mocapd.core.norms import norms
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

MIN_DEPTH = 1e-3
"""Points closer than this (metres, along the optical axis) are treated as not visible."""


@dataclass(frozen=True)
class Camera:
    """A calibrated camera.

    Attributes
    ----------
    name : str
    width, height : int
        Image size in pixels.
    K : array, shape (3, 3)
        Intrinsic matrix (fx, fy, cx, cy; no skew).
    dist : array, shape (5,)
        OpenCV distortion (k1, k2, p1, p2, k3).
    R : array, shape (3, 3)
        World→camera rotation.
    t : array, shape (3,)
        World→camera translation (metres).
    """

    name: str
    width: int
    height: int
    K: FloatArray
    R: FloatArray
    t: FloatArray
    dist: FloatArray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        for attr, shape in (("K", (3, 3)), ("R", (3, 3)), ("t", (3,)), ("dist", (5,))):
            a = np.array(getattr(self, attr), dtype=np.float64)
            if a.shape != shape:
                raise InputError(f"camera {self.name!r}: {attr} must have shape {shape}, got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise InputError(f"camera {self.name!r}: {attr} contains non-finite values")
            a.setflags(write=False)
            object.__setattr__(self, attr, a)
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-6) or np.linalg.det(self.R) < 0:
            raise InputError(f"camera {self.name!r}: R is not a rotation matrix")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise InputError(f"camera {self.name!r}: focal lengths must be positive, got K={self.K.tolist()}")
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"camera {self.name!r}: image size must be positive, got {self.width}x{self.height}")

    # -- geometry -------------------------------------------------------------------------------------
    @property
    def center(self) -> FloatArray:
        """Camera centre in world coordinates, shape (3,)."""
        return np.asarray(-self.R.T @ self.t)

    @property
    def projection_matrix(self) -> FloatArray:
        """``P = K [R | t]``, shape (3, 4) (ignores distortion)."""
        return np.asarray(self.K @ np.hstack((self.R, self.t[:, None])))

    def world2cam(self, X: FloatArray) -> FloatArray:
        """World points (..., 3) to camera coordinates (..., 3)."""
        return np.asarray(np.asarray(X) @ self.R.T + self.t)

    def cam2world(self, Xc: FloatArray) -> FloatArray:
        """Camera coordinates (..., 3) to world points (..., 3)."""
        return np.asarray((np.asarray(Xc) - self.t) @ self.R)

    def project(self, X: FloatArray) -> FloatArray:
        """Pixel coordinates of world points, shape (..., 3) -> (..., 2). Points behind the camera give NaN."""
        uv, _, valid = project_points(self.K, self.dist, self.R, self.t, np.asarray(X, dtype=np.float64), False)
        return np.where(valid[..., None], uv, np.nan)

    def undistort_points(self, uv: FloatArray, iterations: int = 10) -> FloatArray:
        """Undistorted pixel coordinates (same K, no distortion), shape (..., 2) -> (..., 2)."""
        xy = normalized_from_pixels(self.K, self.dist, np.asarray(uv, dtype=np.float64), iterations)
        return np.asarray(xy @ self.K[:2, :2].T + self.K[:2, 2])


def stack_cameras(cameras: list[Camera]) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Stack intrinsics and extrinsics of several cameras for vectorised projection.

    Returns
    -------
    K : (n_cams, 3, 3), dist : (n_cams, 5), R : (n_cams, 3, 3), t : (n_cams, 3)
    """
    if not cameras:
        return np.zeros((0, 3, 3)), np.zeros((0, 5)), np.zeros((0, 3, 3)), np.zeros((0, 3))
    return (
        np.stack([c.K for c in cameras]),
        np.stack([c.dist for c in cameras]),
        np.stack([c.R for c in cameras]),
        np.stack([c.t for c in cameras]),
    )


def project_points(
    K: FloatArray, dist: FloatArray, R: FloatArray, t: FloatArray, X: FloatArray, jacobian: bool = True
) -> tuple[FloatArray, FloatArray | None, NDArray[np.bool_]]:
    """Project world points through one or many cameras, with the Jacobian w.r.t. the world point.

    Parameters
    ----------
    K : array, shape (..., 3, 3)
    dist : array, shape (..., 5)
    R : array, shape (..., 3, 3)
    t : array, shape (..., 3)
        Camera parameters; leading dims broadcast against the points' leading dims *after* a point axis is
        added, i.e. with cameras of shape (n_cams, ...) pass ``X`` of shape (n_pts, 3) to get (n_cams, n_pts).
    X : array, shape (n_pts, 3) or broadcastable (..., n_pts, 3)
    jacobian : bool
        Whether to return ``∂uv/∂X``.

    Returns
    -------
    uv : array, shape (..., n_pts, 2)
    J : array, shape (..., n_pts, 2, 3) or None
    valid : bool array, shape (..., n_pts)
        False where the point is behind (or too close to) the camera; uv and J are then meaningless.
    """
    Xc = np.einsum("...ij,...nj->...ni", R, X) + t[..., None, :]
    z = Xc[..., 2]
    valid = z > MIN_DEPTH
    zs = np.where(valid, z, 1.0)
    iz = 1.0 / zs
    x = Xc[..., 0] * iz
    y = Xc[..., 1] * iz
    k1, k2, p1, p2, k3 = (dist[..., i, None] for i in range(5))
    x2, y2, xy = x * x, y * y, x * y
    r2 = x2 + y2
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
    yd = y * radial + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
    fx, fy = K[..., 0, 0, None], K[..., 1, 1, None]
    cx, cy = K[..., 0, 2, None], K[..., 1, 2, None]
    uv = np.stack((fx * xd + cx, fy * yd + cy), axis=-1)
    if not jacobian:
        return uv, None, valid
    # d(radial)/d(x, y)
    drad = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))
    dxd_dx = radial + x * drad * x + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = x * drad * y + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dx = y * drad * x + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dy = radial + y * drad * y + 6.0 * p1 * y + 2.0 * p2 * x
    # d(x, y)/d(Xc): x = Xc0/z, y = Xc1/z
    J = np.empty((*uv.shape[:-1], 2, 3))
    a = fx * iz
    b = fy * iz
    J[..., 0, 0] = a * dxd_dx
    J[..., 0, 1] = a * dxd_dy
    J[..., 0, 2] = -a * (dxd_dx * x + dxd_dy * y)
    J[..., 1, 0] = b * dyd_dx
    J[..., 1, 1] = b * dyd_dy
    J[..., 1, 2] = -b * (dyd_dx * x + dyd_dy * y)
    # Chain with d(Xc)/dX = R.
    J = J @ R[..., None, :, :]
    return uv, J, valid


def normalized_from_pixels(K: FloatArray, dist: FloatArray, uv: FloatArray, iterations: int = 10) -> FloatArray:
    """Undistorted normalised coordinates from distorted pixels (fixed-point iteration as OpenCV does; compiled:
    :mod:`mocapd.core._undistort_kernel`).

    Parameters
    ----------
    K : (3, 3), dist : (5,), uv : (..., 2)

    Returns
    -------
    array, shape (..., 2)
    """
    uv = np.asarray(uv, dtype=np.float64)
    flat = np.ascontiguousarray(uv.reshape(-1, 2))
    out = np.empty_like(flat)
    normalize_points(
        np.ascontiguousarray(K, dtype=np.float64), np.ascontiguousarray(dist, dtype=np.float64), flat, iterations, out
    )
    return out.reshape(uv.shape)


def _normalized_from_pixels_numpy(K: FloatArray, dist: FloatArray, uv: FloatArray, iterations: int = 10) -> FloatArray:
    """The numpy reference of :func:`normalized_from_pixels` (for the test that compares the two)."""
    k1, k2, p1, p2, k3 = (float(v) for v in dist)
    xd = (uv[..., 0] - K[0, 2]) / K[0, 0]
    yd = (uv[..., 1] - K[1, 2]) / K[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return np.stack((x, y), axis=-1)


def triangulate(
    cameras: list[Camera], uv: FloatArray, weights: FloatArray, min_views: int = 2
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Confidence-weighted linear (DLT) triangulation, seed 003 Eq. 17 without the robust loss.

    Each view contributes two rows ``w (u P3 - P1)`` and ``w (v P3 - P2)`` (undistorted pixels); the point is
    the right singular vector of the smallest singular value.

    Parameters
    ----------
    cameras : list of n_cams Camera
    uv : array, shape (n_cams, n_pts, 2)
        Distorted pixel observations.
    weights : array, shape (n_cams, n_pts)
        Confidence in [0, 1]; 0 (or a non-finite uv) excludes the view.
    min_views : int
        Points seen (weight > 0) in fewer views are returned as NaN.

    Returns
    -------
    X : array, shape (n_pts, 3)
    ok : bool array, shape (n_pts,)
    """
    uv = np.asarray(uv, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    n_cams = len(cameras)
    if uv.ndim != 3 or uv.shape[0] != n_cams or uv.shape[2] != 2:
        raise InputError(f"uv must have shape ({n_cams}, n_pts, 2), got {uv.shape}")
    if w.shape != uv.shape[:2]:
        raise InputError(f"weights must have shape {uv.shape[:2]}, got {w.shape}")
    finite = np.all(np.isfinite(uv), axis=-1) & np.isfinite(w) & (w > 0)
    w = np.where(finite, w, 0.0)
    uv = np.where(finite[..., None], uv, 0.0)
    und = np.stack([c.undistort_points(uv[i]) for i, c in enumerate(cameras)]) if n_cams else uv
    P = np.stack([c.projection_matrix for c in cameras]) if n_cams else np.zeros((0, 3, 4))
    return triangulate_projections(P, und, w, min_views)


def triangulate_projections(
    P: FloatArray, uv: FloatArray, weights: FloatArray, min_views: int = 2, *, normal_equations: bool = False
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The DLT of :func:`triangulate` on projection matrices and undistorted pixels.

    Parameters
    ----------
    P : array, shape (n_cams, 3, 4)
        Projection matrices (undistorted pixels = dehom(P @ [X, 1])).
    uv : array, shape (n_cams, n_pts, 2)
        Undistorted pixel observations.
    weights : array, shape (n_cams, n_pts)
        Confidence; 0 (or a non-finite uv) excludes the view.
    min_views : int
        Points seen (weight > 0) in fewer views are returned as NaN.
    normal_equations : bool
        Take each point from the smallest eigenvector of the 4x4 ``AᵀA`` instead of the SVD of ``A``: half the
        cost on large batches, at the squared condition number (the rows are unit-normalised first); for
        callers that compare many candidate points rather than keep them.

    Returns
    -------
    X : array, shape (n_pts, 3)
    ok : bool array, shape (n_pts,)
    """
    P = np.asarray(P, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    n_cams = P.shape[0] if P.ndim == 3 else -1
    if P.ndim != 3 or P.shape[1:] != (3, 4) or uv.ndim != 3 or uv.shape[0] != n_cams or uv.shape[2] != 2:
        raise InputError(f"P must be (n_cams, 3, 4) and uv (n_cams, n_pts, 2), got {P.shape} and {uv.shape}")
    if w.shape != uv.shape[:2]:
        raise InputError(f"weights must have shape {uv.shape[:2]}, got {w.shape}")
    return triangulate_arrays(P, uv, w, min_views, normal_equations=normal_equations)


def triangulate_arrays(
    P: FloatArray, uv: FloatArray, w: FloatArray, min_views: int = 2, *, normal_equations: bool = False
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """:func:`triangulate_projections` of float64 arrays already of its shapes, without its conversions and checks
    (callers on the solve's hot path that built the arrays themselves: :mod:`mocapd.core.lr_collapse`). The same
    parameters and results."""
    A, w = weighted_dlt_rows(P, uv, w)
    ok = np.count_nonzero(w > 0, axis=0) >= min_views
    X = np.full((uv.shape[1], 3), np.nan)
    if ok.any():
        if normal_equations:
            Ao = A[ok]
            h = np.linalg.eigh(Ao.transpose(0, 2, 1) @ Ao)[1][:, :, 0]  # eigenvalues ascending
        else:
            h = np.linalg.svd(A[ok])[2][:, -1, :]
        X[ok] = dehomogenized(h)
        ok &= np.isfinite(X).all(axis=1)
    return X, ok


def weighted_dlt_rows(P: FloatArray, uv: FloatArray, weights: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The DLT system of every point: each camera's two rows, unit-normed, times its weight (0 where the weight
    is not positive or the pixel not finite).

    Parameters
    ----------
    P : array, shape (n_cams, 3, 4)
    uv : array, shape (n_cams, n_pts, 2)
    weights : array, shape (n_cams, n_pts)

    Returns
    -------
    A : array, shape (n_pts, 2 * n_cams, 4)
        Every camera's u rows, then every camera's v rows.
    w : array, shape (n_cams, n_pts)
        The weights used (0 for an excluded view).
    """
    # Every step the element-wise operation it was (the same floats), written into one array instead of a
    # temporary each, and the rows' norms as np.linalg.norm takes them (mocapd.core.norms): the collapse check and
    # the camera watch build these rows on every person solve (issue 39).
    finite = np.isfinite(uv).all(axis=-1) & np.isfinite(weights) & (weights > 0)
    w = np.where(finite, weights, 0.0)
    uv = np.where(finite[..., None], uv, 0.0)
    n_cams = w.shape[0]
    A = np.empty((2 * n_cams, w.shape[1], 4))
    for k, rows in ((0, A[:n_cams]), (1, A[n_cams:])):
        np.multiply(uv[..., k, None], P[:, None, 2, :], out=rows)
        np.subtract(rows, P[:, None, k, :], out=rows)
    # Unit-norm rows first (conditioning: pixel-sized rows would dominate), then the confidence weight.
    row_norms = norms(A, keepdims=True)
    np.divide(A, np.where(row_norms > 0, row_norms, 1.0), out=A)
    np.multiply(A, np.concatenate((w, w), axis=0)[..., None], out=A)
    return A.transpose(1, 0, 2), w


def dehomogenized(h: FloatArray) -> FloatArray:
    """Points (m, 3) from homogeneous solutions ``h`` (m, 4); NaN where the scale is (nearly) zero."""
    good = np.abs(h[:, 3]) > 1e-12
    X = np.full((h.shape[0], 3), np.nan)
    np.divide(h[:, :3], h[:, 3:4], out=X, where=good[:, None])  # the same divisions, not the others
    return X


def look_at(
    name: str,
    position: FloatArray,
    target: FloatArray,
    width: int,
    height: int,
    focal: float,
    up: FloatArray | None = None,
    dist: FloatArray | None = None,
) -> Camera:
    """A camera at ``position`` looking at ``target`` (world +Y up), principal point at the image centre."""
    up_v = np.array([0.0, 1.0, 0.0]) if up is None else np.asarray(up, dtype=np.float64)
    pos = np.asarray(position, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - pos
    z /= np.linalg.norm(z)
    x = np.cross(z, up_v)  # image +X (right) = forward × up ... with OpenCV +Y pointing down
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack((x, y, z))
    K = np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return Camera(
        name=name,
        width=width,
        height=height,
        K=K,
        R=R,
        t=-R @ pos,
        dist=np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64),
    )

"""The multi-channel probabilistic visual hull (PVH) of seed 001 §3.2–3.3, in a grid that follows one person.

Every camera contributes per-pixel probabilities in ``n_ch`` channels (channel 0: foreground occupancy, the
*matte*; channel 1: the 2D *joint* belief rendered from the detector's keypoints). A voxel's probability in a
channel is the product of the probabilities its centre projects to in every view (Eq. 4–7). Images are given at
a reduced scale (``1/scale`` of the camera's pixels): the voxels are ~67 mm, a few pixels of the full image.

Adapted from the seed (docs/learned-fusion.md says why and what was measured):

- **Geometric mean instead of the bare product.** The product over C views is taken to the power ``1/C``
  (``exp(mean log p)``): one network then reads 4- and 8-camera hulls on the same scale, and a view that misses
  a keypoint lowers that joint's voxels instead of deleting them. Views whose image a voxel does not project into
  (outside the frame, behind the camera), and views that do not see the person at all (no detection: the joint
  channel is *invalid* there), are left out of that voxel's mean.
- **Carving resolution.** The seed carves ~10 mm voxels and averages them down to 30³ (a Gaussian-weighted
  downsample). ``PvhGrid.supersample`` carves ``supersample³`` fine voxels per coarse voxel and averages them
  (``1``: the coarse centres only); the seed's 10 mm would be 200³ = 8 M projections per view and person-frame.
- **The grid follows the person**: an axis-aligned cube of ``extent`` metres centred on the person's hips estimate
  (:func:`person_centre`, triangulated from the same detections), recomputed every frame. The network regresses
  the joints relative to that centre.

Pure numpy: no image library, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera, triangulate
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
F32Array = NDArray[np.float32]
BoolArray = NDArray[np.bool_]

MATTE, JOINTS = 0, 1
"""Channel indices of the two-channel PVH."""

HIP_KEYPOINTS = (11, 12)
"""COCO-17 left and right hip: the grid centre is their triangulated midpoint."""
MIN_CENTRE_CONFIDENCE = 0.2
"""Keypoints below this confidence do not place the grid (a detector's gross errors come with low confidence)."""


@dataclass(frozen=True)
class PvhGrid:
    """The voxel grid around one person.

    Attributes
    ----------
    size : int
        Coarse voxels per side (the network's input is ``size³``; seed 001: 30).
    extent : float
        Side of the cube in metres (seed 001: ~2 m, i.e. 67 mm voxels at 30³).
    supersample : int
        Fine voxels per coarse voxel and axis that are carved and averaged (1: coarse centres only).
    scale : int
        The channel images are ``1/scale`` of the camera's resolution.
    """

    size: int = 30
    extent: float = 2.0
    supersample: int = 1
    scale: int = 8

    def __post_init__(self) -> None:
        if self.size < 2 or self.supersample < 1 or self.scale < 1 or not self.extent > 0:
            raise InputError(f"PVH grid needs size >= 2, supersample >= 1, scale >= 1, extent > 0; got {self}")

    @property
    def voxel(self) -> float:
        """Edge of a coarse voxel (metres)."""
        return self.extent / self.size

    def axis(self) -> FloatArray:
        """Fine voxel centres along one axis relative to the grid centre, shape (size · supersample,)."""
        n = self.size * self.supersample
        h = self.extent / n
        return np.asarray((np.arange(n) + 0.5) * h - 0.5 * self.extent)

    def centres(self, centre: FloatArray) -> FloatArray:
        """World positions of the fine voxel centres, shape (n, n, n, 3) indexed (x, y, z)."""
        a = self.axis()
        c = np.asarray(centre, dtype=np.float64)
        gx, gy, gz = np.meshgrid(a + c[0], a + c[1], a + c[2], indexing="ij")
        return np.stack((gx, gy, gz), axis=-1)

    def image_size(self, camera: Camera) -> tuple[int, int]:
        """(height, width) of the channel images of ``camera``."""
        return -(-camera.height // self.scale), -(-camera.width // self.scale)


def scaled_pixels(uv: FloatArray, scale: int) -> FloatArray:
    """Full-resolution pixel coordinates (centre of the top-left pixel at 0) to those of a ``1/scale`` image."""
    return np.asarray((np.asarray(uv) + 0.5) / scale - 0.5)


def person_centre(
    cameras: list[Camera], uv: FloatArray, conf: FloatArray, fallback: FloatArray | None = None
) -> FloatArray | None:
    """The grid centre for one person: the midpoint of the triangulated hips (keypoints of confidence below
    :data:`MIN_CENTRE_CONFIDENCE` ignored, views that disagree by more than 10 % of the person's size in pixels
    dropped, see :func:`_robust_points`; one hip when the other is not seen by two views).

    Falls back to the mean of every triangulated keypoint lowered by the hips-to-keypoints offset of a standing
    person (0.25 m) when a hip is not seen by two views, then to ``fallback``.

    Parameters
    ----------
    uv : (n_cams, 17, 2) COCO-17 keypoints; conf : (n_cams, 17).

    Returns
    -------
    array (3,) or None when nothing could be triangulated and there is no fallback.
    """
    conf = np.where(conf >= MIN_CENTRE_CONFIDENCE, conf, 0.0)
    if len(cameras) >= 2 and np.count_nonzero(np.any(conf > 0, axis=1)) >= 2:
        uv0 = np.nan_to_num(uv)
        hips = list(HIP_KEYPOINTS)
        Xh, okh = _robust_points(cameras, uv0[:, hips], conf[:, hips], _person_size_px(uv0, conf))
        if np.any(okh):  # both hips, or the one seen (the grid is 2 m: half a hip width off is nothing)
            return np.asarray(Xh[okh].mean(axis=0))
        X, ok = triangulate(cameras, uv0, conf)
        if np.count_nonzero(ok) >= 3:
            c = np.median(X[ok], axis=0)
            c[1] -= 0.25
            return np.asarray(c)
    return None if fallback is None else np.asarray(fallback, dtype=np.float64)


MIN_RAY_ANGLE = np.deg2rad(10.0)
"""A point whose viewing rays span less than this is not triangulated (adjacent cameras of a spread rig)."""


def _ray_angle(cameras: list[Camera], X: FloatArray, w: FloatArray) -> FloatArray:
    """Per point, the widest angle (radians) between the rays of the views that see it; shape (n,)."""
    rays = np.stack([np.nan_to_num(X) - cam.center for cam in cameras])  # (n_cams, n, 3)
    rays /= np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-9)
    cos = np.einsum("anj,bnj->nab", rays, rays)
    used = (w > 0).T  # (n, n_cams)
    cos = np.where(used[:, :, None] & used[:, None, :], cos, 1.0)
    return np.asarray(np.arccos(np.clip(cos.min(axis=(1, 2)), -1.0, 1.0)))


def _person_size_px(uv: FloatArray, conf: FloatArray) -> FloatArray:
    """Per view, the larger side of the confident keypoints' bounding box (pixels; 0 without two of them)."""
    out = np.zeros(uv.shape[0])
    for c in range(uv.shape[0]):
        pts = uv[c][conf[c] > 0]
        if len(pts) >= 2:
            out[c] = float(np.max(pts.max(axis=0) - pts.min(axis=0)))
    return out


def _robust_points(
    cameras: list[Camera], uv: FloatArray, conf: FloatArray, size_px: FloatArray, max_error: float = 0.1
) -> tuple[FloatArray, BoolArray]:
    """Weighted DLT of a few points, dropping per point the view whose reprojection error is largest while it
    exceeds ``max_error`` × that view's person size and more than two views remain (a gross outlier or a left/right
    swap in one view moved the grid centre by metres).

    Parameters
    ----------
    uv : (n_cams, n, 2); conf : (n_cams, n); size_px : (n_cams,).
    """
    w = conf.copy()
    X, ok = triangulate(cameras, uv, w)
    for _ in range(len(cameras) + 1):
        err = np.zeros(w.shape)
        for c, cam in enumerate(cameras):
            err[c] = np.linalg.norm(cam.project(np.nan_to_num(X)) - uv[c], axis=-1) / np.maximum(size_px[c], 1.0)
        err = np.where(w > 0, err, 0.0)
        worst = np.argmax(err, axis=0)
        too_far = (err[worst, np.arange(w.shape[1])] > max_error) & ok
        bad = too_far & (np.count_nonzero(w > 0, axis=0) > 2)
        if not np.any(bad):
            # Two views whose rays miss each other by that much: one of them saw something else (a swap); views
            # (nearly) in line with the point fix its depth by noise.
            return X, ok & ~too_far & (_ray_angle(cameras, X, w) >= MIN_RAY_ANGLE)
        w[worst[bad], np.flatnonzero(bad)] = 0.0
        X, ok = triangulate(cameras, uv, w)
    return X, ok


def joint_map(uv: FloatArray, conf: FloatArray, shape: tuple[int, int], sigma: float, floor: float = 0.1) -> F32Array:
    """The joint-belief channel of one view: ``floor + (1 - floor) · max_k conf_k · exp(-d_k² / 2σ²)``.

    Seed 001 takes the per-pixel maximum over the joint belief maps of CPM/OpenPose (Eq. 2); a keypoint detector
    gives points and confidences, so each keypoint is rendered as a Gaussian of its confidence. ``floor`` keeps a
    view that missed a keypoint from deleting that joint from the hull.

    Parameters
    ----------
    uv : (n_kp, 2) keypoints in the channel image's pixels; conf : (n_kp,) in [0, 1] (0: not detected).
    shape : (height, width); sigma : Gaussian σ in the channel image's pixels.
    """
    h, w = shape
    out = np.zeros((h, w), dtype=np.float32)
    r = max(1, int(np.ceil(3.0 * sigma)))
    inv = -0.5 / (sigma * sigma)
    for (u, v), c in zip(uv, conf, strict=True):
        if c <= 0 or not (np.isfinite(u) and np.isfinite(v)):
            continue
        x0, x1 = max(0, int(np.floor(u)) - r), min(w, int(np.floor(u)) + r + 2)
        y0, y1 = max(0, int(np.floor(v)) - r), min(h, int(np.floor(v)) + r + 2)
        if x0 >= x1 or y0 >= y1:
            continue
        xs = np.arange(x0, x1, dtype=np.float32) - np.float32(u)
        ys = np.arange(y0, y1, dtype=np.float32) - np.float32(v)
        blob = np.float32(c) * np.exp(np.float32(inv) * (ys[:, None] ** 2 + xs[None, :] ** 2))
        np.maximum(out[y0:y1, x0:x1], blob, out=out[y0:y1, x0:x1])
    return np.asarray(np.float32(floor) + np.float32(1.0 - floor) * out, dtype=np.float32)


def joint_sigma(camera: Camera, centre: FloatArray, scale: int, radius: float = 0.05) -> float:
    """σ (channel-image pixels) of a ``radius``-metre blob at the grid centre's depth in ``camera``."""
    depth = float((camera.R @ np.asarray(centre) + camera.t)[2])
    return max(0.7, float(camera.K[0, 0]) * radius / max(depth, 0.3) / scale)


def log_channels(images: F32Array, eps: float = 0.02) -> F32Array:
    """``log(clip(p, eps, 1))`` of channel images (any shape): what :func:`carve` sums over views. ``eps`` keeps a
    single view from zeroing a voxel."""
    return np.asarray(np.log(np.clip(images, eps, 1.0)), dtype=np.float32)


def _project_grid(grid: PvhGrid, centre: FloatArray, cam: Camera) -> tuple[F32Array, F32Array, BoolArray]:
    """Channel-image pixel coordinates (x, y) of every fine voxel centre, flattened in (x, y, z) order, and which
    lie in front of the camera.

    The grid is axis-aligned, so its camera coordinates are sums of three per-axis terms (broadcast, no
    n³ × 3 × 3 product); OpenCV's distortion is applied to the normalised coordinates as
    :func:`mocapd.core.camera.project_points` does.
    """
    a = grid.axis().astype(np.float32)
    R = cam.R.astype(np.float32)
    base = (cam.R @ np.asarray(centre, dtype=np.float64) + cam.t).astype(np.float32)
    xc = [
        (R[d, 0] * a)[:, None, None] + (R[d, 1] * a)[None, :, None] + (R[d, 2] * a + base[d])[None, None, :]
        for d in range(3)
    ]
    z = xc[2].ravel()
    front = z > 1e-3
    iz = np.float32(1.0) / np.where(front, z, np.float32(1.0))
    x = xc[0].ravel() * iz
    y = xc[1].ravel() * iz
    k1, k2, p1, p2, k3 = (np.float32(v) for v in cam.dist)
    if np.any(cam.dist != 0):
        x2, y2, xy = x * x, y * y, x * y
        r2 = x2 + y2
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x, y = (
            x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x2),
            y * radial + p1 * (r2 + 2 * y2) + 2 * p2 * xy,
        )
    s = np.float32(grid.scale)
    K = cam.K
    u = (np.float32(K[0, 0]) * x + np.float32(K[0, 2]) + np.float32(0.5)) / s - np.float32(0.5)
    v = (np.float32(K[1, 1]) * y + np.float32(K[1, 2]) + np.float32(0.5)) / s - np.float32(0.5)
    return u, v, front


def carve(
    grid: PvhGrid,
    centre: FloatArray,
    cameras: list[Camera],
    log_images: list[F32Array],
    valid: BoolArray,
) -> F32Array:
    """The PVH of one person.

    Parameters
    ----------
    centre : (3,) world position of the grid centre.
    log_images : per camera the :func:`log_channels` of its channel images, (n_ch, h, w) at the grid's ``scale``.
    valid : (n_cams, n_ch) whether a camera's channel informs the hull (a camera that does not see the person has
        no joint channel; a camera without a matte has no matte channel).

    Returns
    -------
    array, shape (n_ch, size, size, size), float32 in [0, 1]; axes (channel, x, y, z).

    Each voxel samples the nearest pixel of the channel image (the images are 1/``scale`` of the camera's and
    blurred by more than a pixel: bilinear sampling changed the hull by < 1e-2 and cost 4 gathers).
    """
    if len(log_images) != len(cameras) or valid.shape[0] != len(cameras):
        raise InputError(f"carve: {len(cameras)} cameras, {len(log_images)} images, {valid.shape[0]} validity rows")
    n_ch = valid.shape[1]
    n = (grid.size * grid.supersample) ** 3
    log_sum = np.zeros((n_ch, n), dtype=np.float32)
    count = np.zeros(n, dtype=np.float32)
    counts = np.zeros((n_ch, n), dtype=np.float32)
    for c, cam in enumerate(cameras):
        if not np.any(valid[c]):
            continue
        u, v, front = _project_grid(grid, centre, cam)
        img = log_images[c]
        h, w = img.shape[1:]
        iu = np.rint(u).astype(np.int32)
        iv = np.rint(v).astype(np.int32)
        use = front & (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
        lin = np.where(use, iv * w + iu, 0)
        count[:] = use
        for ch in range(n_ch):
            if valid[c, ch]:
                log_sum[ch] += np.where(use, img[ch].ravel()[lin], np.float32(0.0))
                counts[ch] += count
    prob = np.where(counts > 0, np.exp(log_sum / np.maximum(counts, np.float32(1.0))), np.float32(0.0))
    s, k = grid.size, grid.supersample
    if k > 1:
        prob = prob.reshape(n_ch, s, k, s, k, s, k).mean(axis=(2, 4, 6))
    return np.asarray(prob.reshape(n_ch, s, s, s), dtype=np.float32)

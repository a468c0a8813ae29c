"""Sparse optical flow on image pyramids built once per frame (pyramidal Lucas-Kanade, as OpenCV computes it).

The keypoint tracker (:mod:`mocapd.pipeline.keypoint_tracker`) tracks every frame to the next and back, and a late
detection's keypoints through the frames kept since: each frame takes part in two to four flow computations.
``cv2.calcOpticalFlowPyrLK`` given images builds both pyramids (and the first one's derivatives over the whole
image) in every call, and OpenCV 5's Python binding refuses prebuilt pyramids. :func:`build_pyramid` builds a
frame's pyramid once (``cv2.pyrDown``, padded as OpenCV pads it); :func:`track` runs OpenCV's Lucas-Kanade
iteration on two of them (:mod:`mocapd.core._lk_kernel`), computing derivatives only under the points' windows.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core import _lk_kernel
from mocapd.errors import InputError

MIN_EIGEN = 1e-4  # OpenCV's default minEigThreshold


@dataclass(frozen=True)
class LKOptions:
    """Lucas-Kanade parameters (``cv2.calcOpticalFlowPyrLK``'s ``winSize``, ``maxLevel`` and criteria)."""

    window_px: int = 15
    """Window side (odd)."""
    levels: int = 3
    """Pyramid levels above the image."""
    max_iterations: int = 30
    epsilon_px: float = 0.01
    """A level's iterations stop when a step is at most this long."""


@dataclass(frozen=True)
class Pyramid:
    """One image's pyramid: its levels padded by ``pad`` px (reflected) in one flat buffer.

    Attributes
    ----------
    buffer : ndarray of uint8, shape (N,)
    meta : ndarray of int64, shape (levels + 1, 3)
        Each level's offset in ``buffer``, rows and columns (unpadded).
    pad : int
    shape : (rows, columns)
        The image's.
    """

    buffer: NDArray[np.uint8]
    meta: NDArray[np.int64]
    pad: int
    shape: tuple[int, int]

    @property
    def levels(self) -> int:
        """Levels above the image."""
        return int(self.meta.shape[0]) - 1


def build_pyramid(gray: NDArray[np.uint8], options: LKOptions) -> Pyramid:
    """The pyramid of a gray image (h, w), uint8, for :func:`track` with ``options``: as many levels as
    ``options.levels`` and the image allow (OpenCV stops before a level no larger than the window)."""
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise InputError(f"optical flow: a 2-D uint8 image is needed, got {gray.dtype} {gray.shape}")
    win = options.window_px
    sizes = [(int(gray.shape[0]), int(gray.shape[1]))]  # (rows, columns) of each level
    for _ in range(options.levels):
        h, w = (sizes[-1][0] + 1) // 2, (sizes[-1][1] + 1) // 2
        if w <= win or h <= win:
            break
        sizes.append((h, w))
    padded = [(h + 2 * win) * (w + 2 * win) for h, w in sizes]
    offsets = np.cumsum([0, *padded])
    meta = np.array([[o, h, w] for o, (h, w) in zip(offsets, sizes, strict=False)], np.int64)
    # Each level written in place into the one buffer: padded around the level below it, then the next level
    # made from this one's inside (no list of arrays, no copy into the buffer afterwards).
    buffer = np.empty(int(offsets[-1]), np.uint8)
    level = gray
    for k, (h, w) in enumerate(sizes):
        dst = buffer[offsets[k] : offsets[k + 1]].reshape(h + 2 * win, w + 2 * win)
        cv2.copyMakeBorder(level, win, win, win, win, cv2.BORDER_REFLECT_101, dst=dst)
        if k + 1 < len(sizes):
            nh, nw = sizes[k + 1]
            level = np.asarray(cv2.pyrDown(dst[win : win + h, win : win + w], dstsize=(nw, nh)), np.uint8)
    return Pyramid(buffer, meta, win, sizes[0])


def _check(a: Pyramid, b: Pyramid, options: LKOptions) -> None:
    if a.shape != b.shape or a.pad != options.window_px or b.pad != options.window_px:
        raise InputError(f"optical flow: pyramids of {a.shape} and {b.shape} for a {options.window_px} px window")


def track(
    a: Pyramid, b: Pyramid, points: NDArray[np.float32], options: LKOptions
) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    """Points ``points`` (n, 2) of image ``a`` found in image ``b``: positions (n, 2) and status (n,), 1 where
    found (``cv2.calcOpticalFlowPyrLK``'s result on the two images, to ~1e-3 px)."""
    _check(a, b, options)
    pts = np.ascontiguousarray(points, np.float32).reshape(-1, 2)
    out = np.empty_like(pts)
    status = np.empty(pts.shape[0], np.uint8)
    if pts.shape[0]:
        _lk_kernel.track(a.buffer, a.meta, b.buffer, b.meta, a.pad, pts, options.window_px,
                         min(a.levels, b.levels, options.levels), options.max_iterations, options.epsilon_px,
                         MIN_EIGEN, out, status)  # fmt: skip
    return out, status


def warm_up() -> None:
    """Compile (or load from numba's cache) the flow kernel before the first tracked frame: a first compile takes
    seconds, which on a capture thread would be seconds of frames not tracked."""
    opts = LKOptions(5, 0)
    pyr = build_pyramid(np.zeros((8, 8), np.uint8), opts)
    track(pyr, pyr, np.full((1, 2), 4.0, np.float32), opts)
    alive = np.ones((1, 1), np.bool_)
    carry_keypoints(pyr, pyr, np.full((1, 1, 2), 4.0), alive, ~alive, 1, 1.0, True, opts)


def forward_backward(
    a: Pyramid, b: Pyramid, points: NDArray[np.float32], options: LKOptions
) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.float64]]:
    """Points ``points`` (n, 2) of image ``a`` tracked to image ``b`` and back (:func:`track` both ways, in one
    compiled call): the positions in ``b`` (n, 2), whether both directions found each (n,), and how far from its
    start each came back (n,), px of the images."""
    _check(a, b, options)
    pts = np.ascontiguousarray(points, np.float32).reshape(-1, 2)
    out = np.empty_like(pts)
    fb = np.empty(pts.shape[0], np.float64)
    status = np.empty(pts.shape[0], np.uint8)
    if pts.shape[0]:
        _lk_kernel.forward_backward(a.buffer, a.meta, b.buffer, b.meta, a.pad, pts, options.window_px,
                                    min(a.levels, b.levels, options.levels), options.max_iterations,
                                    options.epsilon_px, MIN_EIGEN, out, fb, status)  # fmt: skip
    return out, status.astype(np.bool_), fb


def carry_keypoints(
    a: Pyramid,
    b: Pyramid,
    keypoints: NDArray[np.float64],
    alive: NDArray[np.bool_],
    coasting: NDArray[np.bool_],
    factor: int,
    max_fb_px: float,
    coast: bool,
    options: LKOptions,
) -> int:
    """People's keypoints (P, K, 2) carried from image ``a`` to ``b`` in place, ``alive`` and ``coasting`` (P, K)
    updated; returns the keypoints lost. The keypoint tracker's step (:meth:`~mocapd.pipeline.keypoint_tracker.
    KeypointTracker._carry` says what it does) in one compiled call: :func:`mocapd.core._lk_kernel.carry_keypoints`."""
    _check(a, b, options)
    if keypoints.shape != (*alive.shape, 2) or coasting.shape != alive.shape:
        raise InputError(f"optical flow: keypoints {keypoints.shape}, alive {alive.shape}, coasting {coasting.shape}")
    lost = _lk_kernel.carry_keypoints(a.buffer, a.meta, b.buffer, b.meta, a.pad, options.window_px,
                                      min(a.levels, b.levels, options.levels), options.max_iterations,
                                      options.epsilon_px, MIN_EIGEN, factor, max_fb_px, coast, keypoints, alive,
                                      coasting)  # fmt: skip
    return int(lost)

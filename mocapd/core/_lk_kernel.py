"""Compiled (numba) sparse pyramidal Lucas-Kanade on pyramids built once per frame
(:mod:`mocapd.pipeline.optical_flow`).

Why not ``cv2.calcOpticalFlowPyrLK``. The keypoint tracker follows each camera frame forward to the next and back
again (its forward-backward check). OpenCV builds both images' pyramids, and the Scharr derivatives of the first
one's every level over the whole image, inside each call: 4 pyramids and 2 derivative sets per tracked frame, for a
few dozen points, ~0.43 of the call's 0.59 ms on the 272x480 tracking image of the camera demo (issue 39). OpenCV
accepts a pyramid from ``cv2.buildOpticalFlowPyramid`` instead of an image in C++, but the Python binding of
OpenCV 5 refuses it ("prevImg is not a numerical tuple"). Here each frame's pyramid is built once
(:func:`mocapd.pipeline.optical_flow.build_pyramid`) and serves both directions and every pair it is in, and the
derivatives are computed only on the windows the points look at.

The arithmetic is OpenCV's (``LKTrackerInvoker`` of ``modules/video/src/lkpyramid.cpp``): the window sampled with
14-bit fixed-point bilinear weights, image values kept in 1/32 grey levels, Scharr derivatives (3, 10, 3) with
reflected borders inside the image and zero outside it, the 2x2 gradient matrix refused below a minimum eigenvalue
of 1e-4 per window pixel, iterations until the step is below ``epsilon`` px or the point oscillates (then halved
back). Sums run in float64 where OpenCV's run in float32: positions agree with OpenCV's to ~1e-3 px
(``tests/test_optical_flow.py``).

A pyramid is one flat buffer of its levels, each padded by ``pad`` pixels on every side (reflected, as OpenCV's
``BORDER_REFLECT_101``), and a table ``meta`` (levels, 3) of each level's offset in the buffer, rows and columns
(unpadded).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

W_BITS = 14  # OpenCV's fixed-point bilinear weights
FLT_SCALE = 1.0 / (1 << 20)


@nb.njit(cache=True, nogil=True)
def _window_derivatives(
    buf: NDArray[np.uint8],
    off: int,
    stride: int,
    pad: int,
    rows: int,
    cols: int,
    r0: int,
    c0: int,
    side: int,
    vs: NDArray[np.int32],
    vd: NDArray[np.int32],
    dx: NDArray[np.int32],
    dy: NDArray[np.int32],
) -> None:
    """Scharr derivatives d/dx, d/dy of the ``side`` x ``side`` pixels from (r0, c0) into ``dx``, ``dy``, as
    OpenCV's ``calcSharrDeriv``: reflected at the image's border (``BORDER_REFLECT_101``: row -1 is row 1, as the
    padded buffer holds it) and zero outside the image (OpenCV pads its derivative images with zeros). Separable:
    a vertical (3, 10, 3) smoothing ``vs`` and difference ``vd`` of each row's columns, then horizontal ones."""
    for y in range(side):
        r = r0 + y
        if r < 0 or r >= rows:
            for x in range(side):
                dx[np.uintp(y * side + x)] = 0
                dy[np.uintp(y * side + x)] = 0
            continue
        # Columns c0 - 1 .. c0 + side of rows r - 1 .. r + 1: inside the buffer (pad >= 2 and the window starts at
        # most pad columns left of the image); the columns outside the padded rows matter only for pixels outside
        # the image, zeroed below.
        start = off + (r - 1 + pad) * stride + pad + c0 - 1
        # One array written per loop, unsigned indices: vectorised (see _interpolate).
        below = start + 2 * stride
        for x in range(side + 2):
            vs[np.uintp(x)] = (3 * (np.int32(buf[np.uintp(start + x)]) + np.int32(buf[np.uintp(below + x)]))
                               + 10 * np.int32(buf[np.uintp(start + stride + x)]))  # fmt: skip
        for x in range(side + 2):
            vd[np.uintp(x)] = np.int32(buf[np.uintp(below + x)]) - np.int32(buf[np.uintp(start + x)])
        o = y * side
        for x in range(side):
            dx[np.uintp(o + x)] = vs[np.uintp(x + 2)] - vs[np.uintp(x)]
        for x in range(side):
            dy[np.uintp(o + x)] = 3 * (vd[np.uintp(x + 2)] + vd[np.uintp(x)]) + 10 * vd[np.uintp(x + 1)]
        for x in range(min(side, -c0)):  # left of the image
            dx[np.uintp(o + x)] = 0
            dy[np.uintp(o + x)] = 0
        for x in range(max(0, cols - c0), side):  # right of it
            dx[np.uintp(o + x)] = 0
            dy[np.uintp(o + x)] = 0


@nb.njit(cache=True, nogil=True)
def _interpolate(
    src: NDArray[np.uint8] | NDArray[np.int32],
    start: int,
    stride: int,
    win: int,
    w00: int,
    w01: int,
    w10: int,
    w11: int,
    shift: int,
    out: NDArray[np.int32],
) -> None:
    """``out`` (win * win, row-major) the window of ``src`` (rows ``stride`` apart) from index ``start``,
    bilinearly interpolated with OpenCV's fixed-point weights and descaled by ``shift`` bits (``CV_DESCALE``).
    One array written per loop and unsigned indices (no negative-index wraparound): the compiler vectorises it."""
    half = 1 << (shift - 1)
    for y in range(win):
        r0 = start + y * stride
        r1 = r0 + stride
        o = y * win
        for x in range(win):
            v = (np.int32(src[np.uintp(r0 + x)]) * w00 + np.int32(src[np.uintp(r0 + x + 1)]) * w01
                 + np.int32(src[np.uintp(r1 + x)]) * w10 + np.int32(src[np.uintp(r1 + x + 1)]) * w11)  # fmt: skip
            out[np.uintp(o + x)] = (v + half) >> shift


@nb.njit(cache=True, nogil=True)
def track(
    prev_buf: NDArray[np.uint8],
    prev_meta: NDArray[np.int64],
    next_buf: NDArray[np.uint8],
    next_meta: NDArray[np.int64],
    pad: int,
    pts: NDArray[np.float32],
    win: int,
    max_level: int,
    max_count: int,
    epsilon: float,
    min_eig: float,
    out: NDArray[np.float32],
    status: NDArray[np.uint8],
) -> None:
    """Points ``pts`` (n, 2) of the previous image found in the next one, into ``out`` (n, 2); ``status`` (n,)
    1 where found. ``win`` odd window side, ``max_level`` levels above the base (at most both pyramids' own),
    ``max_count`` iterations a level, ``epsilon`` px of step that ends them, ``min_eig`` OpenCV's
    ``minEigThreshold``."""
    n = pts.shape[0]
    half = (win - 1) * 0.5
    eps2 = epsilon * epsilon
    # Scratch, flat (index y * side + x): the window's image values and derivatives, the derivatives under it.
    iwin = np.empty(win * win, np.int32)
    jwin = np.empty(win * win, np.int32)
    dxw = np.empty(win * win, np.int32)
    dyw = np.empty(win * win, np.int32)
    dpx = np.empty((win + 1) * (win + 1), np.int32)
    dpy = np.empty((win + 1) * (win + 1), np.int32)
    vs = np.empty(win + 3, np.int32)
    vd = np.empty(win + 3, np.int32)
    one = 1 << W_BITS
    for k in range(n):
        status[k] = 1
        out[k, 0] = pts[k, 0]
        out[k, 1] = pts[k, 1]
    for level in range(max_level, -1, -1):
        poff, prows, pcols = prev_meta[level, 0], prev_meta[level, 1], prev_meta[level, 2]
        noff, nrows, ncols = next_meta[level, 0], next_meta[level, 1], next_meta[level, 2]
        pstride = pcols + 2 * pad
        nstride = ncols + 2 * pad
        scale = 1.0 / (1 << level)
        for k in range(n):
            px = pts[k, 0] * scale - half
            py = pts[k, 1] * scale - half
            if level == max_level:
                nx = pts[k, 0] * scale
                ny = pts[k, 1] * scale
            else:
                nx = out[k, 0] * 2.0
                ny = out[k, 1] * 2.0
            out[k, 0] = nx
            out[k, 1] = ny
            ix = math.floor(px)
            iy = math.floor(py)
            if ix < -win or ix >= pcols or iy < -win or iy >= prows:
                if level == 0:
                    status[k] = 0
                continue
            a = px - ix
            b = py - iy
            w00 = round((1.0 - a) * (1.0 - b) * one)
            w01 = round(a * (1.0 - b) * one)
            w10 = round((1.0 - a) * b * one)
            w11 = one - w00 - w01 - w10
            # The window of the previous image and its derivatives, and their 2x2 gradient matrix.
            _window_derivatives(prev_buf, poff, pstride, pad, prows, pcols, iy, ix, win + 1, vs, vd, dpx, dpy)
            side = win + 1
            _interpolate(prev_buf, poff + (iy + pad) * pstride + ix + pad, pstride, win, w00, w01, w10, w11,
                         W_BITS - 5, iwin)  # fmt: skip
            _interpolate(dpx, 0, side, win, w00, w01, w10, w11, W_BITS, dxw)
            _interpolate(dpy, 0, side, win, w00, w01, w10, w11, W_BITS, dyw)
            a11 = np.int64(0)
            a12 = np.int64(0)
            a22 = np.int64(0)
            for i in range(win * win):
                gx = np.int64(dxw[np.uintp(i)])
                gy = np.int64(dyw[np.uintp(i)])
                a11 += gx * gx
                a12 += gx * gy
                a22 += gy * gy
            f11 = a11 * FLT_SCALE
            f12 = a12 * FLT_SCALE
            f22 = a22 * FLT_SCALE
            det = f11 * f22 - f12 * f12
            eig = (f22 + f11 - math.sqrt((f11 - f22) * (f11 - f22) + 4.0 * f12 * f12)) / (2.0 * win * win)
            if eig < min_eig or det < 1.1920929e-07:  # FLT_EPSILON
                if level == 0:
                    status[k] = 0
                continue
            inv = 1.0 / det
            nx -= half
            ny -= half
            pdx = 0.0
            pdy = 0.0
            for j in range(max_count):
                jx = math.floor(nx)
                jy = math.floor(ny)
                if jx < -win or jx >= ncols or jy < -win or jy >= nrows:
                    if level == 0:
                        status[k] = 0
                    break
                a = nx - jx
                b = ny - jy
                w00 = round((1.0 - a) * (1.0 - b) * one)
                w01 = round(a * (1.0 - b) * one)
                w10 = round((1.0 - a) * b * one)
                w11 = one - w00 - w01 - w10
                _interpolate(next_buf, noff + (jy + pad) * nstride + jx + pad, nstride, win, w00, w01, w10, w11,
                             W_BITS - 5, jwin)  # fmt: skip
                b1 = 0
                b2 = 0
                for i in range(win * win):
                    diff = np.int64(jwin[np.uintp(i)] - iwin[np.uintp(i)])
                    b1 += diff * dxw[np.uintp(i)]
                    b2 += diff * dyw[np.uintp(i)]
                fb1 = b1 * FLT_SCALE
                fb2 = b2 * FLT_SCALE
                ddx = (f12 * fb2 - f22 * fb1) * inv
                ddy = (f12 * fb1 - f11 * fb2) * inv
                nx += ddx
                ny += ddy
                out[k, 0] = nx + half
                out[k, 1] = ny + half
                if ddx * ddx + ddy * ddy <= eps2:
                    break
                if j > 0 and abs(ddx + pdx) < 0.01 and abs(ddy + pdy) < 0.01:
                    out[k, 0] -= ddx * 0.5
                    out[k, 1] -= ddy * 0.5
                    break
                pdx = ddx
                pdy = ddy


@nb.njit(cache=True, nogil=True)
def forward_backward(
    a_buf: NDArray[np.uint8],
    a_meta: NDArray[np.int64],
    b_buf: NDArray[np.uint8],
    b_meta: NDArray[np.int64],
    pad: int,
    pts: NDArray[np.float32],
    win: int,
    max_level: int,
    max_count: int,
    epsilon: float,
    min_eig: float,
    out: NDArray[np.float32],
    fb: NDArray[np.float64],
    status: NDArray[np.uint8],
) -> None:
    """:func:`track` from image a to b (``out``) and back from there: ``fb`` (n,) the distance from the start
    of each point tracked forward and back, ``status`` 1 where both directions found the point. One call: the
    tracker's forward-backward check without a second dispatch and the numpy steps between."""
    n = pts.shape[0]
    back = np.empty((n, 2), np.float32)
    status_back = np.empty(n, np.uint8)
    track(a_buf, a_meta, b_buf, b_meta, pad, pts, win, max_level, max_count, epsilon, min_eig, out, status)
    track(b_buf, b_meta, a_buf, a_meta, pad, out, win, max_level, max_count, epsilon, min_eig, back, status_back)
    for k in range(n):
        status[k] &= status_back[k]
        fb[k] = math.hypot(float(back[k, 0]) - float(pts[k, 0]), float(back[k, 1]) - float(pts[k, 1]))


@nb.njit(cache=True, nogil=True)
def _median(values: NDArray[np.float64]) -> float:
    """``np.median`` of a 1-D array (n >= 1): the middle value, or the mean of the two middle ones."""
    s = np.sort(values)
    n = s.shape[0]
    return float(s[n // 2]) if n % 2 else float((s[n // 2 - 1] + s[n // 2]) / 2)


@nb.njit(cache=True, nogil=True)
def carry_keypoints(
    a_buf: NDArray[np.uint8],
    a_meta: NDArray[np.int64],
    b_buf: NDArray[np.uint8],
    b_meta: NDArray[np.int64],
    pad: int,
    win: int,
    max_level: int,
    max_count: int,
    epsilon: float,
    min_eig: float,
    factor: int,
    max_fb: float,
    coast: bool,
    keypoints: NDArray[np.float64],
    alive: NDArray[np.bool_],
    coasting: NDArray[np.bool_],
) -> int:
    """People's keypoints carried from image a to image b (the keypoint tracker's step, in place; returns the
    keypoints lost). ``keypoints`` (P, K, 2) camera pixels, ``alive`` and ``coasting`` (P, K); the images are the
    camera's downsampled by ``factor`` (block means: pixel j is the mean of camera pixels j*f .. j*f + f - 1).

    Each alive keypoint is tracked forward and back (:func:`forward_backward`); it stays alive where both found it,
    the round trip missed its start by at most ``max_fb`` camera pixels and it landed inside the image, and is lost
    otherwise. With ``coast``, every keypoint lost now or before (``coasting``) moves by the median motion of its
    person's keypoints tracked this step (none: it stays). The arithmetic of the numpy steps it replaces, in one
    call: they were a quarter of the tracker's CPU."""
    n_people, n_kp = alive.shape
    n = 0
    for p in range(n_people):
        for k in range(n_kp):
            n += 1 if alive[p, k] else 0
    if n == 0:
        return 0
    centre = (factor - 1) / 2.0
    idx = np.empty(n, np.int64)
    pts = np.empty((n, 2), np.float32)
    j = 0
    for p in range(n_people):
        for k in range(n_kp):
            if alive[p, k]:
                idx[j] = p * n_kp + k
                pts[j, 0] = np.float32((keypoints[p, k, 0] - centre) / factor)
                pts[j, 1] = np.float32((keypoints[p, k, 1] - centre) / factor)
                j += 1
    found = np.empty((n, 2), np.float32)
    fb = np.empty(n, np.float64)
    status = np.empty(n, np.uint8)
    forward_backward(a_buf, a_meta, b_buf, b_meta, pad, pts, win, max_level, max_count, epsilon, min_eig, found,
                     fb, status)  # fmt: skip
    rows, cols = b_meta[0, 1], b_meta[0, 2]
    was_alive = alive.copy()
    moved = np.empty((n, 2), np.float64)
    kept = np.zeros(n, np.bool_)
    lost = 0
    for j in range(n):
        p, k = idx[j] // n_kp, idx[j] % n_kp
        x, y = float(found[j, 0]), float(found[j, 1])
        # (NaN compares False: a non-finite position is not inside.)
        inside = x >= 0 and y >= 0 and x <= cols - 1 and y <= rows - 1
        if status[j] == 1 and fb[j] * factor <= max_fb and inside:
            nx, ny = x * factor + centre, y * factor + centre
            moved[j, 0], moved[j, 1] = nx - keypoints[p, k, 0], ny - keypoints[p, k, 1]
            keypoints[p, k, 0], keypoints[p, k, 1] = nx, ny
            kept[j] = True
        else:
            alive[p, k] = False
            lost += 1
    if not coast:
        return lost
    for p in range(n_people):
        any_coasting = False
        for k in range(n_kp):
            coasting[p, k] = coasting[p, k] or (was_alive[p, k] and not alive[p, k])
            any_coasting = any_coasting or coasting[p, k]
        if not any_coasting:
            continue
        own = 0
        for j in range(n):
            own += 1 if kept[j] and idx[j] // n_kp == p else 0
        if own == 0:
            continue
        mx = np.empty(own, np.float64)
        my = np.empty(own, np.float64)
        i = 0
        for j in range(n):
            if kept[j] and idx[j] // n_kp == p:
                mx[i], my[i] = moved[j, 0], moved[j, 1]
                i += 1
        dx, dy = _median(mx), _median(my)
        for k in range(n_kp):
            if coasting[p, k]:
                keypoints[p, k, 0] += dx
                keypoints[p, k, 1] += dy
    return lost

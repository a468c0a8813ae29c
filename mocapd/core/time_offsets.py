"""Each camera's time offset from the geometry of the people in view (issue 43): the frame shift that makes it agree
with the other cameras' triangulation.

A camera whose frames run late shows, in its frame ``f + L``, the scene the others show in frame ``f``. The people
the *other* cameras triangulate at frame ``f`` then reproject onto where this camera saw them ``L`` frames later;
at any other shift they miss by about the people's motion over the difference. So per camera:

1. **The others' people.** At each frame, every pair of the other cameras pairs its people (two-view DLT of each
   pairing's body joints, Hungarian on the median reprojection error, a pairing kept within ``pair_threshold`` of
   the image width): each kept pairing is a 3D person. Pairs, not one triangulation of all the others: a camera
   that is itself late spoils only the pairs it is in, and the median below outvotes them.
2. **The residual at a shift** ``s = k + a`` (``k`` whole frames, ``0 <= a < 1``): each 3D person projected into
   the camera, against the camera's nearest person at frame ``f + s``, its keypoints interpolated linearly between
   its frames ``f + k`` and ``f + k + 1`` (a person followed to the next frame as the nearest one there): the
   median over the joints, then over the frame's people. The camera's residual curve is the median over frames of
   those, on a grid of ``step_frames`` over ``±max_shift_frames``, on the frames every shift can be scored on.
3. **The estimate** is the curve's minimum. Its **quality** is the margin over the best shift at least one frame
   away, ``1 - r(best) / r(next)``; its **spread** the standard deviation of the minimum over frames resampled with
   replacement (a bootstrap).

A camera is **refused**, with the reason, when too few frames can be scored, when its people barely move (median
joint motion under ``min_speed_px`` a frame: every shift fits alike), when the minimum lies on the edge of the scan,
or when the quality or the spread say the minimum is not clear.

Every camera is scored against the others, so a late camera leaks into the others' curves (it is in most of their
pairs). The estimate therefore runs in passes: after each pass the camera with the largest accepted whole-frame
shift has its frames moved by that shift for the other cameras' triangulations, and the pass is repeated, until no
accepted camera is a whole frame off. Each camera's offset is then its own curve's minimum against the others as
corrected: the majority of the rig is the reference.

Convention (``[daemon.offsets] cameras``): positive = the camera's frames show the scene late, i.e. its time stamps
run ahead by ``offset_frames / fps`` seconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.assignment import linear_sum_assignment
from mocapd.core.camera import Camera, normalized_from_pixels, triangulate_projections
from mocapd.core.camera_watch import row_medians
from mocapd.core.sorting import Detections2D
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

# COCO-17 shoulders to ankles: the face is placed by guess on a person seen from behind (mocapd.core.self_calibration).
BODY_JOINTS = np.arange(5, 17)
MIN_JOINTS = 4  # joints a pairing or a comparison needs


@dataclass(frozen=True)
class TimeOffsetOptions:
    """What :func:`estimate_time_offsets` scans and what it accepts."""

    max_shift_frames: int = 5
    """Shifts scanned each way, whole frames."""
    step_frames: float = 0.1
    """Grid of the scan, frames (sub-frame shifts interpolate the camera's own keypoints)."""
    min_confidence: float = 0.3
    """Keypoints below this confidence are left out."""
    pair_threshold: float = 0.04
    """Two views' people are one 3D person when their triangulation reprojects within this share of the image
    width (median over the joints; real detections of one person disagree by 1-2 %)."""
    min_frames: int = 10
    """Frames the curve must be scored on."""
    min_speed_px: float = 1.0
    """Median joint motion in the camera, px a frame, below which the people are too still to time it."""
    min_quality: float = 0.1
    """Least margin ``1 - r(best) / r(next)`` accepted."""
    max_spread_frames: float = 0.5
    """Largest bootstrap spread of the minimum accepted, frames."""
    bootstrap: int = 200
    """Resamplings of the frames for the spread."""
    max_passes: int = 4
    """Passes of the estimate (each moves the worst camera's frames for the others)."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.max_shift_frames < 1 or not 0.0 < self.step_frames <= 1.0 or 1.0 / self.step_frames % 1 > 1e-9:
            raise InputError(f"time offsets: max_shift_frames >= 1 and step_frames dividing 1 expected, got "
                             f"{self.max_shift_frames} and {self.step_frames}")  # fmt: skip


@dataclass(frozen=True)
class CameraTimeOffset:
    """One camera's estimate (``offset_frames`` None: refused, ``reason`` says why)."""

    name: str
    offset_frames: float | None
    offset_s: float | None
    quality: float
    """Margin of the minimum over the best shift a frame or more away, ``1 - r(best) / r(next)``, 0..1."""
    spread_frames: float
    """Bootstrap standard deviation of the minimum (frames resampled), frames."""
    residual_px: float
    """The curve at its minimum (median px)."""
    residual_at_zero_px: float
    """The curve at no shift."""
    speed_px: float
    """Median joint motion in the camera, px a frame."""
    frames: int
    """Frames the curve was scored on."""
    curve_px: dict[int, float] = field(default_factory=dict)
    """The curve at whole-frame shifts."""
    reason: str = ""


@dataclass
class _View:
    uv: FloatArray  # (n, J, 2) pixels, NaN where not confident
    xy: FloatArray  # (n, J, 2) undistorted normalised, NaN likewise
    next_uv: FloatArray  # (n, J, 2) the same person in the next frame, NaN where not followed
    next_xy: FloatArray  # (n, J, 2) likewise, undistorted normalised

    def at(self, a: float) -> _View:
        """The view ``a`` (0..1) of the way to the next frame (a person not followed stays where it is)."""
        if a == 0.0:
            return self
        uv = (1.0 - a) * self.uv + a * np.where(np.isnan(self.next_uv), self.uv, self.next_uv)
        xy = (1.0 - a) * self.xy + a * np.where(np.isnan(self.next_xy), self.xy, self.next_xy)
        return _View(uv, xy, self.next_uv, self.next_xy)


def _raw(det: Detections2D, min_conf: float) -> FloatArray:
    """A frame's people as body joints, ``(n, J, 2)`` pixels, NaN below ``min_conf`` (people with too few left out)."""
    kp = np.asarray(det.keypoints, np.float64)
    if kp.shape[0] == 0 or kp.shape[1] < 17:
        return np.zeros((0, len(BODY_JOINTS), 2))
    seen = np.asarray(det.confidences)[:, BODY_JOINTS] >= min_conf
    uv = np.where(seen[..., None], kp[:, BODY_JOINTS], np.nan)
    return np.asarray(uv[np.sum(seen, axis=1) >= MIN_JOINTS])


def _links(a: FloatArray, b: FloatArray, limit_px: float) -> IntArray:
    """Each person of ``a`` in the next frame ``b`` (one to one, nearest first), -1 where nobody is near."""
    out = np.full(len(a), -1, dtype=np.intp)
    if len(a) and len(b):
        d = _median_dist(a[:, None], b[None])
        cost = np.where(np.isfinite(d), d, 1e9)
        rows, cols = linear_sum_assignment(cost)
        keep = cost[rows, cols] < limit_px
        out[rows[keep]] = cols[keep]
    return out


def _views(
    frames: Sequence[Sequence[Detections2D]], cameras: list[Camera], opts: TimeOffsetOptions
) -> list[list[_View]]:
    """Per frame and camera, the people followed to the next frame."""
    n = len(frames)
    out: list[list[_View]] = [[] for _ in range(n)]
    for c, cam in enumerate(cameras):
        raw = [_raw(row[c], opts.min_confidence) for row in frames]
        nxt = [_links(raw[f], raw[f + 1], 0.1 * cam.width) for f in range(n - 1)] + [np.zeros(0, dtype=np.intp)]
        uvs = raw
        xys = [
            np.where(np.isnan(uv), np.nan, normalized_from_pixels(cam.K, cam.dist, np.nan_to_num(uv))) if len(uv)
            else uv.copy()
            for uv in uvs
        ]  # fmt: skip
        for f in range(n):
            next_uv, next_xy = np.full_like(uvs[f], np.nan), np.full_like(uvs[f], np.nan)
            if f < n - 1:
                linked = nxt[f] >= 0
                next_uv[linked], next_xy[linked] = uvs[f + 1][nxt[f][linked]], xys[f + 1][nxt[f][linked]]
            out[f].append(_View(uvs[f], xys[f], next_uv, next_xy))
    return out


def _nanmedian(d: FloatArray) -> FloatArray:
    """Median over the last axis of the finite values (NaN where none): :func:`~mocapd.core.camera_watch.row_medians`
    of every slice at once (``np.nanmedian`` takes a slow masked path on small slices, and this runs per frame and
    shift)."""
    rows = (int(np.prod(d.shape[:-1])), d.shape[-1])
    return row_medians(d.reshape(rows), np.isfinite(d).reshape(rows)).reshape(d.shape[:-1])


def _median_dist(a: FloatArray, b: FloatArray) -> FloatArray:
    """Median over the joints of the pixel distance, ``(..., J, 2)`` against ``(..., J, 2)``; NaN with fewer than
    :data:`MIN_JOINTS` joints in both."""
    d = np.linalg.norm(a - b, axis=-1)
    if d.size == 0:
        return np.zeros(d.shape[:-1])
    m = _nanmedian(d)
    return np.asarray(np.where(np.sum(np.isfinite(d), axis=-1) >= MIN_JOINTS, m, np.nan))


def _people_3d(a: _View, b: _View, ca: Camera, cb: Camera, limit_px: float) -> list[FloatArray]:
    """The people two views share, each ``(J, 3)`` (NaN joints where either view lacks them)."""
    na, nb = len(a.xy), len(b.xy)
    if na == 0 or nb == 0:
        return []
    J = len(BODY_JOINTS)
    xa = np.broadcast_to(a.xy[:, None], (na, nb, J, 2)).reshape(-1, 2)
    xb = np.broadcast_to(b.xy[None], (na, nb, J, 2)).reshape(-1, 2)
    P = np.stack([np.hstack((ca.R, ca.t[:, None])), np.hstack((cb.R, cb.t[:, None]))])
    uv = np.stack([xa, xb])
    w = np.all(np.isfinite(uv), axis=-1).astype(np.float64)
    X, ok = triangulate_projections(P, np.nan_to_num(uv), w, normal_equations=True)
    X = np.where(ok[:, None], X, np.nan).reshape(na, nb, J, 3)
    err = np.fmax(
        _median_dist(ca.project(X), np.broadcast_to(a.uv[:, None], (na, nb, J, 2))),
        _median_dist(cb.project(X), np.broadcast_to(b.uv[None], (na, nb, J, 2))),
    )
    cost = np.where(np.isfinite(err), err, 1e9)
    rows, cols = linear_sum_assignment(cost)
    return [X[i, j] for i, j in zip(rows, cols, strict=True) if cost[i, j] < limit_px]


def _frame_residuals(
    people: list[FloatArray], cam: Camera, views: list[_View], f: int, shifts: FloatArray
) -> FloatArray | None:
    """The signed residuals of one frame's 3D people in ``cam`` at each shift, against the nearest of its people
    there: ``(n_shifts, m, J, 2)`` (NaN where a person has no match), or None where the camera saw nobody."""
    proj = np.stack([cam.project(X) for X in people])  # (m, J, 2)
    out = np.full((len(shifts), *proj.shape), np.nan)
    whole = np.floor(shifts + 1e-9).astype(np.intp)
    for k in np.unique(whole):
        v = views[f + int(k)]
        if len(v.uv) == 0:
            return None
        sel = whole == k
        a = (shifts[sel] - k)[:, None, None, None]  # (s, 1, 1, 1)
        nxt = np.where(np.isnan(v.next_uv), v.uv, v.next_uv)  # not followed: the frame itself
        at = np.where(a == 0.0, v.uv[None], (1.0 - a) * v.uv[None] + a * nxt[None])  # (s, n, J, 2)
        d = _median_dist(proj[None, :, None], at[:, None])  # (s, m, n)
        j = np.argmin(np.where(np.isnan(d), np.inf, d), axis=2)  # nearest person, (s, m)
        matched = np.take_along_axis(at[:, None], j[:, :, None, None, None], axis=2)[:, :, 0]  # (s, m, J, 2)
        none = np.all(np.isnan(d), axis=2)
        out[sel] = np.where(none[..., None, None], np.nan, proj[None] - matched)
    return out


def _curve(
    views: list[list[_View]],
    cameras: list[Camera],
    c: int,
    moved: list[float],
    shifts: FloatArray,
    opts: TimeOffsetOptions,
    cache: dict[tuple[int, int, int, float, float], list[FloatArray]],
) -> FloatArray:
    """Per scored frame, camera ``c``'s residual at each shift against the others (each moved by ``moved`` frames,
    fractions interpolated): ``(n_frames, n_shifts)``.

    Each joint's median signed residual over the take is taken off first: a joint the detector places differently
    in this view than in the others (a hip seen from the front and from behind), or a calibration that is a little
    off, misses by about the same amount at every shift; what is left is what the timing moves."""
    n = len(views)
    lo, hi = opts.max_shift_frames, n - opts.max_shift_frames - 1
    others = [o for o in range(len(cameras)) if o != c]
    found: list[FloatArray] = []
    frame_of: list[int] = []
    for f in range(lo, hi):
        at: dict[int, _View] = {}
        for o in others:
            g = f + moved[o]
            k = int(np.floor(g + 1e-9))
            if 0 <= k < n - 1 or (k == n - 1 and g == k):
                at[o] = views[k][o].at(g - k)
        people: list[FloatArray] = []
        for i, a in enumerate(others):
            for b in others[i + 1 :]:
                if a in at and b in at:
                    key = (f, a, b, moved[a], moved[b])  # a pair's people serve every other camera and scan
                    if key not in cache:
                        limit = opts.pair_threshold * max(cameras[a].width, cameras[b].width)
                        cache[key] = _people_3d(at[a], at[b], cameras[a], cameras[b], limit)
                    people += cache[key]
        if people:
            got = _frame_residuals(people, cameras[c], [v[c] for v in views], f, shifts)
            if got is not None:
                found.append(got)
                frame_of += [len(found) - 1] * got.shape[1]
    if not found:
        return np.zeros((0, len(shifts)))
    e = np.concatenate(found, axis=1)  # (s, N, J, 2)
    bias = _nanmedian(np.moveaxis(e, 1, -1))  # (s, J, 2): per joint, over every person and frame
    per_person = _median_dist(e, bias[:, None])  # (s, N)
    owner = np.asarray(frame_of)
    rows = np.full((len(found), len(shifts)), np.nan)
    for i in range(len(found)):
        rows[i] = _nanmedian(per_person[:, owner == i])
    return rows[np.all(np.isfinite(rows), axis=1)]


def _speed(views: list[list[_View]], c: int) -> float:
    """Median joint motion of camera ``c``'s people between consecutive frames, px."""
    d = [np.linalg.norm(v[c].next_uv - v[c].uv, axis=-1).reshape(-1) for v in views]
    flat = np.concatenate(d) if d else np.zeros(0)
    flat = flat[np.isfinite(flat)]
    return float(np.median(flat)) if flat.size else 0.0


def _refused(name: str, speed: float, n: int, reason: str, curve: dict[int, float] | None = None) -> CameraTimeOffset:
    nan = float("nan")
    return CameraTimeOffset(name, None, None, 0.0, nan, nan, curve.get(0, nan) if curve else nan, speed, n,
                            curve or {}, reason)  # fmt: skip


def _estimate(
    name: str,
    views: list[list[_View]],
    cameras: list[Camera],
    c: int,
    moved: list[float],
    speed: float,
    fps: float,
    opts: TimeOffsetOptions,
    cache: dict[tuple[int, int, int, float, float], list[FloatArray]],
) -> CameraTimeOffset:
    """One camera's estimate: the whole-frame curve, then the sub-frame grid within a frame of its minimum."""
    if speed < opts.min_speed_px:
        why = f"the people barely move in this camera ({speed:.2f} px a frame, needs {opts.min_speed_px:g})"
        return _refused(name, speed, 0, f"{why}: every shift fits alike; walk through the volume")
    m = opts.max_shift_frames
    whole = np.arange(-m, m + 1, dtype=np.float64)
    rows = _curve(views, cameras, c, moved, whole, opts, cache)
    n = len(rows)
    if n < opts.min_frames:
        return _refused(name, speed, n, f"{n} frames with people seen here and by two other cameras; needs "
                                        f"{opts.min_frames}")  # fmt: skip
    curve = np.median(rows, axis=0)
    by_shift = {int(s): round(float(r), 2) for s, r in zip(whole, curve, strict=True)}
    k = int(whole[int(np.argmin(curve))])
    if abs(k) == m:
        return _refused(name, speed, n, f"the best shift is the edge of the ±{m}-frame scan", by_shift)
    fine = np.round(np.arange(k - 1, k + 1 + opts.step_frames / 2, opts.step_frames), 9)
    fine_rows = _curve(views, cameras, c, moved, fine, opts, cache)
    if len(fine_rows) < opts.min_frames:  # the fine scan reaches no further than the whole one: cannot happen
        return _refused(name, speed, len(fine_rows), "too few frames for the sub-frame scan", by_shift)
    fine_curve = np.median(fine_rows, axis=0)
    i = int(np.argmin(fine_curve))
    best, r_best = float(fine[i]), float(fine_curve[i])
    far = np.abs(whole - best) >= 1.0 - 1e-9
    r_next = float(np.min(curve[far]))
    quality = 1.0 - r_best / r_next if r_next > 0 else 0.0
    rng = np.random.default_rng(opts.seed)
    picks = rng.integers(0, len(fine_rows), size=(opts.bootstrap, len(fine_rows)))
    spread = float(np.std(fine[np.argmin(np.median(fine_rows[picks], axis=1), axis=1)]))
    reason = ""
    if quality < opts.min_quality:
        reason = f"no clear minimum (margin {quality:.2f} over the next-best shift, needs {opts.min_quality:g})"
    elif spread > opts.max_spread_frames:
        reason = f"the minimum moves by {spread:.2f} frames over resampled frames (needs <= {opts.max_spread_frames:g})"
    return CameraTimeOffset(
        name, None if reason else round(best, 3), None if reason else best / fps, round(quality, 3),
        round(spread, 3), round(r_best, 2), by_shift[0], round(speed, 2), n, by_shift, reason,
    )  # fmt: skip


def estimate_time_offsets(
    frames: Sequence[Sequence[Detections2D]],
    cameras: list[Camera],
    fps: float,
    options: TimeOffsetOptions | None = None,
) -> list[CameraTimeOffset]:
    """Each camera's time offset against the others' triangulation of the people (module docstring).

    Parameters
    ----------
    frames : [frame][camera] Detections2D
        Synchronised frames (by index) of calibrated cameras, COCO-17 keypoints (pixels, distorted).
    cameras : list of Camera
        Calibrated: intrinsics and extrinsics in one world.
    fps : float
        Frame rate, for the offsets in seconds.

    Returns
    -------
    list of CameraTimeOffset, one per camera in order.
    """
    opts = options or TimeOffsetOptions()
    if len(cameras) < 3:
        raise InputError(f"time offsets need 3 or more cameras (each against two others), got {len(cameras)}")
    if any(len(row) != len(cameras) for row in frames):
        raise InputError(f"time offsets: every frame needs {len(cameras)} cameras' detections")
    if not fps > 0:
        raise InputError(f"time offsets: fps must be positive, got {fps}")
    views = _views(frames, cameras, opts)
    speeds = [_speed(views, c) for c in range(len(cameras))]
    moved = [0.0] * len(cameras)
    cache: dict[tuple[int, int, int, float, float], list[FloatArray]] = {}
    result: list[CameraTimeOffset] = []
    for _ in range(opts.max_passes):
        result = [
            _estimate(cam.name, views, cameras, c, moved, speeds[c], fps, opts, cache) for c, cam in enumerate(cameras)
        ]
        # Each camera's estimate is against the others as moved; the one furthest from where it is moved to goes
        # there for the next pass (while it is a whole frame or more away).
        off = [0.0 if r.offset_frames is None else r.offset_frames - moved[c] for c, r in enumerate(result)]
        worst = int(np.argmax(np.abs(off)))
        if abs(off[worst]) < 1.0:
            break
        moved[worst] += off[worst]
    return result

"""Cameras that stay calibrated (issue 43, part 2): a camera bumped during a run, noticed from the people in view.

Each solved person's keypoints, as the solve sees them (undistorted, after the views' left/right flips were undone),
are a check of every camera's calibration: triangulated from the *other* cameras, they must reproject onto what
this camera detected. Per camera the watch keeps that leave-one-out residual (the median over a person's keypoints,
px) over time:

* its **baseline**: the median over the last ``baseline_s`` before the current window (frozen while the camera is
  in doubt, so a bump does not become the new normal);
* its **current** level: the median over the last ``window_s``.

A camera whose current level rises above its baseline by ``margin_px``, by ``ratio`` of the baseline and by
:data:`SPREAD_FACTOR` times the level's own spread over the baseline span (on real detections a camera that
disagrees with the others by a degree swings with where the people stand), while every camera has a level (one that
sees nobody leaves the others' checks with fewer witnesses than their baselines had), the other cameras' median
rise stays under ``others_ratio`` of its own, none rose more and the runner-up rose less than ``tie_ratio`` of it (a
bump moves one camera and leaks into the others' checks by less; a flood of bad detections, a person half out of
view or the sync drifting raise them all), is *suspect*; suspect for ``hold_s`` it is
*bumped*. One camera is bumped at a time (a second is named once the first is set right or back). A suspect or
bumped camera's confidences are scaled by ``down_weight`` in the solve (:meth:`CameraWatch.observe` returns them),
so the poses published while it is in doubt come from the cameras that agree. The window's median takes half a
window to rise, so a check's people alone also put a camera in doubt for the solve until the next check
(*flagged*: every person of the check that the camera sees puts it off alone, by the same rule on that person's
residuals against the baselines; one bad detection does not): the solve leaves a knocked camera out from the tick
after the first check that sees the knock, about 0.1 s, not half a second later. A flag is no state, names nobody.
Between the checks (the daemon solves 60 times a second, checks 10) each person's own views leave a knocked camera
out of that person's solve within ``1 / screen_hz`` of the knock (50 ms, three solves at 60 Hz): their *all-in*
residuals (the keypoints triangulated from every camera at once, :func:`residuals_all_in`: one triangulation)
screen for a camera off alone with half the flag's rise, ``screen_hz`` times a second per person (every solve when
the caller does not say who the person is); only then are its left-out residuals taken and judged by the flag's
rule, and the camera is left out when its keypoints are off the same way (:data:`COHERENCE`: a knock turns the
whole view; a bad detection is off every which way). A clean screen holds for the person's solves until their
next; one that puts a camera off is repeated on their next solve (the knocked camera stays out of every solve, a
false alarm lasts one).
A bumped camera whose level falls back to its baseline for ``hold_s`` (put back, or a passing disturbance) is *ok*
again.

Two opposite cameras that are each other's only witness of an axis (on a ring of four, cam1 and cam3 alone see
the depth of cam0 and cam2) cannot be told apart when one of them pans: the check sees the same rise in both. The
tie rule names neither while they rise alike; the noise can still tip it to the wrong one (docs/cameras.md).

While a camera is bumped the watch gathers its 2D-3D matches (the others' triangulations and its own detections)
and, from ``reestimate_points`` of them, re-estimates its orientation with the other cameras held
(:func:`reestimate_pose`): a *proposal*, judged by :func:`judge_proposal` (its matches' error must fall well below
what it was and back near the camera's baseline, no other camera's people may reproject farther with it than
without (:func:`rig_residuals` over the people the matches came from), the turn be one a knock gives). With
``apply`` one that passes is handed to the caller (:meth:`CameraWatch.pending`), which swaps the camera in
everything that holds it (the scheduler's :meth:`~mocapd.pipeline.scheduler.FixedLatencyScheduler.replace_camera`)
and tells the watch (:meth:`CameraWatch.apply`: the camera is judged against the new pose from a new baseline, back
in the solve). One that fails is shown with the reason and the matches are gathered again. A camera whose
re-estimates are refused :data:`RELEASE_AFTER` times in a row is put back in the solve (*released*: it may not be the
camera that moved) and not named again for ``baseline_s`` while the others are judged without it.

Time is the solve time passed in (ns); nothing here reads a clock or locks (the pipeline's adapter does).
"""

from __future__ import annotations

import functools
from collections.abc import Hashable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera, dehomogenized, triangulate_arrays, weighted_dlt_rows
from mocapd.core.norms import norms
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

STATES = ("learning", "ok", "suspect", "bumped")
"""A camera's state: no baseline yet, agreeing with the others, in doubt, bumped (held in doubt ``hold_s``)."""


@dataclass(frozen=True)
class WatchOptions:
    """How the bumped-camera watch judges (``[calibration.watch]`` in config.toml)."""

    rate_hz: float = 10.0
    """Ticks a second whose people are checked (the others are passed through untouched)."""
    screen_hz: float = 20.0
    """Solves a second of each person screened for a camera off alone between the checks (:meth:`CameraWatch.observe`
    given the person; the checked ticks count): a clean screen holds for that person's solves for ``1 /
    screen_hz``; one that puts a camera off is repeated on their next solve. A knock is then left out of the
    person's solve within ``1 / screen_hz`` instead of at once (the first check's flag leaves it out within ``1 /
    rate_hz`` either way); the states, names and re-estimates come from the checks alone and do not depend on it."""
    window_s: float = 1.0
    """The current level: the median residual over this window."""
    baseline_s: float = 20.0
    """The baseline: the median over this long before the window."""
    min_baseline_s: float = 5.0
    """A camera is judged once its baseline spans at least this long (before: state "learning")."""
    hold_s: float = 1.5
    """Suspect this long: bumped. Back at its baseline this long: ok again."""
    margin_px: float = 6.0
    """A rise smaller than this (px) is never a bump."""
    ratio: float = 0.3
    """Nor a rise smaller than this share of the camera's baseline."""
    others_ratio: float = 0.5
    """The other cameras' median rise must stay below this share of the camera's own."""
    tie_ratio: float = 0.8
    """The runner-up's rise at this share of the largest or more: which camera moved cannot be told."""
    min_confidence: float = 0.3
    """Keypoints below this confidence take no part."""
    min_keypoints: int = 6
    """A person checks a camera when at least this many of its keypoints are seen by it and two others."""
    down_weight: float = 0.0
    """Confidence factor in the solve of a camera in doubt (0: left out)."""
    reestimate_points: int = 400
    """2D-3D matches gathered from a bumped camera before its pose is re-estimated (0: never)."""
    apply: bool = False
    """A re-estimate that passes :func:`judge_proposal` is applied (handed out by :meth:`CameraWatch.pending`);
    False (the default): only proposed. Off by default: in one of five runs of the camera demo on real detections
    (cameras that never moved) a camera was named and its re-estimate, which fitted the matches better, left
    another camera's people reprojecting worse (18 px against 6)."""
    max_turn_deg: float = 10.0
    """A re-estimated turn larger than this is not applied: no knock turns a camera that far and leaves it seeing
    the same people (a camera that far off is recalibrated)."""

    def __post_init__(self) -> None:
        if not (self.rate_hz > 0 and self.screen_hz > 0 and self.window_s > 0 and self.hold_s > 0
                and self.baseline_s > self.window_s):  # fmt: skip
            raise InputError(
                "camera watch: rate_hz, screen_hz, window_s and hold_s must be positive, baseline_s > window_s"
            )
        if not (0.0 <= self.down_weight <= 1.0):
            raise InputError(f"camera watch: down_weight {self.down_weight} outside [0, 1]")
        if not self.max_turn_deg > 0:
            raise InputError(f"camera watch: max_turn_deg {self.max_turn_deg} must be positive")


@dataclass(frozen=True)
class Proposal:
    """A bumped camera's pose re-estimated from the people with the other cameras held."""

    camera: Camera
    rotation_deg: float  # the turn from the configured pose
    matches: int  # 2D-3D matches it was estimated from
    inliers: int
    median_px_before: float  # the matches' reprojection error with the configured pose
    median_px_after: float  # ... and with the proposed one
    refused: str | None = None  # why it may not be applied (judge_proposal); None: it passed
    rig: tuple[tuple[str, float | None, float | None], ...] = ()
    """The other cameras' median residual (px) over the people the matches came from, with the camera as it was
    and as proposed: (name, before, after) each (None: none of them seen by that camera and two others)."""


FLAG_FACTOR = 3.0
"""A check's people flag a camera (left out until the next check) on a rise this many times the one that makes it
suspect: one moment's residuals are noisier than a window's median (2: two or three flags a minute on the
synthetic detector-like noise of tests/test_camera_watch.py; 3: none, and a 2° knock still flagged at once)."""
SCREEN_FACTOR = 1.5
"""A person's all-in residuals pass the screen for the at-once flag on a rise this many times the suspect one (a
turned camera pulls the all-in points its way, so its all-in rise is a half to three quarters of its left-out one;
1.5 lets every moment of a 2° knock through to the exact check, and one moment in ten of clean walking)."""
RELEASE_AFTER = 3
"""A bumped camera whose re-estimates were refused this many times in a row is put back in the solve (*released*)
and the others re-examined without it for ``baseline_s``: the wrong camera may have been named (a roll of one camera
of a ring of four named its neighbour, whose re-estimates then improved nothing), and a camera held out for good is
a camera fewer for every person."""
SPREAD_FACTOR = 3.0
"""A rise must also be this many times the camera's level's own spread over the baseline span (:func:`_level_spread`):
on real detections a camera whose calibration disagrees with the others by a degree or two has a level that swings
with where the people stand (cam01 of the camera demo: 13 to 25 px around a 17 px baseline, named in one run of
five with margin_px and ratio alone); on the synthetic rig the spread is a fraction of margin_px, and a knock
is named as fast as before."""
COHERENCE = 0.6
"""... and only when its keypoints are off the same way: the median offset at least this share of the median
distance (a 1-2° tilt or pan: 0.9 and more; a bad detection that passes the rest: mostly under 0.5)."""
IMPROVEMENT = 0.5
"""An applied re-estimate's matches reproject at most this share of their error with the old pose."""
WORSEN = 0.05
WORSEN_PX = 0.2
"""... and no other camera's people reproject worse with it than with the old pose by more than :data:`WORSEN` of
their error and :data:`WORSEN_PX` px (the same people, both ways: only the camera differs). A knocked camera set right
brings every other camera's people closer; a camera that did not move, turned to fit its matches, pulls the others'
triangulations away from what they see."""
MIN_INLIER_SHARE = 0.5
"""... and at least this share of its matches agree with it (the others: the detector's outliers)."""


def judge_proposal(p: Proposal, baseline_px: float, options: WatchOptions) -> str | None:
    """Why proposal ``p`` may not be applied, or None when it may: its matches' median error must fall to at most
    :data:`IMPROVEMENT` of what it was, and to within ``margin_px`` of the camera's baseline from before the bump
    (``baseline_px``: where a camera that agrees with the others sits; a re-estimate of the wrong camera, or of a
    camera that moved rather than turned, stays above it), no other camera's people may reproject farther with it
    (``p.rig``, :data:`WORSEN`), at least :data:`MIN_INLIER_SHARE` of the matches must agree, and the turn must be
    at most ``max_turn_deg``."""
    if p.inliers < MIN_INLIER_SHARE * p.matches:
        return f"only {p.inliers} of {p.matches} matches agree with it"
    if p.rotation_deg > options.max_turn_deg:
        return f"a turn of {p.rotation_deg:.1f} deg is more than max_turn_deg {options.max_turn_deg:g}"
    if not p.median_px_after <= IMPROVEMENT * p.median_px_before:
        return f"its matches improve too little ({p.median_px_before} -> {p.median_px_after} px)"
    for name, before, after in p.rig:
        if before is not None and after is not None and after > before * (1.0 + WORSEN) + WORSEN_PX:
            return f"it leaves {name}'s people at {after} px against {before}"
    if np.isfinite(baseline_px) and not p.median_px_after <= baseline_px + options.margin_px:
        return (f"its matches stay {p.median_px_after} px off, more than the camera's {baseline_px:.1f} px before "
                f"the bump + margin_px")  # fmt: skip
    return None


class _Series:
    """(solve time ns, residual px) samples in time order (the checked ticks': their times never go back), in two
    arrays: a check reads its windows as slices (one binary search each) instead of lists built from tuples."""

    __slots__ = ("_end", "_r", "_start", "_t")

    def __init__(self) -> None:
        self._t = np.empty(64, dtype=np.int64)
        self._r = np.empty(64)
        self._start = self._end = 0  # the live samples: [_start, _end)

    def __len__(self) -> int:
        return self._end - self._start

    def append(self, t_ns: int, value: float) -> None:
        """One sample at ``t_ns``, not before the newest one."""
        if self._end == len(self._t):
            n = len(self)
            size = len(self._t) * (2 if 2 * n > len(self._t) else 1)  # grown only while more than half is live
            t, r = np.empty(size, dtype=np.int64), np.empty(size)
            t[:n], r[:n] = self._t[self._start : self._end], self._r[self._start : self._end]
            self._t, self._r, self._start, self._end = t, r, 0, n
        self._t[self._end] = t_ns
        self._r[self._end] = value
        self._end += 1

    def drop_before(self, t_ns: int) -> None:
        """Forget the samples older than ``t_ns``."""
        self._start += int(np.searchsorted(self.times(), t_ns, side="left"))

    def times(self) -> NDArray[np.int64]:
        """Sample times, oldest first (a view), shape (n,)."""
        return self._t[self._start : self._end]

    def values(self) -> FloatArray:
        """Residuals (px), oldest first (a view), shape (n,)."""
        return self._r[self._start : self._end]


@dataclass
class _Camera:
    """One camera's record: (solve time ns, residual px) samples, its state and what the state came from."""

    samples: _Series = field(default_factory=_Series)
    quick: _Series = field(default_factory=_Series)  # (solve time ns, all-in residual px), checked
    quick_baseline: float = float("nan")  # the all-in residual's median over the baseline span
    state: str = "learning"
    since_ns: int = 0  # when the state was entered
    doubt_ns: int | None = None  # when it was last put in doubt after agreeing: flagged, then suspect
    frozen_baseline: float | None = None  # the baseline held while in doubt
    calm_since_ns: int | None = None  # bumped and back at its baseline since then
    baseline: float = float("nan")
    spread: float = float("nan")  # how much its level varies by itself over the baseline span (_level_spread)
    current: float = float("nan")
    bumps: int = 0
    matches: list[tuple[FloatArray, FloatArray]] = field(default_factory=list)  # (X (n, 3), uv (n, 2)) while bumped
    # ... and the people they came from, (uv, conf) each: every camera's residuals judge the re-estimate
    people: list[tuple[FloatArray, FloatArray]] = field(default_factory=list)
    n_matches: int = 0
    proposal: Proposal | None = None  # the latest re-estimate (one that was refused: the matches gathered again)
    applied: int = 0  # re-estimates applied to this camera so far
    refusals: int = 0  # re-estimates refused in a row since it was named
    released: int = 0  # times it was put back after RELEASE_AFTER refusals
    barred_until_ns: int | None = None  # released: not named again before then (the others re-examined)


def residuals_left_out(
    P: FloatArray, uv: FloatArray, conf: FloatArray, *, min_confidence: float, min_keypoints: int
) -> tuple[FloatArray, list[tuple[FloatArray, FloatArray]]]:
    """Per camera: the median distance (px) between one person's keypoints it detected and the same keypoints
    triangulated from the other cameras, projected into it.

    Parameters
    ----------
    P : array, shape (n_cams, 3, 4)
        Projection matrices (undistorted pixels).
    uv : array, shape (n_cams, n_kp, 2)
        The person's undistorted keypoints per camera.
    conf : array, shape (n_cams, n_kp)
        Their confidences (0: not seen).

    Returns
    -------
    residual : array, shape (n_cams,)
        NaN where fewer than ``min_keypoints`` keypoints were seen by the camera and two others.
    matches : list of (X (m, 3), uv (m, 2)) per camera
        The triangulated points and the camera's own keypoints the residual was measured on.
    """
    n_cams = P.shape[0]
    w = np.where((conf >= min_confidence) & np.all(np.isfinite(uv), axis=-1), conf, 0.0)
    out = np.full(n_cams, np.nan)
    matches: list[tuple[FloatArray, FloatArray]] = []
    # Only the keypoints each camera measured: the others' points are not used (fewer SVDs where a view misses
    # keypoints, the same points where it does not)
    X_left, ok_left = triangulate_left_out(P, uv, w, w > 0) if n_cams >= 3 else (None, None)
    # Each camera's errors in a row of its own (the keypoints it measured marked), their medians from one sort
    # (row_medians: np.median's to the bit); the homogeneous points built by concatenation, not np.c_ (the same
    # array, without its index machinery): the check runs 10 times a second per person on the event loop.
    errs = np.zeros((n_cams, uv.shape[1]))
    measured = np.zeros((n_cams, uv.shape[1]), dtype=bool)
    for c in range(n_cams):
        seen = w[c] > 0
        if X_left is None or ok_left is None or np.count_nonzero(seen) < min_keypoints:
            matches.append((np.zeros((0, 3)), np.zeros((0, 2))))
            continue
        X, ok = X_left[c], ok_left[c] & seen
        m = int(np.count_nonzero(ok))
        if m < min_keypoints:
            matches.append((np.zeros((0, 3)), np.zeros((0, 2))))
            continue
        Xh = np.empty((m, 4))  # [X, 1] row by row: the array np.concatenate made, without its temporaries
        Xh[:, :3] = X[ok]
        Xh[:, 3] = 1.0
        h = Xh @ P[c].T
        front = h[:, 2] > 1e-9
        d = h[:, :2] / np.where(front, h[:, 2], 1.0)[:, None] - uv[c, ok]
        errs[c, :m] = np.where(front, norms(d, axis=1), np.inf)
        measured[c, :m] = True
        matches.append((X[ok][front], uv[c, ok][front]))
    rows = measured.any(axis=1)
    if rows.any():
        out[rows] = row_medians(errs[rows], measured[rows])
    return out, matches


def triangulate_left_out(
    P: FloatArray, uv: FloatArray, weights: FloatArray, need: NDArray[np.bool_] | None = None
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Per camera, the points triangulated from the *other* cameras: what
    :func:`~mocapd.core.camera.triangulate_projections` gives for ``P[others], uv[others], weights[others]``
    (two views or more), to the bit, for every camera in one SVD call instead of one call each.

    Its rows are the DLT rows of :func:`~mocapd.core.camera.triangulate_projections`
    (:func:`~mocapd.core.camera.weighted_dlt_rows`: each a camera's, unit-normed, times its weight: the same floats
    whichever cameras are in), and each camera's systems leave out its two rows;
    the SVD of a stack solves each system on its own, so the points are the same.

    Parameters
    ----------
    P : array, shape (n_cams, 3, 4)
    uv : array, shape (n_cams, n_pts, 2)
    weights : array, shape (n_cams, n_pts)
    need : bool array, shape (n_cams, n_pts), optional
        Only these points are triangulated (the others NaN, not ok): each system is solved on its own, so the
        points solved are the same floats as without it.

    Returns
    -------
    X : array, shape (n_cams, n_pts, 3)
        ``X[c]``: the points from every camera but ``c``; NaN where not triangulated.
    ok : bool array, shape (n_cams, n_pts)
    """
    P = np.asarray(P, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    n_cams, n_pts = uv.shape[:2]
    A, w = weighted_dlt_rows(P, uv, weights)  # (n_pts, 2 * n_cams, 4): every camera's rows
    A_left = A[:, _left_out_rows(n_cams)].transpose(1, 0, 2, 3)  # (n_cams, n_pts, 2 n - 2, 4)
    views = np.sum(w > 0, axis=0)
    ok = (views[None, :] - (w > 0)) >= 2  # seen by two of the others
    if need is not None:
        ok &= need
    X = np.full((n_cams, n_pts, 3), np.nan)
    if np.any(ok):
        X[ok] = dehomogenized(np.linalg.svd(A_left[ok])[2][:, -1, :])
        ok = ok & np.all(np.isfinite(X), axis=-1)
    return X, ok


@functools.lru_cache(maxsize=16)
def _left_out_rows(n_cams: int) -> NDArray[np.intp]:
    """Per camera, the DLT rows of the others (their u rows, then their v rows, as
    :func:`~mocapd.core.camera.triangulate_projections` stacks them), shape (n_cams, 2 n_cams - 2); read-only."""
    cams = np.arange(n_cams)
    rows = np.array([np.r_[np.delete(cams, c), n_cams + np.delete(cams, c)] for c in cams], dtype=np.intp)
    rows.flags.writeable = False
    return rows


def residuals_all_in(
    P: FloatArray, uv: FloatArray, conf: FloatArray, *, min_confidence: float, min_keypoints: int
) -> FloatArray:
    """Per camera: the median distance (px) between one person's keypoints it detected and the same keypoints
    triangulated from *all* cameras (itself included), projected into it: one triangulation for the rig instead of
    one per camera (:func:`residuals_left_out`), cheap enough for every tick. Only keypoints seen by three cameras
    or more count (with two, both views share any error alike). A turned camera pulls the points towards itself by
    its share of the views, so its rise is smaller than the left-out one, and leaks into the others by that share.

    Parameters
    ----------
    P : array, shape (n_cams, 3, 4)
    uv : array, shape (n_cams, n_kp, 2)
    conf : array, shape (n_cams, n_kp)

    Returns
    -------
    residual : array, shape (n_cams,)
        NaN where the camera sees fewer than ``min_keypoints`` of those keypoints.
    """
    P = np.asarray(P, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    w = np.where((conf >= min_confidence) & np.isfinite(uv).all(axis=-1), conf, 0.0)
    out = np.full(P.shape[0], np.nan)
    # triangulate_projections' work without its checks (the watch's own arrays, of its shapes): every screen
    X, ok = triangulate_arrays(P, uv, w, 3, normal_equations=True)
    if np.count_nonzero(ok) < min_keypoints:
        return out
    h = P[:, None, :, :3] @ X[ok][None, :, :, None] + P[:, None, :, 3:]  # (n_cams, n_ok, 3, 1)
    front = h[..., 2, 0] > 1e-9
    d = h[..., :2, 0] / np.where(front, h[..., 2, 0], 1.0)[..., None] - uv[:, ok]
    err = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)
    use = front & (w[:, ok] > 0)
    counted = use.sum(axis=1) >= min_keypoints
    out[counted] = row_medians(err[counted], use[counted])
    return out


def _column_nanmedians(values: FloatArray) -> FloatArray:
    """``np.nanmedian(values, axis=0)`` for a few rows (people) by columns (cameras), each column with a value that is
    not NaN, to the bit (:func:`row_medians` of the values that are not NaN): numpy takes small arrays through
    masked arrays, ~40 times slower here."""
    return row_medians(values.T, ~np.isnan(values.T))


def row_medians(values: FloatArray, use: NDArray[np.bool_]) -> FloatArray:
    """Per row of ``values`` (n, m), the median of the entries ``use`` (n, m) marks (NaN for none), as
    ``np.median`` gives it to the bit: the middle one, or ``(a + b) / 2`` of the two middle ones (``np.median`` takes
    ``np.mean`` of them), from one sort of all rows instead of one ``np.median`` call each. A row holding NaN
    goes to ``np.median`` itself (it sorts NaN last, where the padding is)."""
    n = use.sum(axis=1)
    if values.shape[1] == 0:
        return np.full(len(n), np.nan)
    srt = np.sort(np.where(use, values, np.inf), axis=1)  # the used entries first, in order
    rows = np.arange(len(n))
    hi = srt[rows, np.minimum(n // 2, values.shape[1] - 1)]
    lo = srt[rows, np.maximum(n // 2 - 1, 0)]
    out: FloatArray = np.where(n % 2 == 1, hi, (lo + hi) / 2.0)
    out[n == 0] = np.nan  # np.median of nothing
    for i in np.flatnonzero(np.isnan(srt[:, -1])):  # a used NaN sorts last, past the infinite padding
        out[i] = float(np.median(values[i, use[i]]))
    return out


def reestimate_pose(
    camera: Camera, X: FloatArray, uv: FloatArray, threshold_px: float = 20.0, iterations: int = 5
) -> Proposal | None:
    """``camera``'s orientation from 2D-3D matches (its undistorted keypoints ``uv`` (n, 2), the points ``X``
    (n, 3) the other cameras triangulated), its centre and intrinsics kept: a bump turns a camera on its mount.

    The turn that best maps the rays from the camera's centre to the points onto the rays through its keypoints is
    Wahba's problem (closed form, an SVD); it is solved again on the matches within ``threshold_px`` of the
    previous answer (twice the median error while that is larger: the detector's outliers and swapped limbs left
    out), ``iterations`` times. A free centre
    (PnP) would trade a turn of the camera for a sideways move of it over a few metres' depth. None when fewer than
    12 matches agree."""
    if len(X) < 12:
        return None
    d = X - camera.center
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    b = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(np.asarray(camera.K)).T
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    R = np.asarray(camera.R)
    keep = np.ones(len(X), dtype=bool)
    for _ in range(iterations):
        err = _errors(replace(camera, R=R, t=-R @ camera.center), X, uv)
        # Twice the median error at first (the bump itself may be larger than the threshold), then the threshold.
        keep = err < max(threshold_px, 2.0 * float(np.median(err)))
        if keep.sum() < 12:
            return None
        U, _, Vt = np.linalg.svd(b[keep].T @ d[keep])  # argmax_R sum b^T R d
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    new = replace(camera, R=R, t=-R @ camera.center)
    before, after = _errors(camera, X, uv), _errors(new, X, uv)
    turn = float(np.degrees(np.arccos(np.clip((np.trace(new.R @ camera.R.T) - 1.0) / 2.0, -1.0, 1.0))))
    return Proposal(new, round(turn, 3), len(X), int(keep.sum()), round(float(np.median(before)), 2),
                    round(float(np.median(after)), 2))  # fmt: skip


def rig_residuals(
    P: FloatArray, people: list[tuple[FloatArray, FloatArray]], *, min_confidence: float, min_keypoints: int
) -> FloatArray:
    """Per camera: the median over ``people`` ((uv (n_cams, n_kp, 2), conf (n_cams, n_kp)) each) of their
    :func:`residuals_left_out` with the projections ``P`` (n_cams, 3, 4); NaN where none was measured."""
    res = np.full((max(len(people), 1), P.shape[0]), np.nan)
    for j, (uv, conf) in enumerate(people):
        res[j], _ = residuals_left_out(P, uv, conf, min_confidence=min_confidence, min_keypoints=min_keypoints)
    seen = np.isfinite(res).any(axis=0)
    out = np.full(P.shape[0], np.nan)
    out[seen] = _column_nanmedians(res[:, seen])
    return out


def _level_spread(t: NDArray[np.int64], r: FloatArray, split_ns: int, window_s: float) -> float:
    """How much a camera's level (the median residual over ``window_s``) varies by itself over the baseline span
    (the samples at times ``t`` (n,), residuals ``r`` (n,), all before ``split_ns``): the standard deviation of the
    medians of its ``window_s`` stretches (those with 3 samples or more), px; NaN with fewer than 3 stretches. Not a
    robust scale: a level that spent two of its five first seconds 8 px below the others (the camera demo's cam01,
    the people where its error is small) has a median absolute deviation of 2 px and is named when they walk back.

    Every stretch's median from one sort, in the order ``np.unique`` gives the stretches (nearest to ``split_ns``
    first): the middle value, or the two middle values' ``(a + b) / 2``, which is what ``np.median`` computes
    (``np.mean`` of them), so the result is ``np.median`` per stretch to the bit."""
    if not len(t):
        return float("nan")
    stretch = (split_ns - t) // round(window_s * 1e9)
    order = np.lexsort((r, stretch))  # by stretch, then by value within it
    stretch, r = stretch[order], r[order]
    starts = np.flatnonzero(np.concatenate(([True], stretch[1:] != stretch[:-1])))  # np.r_'s arrays, not its parser
    counts = np.diff(np.concatenate((starts, [len(stretch)])))
    starts, counts = starts[counts >= 3], counts[counts >= 3]
    if len(starts) < 3:
        return float("nan")
    mid = starts + counts // 2
    levels = np.where(counts % 2 == 1, r[mid], (r[mid - 1] + r[mid]) / 2.0)
    return float(np.std(levels, ddof=1))


def _offsets(camera: Camera, X: FloatArray, uv: FloatArray) -> FloatArray:
    """Undistorted-pixel offsets (n, 2) of points ``X`` (n, 3) projected by ``camera`` from ``uv`` (n, 2)."""
    h = np.c_[X, np.ones(len(X))] @ camera.projection_matrix.T
    d: FloatArray = h[:, :2] / h[:, 2:3] - uv
    return d


def _errors(camera: Camera, X: FloatArray, uv: FloatArray) -> FloatArray:
    """Undistorted-pixel reprojection errors (n,) of points ``X`` against ``uv``."""
    h = np.c_[X, np.ones(len(X))] @ camera.projection_matrix.T
    z = np.where(h[:, 2] > 1e-9, h[:, 2], np.nan)
    err: FloatArray = np.linalg.norm(h[:, :2] / z[:, None] - uv, axis=1)
    return np.where(np.isfinite(err), err, np.inf)


class CameraWatch:
    """The per-camera residual record and the bump decisions (module docstring).

    Parameters
    ----------
    cameras : list of Camera
        The rig as configured (its projections: undistorted pixels).
    options : WatchOptions
    """

    def __init__(self, cameras: list[Camera], options: WatchOptions | None = None) -> None:
        self.options = options if options is not None else WatchOptions()
        self.cameras = list(cameras)
        self._P = np.stack([c.projection_matrix for c in cameras]) if cameras else np.zeros((0, 3, 4))
        self._cams = [_Camera() for _ in cameras]
        self._tick_ns: int | None = None  # the solve time being checked now (all its people are)
        self._flagged = np.zeros(len(cameras), dtype=bool)  # the last check's people put it off alone
        self._votes: list[FloatArray] | None = None  # this check's people's residuals (n_cams,) each
        self._flag_since: list[int | None] = [None] * len(cameras)  # the check that began each flagged run
        self._last_ns: int | None = None  # the last tick checked
        # Per person (observe's key): the solve time of their last screen and its verdict (the camera their own
        # views put off alone, or None: clean, not screened again for 1 / screen_hz).
        self._screens: dict[Hashable, tuple[int, int | None]] = {}
        self._screen_ns = round(1e9 / self.options.screen_hz * 0.999)  # as the checks' period: rounding's slack
        self.screened = 0  #: all-in screens so far (the per-solve cost between the checks)
        #: what happened, newest last: (solve time ns, camera name, event, details) for the log and the session
        self.events: list[tuple[int, str, str, dict[str, Any]]] = []

    # ------------------------------------------------------------------------------------------ input
    def observe(self, t_ns: int, uv: FloatArray, conf: FloatArray, person: Hashable | None = None) -> FloatArray:
        """One solved person at solve time ``t_ns``: ``uv`` (n_cams, n_kp, 2) undistorted keypoints and ``conf``
        (n_cams, n_kp). Checks the cameras on ``rate_hz`` of the ticks; returns the confidences the solve should
        use (a camera in doubt scaled by ``down_weight``). ``person``: who this is (any key that stays the same from
        solve to solve), so that their solves between the checks are screened at most ``screen_hz`` times a second;
        None: every solve is screened."""
        n = len(self.cameras)
        if uv.shape[:1] != (n,) or conf.shape != uv.shape[:2]:
            raise InputError(f"camera watch: keypoints {uv.shape} / confidences {conf.shape} for {n} cameras")
        o = self.options
        due = self._due(t_ns)
        # The all-in residuals: recorded on the checked ticks (their baselines), screened between them while every
        # camera agrees (otherwise the state machine has it and nothing is flagged at once: not computed), at most
        # screen_hz times a second per person: a knock is a slow event next to the 60 Hz solves.
        all_ok = all(c.state == "ok" for c in self._cams)
        # A person whose last screen put a camera off is screened again on every solve until one clears it: a knock
        # stays out of each of their solves, a false alarm (one moment of noise) lasts one solve, as unbounded.
        held = self._screens.get(person) if person is not None and all_ok and not due else None
        screen = due or (all_ok and (held is None or held[1] is not None or t_ns - held[0] >= self._screen_ns))
        quick = (residuals_all_in(self._P, uv, conf, min_confidence=o.min_confidence, min_keypoints=o.min_keypoints)
                 if screen else None)  # fmt: skip
        if quick is not None:
            self.screened += 1
        if due:
            assert quick is not None
            self._check(t_ns, uv, conf, quick)
        elif self._votes is not None:
            self._settle_flags()  # the checked tick is complete: its people's verdicts hold until the next check
        doubt = self.in_doubt() | self._flagged
        if quick is not None and all_ok:
            at_once = self._at_once(uv, conf, quick)
            if person is not None:
                self._screens[person] = (t_ns, at_once)
        else:
            at_once = None  # screened clean within 1 / screen_hz (or a camera in doubt: the state machine has it)
        if at_once is not None:
            doubt[at_once] = True  # this person's own views put it off alone: out of this solve
        if not doubt.any():
            return conf
        return conf * np.where(doubt, self.options.down_weight, 1.0)[:, None]

    def in_doubt(self) -> NDArray[np.bool_]:
        """Per camera: suspect or bumped."""
        return np.array([c.state in ("suspect", "bumped") for c in self._cams], dtype=bool)

    def _due(self, t_ns: int) -> bool:
        if t_ns == self._tick_ns:
            return True  # another person of the tick being checked
        if self._last_ns is not None and t_ns - self._last_ns < 1e9 / self.options.rate_hz * 0.999:
            return False
        if self._tick_ns is not None:
            self._judge(self._tick_ns)  # the previous checked tick is complete: judge on all its people
            if self._votes is not None:
                self._settle_flags()
        self._tick_ns = self._last_ns = t_ns
        self._votes = []
        # People not screened for a second are gone (or their verdict stale): forgotten, so the record stays small.
        if self._screens:
            self._screens = {k: v for k, v in self._screens.items() if t_ns - v[0] < 1_000_000_000}
        return True

    def _at_once(self, uv: FloatArray, conf: FloatArray, quick: FloatArray) -> int | None:
        """The camera this person's own views put off alone, now: screened on the all-in residuals ``quick``
        (n_cams,) with half the flag's rise (:data:`SCREEN_FACTOR`: one triangulation, every moment), confirmed on
        the person's left-out residuals by the flag's own rule (:data:`FLAG_FACTOR`; a triangulation per camera,
        only on the moments the screen passes). None while a camera is in doubt, or any camera has no baseline."""
        if self._off_alone(quick, np.array([c.quick_baseline for c in self._cams]), SCREEN_FACTOR) is None:
            return None
        o = self.options
        res, matches = residuals_left_out(self._P, uv, conf, min_confidence=o.min_confidence,
                                          min_keypoints=o.min_keypoints)  # fmt: skip
        off = self._off_alone(res, np.array([c.baseline for c in self._cams]))
        if off is None:
            return None
        # A knock turns the whole view: its keypoints are off the same way. A bad detection (limbs swapped, a
        # few outliers) is off every which way: the median offset is a small part of the median distance.
        X, seen = matches[off]
        shift = float(np.linalg.norm(np.median(_offsets(self.cameras[off], X, seen), axis=0)))
        return off if shift >= COHERENCE * res[off] else None

    def _check(self, t_ns: int, uv: FloatArray, conf: FloatArray, quick: FloatArray) -> None:
        o = self.options
        res, matches = residuals_left_out(self._P, uv, conf, min_confidence=o.min_confidence,
                                          min_keypoints=o.min_keypoints)  # fmt: skip
        if self._votes is not None:
            self._votes.append(res)
        keep_ns = round((o.baseline_s + o.window_s) * 1e9)
        for c, cam in enumerate(self._cams):
            if np.isfinite(res[c]):
                cam.samples.append(t_ns, float(res[c]))
            if np.isfinite(quick[c]):
                cam.quick.append(t_ns, float(quick[c]))
            cam.samples.drop_before(t_ns - keep_ns)
            cam.quick.drop_before(t_ns - keep_ns)
            gathering = cam.proposal is None or cam.proposal.refused is not None
            if cam.state == "bumped" and o.reestimate_points > 0 and gathering and len(matches[c][0]):
                cam.matches.append(matches[c])
                cam.people.append((uv.copy(), conf.copy()))
                cam.n_matches += len(matches[c][0])
                if cam.n_matches >= o.reestimate_points:
                    self._reestimate(t_ns, c)

    # ------------------------------------------------------------------------------------------ decisions
    def _settle_flags(self) -> None:
        """The camera the complete checked tick's people put off alone (their median residual per camera), if any."""
        votes, self._votes = self._votes or [], None
        self._flagged[:] = False
        if votes:
            res = np.stack(votes)
            seen = np.isfinite(res).any(axis=0)
            pooled = np.full(len(self._cams), np.nan)
            pooled[seen] = _column_nanmedians(res[:, seen])
            off = self._off_alone(pooled, np.array([c.baseline for c in self._cams]))
            if off is not None:
                self._flagged[off] = True
        for c, flagged in enumerate(self._flagged):
            if not flagged:
                self._flag_since[c] = None
            elif self._flag_since[c] is None:
                self._flag_since[c] = self._tick_ns

    def _off_alone(self, res: FloatArray, base: FloatArray, factor: float = FLAG_FACTOR) -> int | None:
        """The camera one check's residuals ``res`` (n_cams,) put off alone, by the rule that makes a camera
        suspect with a rise ``factor`` times larger (against the baselines ``base`` (n_cams,); none while a camera
        is in doubt or without baselines), or None."""
        o = self.options
        if any(c.state != "ok" for c in self._cams):
            return None  # learning (no baseline), or a camera already in doubt: the state machine has it
        rise = np.where(self._barred(self._last_ns), np.nan, res - base)
        finite = np.isfinite(rise)
        if finite.sum() < 3:
            return None
        i = int(np.argmax(np.where(finite, rise, -np.inf)))
        ranked = np.sort(rise[finite])
        others = np.delete(rise, i)
        others = others[np.isfinite(others)]
        if not (rise[i] > factor * self._threshold(i, base[i]) and ranked[-2] < o.tie_ratio * rise[i]):
            return None
        return i if float(np.median(others)) < o.others_ratio * rise[i] else None

    def _levels(self, t_ns: int) -> None:
        o = self.options
        split = t_ns - round(o.window_s * 1e9)
        for cam in self._cams:
            # The samples are in time order: those before the split are a prefix, found by one binary search.
            t, r = cam.quick.times(), cam.quick.values()
            k = int(np.searchsorted(t, split, side="left"))
            quick_span = (split - int(t[0])) / 1e9 if k else 0.0
            cam.quick_baseline = float(np.median(r[:k])) if quick_span >= o.min_baseline_s else float("nan")
            t, r = cam.samples.times(), cam.samples.values()
            k = int(np.searchsorted(t, split, side="left"))
            span = (split - int(t[0])) / 1e9 if k else 0.0
            cam.current = float(np.median(r[k:])) if len(r) - k >= 3 else float("nan")
            if cam.frozen_baseline is not None:
                cam.baseline = cam.frozen_baseline  # and its spread, as it was
            else:
                cam.baseline = float(np.median(r[:k])) if span >= o.min_baseline_s else float("nan")
                cam.spread = _level_spread(t[:k], r[:k], split, o.window_s) if np.isfinite(cam.baseline) else np.nan

    def _rise(self, cam: _Camera) -> float:
        return cam.current - cam.baseline if np.isfinite(cam.current) and np.isfinite(cam.baseline) else float("nan")

    def _barred(self, t_ns: int | None) -> NDArray[np.bool_]:
        """Per camera: released and still being re-examined (not named, nor flagged, and no measure of the others)."""
        if t_ns is None:
            return np.zeros(len(self._cams), dtype=bool)
        return np.array([c.barred_until_ns is not None and t_ns < c.barred_until_ns for c in self._cams], dtype=bool)

    def _high(self, i: int) -> bool:
        rise = self._rise(self._cams[i])
        return bool(np.isfinite(rise) and rise > self._threshold(i))

    def _threshold(self, i: int, baseline: float | None = None) -> float:
        """The rise (px) that makes camera ``i`` suspect: ``margin_px``, ``ratio`` of its baseline (``baseline``
        where given: the all-in one) and :data:`SPREAD_FACTOR` times its level's own spread over the baseline span,
        the largest."""
        o, cam = self.options, self._cams[i]
        base = cam.baseline if baseline is None else baseline
        spread = SPREAD_FACTOR * cam.spread if np.isfinite(cam.spread) else 0.0
        return max(o.margin_px, o.ratio * base if np.isfinite(base) else 0.0, spread)

    def _judge(self, t_ns: int) -> None:
        o = self.options
        self._levels(t_ns)
        hold = round(o.hold_s * 1e9)
        barred = self._barred(t_ns)
        # A released camera's rise is left out of the comparisons: the others are re-examined without it.
        rises = np.array([np.nan if b else self._rise(c) for c, b in zip(self._cams, barred, strict=True)])
        doubt = bool(np.array([c.state == "bumped" for c in self._cams]).any())
        finite = np.sort(rises[np.isfinite(rises)])
        # Nobody is named while a camera has no level to compare (it sees nobody now): the others' checks then come
        # from fewer witnesses than their baselines did (a person seen by two cameras instead of three), and the
        # rise of one may be that, not a knock (the camera demo: cam01 named the moment cam02 saw nobody).
        complete = finite.size == int((~barred).sum())
        # Two cameras rising alike cannot be told apart (opposite cameras that are each other's only witness of
        # an axis see one's bump as the other's): neither is named.
        tied = finite.size >= 2 and finite[-2] >= o.tie_ratio * finite[-1]
        for i, cam in enumerate(self._cams):
            others = np.delete(rises, i)
            others = others[np.isfinite(others)]
            # The camera that rose most, and alone: a bump of one camera leaks into the others' checks (it takes
            # part in their triangulations) by less than it shows in its own.
            alone = (self._high(i) and complete and rises[i] >= np.nanmax(rises) and not tied and not doubt
                     and (others.size == 0 or float(np.median(others)) < o.others_ratio * rises[i]))  # fmt: skip
            if cam.state == "learning":
                if np.isfinite(cam.baseline):
                    self._enter(cam, i, "ok", t_ns)
            elif cam.state == "ok":
                if alone:
                    cam.frozen_baseline = cam.baseline
                    since = self._flag_since[i]  # flagged since then, without a break
                    cam.doubt_ns = t_ns if since is None else min(since, t_ns)
                    self._enter(cam, i, "suspect", t_ns)
            elif cam.state == "suspect":
                up = np.isfinite(rises[i]) and rises[i] > 0.5 * self._threshold(i)
                if not up or rises[i] < np.nanmax(rises) or tied:
                    # well back down (half the threshold: a level hovering at it does not flicker in and out), or
                    # another camera rose as much or more: this one's rise may be that camera's leaking into it
                    cam.frozen_baseline = None
                    self._enter(cam, i, "ok", t_ns)
                elif t_ns - cam.since_ns >= hold:
                    cam.bumps += 1
                    self._enter(cam, i, "bumped", t_ns)
            elif cam.state == "bumped":
                calm = np.isfinite(rises[i]) and rises[i] < 0.5 * self._threshold(i)
                if not calm:
                    cam.calm_since_ns = None
                elif cam.calm_since_ns is None:
                    cam.calm_since_ns = t_ns
                elif t_ns - cam.calm_since_ns >= hold:
                    self._clear(cam)
                    self._enter(cam, i, "ok", t_ns)

    def _enter(self, cam: _Camera, i: int, state: str, t_ns: int) -> None:
        if cam.state == state:
            return
        details = {"from": cam.state, "residual_px": _r(cam.current), "baseline_px": _r(cam.baseline)}
        if state == "bumped" or cam.state == "bumped":  # news: a bump, or a bumped camera back in agreement
            self.events.append((t_ns, self.cameras[i].name, state, details))
        cam.state, cam.since_ns = state, t_ns

    def _clear(self, cam: _Camera) -> None:
        cam.frozen_baseline = None
        cam.calm_since_ns = None
        cam.matches.clear()
        cam.people.clear()
        cam.n_matches = 0
        cam.proposal = None

    def _reestimate(self, t_ns: int, c: int) -> None:
        cam = self._cams[c]
        X = np.concatenate([m[0] for m in cam.matches])
        uv = np.concatenate([m[1] for m in cam.matches])
        people = list(cam.people)
        cam.matches.clear()
        cam.people.clear()
        cam.n_matches = 0
        prop = reestimate_pose(self.cameras[c], X, uv)
        if prop is None:
            return  # too few matches agree: gather again
        # Every camera's people, with the camera as it is and as proposed: a turn that fits its own matches better
        # may still pull the others' triangulations (it takes part in them) away from what they see.
        o = self.options
        P = self._P.copy()
        P[c] = prop.camera.projection_matrix
        before = rig_residuals(self._P, people, min_confidence=o.min_confidence, min_keypoints=o.min_keypoints)
        after = rig_residuals(P, people, min_confidence=o.min_confidence, min_keypoints=o.min_keypoints)
        rig = tuple((self.cameras[k].name, _r(before[k]), _r(after[k])) for k in range(len(self.cameras)) if k != c)
        prop = replace(prop, rig=rig)
        cam.proposal = replace(prop, refused=judge_proposal(prop, cam.baseline, self.options))
        self.events.append((t_ns, self.cameras[c].name, "re-estimated", _proposal_json(cam.proposal)))
        cam.refusals = cam.refusals + 1 if cam.proposal.refused is not None else 0
        if cam.refusals >= RELEASE_AFTER and cam.state == "bumped":
            self._release(t_ns, c)

    def _release(self, t_ns: int, c: int) -> None:
        """Bumped camera ``c``, whose re-estimates keep being refused, back in the solve; not named again for
        ``baseline_s`` while the others are judged without it (:data:`RELEASE_AFTER`)."""
        cam = self._cams[c]
        reason = cam.proposal.refused if cam.proposal is not None else None
        details = {"refused": cam.refusals, "reason": reason, "re_examine_s": self.options.baseline_s}
        self.events.append((t_ns, self.cameras[c].name, "released", details))
        self._clear(cam)
        cam.refusals = 0
        cam.released += 1
        cam.barred_until_ns = t_ns + round(self.options.baseline_s * 1e9)
        cam.state, cam.since_ns = "ok", t_ns

    # ------------------------------------------------------------------------------------------ output
    def proposal(self, camera: int) -> Proposal | None:
        """The bumped camera's re-estimated pose, once there is one."""
        return self._cams[camera].proposal

    def doubted_since(self, camera: int) -> int | None:
        """The solve time of the check that first put ``camera`` in doubt, flagged or suspect (None: never, or not
        since its last re-estimate was applied)."""
        return self._cams[camera].doubt_ns

    def pending(self) -> list[tuple[int, Proposal]]:
        """With ``apply``: the bumped cameras whose re-estimate passed its checks, waiting to be applied (the caller
        swaps the camera everywhere, then calls :meth:`apply`)."""
        if not self.options.apply:
            return []
        return [(i, c.proposal) for i, c in enumerate(self._cams)
                if c.state == "bumped" and c.proposal is not None and c.proposal.refused is None]  # fmt: skip

    def apply(self, camera: int, new: Camera) -> None:
        """``camera`` now has the pose ``new`` (a proposal applied, or a recalibration): its residuals are measured
        against it, from a new baseline (state "learning" until there is one); back in the solve at once."""
        self.cameras[camera] = new
        self._P = np.stack([c.projection_matrix for c in self.cameras])
        self._flagged[:] = False
        self._votes = None
        self._flag_since = [None] * len(self.cameras)
        self._screens.clear()  # verdicts against the old pose
        old = self._cams[camera]
        self._cams[camera] = _Camera(bumps=old.bumps, applied=old.applied + (old.state == "bumped"))

    def states(self) -> list[str]:
        return [c.state for c in self._cams]

    def status(self) -> dict[str, Any]:
        """JSON-able: per camera its state, current and baseline residual (px), bumps so far and any proposal."""
        return {
            cam.name: {
                "state": c.state, "residual_px": _r(c.current), "baseline_px": _r(c.baseline), "bumps": c.bumps,
                "applied": c.applied, "samples": len(c.samples), "released": c.released,
                "re_examining": bool(self._barred(self._last_ns)[i]),
                "proposal": None if c.proposal is None else _proposal_json(c.proposal),
            }
            for i, (cam, c) in enumerate(zip(self.cameras, self._cams, strict=True))
        }  # fmt: skip


def _r(x: float) -> float | None:
    return round(float(x), 2) if np.isfinite(x) else None


def _proposal_json(p: Proposal) -> dict[str, Any]:
    return {
        "rotation_deg": p.rotation_deg, "matches": p.matches, "inliers": p.inliers,
        "median_px_before": p.median_px_before, "median_px_after": p.median_px_after,
        "rig": {name: {"before": b, "after": a} for name, b, a in p.rig},
        "R": np.round(p.camera.R, 9).tolist(), "t": np.round(p.camera.t, 6).tolist(), "refused": p.refused,
    }  # fmt: skip

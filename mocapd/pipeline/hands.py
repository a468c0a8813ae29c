"""The per-person finger solve of the scheduler (issue 44): hands on when the detections carry hand keypoints.

The detector delivers a person's two hands as 42 extra columns after the body's (the ``<body>_hands`` formats of
:func:`mocapd.core.keypoints.with_hands`: ``left_hand_wrist`` ... ``right_hand_pinky_tip``). The scheduler makes a
:class:`HandStage` only when its columns name them (:meth:`HandStage.from_names`); without one nothing here runs and
the body-only tick is the same code and the same work as before.

Per person and tick, after the body solve (in the same person job, so on the solve pool where there is one):

1. both hands' frames from the body's θ (:func:`~mocapd.core.hand_solver.body_hand_frames`);
2. each hand seen in enough views is fitted (:class:`~mocapd.core.hand_solver.HandSolver`), warm-started from
   its previous solve (kept :attr:`HandStage.max_gap` ticks), else from its palm triangulated and laid onto the
   model (:func:`~mocapd.core.hand_solver.palm_rotation`);
3. the hand's size: from the body's forearm (:meth:`~mocapd.core.hand_skeleton.HandSkeleton.from_body`), then
   refined once from the median of :attr:`HandStage.size_frames` triangulated samples
   (:func:`~mocapd.core.hand_solver.hand_scale_sample`), within ±20 % of the forearm's guess;
4. out: a :class:`~mocapd.core.hand_skeleton.HandPose` (the fingers' local rotations, which hands are present)
   and θ with each solved hand bone's rotation replaced by the one its keypoints gave (a body keypoint set barely
   constrains it).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import triangulate_projections
from mocapd.core.hand_skeleton import HAND_BONES, N_FINGER_BONES, SIDES, HandPose, HandSkeleton
from mocapd.core.hand_solver import (
    HandResult,
    HandSolveOptions,
    HandSolver,
    body_hand_frames,
    hand_scale_sample,
    palm_rotation,
)
from mocapd.core.keypoints import hand_keypoint_names
from mocapd.core.rotations import rotvec_from_matrix
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.pipeline.latency import LatencyStats

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

SIZE_MIN_CONFIDENCE = 0.5  # hand keypoints below this take no part in the size triangulation
SIZE_RANGE = (0.8, 1.2)  # the refined size stays within this factor of the forearm's guess


@dataclass
class _HandTrack:
    """One person's hands between ticks."""

    previous: list[HandResult | None] = field(default_factory=lambda: [None, None])
    gap: list[int] = field(default_factory=lambda: [0, 0])  # ticks since each hand was last solved
    samples: list[list[float]] = field(default_factory=lambda: [[], []])
    factor: list[float | None] = field(default_factory=lambda: [None, None])  # refined size / forearm's guess
    skeleton: Skeleton | None = None  # the body skeleton ``hands`` was sized from
    hands: HandSkeleton | None = None
    solvers: list[HandSolver] = field(default_factory=list)


class HandStage:
    """Both hands of every tracked person.

    Parameters
    ----------
    columns : int array, shape (2, 21)
        Where each hand's 21 keypoints (left, right) are among the detections' columns.
    projections : array, shape (n_cams, 3, 4)
        The rig's projection matrices (undistorted pixels).
    options : HandSolveOptions, optional
    size_frames : int
        Size samples gathered per hand before its size is refined (0: the forearm's guess stays).
    max_gap : int
        Ticks a hand's last solve stays its warm start while it is not seen.
    """

    def __init__(
        self,
        columns: IntArray,
        projections: FloatArray,
        options: HandSolveOptions | None = None,
        *,
        size_frames: int = 30,
        max_gap: int = 30,
    ) -> None:
        self.columns = np.asarray(columns, dtype=np.intp).reshape(2, -1)
        self.projections = projections
        self.options = options if options is not None else HandSolveOptions()
        self.size_frames = size_frames
        self.max_gap = max_gap
        self._tracks: dict[str, _HandTrack] = {}
        self._lock = threading.Lock()
        self.counters = {"hands_solved": 0, "hands_missing": 0, "hands_sized": 0}
        #: CPU time of each person's hand solve (both hands; the scheduler's clock, recorded by the scheduler)
        self.cpu = LatencyStats()

    @classmethod
    def from_names(cls, names: Sequence[str], projections: FloatArray, **kw: object) -> HandStage | None:
        """The stage for detections whose columns are ``names``; None when they carry no hand keypoints (hands
        off: the scheduler then does nothing for hands)."""
        wanted = [hand_keypoint_names(side.lower()) for side in SIDES]
        if not all(n in names for hand in wanted for n in hand):
            return None
        where = {n: i for i, n in enumerate(names)}
        columns = np.array([[where[n] for n in hand] for hand in wanted], dtype=np.intp)
        return cls(columns, projections, **kw)  # type: ignore[arg-type]

    def swapped(self, pixels: FloatArray, confidences: FloatArray) -> tuple[FloatArray, FloatArray]:
        """A view's columns (n_columns, 2) and confidences (n_columns,) with the two hands' keypoints exchanged
        (copies): the view's left/right labels were swapped (the scheduler's per-view flips)."""
        left, right = self.columns
        pixels, confidences = pixels.copy(), confidences.copy()
        pixels[left], pixels[right] = pixels[right], pixels[left].copy()
        confidences[left], confidences[right] = confidences[right], confidences[left].copy()
        return pixels, confidences

    def solve(
        self,
        identity: str,
        skeleton: Skeleton,
        theta: FloatArray,
        views: Mapping[int, tuple[FloatArray, FloatArray]],
    ) -> tuple[HandPose, FloatArray]:
        """One person's hands at this tick.

        Parameters
        ----------
        identity : str
            The person (their state is kept between ticks).
        skeleton, theta
            The body solve: its skeleton and θ (66,).
        views : mapping camera -> (undistorted pixels (n_columns, 2), confidences (n_columns,))
            The person's detection in each camera that sees them, every column.

        Returns
        -------
        HandPose, and θ (66,) with the solved hands' bone rotations from their keypoints.
        """
        track = self._track(identity, skeleton)
        assert track.hands is not None
        n_cams = len(self.projections)
        uv = np.full((2, n_cams, self.columns.shape[1], 2), np.nan)
        conf = np.zeros((2, n_cams, self.columns.shape[1]))
        for cam, (pixels, confidences) in views.items():
            uv[:, cam] = pixels[self.columns]
            conf[:, cam] = np.clip(np.nan_to_num(confidences[self.columns]), 0.0, 1.0)
        rotations, wrists, forearms = body_hand_frames(skeleton, theta)
        local = np.zeros((2, N_FINGER_BONES, 4))
        local[..., 0] = 1.0
        present = np.zeros(2, dtype=bool)
        theta = theta.copy()
        for side in (0, 1):
            start = None
            if track.previous[side] is None or self.size_frames > len(track.samples[side]):
                start = self._triangulated(track, side, uv[side], conf[side])
            result = track.solvers[side].solve(
                self.projections, uv[side], conf[side], rotations[side], wrists[side], track.previous[side], start
            )
            if result is None:
                track.gap[side] += 1
                if track.gap[side] > self.max_gap:
                    track.previous[side] = None
                continue
            track.previous[side], track.gap[side] = result, 0
            local[side], present[side] = result.local, True
            b = BONE_INDEX[HAND_BONES[SIDES[side]]]
            theta[3 + 3 * b : 6 + 3 * b] = rotvec_from_matrix(forearms[side].T @ result.rotation)
        with self._lock:
            self.counters["hands_solved"] += int(present.sum())
            self.counters["hands_missing"] += int((~present).sum())
        return HandPose(local, present, track.hands), theta

    def forget(self, keep: set[str]) -> None:
        """Drop the state of every person not in ``keep``."""
        for identity in [k for k in self._tracks if k not in keep]:
            del self._tracks[identity]

    def _track(self, identity: str, skeleton: Skeleton) -> _HandTrack:
        track = self._tracks.get(identity)
        if track is None:
            track = self._tracks[identity] = _HandTrack()
        if track.skeleton is not skeleton:  # new, or the body was (re)sized: the hands follow its forearms
            track.skeleton = skeleton
            self._resize(track)
        return track

    def _resize(self, track: _HandTrack) -> None:
        assert track.skeleton is not None
        hands = HandSkeleton.from_body(track.skeleton)
        for side, factor in enumerate(track.factor):
            if factor is not None:
                hands = hands.rescaled(side, factor)
        track.hands = hands
        track.solvers = [HandSolver(hands, side, self.options) for side in (0, 1)]

    def _triangulated(self, track: _HandTrack, side: int, uv: FloatArray, conf: FloatArray) -> FloatArray | None:
        """The hand's keypoints triangulated: a size sample while the size is being refined, and the palm's
        rotation as a start when there is no previous solve."""
        assert track.hands is not None
        weights = np.where(np.isfinite(uv).all(axis=-1) & (conf >= SIZE_MIN_CONFIDENCE), conf, 0.0)
        if np.count_nonzero(weights.sum(axis=0) > 0) < 6:
            return None
        points, ok = triangulate_projections(self.projections, np.nan_to_num(uv), weights)
        if track.factor[side] is None and self.size_frames > 0:
            sample = hand_scale_sample(track.hands, side, points, ok)
            if sample is not None:
                track.samples[side].append(sample)
            if len(track.samples[side]) >= self.size_frames:
                lo, hi = SIZE_RANGE
                track.factor[side] = float(np.clip(np.median(track.samples[side]), lo, hi))
                self._resize(track)
                with self._lock:
                    self.counters["hands_sized"] += 1
        return palm_rotation(track.hands, side, points, ok) if track.previous[side] is None else None

"""Sorting unordered 2D person detections from all views into tracked subjects (seed 003 §3.3.1, Algorithm 1).

Per frame, every pair of 2D people across every pair of views is triangulated on the keypoints confident in
both; a pair whose mean reprojection error exceeds ``max_reprojection_error`` (fraction of image width) is
rejected as two different people. Surviving 3D candidates closer than ``same_person_distance`` (mean over shared
keypoints) to an existing candidate are merged into it; the others start new candidates. Each tracked subject
then takes the nearest unused candidate within ``max_interframe_movement`` of its last position (subjects in
the order given). The solver uses the 2D detections of each subject's candidate, not the triangulation.

Beyond the pseudo-code, each measured on the close-interaction scene of ``mocapd eval tracking``:
(1) pairs are clustered in order of reprojection error, and a pair never joins a candidate that already holds a
*different* 2D person of one of its cameras — one camera sees a person once, so two people standing closer than
the same-person distance stay apart (a candidate therefore holds at most one detection per view); (2) each 2D detection
is finally given to one candidate only, the one supported by most views (:func:`_resolve_claims`): with the seed's
loose threshold, two different people seen by two facing cameras otherwise pair into spurious 2-view candidates;
(3) subjects take candidates by an optimal assignment rather than in subject order; (4) a left/right pair of
keypoints pairs as labelled or with the second view's labels exchanged, whichever fits better
(:attr:`SortingOptions.flip_aware`, measured on the Pose2Sim demos by ``mocapd eval video``). Triangulation is the
two-ray midpoint, all the association needs; reprojection errors are measured in the undistorted image. The
per-pair work runs in one compiled call (:mod:`mocapd.core._sorting_kernel`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core import _sorting_kernel
from mocapd.core.assignment import linear_sum_assignment
from mocapd.core.camera import MIN_DEPTH, Camera, stack_cameras
from mocapd.core.lr_flips import COCO17_LR_PAIRS, lr_pairs
from mocapd.core.norms import norms
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SortingOptions:
    """Thresholds of Algorithm 1 (defaults: the seed's empirical values)."""

    min_confidence: float = 0.3
    """A keypoint counts when its detector confidence is at least this."""
    min_shared_keypoints: int = 5
    """A pair of 2D people must share this many confident keypoints to be triangulated."""
    max_reprojection_error: float = 0.025
    """ThreshTriError: mean reprojection error, as a fraction of the image width. 2.5 %, not the 1.5 % tuned on
    synthetic detections: real detections of one person disagree across views by 13-20 px median on 1088-px-wide
    cameras, and at 1.5 % a view of the Pose2Sim demos was dropped in a quarter of the frames
    (docs/accuracy-video.md)."""
    same_person_distance: float = 0.30
    """ThreshDistSamePerson: mean keypoint distance (m) under which two candidates are one person."""
    max_interframe_movement: float = 1.0
    """ThreshInterFrameMovement: how far (m) a subject may move between the frames it is seen in."""
    flip_aware: bool = True
    """Pair each left/right pair of keypoints of two views as labelled or with the second view's labels exchanged,
    whichever fits better: a view whose detector confused the person's left and right (back views) still joins
    the person (the solve undoes the flip, :mod:`mocapd.core.lr_flips`) instead of failing the limit."""


@dataclass(frozen=True)
class Detections2D:
    """The 2D people one camera detected in one frame.

    Attributes
    ----------
    keypoints : array, shape (n_people, n_kp, 2)
        Pixels (distorted, as detected).
    confidences : array, shape (n_people, n_kp)
    undistorted : array, shape (n_people, n_kp, 2), optional
        The same keypoints undistorted (pixels of the camera without its lens distortion), where the receiver
        made them once as the frame arrived (:meth:`FixedLatencyScheduler.add_detections`) rather than on every
        tick that uses the frame.
    """

    keypoints: FloatArray
    confidences: FloatArray
    undistorted: FloatArray | None = None

    def __post_init__(self) -> None:
        kp = np.asarray(self.keypoints, dtype=np.float64)
        cf = np.asarray(self.confidences, dtype=np.float64)
        if kp.ndim != 3 or kp.shape[2] != 2 or cf.shape != kp.shape[:2]:
            raise InputError(f"detections: keypoints (n, n_kp, 2) and confidences (n, n_kp) expected, "
                             f"got {kp.shape} and {cf.shape}")  # fmt: skip
        if self.undistorted is not None and np.shape(self.undistorted) != kp.shape:
            raise InputError(f"detections: undistorted keypoints {np.shape(self.undistorted)} for {kp.shape}")
        object.__setattr__(self, "keypoints", kp)
        object.__setattr__(self, "confidences", cf)

    def with_undistorted(self, undistorted: FloatArray) -> Detections2D:
        """These detections with their undistorted copy: :func:`dataclasses.replace` without converting and
        checking the keypoints and confidences again (done when these were made; once per keypoint set arriving
        on the event loop, issue 39)."""
        if np.shape(undistorted) != self.keypoints.shape:
            raise InputError(f"detections: undistorted keypoints {np.shape(undistorted)} for {self.keypoints.shape}")
        out = object.__new__(Detections2D)
        object.__setattr__(out, "keypoints", self.keypoints)
        object.__setattr__(out, "confidences", self.confidences)
        object.__setattr__(out, "undistorted", undistorted)
        return out

    @classmethod
    def empty(cls, n_kp: int) -> Detections2D:
        return cls(np.zeros((0, n_kp, 2)), np.zeros((0, n_kp)))

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


@dataclass
class Candidate:
    """A 3D person candidate: its keypoints and the 2D detections (camera -> person index) it came from."""

    points: FloatArray  # (n_kp, 3), NaN where not triangulated
    sources: dict[int, int] = field(default_factory=dict)
    errors: dict[int, float] = field(default_factory=dict)  # camera -> reprojection error of its detection (px)

    @property
    def centre(self) -> FloatArray:
        """``np.nanmean(points, axis=0)`` without its Python layers (the same sums and division; NaN where no
        keypoint has the coordinate, without nanmean's warning)."""
        nan = np.isnan(self.points)
        with np.errstate(invalid="ignore"):
            return np.asarray(np.add.reduce(np.where(nan, 0.0, self.points), axis=0)
                              / np.add.reduce(~nan, axis=0, dtype=np.intp))  # fmt: skip


def mean_keypoint_distance(a: FloatArray, b: FloatArray) -> float:
    """Mean distance over keypoints present in both (inf when none are).

    The sum and mean :func:`numpy.linalg.norm` and :meth:`numpy.ndarray.mean` take, without their Python layers
    (the same floats; this runs several times a tick on the event loop, issue 39)."""
    x = a - b
    return _finite_mean(norms(x))


def mean_keypoint_distances(a: FloatArray, b: FloatArray) -> FloatArray:
    """:func:`mean_keypoint_distance` of every ``a[i]`` and ``b[j]``: one subtraction and norm for all pairs.

    Parameters
    ----------
    a : array, shape (m, n_kp, 3)
    b : array, shape (n, n_kp, 3)

    Returns
    -------
    array, shape (m, n)
    """
    x = a[:, None] - b[None]
    d = norms(x)  # (m, n, n_kp)
    out = np.empty(d.shape[:2])
    for i in range(d.shape[0]):
        for j in range(d.shape[1]):
            out[i, j] = _finite_mean(d[i, j])  # per pair: the same summation order as one pair's mean
    return out


def _finite_mean(d: FloatArray) -> float:
    d = d[np.isfinite(d)]
    return float(np.add.reduce(d) / d.size) if d.size else np.inf


def _mean_error(errors: dict[int, float]) -> float:
    """``np.mean`` of a candidate's per-camera errors: for fewer than 8 values numpy adds them in order, as this
    loop does (beyond, its pairwise sum; none: NaN, as ``np.mean`` gives)."""
    if len(errors) >= 8 or not errors:
        return float(np.mean(list(errors.values())))
    total = 0.0
    for e in errors.values():
        total += e
    return total / len(errors)


def _resolve_claims(cands: list[Candidate]) -> list[Candidate]:
    """Give each 2D detection to one candidate: the one seen in most views, then with the lowest error.

    With the seed's loose reprojection threshold, two *different* people can pair up across a near-degenerate
    view pair (e.g. two cameras facing each other) into a spurious 2-view candidate. A real person is supported by
    every view that sees them, so support decides; candidates left with fewer than two views are dropped.
    """
    owner: dict[tuple[int, int], int] = {}
    order = sorted(range(len(cands)), key=lambda k: (-len(cands[k].sources), _mean_error(cands[k].errors)))
    kept: list[Candidate] = []
    for k in order:
        c = cands[k]
        free = {cam: p for cam, p in c.sources.items() if (cam, p) not in owner}
        if len(free) < 2:
            continue
        for cam, p in free.items():
            owner[(cam, p)] = k
        kept.append(Candidate(c.points, free, {cam: c.errors[cam] for cam in free}))
    return kept


class DetectionSorter:
    """Algorithm 1 for a fixed camera rig.

    Parameters
    ----------
    cameras : list of Camera
        At least two (the seed's method needs triangulation), or none: a rig of IMU suits alone, where no one is
        ever found (the scheduler solves the suits by themselves).
    options : SortingOptions
    """

    def __init__(
        self, cameras: list[Camera], options: SortingOptions | None = None, keypoint_names: tuple[str, ...] = ()
    ) -> None:
        if len(cameras) == 1:
            raise InputError("detection sorting needs at least two cameras (it triangulates across views), or none")
        self.cameras = list(cameras)
        self.options = options if options is not None else SortingOptions()
        self._K, self._dist, self._R, self._t = (np.ascontiguousarray(a) for a in stack_cameras(self.cameras))
        self._widths = np.array([c.width for c in cameras], dtype=np.float64)
        self.keypoint_names = tuple(keypoint_names)
        self._partners: dict[tuple[int, tuple[str, ...]], NDArray[np.int64]] = {}
        self._owners: dict[tuple[int, ...], tuple[NDArray[np.int64], NDArray[np.int64]]] = {}

    def set_camera(self, index: int, camera: Camera) -> None:
        """Camera ``index`` is ``camera`` from the next frame on (a recalibrated camera)."""
        if not 0 <= index < len(self.cameras):
            raise InputError(f"sorting: no camera {index} (it has {len(self.cameras)})")
        self.cameras[index] = camera
        self._K, self._dist, self._R, self._t = (np.ascontiguousarray(a) for a in stack_cameras(self.cameras))
        self._widths = np.array([c.width for c in self.cameras], dtype=np.float64)

    def _partner(self, n_kp: int) -> NDArray[np.int64]:
        """Each keypoint's left/right counterpart (itself where it has none): from the keypoint names, COCO-17's
        when none were given and detections have 17 keypoints. Worked out once per keypoint count: not to be
        written to (left writable: numba compiles another kernel for a read-only array)."""
        key = (n_kp, self.keypoint_names)
        partner = self._partners.get(key)
        if partner is None:
            partner = self._partners[key] = self._make_partner(n_kp)
        return partner

    def _make_partner(self, n_kp: int) -> NDArray[np.int64]:
        partner = np.arange(n_kp, dtype=np.int64)
        if len(self.keypoint_names) == n_kp:
            pairs = lr_pairs(self.keypoint_names)
        else:
            pairs = COCO17_LR_PAIRS if n_kp == 17 else ()
        for left, right in pairs:
            partner[left], partner[right] = right, left
        return partner

    def warm_up(self, n_keypoints: int) -> None:
        """Compile (or load from numba's cache) the pairing kernel now, not when the first two people appear in
        the live tick: one made-up person in every camera."""
        one = Detections2D(np.zeros((1, n_keypoints, 2)), np.ones((1, n_keypoints)))
        self.candidates([one] * len(self.cameras))

    # -- candidates ----------------------------------------------------------------------------------------
    def candidates(self, detections: list[Detections2D]) -> list[Candidate]:
        """Lines 1–17 of Algorithm 1: the viable 3D candidates of this frame (then claims resolved)."""
        if len(detections) != len(self.cameras):
            raise InputError(f"sorting: {len(self.cameras)} cameras but detections for {len(detections)}")
        o = self.options
        counts = [len(d) for d in detections]
        if sum(1 for n in counts if n) < 2:
            return []
        n_kp = detections[0].keypoints.shape[1]
        kp = np.concatenate([d.keypoints for d in detections]).reshape(-1, n_kp, 2)
        usable = np.concatenate([d.confidences for d in detections]).reshape(-1, n_kp) >= o.min_confidence
        camera_of, person_of = self._owner_indices(counts)
        points, members, member_errors = _sorting_kernel.candidate_pairs(
            np.ascontiguousarray(kp), usable, camera_of, person_of, self._K, self._dist, self._R, self._t,
            self._widths, o.max_reprojection_error, o.min_shared_keypoints, o.same_person_distance, MIN_DEPTH,
            self._partner(n_kp), o.flip_aware, True,
        )  # fmt: skip
        cands = []
        for q, (row, errs) in enumerate(zip(members.tolist(), member_errors.tolist(), strict=True)):
            cams = [c for c, p in enumerate(row) if p >= 0]
            cands.append(Candidate(points[q], {c: row[c] for c in cams}, {c: errs[c] for c in cams}))
        return _resolve_claims(cands)

    def _owner_indices(self, counts: list[int]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Per 2D person of a frame with ``counts`` people per camera, its camera and its index in that camera
        (the kernel's ``camera_of``, ``person_of``), kept per distinct ``counts`` (a handful in a session; not to be
        written to, left writable as :meth:`_partner`'s)."""
        key = tuple(counts)
        found = self._owners.get(key)
        if found is None:
            camera_of = np.repeat(np.arange(len(counts)), counts).astype(np.int64)
            person_of = np.concatenate([np.arange(n) for n in counts]).astype(np.int64)
            found = self._owners[key] = (camera_of, person_of)
            if len(self._owners) > 256:  # bounded: people coming and going give new counts
                self._owners.pop(next(iter(self._owners)))
        return found

    # -- assignment ----------------------------------------------------------------------------------------
    def assign(self, cands: list[Candidate], last_positions: list[FloatArray | None]) -> list[Candidate | None]:
        """Lines 18–30, with one change: subjects and candidates are matched optimally, not in subject order.

        Each subject gets at most one candidate within ``max_interframe_movement`` of its last position, and
        the pairing minimises the total distance (Hungarian) — the seed's greedy order lets the first subject
        take the other person's candidate when two people stand close.

        Parameters
        ----------
        last_positions : per subject, its last seen keypoints (n_kp, 3) or None if never seen.
        """
        out: list[Candidate | None] = [None] * len(last_positions)
        if not cands or not last_positions:
            return out
        limit = self.options.max_interframe_movement
        dist = np.full((len(last_positions), len(cands)), np.inf)
        known = [(i, last) for i, last in enumerate(last_positions) if last is not None]
        if known:
            lasts = np.stack([last for _, last in known])
            dist[[i for i, _ in known]] = mean_keypoint_distances(lasts, np.stack([c.points for c in cands]))
        usable = dist < limit
        rows, cols = linear_sum_assignment(np.where(usable, dist, 1e6))
        for i, j in zip(rows, cols, strict=True):
            if usable[i, j]:
                out[i] = cands[j]
        return out

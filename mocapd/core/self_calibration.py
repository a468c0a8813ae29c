"""Camera extrinsics from the people in view: no board (issue 43).

Input: per synchronised moment and camera, the 2D people a detector found (COCO-17 keypoints with confidences,
:class:`~mocapd.core.sorting.Detections2D`, unordered and unlabelled), and each camera's intrinsics (known, or a
guess whose focal length and principal point the adjustment may refine). Output: every camera in a metric, +Y up
world with the floor at y = 0, and a quality report that says what to do when the result is poor.

1. **Pairs.** For each camera pair, every pairing of a person in one view with a person in the other at the same
   moment gives keypoint correspondences; the essential matrix is estimated by RANSAC on the undistorted
   normalised points (``cv2.findEssentialMat``), from the moments with one person in both views when there are
   enough of them (no wrong pairings), else from all pairings (a wrong pairing moves unlike a rigid epipolar
   geometry over many moments, so RANSAC treats it as outliers). Each moment's people are then paired by the
   Hungarian method on their median Sampson distance, a pairing kept below ``pair_threshold`` of the image width;
   the essential matrix is estimated again on the kept pairings and decomposed (``cv2.recoverPose``).
2. **People across views.** The kept pairings link detections (moment, camera, person) into groups (union-find);
   a group with two detections of one camera keeps the better-linked one. Each group is one person at one moment:
   its 17 keypoints are 17 unknown 3D points.
3. **Chaining.** The pair with the most inliers starts the reconstruction (the first camera at the origin, the
   baseline of length 1); the people they share are triangulated. The camera that sees most of what is already
   triangulated joins next, placed by PnP (RANSAC, then Levenberg-Marquardt), and everything is triangulated
   again; so the rig grows along its strongest links (a spanning tree of the camera graph).
4. **Bundle adjustment** of every camera's pose (the first one fixed: gauge), optionally the focal length (one
   factor per camera) and principal point, and every 3D keypoint, on the confidence-weighted pixel residuals with a
   soft-L1 loss (``scipy.optimize.least_squares``, TRF, sparse Jacobian: a residual depends on one camera and one
   point); observations beyond 4 robust standard deviations are dropped and the adjustment is run again.
5. **Scale** from the people's size: the thigh and shank lengths over everybody (trimmed means) give a height the way
   :func:`mocapd.core.body_size.estimate_skeleton` does (leg length against the reference skeleton's); the
   reconstruction is scaled so that height is ``height_m`` (the people's mean height, given, or the 1.75 m default
   when not: then the scale is as good as that guess, a 1.60 m person makes the world 9 % too large).
6. **Up and floor** from the feet: the ankles' lowest points over time (per floor cell of 0.5 m, its lowest
   quarter), fitted by a plane whose normal, turned towards the heads, is +Y; the floor lies one ankle height (the
   skeleton's, at that height) below it. When the people's feet cover too narrow a strip to tilt a plane (a walk
   along a line), +Y is the median direction from the ankles to the shoulders instead (the report says which).
7. **Origin and heading.** ``origin="people"`` (the default): the origin is the middle of where people walked (the
   median of their feet, on the floor) and +Z is the first camera's viewing direction along the floor (from the
   first camera into the volume). ``origin="person"`` with ``origin_moments``: the person who stands still during
   those moments (the one whose feet stay within 0.25 m; others may walk by) stands at the origin (the middle of
   their ankles, on the floor) and faces +Z (their left, hips and shoulders, is +X), as every skeleton's rest pose
   does.

The report (:class:`SelfCalibrationReport`) gives per camera the observations used, the RMS and median
reprojection error, the share of its image the people covered and the empty parts; per camera pair the 3D points
both saw; the extent of the volume walked; and advice where something is weak.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from mocapd.core.bundle_adjustment import adjust
from mocapd.core.camera import Camera, normalized_from_pixels, triangulate_projections
from mocapd.core.keypoints import COCO17, coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import matrix_from_rotvec, skew
from mocapd.core.skeleton import POSE_DIM, REFERENCE_HEIGHT, Skeleton
from mocapd.core.sorting import Detections2D
from mocapd.errors import CalibrationError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

N_KP = len(COCO17)
_KP = {name: i for i, (name, _, _) in enumerate(COCO17)}
_LEGS = [(_KP[f"{s}_hip"], _KP[f"{s}_knee"], _KP[f"{s}_ankle"]) for s in ("left", "right")]
_ANKLES = [_KP["left_ankle"], _KP["right_ankle"]]
_SHOULDERS = [_KP["left_shoulder"], _KP["right_shoulder"]]
_HIPS = [_KP["left_hip"], _KP["right_hip"]]

Origin = Literal["people", "person"]

# The body's joints (shoulders to ankles), not the face: a detector puts the nose, eyes and ears of a person seen
# from behind where it guesses them (the nose on the back of the head), so across a front and a back view they do
# not correspond; the relative poses are estimated from the joints only.
_BODY = np.arange(N_KP) >= _KP["left_shoulder"]


@dataclass(frozen=True)
class SelfCalibrationOptions:
    """Settings of :func:`calibrate_from_people`.

    Attributes
    ----------
    height_m : float or None
        The people's mean height (metres); None: :data:`~mocapd.core.skeleton.REFERENCE_HEIGHT` (1.75 m), stated
        in the report as a default.
    min_confidence : float
        Keypoints below this confidence are not used.
    pair_threshold : float
        Largest median Sampson distance of a kept pairing of two views' people, as a fraction of the image width
        (0.025: 27 px on a 1088-px-wide camera; real detections of one person disagree across views by ~20 px).
    ransac_threshold_px : float
        RANSAC inlier threshold of the essential matrices (pixels).
    refine_focal, refine_principal_point : bool
        Also adjust each camera's focal length (one factor on fx and fy) / its principal point and focal length.
    max_moments : int
        Moments used at most (evenly spaced): bounds the adjustment's size.
    origin : "people" or "person"
        Where the world's origin and heading come from (module docstring, step 7).
    origin_moments : (first, last) or None
        With ``origin="person"``: the moments (indices into the input, last excluded) during which the person
        stands at the origin facing +Z.
    seed : int
        Seeds the RANSAC samples and the subsampling: the same input gives the same calibration.
    rounds : int
        Association and adjustment rounds (the second associates under the first's adjusted poses).
    seeds : int
        Candidate pair poses the rig is grown from (the best by inliers over every pair); the one whose brief
        adjustment explains most keypoints is kept.
    """

    height_m: float | None = None
    min_confidence: float = 0.5
    pair_threshold: float = 0.025
    ransac_threshold_px: float = 4.0
    refine_focal: bool = False
    refine_principal_point: bool = False
    max_moments: int = 400
    origin: Origin = "people"
    origin_moments: tuple[int, int] | None = None
    seed: int = 0
    seeds: int = 8
    rounds: int = 2

    def __post_init__(self) -> None:
        if self.height_m is not None and not 0.5 <= self.height_m <= 2.6:
            raise CalibrationError(f"height {self.height_m} m; allowed: 0.5..2.6 m")
        if not 0.0 <= self.min_confidence < 1.0:
            raise CalibrationError(f"min_confidence {self.min_confidence}; allowed: 0..1")
        if self.origin not in ("people", "person"):
            raise CalibrationError(f"origin {self.origin!r}; allowed: 'people', 'person'")
        if self.max_moments < 10 or self.seeds < 1:
            raise CalibrationError(f"max_moments {self.max_moments} (allowed: >= 10), seeds {self.seeds} (>= 1)")
        if self.origin == "person" and self.origin_moments is None:
            raise CalibrationError("origin 'person' needs origin_moments: when the person stands at the origin")


@dataclass(frozen=True)
class CameraQuality:
    """How well one camera is calibrated.

    Attributes
    ----------
    observations : int
        Keypoints of this camera in the final adjustment.
    rejected : int
        Its keypoints dropped as outliers.
    rms_px, median_px : float
        Reprojection error of the kept keypoints.
    coverage : float
        Share of the cells of a 4×4 grid over the image in which people's keypoints were seen (at least 5 each).
    empty : list of str
        The parts of the image (3×3: "top left" … "bottom right") where nobody was seen.
    """

    name: str
    observations: int
    rejected: int
    rms_px: float
    median_px: float
    coverage: float
    empty: list[str]


@dataclass(frozen=True)
class SelfCalibrationReport:
    """The quality report of a self-calibration (see the module docstring)."""

    cameras: list[CameraQuality]
    shared_points: dict[tuple[str, str], int]
    """3D keypoints seen by both cameras of a pair (kept observations)."""
    pair_inliers: dict[tuple[str, str], int]
    """Essential-matrix inliers of each camera pair (0: no usable pair)."""
    moments: int
    people_instances: int
    """People at a moment seen by at least two cameras (each one a set of 3D keypoints)."""
    points: int
    height_m: float
    height_given: bool
    measured_height: float
    """The people's height in the unscaled reconstruction's units (the scale divides ``height_m`` by it)."""
    up_from: str
    """"floor plane" or "body direction"."""
    floor_extent_m: tuple[float, float]
    """Extent of the people's feet along X and Z (metres, 5th to 95th percentile)."""
    origin: str
    advice: list[str] = field(default_factory=list)
    poor_px: dict[str, float] = field(default_factory=dict)
    """Per camera, the median reprojection error above which the calibration is poor (1.5 % of the width)."""

    @property
    def verdict(self) -> str:
        """ "good" (no advice), "poor" (a camera's median reprojection error over 1.5 % of its width, a coverage
        under 20 % or fewer than 50 keypoints) or "usable" (advice, nothing that bad)."""
        if not self.advice:
            return "good"
        bad = any(c.coverage < 0.2 or c.observations < 50 or not c.median_px <= self.poor_px.get(c.name, np.inf)
                  for c in self.cameras)  # fmt: skip
        return "poor" if bad else "usable"


@dataclass(frozen=True)
class SelfCalibration:
    """The result: ``cameras`` (the input's order, in the world of the module docstring) and the report."""

    cameras: list[Camera]
    report: SelfCalibrationReport
    points: FloatArray
    """The adjusted 3D keypoints in the world (n_points, 3), metres."""


# -- input ------------------------------------------------------------------------------------------------------


@dataclass
class _Views:
    """The input flattened: per camera, per (moment, person) keypoints in pixels and normalised coordinates."""

    moments: IntArray  # (n_moments,) indices into the input
    uv: list[list[FloatArray]]  # [moment][camera] (n_people, 17, 2) distorted pixels
    xy: list[list[FloatArray]]  # [moment][camera] (n_people, 17, 2) undistorted normalised
    conf: list[list[FloatArray]]  # [moment][camera] (n_people, 17), 0 below min_confidence


def _flatten(frames: Sequence[Sequence[Detections2D]], cameras: list[Camera], opts: SelfCalibrationOptions) -> _Views:
    n_cams = len(cameras)
    usable = [f for f, row in enumerate(frames) if sum(len(d) > 0 for d in row) >= 2]
    if len(usable) > opts.max_moments:
        usable = [usable[i] for i in np.linspace(0, len(usable) - 1, opts.max_moments).round().astype(int)]
    keep = np.array(usable, dtype=np.intp)
    uv, xy, cf = [], [], []
    for f in keep:
        row = frames[f]
        if len(row) != n_cams:
            raise CalibrationError(f"moment {f}: {len(row)} cameras' detections, expected {n_cams}")
        ru, rx, rc = [], [], []
        for c, det in enumerate(row):
            if det.keypoints.shape[1] != N_KP:
                raise CalibrationError(f"camera {cameras[c].name}: {det.keypoints.shape[1]} keypoints; COCO-17 needed")
            k = np.where(np.isfinite(det.keypoints), det.keypoints, 0.0)
            conf = np.where(np.all(np.isfinite(det.keypoints), -1) & (det.confidences >= opts.min_confidence),
                            det.confidences, 0.0)  # fmt: skip
            ru.append(k)
            rx.append(normalized_from_pixels(cameras[c].K, cameras[c].dist, k))
            rc.append(conf)
        uv.append(ru)
        xy.append(rx)
        cf.append(rc)
    return _Views(keep, uv, xy, cf)


# -- step 1: pairs ----------------------------------------------------------------------------------------------


@dataclass
class _Pair:
    a: int
    b: int
    R: FloatArray  # a -> b
    t: FloatArray  # unit
    inliers: int
    pairings: list[tuple[int, int, int]]  # (moment index, person in a, person in b)


def _correspondences(v: _Views, a: int, b: int, pairings: list[tuple[int, int, int]]) -> tuple[FloatArray, FloatArray]:
    pa, pb = [], []
    for m, i, j in pairings:
        ok = (v.conf[m][a][i] > 0) & (v.conf[m][b][j] > 0) & _BODY
        pa.append(v.xy[m][a][i][ok])
        pb.append(v.xy[m][b][j][ok])
    if not pa:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(pa), np.concatenate(pb)


def _sampson(E: FloatArray, x1: FloatArray, x2: FloatArray) -> FloatArray:
    """Sampson distances (normalised units) of correspondences x1 (n, 2) ↔ x2 (n, 2) under E (x2ᵀ E x1 = 0)."""
    h1 = np.concatenate((x1, np.ones((len(x1), 1))), axis=1)
    h2 = np.concatenate((x2, np.ones((len(x2), 1))), axis=1)
    Ex1 = h1 @ E.T
    Etx2 = h2 @ E
    num = np.sum(h2 * Ex1, axis=1)
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    return np.asarray(np.abs(num) / np.sqrt(np.maximum(den, 1e-18)))


def _essential(
    x1: FloatArray, x2: FloatArray, thr: float, rng: np.random.Generator, cap: int = 3000
) -> tuple[FloatArray, FloatArray, FloatArray, int] | None:
    if len(x1) > cap:
        pick = rng.choice(len(x1), cap, replace=False)
        x1, x2 = x1[pick], x2[pick]
    if len(x1) < 15:
        return None
    cv2.setRNGSeed(int(rng.integers(1 << 30)))
    # prob 0.999, not 0.9999: below ~35 % inliers maxIters binds either way; above, 0.9999 only adds iterations of the
    # five-point solver (its cost, not the points') to runs that already found the model, six runs per camera pair.
    # The synthetic rig: the same calibration to 0.001° and 0.1 mm, findEssentialMat 11.8 -> 9.2 s of CPU.
    E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=thr, maxIters=1000)
    if E is None or E.shape != (3, 3):
        return None
    n, R, t, _ = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask.copy())
    return np.asarray(E, np.float64), np.asarray(R, np.float64), np.asarray(t, np.float64).reshape(3), int(n)


def _hypotheses(
    v: _Views, a: int, b: int, width: float, f: float, opts: SelfCalibrationOptions, rng: np.random.Generator
) -> list[_Pair]:
    """Candidate relative poses of cameras a and b: RANSAC run six times (three thresholds, twice each),
    the distinct outcomes (rotations more than 3° apart) best first. On short takes of one person the two-view
    problem is ambiguous (a wrong pose can have more inliers than the right one), so several are kept and the whole
    rig decides (:func:`_initialise`)."""
    single, every = [], []
    for m in range(len(v.moments)):
        na, nb = len(v.conf[m][a]), len(v.conf[m][b])
        if na == 0 or nb == 0 or na * nb > 16:
            continue
        cand = [(m, i, j) for i in range(na) for j in range(nb)]
        every += cand
        if na == 1 and nb == 1:
            single += cand
    x1, x2 = _correspondences(v, a, b, single)
    if len(x1) < 300:
        x1, x2 = _correspondences(v, a, b, every)
    out: list[_Pair] = []
    for k in range(6):
        thr = opts.ransac_threshold_px * (1.0, 2.0, 4.0)[k % 3] / f
        est = _essential(x1, x2, thr, rng)
        if est is None:
            continue
        kept = _pairings(v, a, b, est[0], opts.pair_threshold * width / f)
        x1k, x2k = _correspondences(v, a, b, kept)
        est2 = _essential(x1k, x2k, thr, rng)
        if est2 is None or est2[3] < 30:
            continue
        if all(_angle(est2[1] @ o.R.T) > 3.0 for o in out):
            out.append(_Pair(a, b, est2[1], est2[2], est2[3], kept))
    return sorted(out, key=lambda p: -p.inliers)


def _pairings(v: _Views, a: int, b: int, E: FloatArray, limit: float) -> list[tuple[int, int, int]]:
    """Each moment's people of views a and b paired (Hungarian on the median Sampson distance under E, normalised
    units), the pairings below ``limit`` kept: (moment, person in a, person in b)."""
    kept: list[tuple[int, int, int]] = []
    for m in range(len(v.moments)):
        na, nb = len(v.conf[m][a]), len(v.conf[m][b])
        if na == 0 or nb == 0:
            continue
        cost = np.full((na, nb), np.inf)
        for i in range(na):
            for j in range(nb):
                ok = (v.conf[m][a][i] > 0) & (v.conf[m][b][j] > 0) & _BODY
                if ok.sum() >= 6:
                    cost[i, j] = float(np.median(_sampson(E, v.xy[m][a][i][ok], v.xy[m][b][j][ok])))
        big = np.where(np.isfinite(cost), cost, 1e9)
        for i, j in zip(*linear_sum_assignment(big), strict=True):
            if cost[i, j] < limit:
                kept.append((m, int(i), int(j)))
    return kept


def _pair_from_poses(v: _Views, a: int, b: int, cams: list[Camera], limit: float) -> _Pair:
    """A pair's geometry from known poses (refining a calibration): E = [t]× R of the relative pose."""
    R = cams[b].R @ cams[a].R.T
    t = cams[b].t - R @ cams[a].t
    E = skew(t / max(float(np.linalg.norm(t)), 1e-12)) @ R
    kept = _pairings(v, a, b, E, limit)
    return _Pair(a, b, R, t, len(kept), kept)


# -- step 2: people across views --------------------------------------------------------------------------------


@dataclass
class _Instance:
    """One person at one moment: camera -> person index in that camera's detections."""

    moment: int
    views: dict[int, int]


def _group(v: _Views, pairs: list[_Pair], n_cams: int) -> list[_Instance]:
    parent: dict[tuple[int, int, int], tuple[int, int, int]] = {}

    def find(x: tuple[int, int, int]) -> tuple[int, int, int]:
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    degree: dict[tuple[int, int, int], int] = {}
    for p in pairs:
        for m, i, j in p.pairings:
            na, nb = (m, p.a, i), (m, p.b, j)
            degree[na] = degree.get(na, 0) + 1
            degree[nb] = degree.get(nb, 0) + 1
            ra, rb = find(na), find(nb)
            if ra != rb:
                parent[ra] = rb
    groups: dict[tuple[int, int, int], list[tuple[int, int, int]]] = {}
    for node in parent:
        groups.setdefault(find(node), []).append(node)
    out = []
    for nodes in groups.values():
        views: dict[int, int] = {}
        for _m, c, i in sorted(nodes, key=lambda n: -degree.get(n, 0)):
            views.setdefault(c, i)  # two detections of one camera: the better-linked one stays
        if len(views) >= 2:
            out.append(_Instance(nodes[0][0], views))
    out.sort(key=lambda ins: (ins.moment, min(ins.views)))
    return out


# -- observations and triangulation -----------------------------------------------------------------------------


@dataclass
class _Obs:
    """Every keypoint observation of the instances: point index, camera, pixels, normalised coordinates, weight."""

    point: IntArray
    cam: IntArray
    uv: FloatArray
    xy: FloatArray
    w: FloatArray
    n_points: int
    instance_of_point: IntArray
    kp_of_point: IntArray


def _observations(v: _Views, inst: list[_Instance]) -> _Obs:
    pt, cam, uv, xy, w = [], [], [], [], []
    for n, ins in enumerate(inst):
        m = ins.moment
        for c, i in ins.views.items():
            ok = np.flatnonzero(v.conf[m][c][i] > 0)
            pt.append(n * N_KP + ok)
            cam.append(np.full(len(ok), c))
            uv.append(v.uv[m][c][i][ok])
            xy.append(v.xy[m][c][i][ok])
            w.append(v.conf[m][c][i][ok])
    n_pts = len(inst) * N_KP
    return _Obs(
        np.concatenate(pt).astype(np.intp), np.concatenate(cam).astype(np.intp), np.concatenate(uv),
        np.concatenate(xy), np.concatenate(w), n_pts,
        np.repeat(np.arange(len(inst)), N_KP), np.tile(np.arange(N_KP), len(inst)),
    )  # fmt: skip


def _triangulate(obs: _Obs, poses: dict[int, tuple[FloatArray, FloatArray]], n_cams: int) -> FloatArray:
    """Points (n_points, 3) from the placed cameras' normalised observations (NaN where fewer than 2 views)."""
    uv = np.full((n_cams, obs.n_points, 2), np.nan)
    w = np.zeros((n_cams, obs.n_points))
    sel = np.isin(obs.cam, list(poses))
    uv[obs.cam[sel], obs.point[sel]] = obs.xy[sel]
    w[obs.cam[sel], obs.point[sel]] = obs.w[sel]
    P = np.zeros((n_cams, 3, 4))
    for c, (R, t) in poses.items():
        P[c] = np.hstack((R, t[:, None]))
    X, ok = triangulate_projections(P, uv, w)
    # In front of every camera that sees it, else not trusted.
    for c, (R, t) in poses.items():
        z = X @ R[2] + t[2]
        seen = w[c] > 0
        ok &= ~seen | (z > 0)
    X[~ok] = np.nan
    return X


# -- step 4: bundle adjustment ----------------------------------------------------------------------------------


def _bundle_adjust(
    cameras: list[Camera],
    X: FloatArray,
    obs: _Obs,
    keep: NDArray[np.bool_],
    opts: SelfCalibrationOptions,
    iterations: int = 40,
) -> tuple[list[Camera], FloatArray, FloatArray]:
    """Adjust the placed ``cameras`` and the points ``X`` (NaN: not triangulated) on the kept observations; returns
    the cameras, the points and every observation's pixel error (inf where its point is missing)."""
    pts = np.flatnonzero(np.all(np.isfinite(X), axis=1))
    remap = np.full(len(X), -1)
    remap[pts] = np.arange(len(pts))
    sel = keep & (remap[obs.point] >= 0)
    # The loss scale: the typical initial error (robust), at least 1 px.
    e0 = _pixel_errors(cameras, X, obs)[sel]
    sigma = max(1.0, 1.4826 * float(np.median(e0)) / 1.18)
    intr = 3 if opts.refine_principal_point else (1 if opts.refine_focal else 0)
    res = adjust(cameras, X[pts], obs.cam[sel], remap[obs.point[sel]], obs.uv[sel], obs.w[sel], sigma_px=sigma,
                 fixed=0, intrinsics=intr, iterations=iterations)  # fmt: skip
    Xall = np.full_like(X, np.nan)
    Xall[pts] = res.points
    return res.cameras, Xall, _pixel_errors(res.cameras, Xall, obs)


def _pixel_errors(cameras: list[Camera], X: FloatArray, obs: _Obs) -> FloatArray:
    err = np.full(len(obs.cam), np.inf)
    for c, cam in enumerate(cameras):
        s = (obs.cam == c) & np.all(np.isfinite(X[obs.point]), axis=1)
        if s.any():
            e = np.linalg.norm(cam.project(X[obs.point[s]]) - obs.uv[s], axis=1)
            err[s] = np.where(np.isfinite(e), e, np.inf)
    return err


# -- steps 5-7: scale, up, origin -------------------------------------------------------------------------------


def _leg_length(X: FloatArray) -> float:
    """Thigh + shank over every person-moment (units of X), both sides pooled: each the mean between its 10th and
    90th percentiles (robust to mis-detections; with several people, their mean, as ``height_m`` is)."""
    kp = X.reshape(-1, N_KP, 3)
    thigh, shank = [], []
    for h, k, a in _LEGS:
        thigh.append(np.linalg.norm(kp[:, h] - kp[:, k], axis=1))
        shank.append(np.linalg.norm(kp[:, k] - kp[:, a], axis=1))
    th, sh = np.concatenate(thigh), np.concatenate(shank)
    th, sh = th[np.isfinite(th)], sh[np.isfinite(sh)]
    if th.size < 10 or sh.size < 10:
        raise CalibrationError("too few legs seen by two cameras to measure the people's size: walk through the "
                               "volume where at least two cameras see your whole body")  # fmt: skip
    return _trimmed_mean(th) + _trimmed_mean(sh)


def _trimmed_mean(x: FloatArray) -> float:
    lo, hi = np.percentile(x, [10, 90])
    return float(np.mean(x[(x >= lo) & (x <= hi)]))


def _reference_sites(height: float) -> FloatArray:
    """The rest-pose COCO-17 sites of a skeleton of ``height`` standing on y = 0, shape (17, 3)."""
    sk = Skeleton.from_height(height)
    kin, tg = Kinematics(sk), coco17_targets(sk)
    theta = np.zeros((1, POSE_DIM))
    theta[0, 1] = sk.root_height
    return np.asarray(kin.targets(kin.forward(theta), tg.bones, tg.offsets)[0])


def _reference_leg(height: float) -> float:
    s = _reference_sites(height)
    return float(np.linalg.norm(s[_KP["left_hip"]] - s[_KP["left_knee"]]) +
                 np.linalg.norm(s[_KP["left_knee"]] - s[_KP["left_ankle"]]))  # fmt: skip


def _mid(kp: FloatArray, idx: list[int]) -> FloatArray:
    return np.asarray(kp[:, idx].mean(axis=1))


def _up_and_floor(X: FloatArray, ankle_height: float) -> tuple[FloatArray, float, str, FloatArray]:
    """World up (unit, scaled reconstruction), the floor's offset along it, how up was found, the low ankles."""
    kp = X.reshape(-1, N_KP, 3)
    body = _mid(kp, _SHOULDERS) - _mid(kp, _ANKLES)
    body = body[np.all(np.isfinite(body), axis=1)]
    if len(body) < 5:
        raise CalibrationError("too few people seen whole by two cameras to find the floor: walk through the volume")
    body /= np.linalg.norm(body, axis=1, keepdims=True)
    up = np.median(body, axis=0)
    up /= np.linalg.norm(up)
    body_up = up.copy()
    ank = kp[:, _ANKLES].reshape(-1, 3)
    ank = ank[np.all(np.isfinite(ank), axis=1)]
    how = "body direction"
    low = ank
    for _ in range(3):
        e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(up, e1)
        h = ank @ up
        cell = np.floor(np.stack((ank @ e1, ank @ e2), axis=1) / 0.5).astype(np.int64)
        keys = cell[:, 0] * 100003 + cell[:, 1]
        pick = np.zeros(len(ank), dtype=bool)
        for k in np.unique(keys):
            s = keys == k
            pick |= s & (h <= np.percentile(h[s], 25))
        low = ank[pick]
        if len(low) < 10:
            break
        centred = low - low.mean(axis=0)
        sv, vec = np.linalg.svd(centred, full_matrices=False)[1:]
        # A strip narrower than 0.3 m (std) across the walk does not tilt a plane reliably.
        if sv[1] / np.sqrt(len(low)) < 0.3:
            up, how = body_up, "body direction"
            break
        n = vec[2] * np.sign(vec[2] @ body_up)
        if np.degrees(np.arccos(np.clip(n @ body_up, -1, 1))) > 20.0:
            up, how = body_up, "body direction"
            break
        up, how = n, "floor plane"
    floor = float(np.median(low @ up)) - ankle_height
    return up, floor, how, low


def _world_frame(
    X: FloatArray,
    up: FloatArray,
    floor: float,
    R_first: FloatArray,
    inst: list[_Instance],
    opts: SelfCalibrationOptions,
    moments: IntArray,
) -> tuple[FloatArray, FloatArray, str]:
    """Rotation (rows: world X, Y, Z in reconstruction coordinates) and origin of the world (module doc, 7)."""
    kp = X.reshape(-1, N_KP, 3)
    feet = _mid(kp, _ANKLES)
    if opts.origin == "person" and opts.origin_moments is not None:
        lo, hi = opts.origin_moments
        idx = [n for n, ins in enumerate(inst) if lo <= moments[ins.moment] < hi]
        if not idx:
            raise CalibrationError(f"nobody seen by two cameras during moments {lo}..{hi}: the person at the origin "
                                   "must be in view of at least two cameras")  # fmt: skip
        # The person who stands still then (several people: the one whose feet stay put; walkers pass by).
        f = feet[idx]
        ok = np.all(np.isfinite(f), axis=1)
        if not ok.any():
            raise CalibrationError("the person at the origin was not seen whole by two cameras: stand where at "
                                   "least two cameras see your feet")  # fmt: skip
        near = np.linalg.norm(f[:, None] - f[None], axis=-1) < 0.25
        best = int(np.argmax(np.where(ok, near.sum(axis=1), -1)))
        mine = [n for n, close in zip(idx, near[best], strict=True) if close]
        o = np.nanmedian(feet[mine], axis=0)
        left = np.nanmedian(_mid(kp[mine], [_KP["left_hip"], _KP["left_shoulder"]]) -
                            _mid(kp[mine], [_KP["right_hip"], _KP["right_shoulder"]]), axis=0)  # fmt: skip
        forward = np.cross(left, up)
        what = f"the person at the origin during moments {lo}..{hi}, facing +Z"
    else:
        o = np.nanmedian(feet, axis=0)
        forward = R_first[2].copy()  # the first camera's optical axis in reconstruction coordinates
        what = "the middle of where people walked; +Z along the first camera's view"
    forward = forward - (forward @ up) * up
    if not np.all(np.isfinite(forward)) or np.linalg.norm(forward) < 1e-6:
        raise CalibrationError("the heading is undefined (the first camera looks straight down?): use origin 'person'")
    z = forward / np.linalg.norm(forward)
    x = np.cross(up, z)
    o = o - (o @ up - floor) * up
    return np.stack((x, up, z)), o, what


def _near(a: FloatArray, b: FloatArray) -> bool:
    return bool(np.all(np.isfinite(a)) and np.linalg.norm(a - b) < 0.6)


# -- report -----------------------------------------------------------------------------------------------------

_PARTS = [["top left", "top", "top right"], ["left", "centre", "right"], ["bottom left", "bottom", "bottom right"]]


def _coverage(cam: Camera, uv: FloatArray) -> tuple[float, list[str]]:
    def occupied(n: int) -> NDArray[np.bool_]:
        gx = np.clip((uv[:, 0] / cam.width * n).astype(int), 0, n - 1)
        gy = np.clip((uv[:, 1] / cam.height * n).astype(int), 0, n - 1)
        counts = np.zeros((n, n), dtype=int)
        np.add.at(counts, (gy, gx), 1)
        return np.asarray(counts >= 5)

    occ3 = occupied(3)
    return float(occupied(4).mean()), [_PARTS[r][c] for r in range(3) for c in range(3) if not occ3[r, c]]


def _report(
    cameras: list[Camera],
    obs: _Obs,
    keep: NDArray[np.bool_],
    err: FloatArray,
    pairs: dict[tuple[int, int], int],
    n_moments: int,
    inst: list[_Instance],
    X: FloatArray,
    height: float,
    given: bool,
    measured: float,
    up_from: str,
    origin: str,
) -> SelfCalibrationReport:
    names = [c.name for c in cameras]
    per = []
    for c, cam in enumerate(cameras):
        s = keep & (obs.cam == c) & np.isfinite(err)
        e = err[s]
        cov, empty = _coverage(cam, obs.uv[s])
        per.append(CameraQuality(
            cam.name, int(s.sum()), int(((obs.cam == c) & ~keep).sum()),
            float(np.sqrt(np.mean(e**2))) if e.size else float("nan"),
            float(np.median(e)) if e.size else float("nan"), cov, empty,
        ))  # fmt: skip
    seen = np.zeros((len(cameras), obs.n_points), dtype=bool)
    s = keep & np.isfinite(err)
    seen[obs.cam[s], obs.point[s]] = True
    shared = {(names[a], names[b]): int((seen[a] & seen[b]).sum())
              for a in range(len(cameras)) for b in range(a + 1, len(cameras))}  # fmt: skip
    feet = _mid(X.reshape(-1, N_KP, 3), _ANKLES)
    feet = feet[np.all(np.isfinite(feet), axis=1)]
    ext = np.percentile(feet, 95, axis=0) - np.percentile(feet, 5, axis=0) if len(feet) else np.zeros(3)
    rep = SelfCalibrationReport(
        per, shared, {(names[a], names[b]): n for (a, b), n in pairs.items()}, n_moments, len(inst),
        int(np.all(np.isfinite(X), axis=1).sum()), height, given, measured, up_from,
        (round(float(ext[0]), 2), round(float(ext[2]), 2)), origin,
    )  # fmt: skip
    return replace(rep, advice=_advice(rep, cameras), poor_px={c.name: 0.015 * c.width for c in cameras})


def _advice(rep: SelfCalibrationReport, cameras: list[Camera]) -> list[str]:
    out = []
    most = max(c.observations for c in rep.cameras)
    for q, cam in zip(rep.cameras, cameras, strict=True):
        if q.coverage < 0.35:
            where = f" (nobody was seen in its {', '.join(q.empty)})" if q.empty else ""
            out.append(f"{q.name}: people covered {q.coverage:.0%} of its image{where}: walk nearer {q.name} and "
                       "across its whole view")  # fmt: skip
        if q.observations < 0.25 * most:
            out.append(f"{q.name}: few keypoints shared with the other cameras ({q.observations}): walk where "
                       f"{q.name} and the others see you together (more overlap)")  # fmt: skip
        if np.isfinite(q.median_px) and q.median_px > 0.015 * cam.width:
            out.append(f"{q.name}: median reprojection error {q.median_px:.1f} px: check that the cameras are "
                       f"synchronised, its intrinsics, and that {q.name} did not move during the take")  # fmt: skip
    if rep.moments < 300:
        out.append(f"only {rep.moments} moments with people in two or more views: walk for about a minute")
    if rep.up_from != "floor plane":
        out.append("the floor's tilt was not measured from the feet (too narrow a strip of floor walked, or the feet "
                   "seldom on it): walk across the whole floor; up was taken from the people's posture")  # fmt: skip
    if not rep.height_given:
        out.append(f"the scale assumes the people are {rep.height_m:.2f} m tall on average: give their height "
                   "(--height) for a metric scale within a few per cent")  # fmt: skip
    return out


def _associate(
    v: _Views, cams: list[Camera], opts: SelfCalibrationOptions
) -> tuple[list[_Instance], _Obs, FloatArray, dict[tuple[int, int], int]]:
    """People across views under known poses: pairings of every camera pair, grouped; the observations and their
    triangulation; the pairings per camera pair."""
    n_cams = len(cams)
    pairs = []
    for a in range(n_cams):
        for b in range(a + 1, n_cams):
            f = float(np.sqrt(cams[a].K[0, 0] * cams[b].K[0, 0]))
            width = float(min(cams[a].width, cams[b].width))
            pairs.append(_pair_from_poses(v, a, b, cams, opts.pair_threshold * width / f))
    inst = _group(v, [p for p in pairs if p.pairings], n_cams)
    if not inst:
        raise CalibrationError("no two cameras see the same people: walk where at least two cameras overlap")
    obs = _observations(v, inst)
    X = _triangulate(obs, {c: (cams[c].R, cams[c].t) for c in range(n_cams)}, n_cams)
    return inst, obs, X, {(p.a, p.b): p.inliers for p in pairs}


def _subset(v: _Views, n: int) -> _Views:
    idx = np.unique(np.linspace(0, len(v.moments) - 1, min(n, len(v.moments))).round().astype(int))
    return _Views(v.moments[idx], [v.uv[i] for i in idx], [v.xy[i] for i in idx], [v.conf[i] for i in idx])


def _initialise(
    v: _Views, cameras: list[Camera], opts: SelfCalibrationOptions, rng: np.random.Generator
) -> list[Camera]:
    """Steps 1 and 3: candidate relative poses of every pair; from each of the best few, the rig grown by PnP and
    briefly adjusted on a subset of the moments; the one whose adjustment explains most keypoints wins."""
    n_cams = len(cameras)
    hyps: list[_Pair] = []
    for a in range(n_cams):
        for b in range(a + 1, n_cams):
            f = float(np.sqrt(cameras[a].K[0, 0] * cameras[b].K[0, 0]))
            hyps += _hypotheses(v, a, b, float(min(cameras[a].width, cameras[b].width)), f, opts, rng)
    if not hyps:
        raise CalibrationError("no two cameras see the same people: walk where at least two cameras overlap")
    small = _subset(v, 120)
    best: tuple[float, list[Camera]] | None = None
    failures = []
    for seed in sorted(hyps, key=lambda h: -h.inliers)[: opts.seeds]:
        try:
            cams = _grow(v, cameras, seed, opts, rng)
            _, obs, X, _ = _associate(small, cams, opts)
            cams, X, err = _bundle_adjust(cams, X, obs, np.ones(len(obs.cam), dtype=bool), opts, iterations=10)
        except CalibrationError as exc:
            failures.append(str(exc))
            continue
        limit = opts.pair_threshold * float(np.mean([c.width for c in cameras]))
        explained = float((err < limit).sum())
        if best is None or explained > best[0]:
            best = (explained, cams)
    if best is None:
        raise CalibrationError(failures[0] if failures else "no camera pair could be calibrated")
    return best[1]


def _grow(
    v: _Views, cameras: list[Camera], seed: _Pair, opts: SelfCalibrationOptions, rng: np.random.Generator
) -> list[Camera]:
    """The rig from one pair's relative pose: each next camera (the one with most candidate matches) placed by PnP
    RANSAC on every (3D person, detection) combination of its moments, then its detections assigned to the people
    they reproject onto."""
    n_cams = len(cameras)
    f_mean = float(np.mean([c.K[0, 0] for c in cameras]))
    width = float(np.mean([c.width for c in cameras]))
    poses: dict[int, tuple[FloatArray, FloatArray]] = {seed.a: (np.eye(3), np.zeros(3)), seed.b: (seed.R, seed.t)}
    inst = [_Instance(m, {seed.a: i, seed.b: j}) for m, i, j in seed.pairings]
    while True:
        obs = _observations(v, inst)
        X = _triangulate(obs, poses, n_cams).reshape(-1, N_KP, 3)
        if len(poses) == n_cams:
            break
        cand = {c: _candidates(v, inst, X, c) for c in range(n_cams) if c not in poses}
        c = max(cand, key=lambda k: len(cand[k][0]))
        obj, img, _ = cand[c]
        placed = _pnp(obj, img, opts.ransac_threshold_px * 2.0 / f_mean, rng)
        if placed is None:
            missing = [cameras[k].name for k in cand]
            raise CalibrationError(f"camera(s) {missing} share too few people with the calibrated ones: walk where "
                                   "they overlap with at least one other camera")  # fmt: skip
        poses[c] = placed
        _assign(v, inst, X, c, placed, opts.pair_threshold * width / f_mean)
    R0, t0 = poses[0] if 0 in poses else (np.eye(3), np.zeros(3))
    # Camera 0 holds the gauge in the adjustments: the poses in its frame.
    return [replace(cameras[c], R=poses[c][0] @ R0.T, t=poses[c][1] - poses[c][0] @ R0.T @ t0) for c in range(n_cams)]


def _candidates(
    v: _Views, inst: list[_Instance], X: FloatArray, c: int
) -> tuple[FloatArray, FloatArray, list[tuple[int, int]]]:
    """2D-3D matches of camera c: every triangulated person with every detection of c at that moment (body joints)."""
    obj, img, lab = [], [], []
    for n, ins in enumerate(inst):
        for j in range(len(v.conf[ins.moment][c])):
            ok = (v.conf[ins.moment][c][j] > 0) & _BODY & np.all(np.isfinite(X[n]), axis=1)
            if ok.sum() >= 4:
                obj.append(X[n][ok])
                img.append(v.xy[ins.moment][c][j][ok])
                lab.append((n, j))
    if not obj:
        return np.zeros((0, 3)), np.zeros((0, 2)), []
    return np.concatenate(obj), np.concatenate(img), lab


def _pnp(
    obj: FloatArray, img: FloatArray, thr: float, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray] | None:
    """Pose of a camera from 2D-3D matches (normalised image points): RANSAC on at most 2000 of them (its cost
    grows with every point), then Levenberg-Marquardt on every match within the threshold."""
    if len(obj) < 12:
        return None
    pick = rng.choice(len(obj), 2000, replace=False) if len(obj) > 2000 else np.arange(len(obj))
    cv2.setRNGSeed(int(rng.integers(1 << 30)))
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        obj[pick],
        img[pick],
        np.eye(3),
        None,
        reprojectionError=thr,
        iterationsCount=1000,
        confidence=0.999,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or inl is None or len(inl) < 12:
        return None
    Xc = obj @ matrix_from_rotvec(np.asarray(rvec, np.float64).reshape(3)).T + np.asarray(tvec).reshape(3)
    err = np.linalg.norm(Xc[:, :2] / np.where(Xc[:, 2:] > 1e-6, Xc[:, 2:], np.nan) - img, axis=1)
    i = np.flatnonzero(err < thr)
    if len(i) < 12:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj[i], img[i], np.eye(3), None, rvec, tvec)
    return matrix_from_rotvec(np.asarray(rvec, np.float64).reshape(3)), np.asarray(tvec, np.float64).reshape(3)


def _assign(
    v: _Views, inst: list[_Instance], X: FloatArray, c: int, pose: tuple[FloatArray, FloatArray], limit: float
) -> None:
    """Add camera c's detections to the people they reproject onto (Hungarian per moment, median error < limit)."""
    R, t = pose
    by_moment: dict[int, list[int]] = {}
    for n, ins in enumerate(inst):
        by_moment.setdefault(ins.moment, []).append(n)
    for m, ns in by_moment.items():
        nd = len(v.conf[m][c])
        if nd == 0:
            continue
        cost = np.full((len(ns), nd), np.inf)
        for r, n in enumerate(ns):
            Xc = X[n] @ R.T + t
            proj = Xc[:, :2] / np.where(Xc[:, 2:] > 1e-6, Xc[:, 2:], np.nan)
            for j in range(nd):
                ok = (v.conf[m][c][j] > 0) & _BODY & np.all(np.isfinite(proj), axis=1)
                if ok.sum() >= 4:
                    cost[r, j] = float(np.median(np.linalg.norm(proj[ok] - v.xy[m][c][j][ok], axis=1)))
        for r, j in zip(*linear_sum_assignment(np.where(np.isfinite(cost), cost, 1e9)), strict=True):
            if cost[r, j] < limit:
                inst[ns[r]].views[c] = int(j)


# -- the whole ---------------------------------------------------------------------------------------------------


def calibrate_from_people(
    frames: Sequence[Sequence[Detections2D]],
    cameras: list[Camera],
    options: SelfCalibrationOptions | None = None,
    *,
    initial: list[Camera] | None = None,
) -> SelfCalibration:
    """Calibrate ``cameras`` (their intrinsics; their poses are ignored) from people's COCO-17 detections.

    Parameters
    ----------
    frames : [moment][camera] Detections2D
        Synchronised detections: keypoints (n_people, 17, 2) in distorted pixels, confidences (n_people, 17).
    cameras : list of Camera
        Intrinsics (K, dist, width, height) and names, in the order of ``frames``' cameras.
    options : SelfCalibrationOptions
    initial : list of Camera or None
        A calibration to refine instead of starting from nothing (its poses pair the people across views and start
        the adjustment; steps 1 and 3 are skipped). Scale, up and origin are found again.

    Raises
    ------
    CalibrationError
        Fewer than two cameras, a camera that shares too few people with the others to be placed (named), or too
        few people seen whole to measure their size and the floor.
    """
    opts = options or SelfCalibrationOptions()
    n_cams = len(cameras)
    if n_cams < 2:
        raise CalibrationError("calibrating from people needs at least two cameras")
    rng = np.random.default_rng(opts.seed)
    v = _flatten(frames, cameras, opts)
    if len(v.moments) < 10:
        raise CalibrationError(f"{len(v.moments)} moments with people in two or more views; at least 10 needed "
                               "(walk through the volume for about a minute)")  # fmt: skip
    if initial is None:
        initial = _initialise(v, cameras, opts, rng)
    # Camera 0 holds the gauge in the adjustment: everything in its frame (the intrinsics are the input's).
    R0, t0 = initial[0].R, initial[0].t
    cams = [
        replace(cameras[c], R=initial[c].R @ R0.T, t=initial[c].t - initial[c].R @ R0.T @ t0) for c in range(n_cams)
    ]
    # Associate, adjust (twice, outliers dropped in between); then associate again under the adjusted poses (people
    # the first poses paired wrongly or missed) and adjust once more.
    for _ in range(opts.rounds):
        inst, obs, X, pair_counts = _associate(v, cams, opts)
        keep = np.ones(len(obs.cam), dtype=bool)
        for _ in range(2):
            cams, X, err = _bundle_adjust(cams, X, obs, keep, opts)
            e = err[keep & np.isfinite(err)]
            keep = keep & (err < max(4.0 * 1.4826 * float(np.median(e)), 2.0))
    lost = [cams[c].name for c in range(n_cams) if not np.any(keep & (obs.cam == c) & np.isfinite(err))]
    if lost:  # placed by nothing: a file with these poses would be a silent wrong answer
        raise CalibrationError(f"camera(s) {lost} keep no person after the adjustment (nothing holds their poses): "
                               "check their intrinsics, and walk where they and the others overlap")  # fmt: skip
    # Scale, up, floor, origin.
    height = opts.height_m if opts.height_m is not None else REFERENCE_HEIGHT
    measured = REFERENCE_HEIGHT * _leg_length(X) / _reference_leg(REFERENCE_HEIGHT)
    s = height / measured
    Xs = X * s
    ankle_h = float(_reference_sites(height)[_ANKLES, 1].mean())
    up, floor, up_from, _ = _up_and_floor(Xs, ankle_h)
    Rw, o, origin = _world_frame(Xs, up, floor, cams[0].R, inst, opts, v.moments)
    # X_rec = Rwᵀ X_w + o and x_cam = R X_rec + s t  →  x_cam = R Rwᵀ X_w + (R o + s t)
    out = [replace(cam, R=cam.R @ Rw.T, t=cam.R @ o + s * cam.t) for cam in cams]
    Xw = (Xs - o) @ Rw.T
    rep = _report(out, obs, keep, err, pair_counts, len(v.moments), inst, Xw, height,
                  opts.height_m is not None, measured, up_from, origin)  # fmt: skip
    return SelfCalibration(out, rep, Xw)


# -- comparison with a reference calibration ----------------------------------------------------------------------


@dataclass(frozen=True)
class CalibrationComparison:
    """A calibration against a reference of the same cameras, after the similarity that best maps the reference's
    camera centres onto the calibration's (Umeyama: rotation, translation, scale).

    Attributes
    ----------
    rotation_deg : dict
        Per camera, the angle between its orientation and the reference's (in the aligned frame).
    centre_mm : dict
        Per camera, the distance between its centre and the reference's after alignment, in the reference's mm.
    scale_error : float
        The calibration's metres per reference metre, minus 1 (0.02: the calibration's world 2 % too large).
    up_deg : float
        Angle between the calibration's +Y and the reference's +Y (the world's up, not the alignment's).
    relative_rotation_deg : float
        Largest error of any camera pair's relative rotation (independent of any alignment).
    """

    rotation_deg: dict[str, float]
    centre_mm: dict[str, float]
    scale_error: float
    up_deg: float
    relative_rotation_deg: float


def _angle(R: FloatArray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def compare_calibrations(calibration: Sequence[Camera], reference: Sequence[Camera]) -> CalibrationComparison:
    """Compare two calibrations of the same cameras (matched by name; at least three in common)."""
    ref = {c.name: c for c in reference}
    pairs = [(c, ref[c.name]) for c in calibration if c.name in ref]
    if len(pairs) < 3:
        raise CalibrationError("the comparison needs at least three cameras in both calibrations")
    A = np.array([r.center for _, r in pairs])
    B = np.array([c.center for c, _ in pairs])
    ma, mb = A.mean(axis=0), B.mean(axis=0)
    U, S, Vt = np.linalg.svd((B - mb).T @ (A - ma))
    d = np.sign(np.linalg.det(U @ Vt))
    Ra = U @ np.diag([1.0, 1.0, d]) @ Vt  # B ≈ s Ra A + tb
    s = float(np.sum(S * [1.0, 1.0, d]) / np.sum((A - ma) ** 2))
    tb = mb - s * Ra @ ma
    rot, centre = {}, {}
    for c, r in pairs:
        rot[c.name] = round(_angle(c.R @ Ra @ r.R.T), 4)
        back = Ra.T @ (c.center - tb) / s
        centre[c.name] = round(float(np.linalg.norm(back - r.center)) * 1000.0, 1)
    up = _angle_between(Ra.T @ np.array([0.0, 1.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    rel = max(_angle((ci.R @ cj.R.T) @ (ri.R @ rj.R.T).T) for ci, ri in pairs for cj, rj in pairs)
    return CalibrationComparison(rot, centre, round(s - 1.0, 5), round(up, 3), round(rel, 4))


def _angle_between(a: FloatArray, b: FloatArray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0))))

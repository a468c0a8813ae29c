"""Finger joint angles from multi-view 2D hand keypoints: one small Levenberg–Marquardt solve per hand.

Each hand is a chain of 21 hinges on the 15 bones of :mod:`mocapd.core.hand_skeleton` (:data:`HINGES`): per finger
an abduction then a flexion hinge at the MCP and one flexion hinge at each of the PIP and DIP; the thumb's
carpometacarpal joint has three (adduction in the palm's plane, palmar abduction out of it, and the roll that,
with them, makes opposition), its MCP and IP one flexion hinge each. A bone's local rotation is the product of its
hinges' rotations in order (each hinge's axis is given in the frame the previous ones left), so angles 0 are the
flat T-pose hand. The right hand's axes are the left's mirrored (an axial vector under x -> -x: (x, -y, -z)), so
an angle means the same motion on both hands: flexion positive curls toward the palm.

Unknowns (27 per hand): the 21 hinge angles, a rotation of the whole hand (right-multiplied on the hand bone's
global rotation, the body solve's as the start) and a shift of its wrist (from the body solve's wrist joint).
Cost, with every residual in units of its own standard deviation:

* **reprojection** of the 21 landmarks in every view (undistorted pixels, projection matrices, as the body solve's
  E_P), confidence-weighted, Cauchy-robust (:attr:`HandSolveOptions.cauchy_px`), per-pixel noise
  :attr:`HandSolveOptions.sigma_px`;
* **hand pose prior**: a diagonal Gaussian on the 21 angles (:data:`HINGES` mean and sigma), plus the classic
  DIP ≈ 2/3 PIP coupling of the four fingers (Rijpkema & Girard 1991, *Computer animation of knowledge-based human
  grasping*, SIGGRAPH '91) with 15° of slack. The means are a relaxed hand (fingers a little curled, MCP 20°, PIP
  25°, DIP 15°); each sigma is about a third of the joint's range. Hand-set from the ranges below, not trained
  (no hand motion data set ships with mocapd);
* **wrist**: the hand's rotation within :attr:`HandSolveOptions.wrist_rotation_sigma_deg` of the body solve's (a
  body keypoint set barely constrains the hand bone's rotation, so this is loose) and its wrist within
  :attr:`HandSolveOptions.wrist_position_sigma_m` of the body's wrist joint.

**Anatomical limits** are hard: every step is projected onto each hinge's range (:data:`HINGES` lo/hi, degrees).
Flexion ranges follow the American Academy of Orthopaedic Surgeons' normal active motion (MCP 0–90°, PIP 0–100°,
DIP 0–90°, thumb MCP 0–50°, thumb IP 0–80°, thumb palmar abduction 0–70°) widened by 5-30° of hyperextension;
abduction at the MCPs is small (±15-20°; the little finger to 30°, after the maximum spreads measured by
Chatzıoglou, Pınar & Govsa 2024: index-middle 17°, ring-little 32°).

Jacobians are analytic (each hinge rotates everything beyond its joint about its current world axis), checked
against finite differences in the tests. Pure: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core import _hand_kernel
from mocapd.core.hand_skeleton import FINGERS, LANDMARK_BONE, LANDMARK_IS_TIP, N_FINGER_BONES, HandSkeleton
from mocapd.core.rotations import matrix_from_rotvec, quat_from_matrix, skew
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_S2 = 1.0 / math.sqrt(2.0)
_THUMB_FLEX = (_S2, 0.0, -_S2)  # the left thumb's rest direction × the palm's normal (-Y): curls it palmward
_THUMB_LONG = (_S2, 0.0, _S2)
_FLEX = (0.0, 0.0, -1.0)  # the left fingers' flexion axis: +X (the finger) toward -Y (the palm)

# name, bone, axis (left hand, in the frame its earlier hinges leave), lo, hi, mean, sigma (degrees)
HINGES: tuple[tuple[str, int, tuple[float, float, float], float, float, float, float], ...] = (
    ("thumb_cmc_adduction", 0, (0.0, 1.0, 0.0), -20.0, 45.0, 5.0, 15.0),
    ("thumb_cmc_palmar", 0, _THUMB_FLEX, -15.0, 70.0, 15.0, 20.0),
    ("thumb_cmc_roll", 0, _THUMB_LONG, -30.0, 60.0, 10.0, 20.0),
    ("thumb_mcp_flexion", 1, _THUMB_FLEX, -10.0, 60.0, 15.0, 20.0),
    ("thumb_ip_flexion", 2, _THUMB_FLEX, -20.0, 80.0, 15.0, 25.0),
    *(
        hinge
        for f, finger, spread, (lo, hi) in (
            (1, "index", -1.0, (-20.0, 20.0)),  # spread positive: away from the middle finger (index: to +Z)
            (2, "middle", -1.0, (-15.0, 15.0)),  # radial (toward the thumb) positive
            (3, "ring", 1.0, (-15.0, 15.0)),
            (4, "little", 1.0, (-15.0, 30.0)),
        )
        for hinge in (
            (f"{finger}_mcp_abduction", 3 * f, (0.0, spread, 0.0), lo, hi, 0.0, 8.0),
            (f"{finger}_mcp_flexion", 3 * f, _FLEX, -30.0, 90.0, 20.0, 30.0),
            (f"{finger}_pip_flexion", 3 * f + 1, _FLEX, -5.0, 110.0, 25.0, 35.0),
            (f"{finger}_dip_flexion", 3 * f + 2, _FLEX, -10.0, 90.0, 15.0, 25.0),
        )
    ),
)
"""The 21 hinges of one hand in parameter order (see the module docstring for the numbers' sources)."""
N_HINGES = len(HINGES)
HINGE_NAMES: tuple[str, ...] = tuple(h[0] for h in HINGES)
FLEXION_HINGES: tuple[int, ...] = tuple(
    HINGE_NAMES.index(n)
    for n in ("thumb_cmc_palmar", "thumb_mcp_flexion", "thumb_ip_flexion",
              *(f"{f}_{j}_flexion" for f in ("index", "middle", "ring", "little") for j in ("mcp", "pip", "dip")))
)  # fmt: skip
"""Per finger bone (:data:`mocapd.core.hand_skeleton.FINGER_BONES` order): the hinge that flexes it."""
_COUPLED = tuple(
    (HINGE_NAMES.index(f"{f}_pip_flexion"), HINGE_NAMES.index(f"{f}_dip_flexion"))
    for f in ("index", "middle", "ring", "little")
)
_DEG = math.pi / 180.0
_BONE = np.array([h[1] for h in HINGES], dtype=np.intp)
_AXIS_LEFT = np.array([h[2] for h in HINGES], dtype=np.float64)
LOWER = np.array([h[3] for h in HINGES]) * _DEG
"""Hinge limits (radians), shape (21,)."""
UPPER = np.array([h[4] for h in HINGES]) * _DEG
PRIOR_MEAN = np.array([h[5] for h in HINGES]) * _DEG
"""The prior's mean hand (radians), shape (21,)."""
PRIOR_SIGMA = np.array([h[6] for h in HINGES]) * _DEG
_COUPLING_SIGMA = 15.0 * _DEG
_COUPLING_RATIO = 2.0 / 3.0
_PRIOR_TABLE = np.ascontiguousarray(np.stack([PRIOR_MEAN, PRIOR_SIGMA, LOWER, UPPER]))
_COUPLED_ARRAY = np.array(_COUPLED, dtype=np.intp)

# Each bone's hinges in order, padded to three slots with a hinge-free slot (index N_HINGES: identity).
_SLOTS = np.full((N_FINGER_BONES, 3), N_HINGES, dtype=np.intp)
for _b in range(N_FINGER_BONES):
    _own = np.flatnonzero(np.equal(_BONE, _b))
    _SLOTS[_b, : len(_own)] = _own
_SLOT_OF = np.array([int(np.flatnonzero(_SLOTS[b] == k)[0]) for k, b in enumerate(_BONE)], dtype=np.intp)
_LEVELS = tuple(np.arange(5) * 3 + j for j in range(3))
_LM_BONE = np.array(LANDMARK_BONE, dtype=np.intp)
_LM_TIP = np.array(LANDMARK_IS_TIP, dtype=bool)
_LM_FINGER = np.array([max(b, 0) // 3 for b in LANDMARK_BONE], dtype=np.intp)


def _depends() -> BoolArray:
    """``D[l, k]``: landmark l moves with hinge k (a joint moves with its bone's ancestors; a tip with its own bone
    too)."""
    dep = np.zeros((len(LANDMARK_BONE), N_HINGES), dtype=bool)
    for lm, (bone, tip) in enumerate(zip(LANDMARK_BONE, LANDMARK_IS_TIP, strict=True)):
        if bone < 0:
            continue
        for k, hb in enumerate(_BONE):
            same_finger = hb // 3 == bone // 3
            dep[lm, k] = same_finger and (hb < bone or (tip and hb == bone))
    return dep


_DEPENDS = _depends()
PALM_LANDMARKS: tuple[int, ...] = (0, 1, 5, 9, 13, 17)
"""The wrist, the thumb's CMC and the four MCPs: rigid with the hand bone (none moves with a hinge)."""
_MIRROR_AXIAL = np.array([1.0, -1.0, -1.0])


def hinge_axes(side: int) -> FloatArray:
    """Hinge axes (21, 3) of hand ``side`` (0 left, 1 right) in the frames their earlier hinges leave."""
    return _AXIS_LEFT if side == 0 else _AXIS_LEFT * _MIRROR_AXIAL


@dataclass(frozen=True)
class HandSolveOptions:
    """How one hand is fitted (defaults chosen on the synthetic hands of :mod:`mocapd.eval.hands`)."""

    sigma_px: float = 4.0
    """Standard deviation (pixels) of a hand keypoint: a few pixels, as the hand landmark model's."""
    cauchy_px: float = 12.0
    """Scale of the Cauchy loss on each keypoint's pixel error: errors beyond it count less and less."""
    prior_weight: float = 1.0
    """Multiplies the hand pose prior (0: none)."""
    wrist_rotation_sigma_deg: float = 45.0
    """How far the hand's rotation may stray from the body solve's hand bone."""
    wrist_position_sigma_m: float = 0.02
    """How far the hand's wrist may stray from the body solve's wrist joint."""
    min_confidence: float = 0.2
    """Keypoints below this confidence are not used."""
    min_observations: int = 12
    """Fewer usable keypoint observations (over views) than this: the hand is not solved this frame."""
    max_iterations: int = 10
    tolerance: float = 1e-4
    """Stop when a step changes no angle by more than this (radians) or the cost by less than this fraction."""

    def __post_init__(self) -> None:
        positive = ("sigma_px", "cauchy_px", "wrist_rotation_sigma_deg", "wrist_position_sigma_m", "tolerance")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"hand solve {name} must be a finite number > 0, got {value!r}")
        if not (math.isfinite(self.prior_weight) and self.prior_weight >= 0):
            raise InputError(f"hand solve prior_weight must be finite and >= 0, got {self.prior_weight!r}")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise InputError(f"hand solve min_confidence must be within [0, 1], got {self.min_confidence!r}")
        if self.max_iterations < 1 or self.min_observations < 1:
            raise InputError("hand solve max_iterations and min_observations must be >= 1")


@dataclass(frozen=True)
class HandFK:
    """One hand posed.

    Attributes
    ----------
    landmarks : array, shape (21, 3)
        World positions of the 21 landmarks (:data:`mocapd.core.hand_skeleton.HAND21`).
    local : array, shape (15, 3, 3)
        Local rotation of each finger bone.
    global_rotations : array, shape (15, 3, 3)
    joints : array, shape (15, 3)
    axes : array, shape (21, 3)
        Each hinge's world axis now.
    """

    landmarks: FloatArray
    local: FloatArray
    global_rotations: FloatArray
    joints: FloatArray
    axes: FloatArray


def _rodrigues(axes: FloatArray, angles: FloatArray) -> FloatArray:
    """Rotation matrices (n, 3, 3) about unit ``axes`` (n, 3) by ``angles`` (n,)."""
    c, s = np.cos(angles)[:, None, None], np.sin(angles)[:, None, None]
    K = np.zeros((len(angles), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axes[:, 2], axes[:, 1], -axes[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = axes[:, 2], -axes[:, 1], axes[:, 0]
    outer = axes[:, :, None] * axes[:, None, :]
    return c * np.eye(3) + s * K + (1.0 - c) * outer


def hand_fk(hand: HandSkeleton, side: int, angles: FloatArray, rotation: FloatArray, wrist: FloatArray) -> HandFK:
    """Forward kinematics of hand ``side``.

    Parameters
    ----------
    angles : array, shape (21,)
        Hinge angles (radians, :data:`HINGES` order).
    rotation : array, shape (3, 3)
        Global rotation of the body's hand bone.
    wrist : array, shape (3,)
        Its joint (the wrist) in the world (metres).
    """
    axes = hinge_axes(side)
    H = np.concatenate([_rodrigues(axes, angles), np.eye(3)[None]])  # (22, 3, 3): the last one the empty slot
    S = H[_SLOTS]  # (15, 3 slots, 3, 3)
    prefix = np.empty((N_FINGER_BONES, 4, 3, 3))  # product of a bone's first k hinges
    prefix[:, 0] = np.eye(3)
    for k in range(3):
        prefix[:, k + 1] = prefix[:, k] @ S[:, k]
    local = prefix[:, 3]
    G = np.empty((N_FINGER_BONES, 3, 3))
    J = np.empty((N_FINGER_BONES, 3))
    Gp = np.empty((N_FINGER_BONES, 3, 3))  # each bone's parent's global rotation
    offsets = hand.offsets[side]
    for level, idx in enumerate(_LEVELS):
        pg = rotation[None] if level == 0 else G[idx - 1]
        px = wrist[None] if level == 0 else J[idx - 1]
        Gp[idx] = pg
        J[idx] = px + np.einsum("nij,nj->ni", pg, offsets[idx])
        G[idx] = pg @ local[idx]
    landmarks = np.empty((len(LANDMARK_BONE), 3))
    landmarks[0] = wrist
    joints = ~_LM_TIP & (_LM_BONE >= 0)
    landmarks[joints] = J[_LM_BONE[joints]]
    distal = _LM_BONE[_LM_TIP]
    landmarks[_LM_TIP] = J[distal] + np.einsum("nij,nj->ni", G[distal], hand.tips[side])
    # hinge k's world axis: the parent's rotation, then the bone's earlier hinges, applied to its own axis
    world_axes = np.einsum("kij,kjl,kl->ki", Gp[_BONE], prefix[_BONE, _SLOT_OF], axes)
    return HandFK(landmarks, local, G, J, world_axes)


def landmark_jacobian(fk: HandFK, rotation: FloatArray, wrist: FloatArray) -> FloatArray:
    """∂landmarks/∂(angles, hand rotation δ, wrist shift), shape (21, 3, 27).

    The hand rotation is perturbed on the right (``R exp(δ)``, δ in the hand bone's frame).
    """
    out = np.zeros((len(LANDMARK_BONE), 3, N_HINGES + 6))
    pivots = fk.joints[_BONE]  # (21 hinges, 3): each hinge turns about its bone's joint
    lever = fk.landmarks[:, None, :] - pivots[None, :, :]  # (21 lm, 21 hinges, 3)
    d = np.cross(fk.axes[None, :, :], lever) * _DEPENDS[:, :, None]
    out[:, :, :N_HINGES] = d.transpose(0, 2, 1)
    rel = fk.landmarks - wrist
    out[:, :, N_HINGES : N_HINGES + 3] = -np.einsum("lij,jk->lik", skew(rel), rotation)
    out[:, :, N_HINGES + 3 :] = np.eye(3)
    return out


@dataclass(frozen=True)
class HandResult:
    """One solved hand.

    Attributes
    ----------
    angles : array, shape (21,)
        Hinge angles (radians).
    rotation : array, shape (3, 3)
        The hand bone's global rotation (the body solve's, corrected by the hand's keypoints).
    wrist : array, shape (3,)
    local : array, shape (15, 4)
        Each finger bone's local rotation, (w, x, y, z).
    iterations : int
    cost : float
    observations : int
        Keypoint observations (over views) used.
    """

    angles: FloatArray
    rotation: FloatArray
    wrist: FloatArray
    local: FloatArray
    iterations: int
    cost: float
    observations: int


class HandSolver:
    """Fits one hand (``side`` 0 left, 1 right) of a sized :class:`HandSkeleton` to its keypoints.

    ``backend``: "compiled" (:mod:`mocapd.core._hand_kernel`, the default) or "numpy" (the reference the kernel is
    tested against)."""

    def __init__(
        self, hand: HandSkeleton, side: int, options: HandSolveOptions | None = None, backend: str = "compiled"
    ) -> None:
        if side not in (0, 1):
            raise InputError(f"hand side must be 0 (left) or 1 (right), got {side!r}")
        if backend not in ("compiled", "numpy"):
            raise InputError(f"hand solver backend must be 'compiled' or 'numpy', got {backend!r}")
        self.backend = backend
        self._axes = np.ascontiguousarray(hinge_axes(side))
        self.hand = hand
        self.side = side
        self.options = options if options is not None else HandSolveOptions()

    def solve(
        self,
        projections: FloatArray,
        uv: FloatArray,
        confidences: FloatArray,
        body_rotation: FloatArray,
        body_wrist: FloatArray,
        previous: HandResult | None = None,
        start_rotation: FloatArray | None = None,
    ) -> HandResult | None:
        """The hand's angles at this frame, or None when too few keypoints were seen.

        Parameters
        ----------
        projections : array, shape (n_cams, 3, 4)
            Projection matrices (undistorted pixels).
        uv : array, shape (n_cams, 21, 2)
            Undistorted pixels of the hand's landmarks per view (NaN or confidence 0: not seen).
        confidences : array, shape (n_cams, 21)
        body_rotation : array, shape (3, 3)
            The body solve's global rotation of the hand bone (the prior's centre).
        body_wrist : array, shape (3,)
            The body solve's wrist joint.
        previous : HandResult, optional
            The last frame's solve of this hand: the warm start.
        start_rotation : array, shape (3, 3), optional
            Where the hand's rotation starts when there is no ``previous`` (e.g. :func:`palm_rotation`), else the
            body's.
        """
        o = self.options
        conf = np.where(np.isfinite(uv).all(axis=-1), np.nan_to_num(confidences), 0.0)
        conf = np.where(conf >= o.min_confidence, np.clip(conf, 0.0, 1.0), 0.0)
        n_obs = int(np.count_nonzero(conf))
        if n_obs < o.min_observations:
            return None
        uv = np.nan_to_num(uv)
        if previous is not None:
            angles, rotation, wrist = previous.angles.copy(), previous.rotation.copy(), previous.wrist.copy()
        else:
            angles = PRIOR_MEAN.copy()
            rotation = (start_rotation if start_rotation is not None else body_rotation).copy()
            wrist = body_wrist.copy()
        state = (angles, rotation, wrist)
        obs = (projections, uv, conf, body_rotation, body_wrist)
        cost, JtJ, g = self.normal_equations(state, *obs)
        lam = 1e-3
        iterations = 0
        eye = np.eye(len(g))
        while iterations < o.max_iterations:
            iterations += 1
            damped = JtJ + lam * (np.diag(np.diag(JtJ)) + 1e-9 * eye)
            step = np.asarray(np.linalg.solve(damped, -g), dtype=np.float64)
            trial = _apply(state, step)
            t_cost, t_JtJ, t_g = self.normal_equations(trial, *obs)
            if t_cost < cost:
                change = float(np.max(np.abs(trial[0] - state[0])))
                small = (cost - t_cost) < o.tolerance * cost or change < o.tolerance
                state, cost, JtJ, g = trial, t_cost, t_JtJ, t_g
                lam = max(lam / 3.0, 1e-7)
                if small:
                    break
            else:
                lam *= 4.0
                if lam > 1e6:
                    break
        angles, rotation, wrist = state
        fk = hand_fk(self.hand, self.side, angles, rotation, wrist)
        return HandResult(angles, rotation, wrist, quat_from_matrix(fk.local), iterations, float(cost), n_obs)

    def normal_equations(
        self,
        state: tuple[FloatArray, FloatArray, FloatArray],
        projections: FloatArray,
        uv: FloatArray,
        conf: FloatArray,
        body_rotation: FloatArray,
        body_wrist: FloatArray,
    ) -> tuple[float, FloatArray, FloatArray]:
        """Cost, ``JᵀJ`` (27, 27) and ``Jᵀr`` (27,) at ``state`` (angles, rotation, wrist): the compiled kernel
        (:mod:`mocapd.core._hand_kernel`), or the numpy reference with ``backend="numpy"``."""
        if self.backend == "numpy":
            cost, r, Jac = self._evaluate(state, projections, uv, conf, body_rotation, body_wrist, True)
            assert Jac is not None
            return cost, Jac.T @ Jac, Jac.T @ r
        o = self.options
        angles, rotation, wrist = state
        JtJ = np.empty((N_HINGES + 6, N_HINGES + 6))
        g = np.empty(N_HINGES + 6)
        scalars = np.array([o.prior_weight, _COUPLING_SIGMA, _COUPLING_RATIO, o.wrist_rotation_sigma_deg * _DEG,
                            o.wrist_position_sigma_m, o.sigma_px, o.cauchy_px])  # fmt: skip
        cost = _hand_kernel.evaluate(
            angles, rotation, wrist, self._axes, _SLOTS, _BONE, self.hand.offsets[self.side],
            self.hand.tips[self.side], _LM_BONE, _LM_TIP, _DEPENDS, np.ascontiguousarray(projections, dtype=np.float64),
            np.ascontiguousarray(uv, dtype=np.float64), np.ascontiguousarray(conf, dtype=np.float64), _PRIOR_TABLE,
            _COUPLED_ARRAY, scalars, np.ascontiguousarray(body_rotation, dtype=np.float64),
            np.ascontiguousarray(body_wrist, dtype=np.float64), JtJ, g,
        )  # fmt: skip
        return float(cost), JtJ, g

    def _evaluate(
        self,
        state: tuple[FloatArray, FloatArray, FloatArray],
        projections: FloatArray,
        uv: FloatArray,
        conf: FloatArray,
        body_rotation: FloatArray,
        body_wrist: FloatArray,
        jacobian: bool,
    ) -> tuple[float, FloatArray, FloatArray | None]:
        """Robust cost, whitened residuals and their Jacobian (IRLS: the Cauchy loss as per-residual weights)."""
        o = self.options
        angles, rotation, wrist = state
        fk = hand_fk(self.hand, self.side, angles, rotation, wrist)
        M, m = projections[:, :, :3], projections[:, :, 3]
        X = np.einsum("cij,lj->cli", M, fk.landmarks) + m[:, None, :]  # (n_cams, 21, 3)
        depth = X[..., 2]
        seen = (conf > 0) & (depth > 1e-3)
        z = np.where(seen, depth, 1.0)
        pred = X[..., :2] / z[..., None]
        err = np.where(seen[..., None], pred - uv, 0.0)  # (n_cams, 21, 2) pixels
        sq = np.sum(err * err, axis=-1)
        c2 = o.cauchy_px**2
        w = np.where(seen, conf, 0.0) / (1.0 + sq / c2)  # confidence × ρ'(s)
        s2 = o.sigma_px**2
        data_cost = float(np.sum(np.where(seen, conf, 0.0) * c2 * np.log1p(sq / c2)) / s2)
        sw = np.sqrt(w)[..., None] / o.sigma_px
        r_data = (err * sw).reshape(-1)
        # priors: angles, DIP-PIP coupling, hand rotation and wrist near the body's
        lp = math.sqrt(o.prior_weight)
        r_prior = lp * (angles - PRIOR_MEAN) / PRIOR_SIGMA
        pip, dip = np.array(_COUPLED).T
        r_couple = lp * (angles[dip] - _COUPLING_RATIO * angles[pip]) / _COUPLING_SIGMA
        A = body_rotation.T @ rotation  # its antisymmetric part: sin(angle)·axis, cheap and enough for a prior
        r_rot = 0.5 * np.array([A[2, 1] - A[1, 2], A[0, 2] - A[2, 0], A[1, 0] - A[0, 1]])
        r_rot /= o.wrist_rotation_sigma_deg * _DEG
        r_pos = (wrist - body_wrist) / o.wrist_position_sigma_m
        r = np.concatenate([r_data, r_prior, r_couple, r_rot, r_pos])
        cost = data_cost + float(np.sum(r[len(r_data) :] ** 2))
        if not jacobian:
            return cost, r, None
        dL = landmark_jacobian(fk, rotation, wrist)  # (21, 3, 27)
        # d(u, v)/dX of the projection: (M_row - uv · M_row3) / depth
        duv = (M[:, None, :2, :] - pred[..., :, None] * M[:, None, 2:3, :]) / z[..., None, None]  # (c, 21, 2, 3)
        J_data = np.einsum("clij,ljp->clip", duv, dL) * sw[..., None]
        n_p = N_HINGES + 6
        J_prior = np.zeros((N_HINGES, n_p))
        J_prior[np.arange(N_HINGES), np.arange(N_HINGES)] = lp / PRIOR_SIGMA
        J_couple = np.zeros((len(_COUPLED), n_p))
        J_couple[np.arange(len(_COUPLED)), dip] = lp / _COUPLING_SIGMA
        J_couple[np.arange(len(_COUPLED)), pip] = -lp * _COUPLING_RATIO / _COUPLING_SIGMA
        J_rot = np.zeros((3, n_p))
        J_rot[:, N_HINGES : N_HINGES + 3] = np.eye(3) / (o.wrist_rotation_sigma_deg * _DEG)  # small-angle
        J_pos = np.zeros((3, n_p))
        J_pos[:, N_HINGES + 3 :] = np.eye(3) / o.wrist_position_sigma_m
        Jac = np.concatenate([J_data.reshape(-1, n_p), J_prior, J_couple, J_rot, J_pos])
        return cost, r, Jac


def _apply(state: tuple[FloatArray, FloatArray, FloatArray], step: FloatArray) -> tuple[
    FloatArray, FloatArray, FloatArray]:  # fmt: skip
    """The state moved by an LM step: angles projected onto their limits, the rotation on the right."""
    angles, rotation, wrist = state
    new_angles = np.clip(angles + step[:N_HINGES], LOWER, UPPER)
    new_rotation = rotation @ matrix_from_rotvec(step[N_HINGES : N_HINGES + 3])
    return new_angles, new_rotation, wrist + step[N_HINGES + 3 :]


def palm_rotation(hand: HandSkeleton, side: int, points: FloatArray, ok: BoolArray) -> FloatArray | None:
    """The hand bone's rotation that best lays the rest hand's palm (:data:`PALM_LANDMARKS`) onto triangulated
    ``points`` (21, 3) where ``ok`` (21,) (Kabsch), or None when fewer than four palm points are known."""
    idx = [i for i in PALM_LANDMARKS if ok[i]]
    if len(idx) < 4:
        return None
    model = hand_fk(hand, side, np.zeros(N_HINGES), np.eye(3), np.zeros(3)).landmarks[idx]
    world = points[idx]
    a, b = model - model.mean(axis=0), world - world.mean(axis=0)
    U, _, Vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(U @ Vt))
    R: FloatArray = U @ np.diag([1.0, 1.0, d]) @ Vt
    return R


def finger_of_landmark(landmark: int) -> str:
    """The finger (:data:`mocapd.core.hand_skeleton.FINGERS`) a landmark belongs to ("" for the wrist)."""
    return "" if landmark == 0 else FINGERS[int(_LM_FINGER[landmark])]

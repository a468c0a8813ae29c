"""Per-person kinematic pose solver: Levenberg–Marquardt on the multi-term cost of seed 003 §3.2.

One :class:`PoseSolver` per tracked person holds the static problem (skeleton, cameras, track targets, IMU
mounts, prior, options) and preallocated buffers, and the warm-start state (previous θ and the previous two
solved IMU sites for the acceleration term). Each frame, :meth:`PoseSolver.solve` takes that frame's
:class:`Observations` and returns the new θ and a :class:`SolveSummary`.

The minimiser follows Ceres's trust-region Levenberg–Marquardt (``levenberg_marquardt_strategy.cc``,
``trust_region_minimizer.cc``): the step solves ``(JᵀJ + diag(D)/radius) δ = -Jᵀf`` with D the clamped diagonal of
``JᵀJ``; a step is accepted when its actual/model cost reduction ratio exceeds ``min_relative_decrease``,
after which ``radius /= max(1/3, 1 - (2ρ - 1)³)``; a rejected step divides the radius by a factor that doubles
with each consecutive rejection. Robust losses enter through Ceres's corrector (see :mod:`mocapd.core.loss`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from mocapd.core import _kernel
from mocapd.core.camera import Camera, stack_cameras
from mocapd.core.imu import ImuMount
from mocapd.core.keypoints import TrackTargets, coco17_targets, floor_targets
from mocapd.core.kinematics import FKState, Kinematics
from mocapd.core.loss import CauchyLoss, HuberLoss, Loss, TrivialLoss, corrector_weights
from mocapd.core.prior import PcaPrior
from mocapd.core.skeleton import POSE_DIM, Skeleton
from mocapd.core.terms import (
    CostOptions,
    PriorMatrices,
    acceleration_term,
    floor_term,
    orientation_term,
    position_term,
)
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

TERM_NAMES = ("position", "orientation", "acceleration", "prior_projection", "prior_deviation", "floor")


@dataclass(frozen=True)
class LMOptions:
    """Levenberg–Marquardt settings (names and defaults after Ceres, with a real-time iteration cap)."""

    max_iterations: int = 20
    """Cap on iterations (accepted and rejected steps), which bounds the per-frame cost."""
    function_tolerance: float = 1e-6
    """Stop when an accepted step reduces the cost by less than this fraction of it."""
    gradient_tolerance: float = 1e-10
    """Stop when the largest gradient component is below this."""
    parameter_tolerance: float = 1e-8
    """Stop when ``||δ|| <= tol (||θ|| + tol)``."""
    initial_trust_region_radius: float = 1e4
    max_trust_region_radius: float = 1e16
    min_trust_region_radius: float = 1e-32
    min_relative_decrease: float = 1e-3
    """Accept a step when actual/predicted cost reduction exceeds this."""
    min_lm_diagonal: float = 1e-6
    max_lm_diagonal: float = 1e32


class Termination(enum.Enum):
    """Why a solve stopped."""

    FUNCTION_TOLERANCE = "function_tolerance"
    GRADIENT_TOLERANCE = "gradient_tolerance"
    PARAMETER_TOLERANCE = "parameter_tolerance"
    MAX_ITERATIONS = "max_iterations"
    TRUST_REGION_COLLAPSED = "trust_region_collapsed"
    NUMERICAL_FAILURE = "numerical_failure"


@dataclass(frozen=True)
class SolveSummary:
    """What happened in one solve.

    ``converged`` is False only for a numerical failure (the previous pose was kept) — running out of
    iterations still returns the best pose found, which is normal in a real-time budget.
    """

    initial_cost: float
    final_cost: float
    iterations: int
    successful_iterations: int
    termination: Termination
    message: str = ""
    term_costs: dict[str, float] = field(default_factory=dict)

    @property
    def converged(self) -> bool:
        return self.termination is not Termination.NUMERICAL_FAILURE


@dataclass(frozen=True)
class SolveResult:
    theta: FloatArray
    """Solved pose, shape (66,)."""
    summary: SolveSummary


@dataclass(frozen=True)
class Observations:
    """One person's measurements at one solve time.

    Attributes
    ----------
    keypoints : array, shape (n_cams, n_kp, 2), optional
        Distorted pixel positions of the track targets per camera. Rows with confidence 0 are missing and may
        hold NaN.
    confidences : array, shape (n_cams, n_kp), optional
        Detector confidences w_cp in [0, 1]; 0 = missing.
    imu_orientations : array, shape (n_imu, 4), optional
        Measured global bone orientations R_gb (Eq. 8), quaternions (w, x, y, z).
    imu_accelerations : array, shape (n_imu, 3), optional
        Measured global accelerations at the *previous* frame t-1 (Eq. 12), m/s², gravity removed.
    imu_mask : bool array, shape (n_imu,), optional
        Which IMUs have a measurement (default: all). Masked rows may hold NaN.
    dt : float
        Frame period Δt (seconds) for the acceleration term.
    """

    keypoints: FloatArray | None = None
    confidences: FloatArray | None = None
    imu_orientations: FloatArray | None = None
    imu_accelerations: FloatArray | None = None
    imu_mask: BoolArray | None = None
    dt: float = 1.0 / 60.0


class _Validated:
    """Observations checked and converted to dense arrays for a given problem size."""

    def __init__(self, obs: Observations, n_cams: int, n_kp: int, n_imu: int) -> None:
        if not (np.isfinite(obs.dt) and obs.dt > 0):
            raise InputError(f"observations: dt must be a positive finite period in seconds, got {obs.dt!r}")
        self.dt = float(obs.dt)
        if obs.keypoints is None and obs.confidences is None:
            self.uv = np.zeros((n_cams, n_kp, 2))
            self.conf = np.zeros((n_cams, n_kp))
        else:
            uv = _array("keypoints", obs.keypoints, (n_cams, n_kp, 2))
            conf = _array("confidences", obs.confidences, (n_cams, n_kp))
            if not np.all(np.isfinite(conf)) or np.any(conf < 0) or np.any(conf > 1):
                raise InputError("observations: confidences must be finite and within [0, 1]")
            used = conf > 0
            if not np.all(np.isfinite(uv[used])):
                raise InputError(
                    "observations: keypoints with confidence > 0 must be finite (use confidence 0 "
                    "for missing keypoints)"
                )
            self.uv = np.where(used[..., None], uv, 0.0)
            self.conf = conf
        mask = np.ones(n_imu, dtype=bool) if obs.imu_mask is None else _bool_array("imu_mask", obs.imu_mask, (n_imu,))
        self.has_orientation = obs.imu_orientations is not None and n_imu > 0
        self.has_acceleration = obs.imu_accelerations is not None and n_imu > 0
        self.q = np.tile([1.0, 0.0, 0.0, 0.0], (n_imu, 1))
        self.acc = np.zeros((n_imu, 3))
        self.mask = mask
        if obs.imu_orientations is not None:
            q = _array("imu_orientations", obs.imu_orientations, (n_imu, 4))
            if not np.all(np.isfinite(q[mask])):
                raise InputError("observations: imu_orientations must be finite where imu_mask is set")
            norms = np.linalg.norm(q[mask], axis=-1)
            if np.any(np.abs(norms - 1.0) > 1e-3):
                raise InputError("observations: imu_orientations must be unit quaternions (w, x, y, z)")
            self.q[mask] = q[mask] / norms[:, None]
        if obs.imu_accelerations is not None:
            a = _array("imu_accelerations", obs.imu_accelerations, (n_imu, 3))
            if not np.all(np.isfinite(a[mask])):
                raise InputError("observations: imu_accelerations must be finite where imu_mask is set")
            self.acc[mask] = a[mask]


def _array(name: str, value: object, shape: tuple[int, ...]) -> FloatArray:
    if value is None:
        raise InputError(f"observations: {name} is missing (expected shape {shape})")
    a = np.asarray(value, dtype=np.float64)
    if a.shape != shape:
        raise InputError(f"observations: {name} must have shape {shape}, got {a.shape}")
    return a


def _bool_array(name: str, value: object, shape: tuple[int, ...]) -> BoolArray:
    a = np.asarray(value)
    if a.shape != shape or a.dtype != np.bool_:
        raise InputError(f"observations: {name} must be a boolean array of shape {shape}, got {a.dtype} {a.shape}")
    return a


@dataclass(frozen=True)
class _KernelProblem:
    """The static problem in the compiled kernel's argument layout (integer arrays as float64)."""

    parents: FloatArray
    offsets: FloatArray
    point_bones: FloatArray
    point_offsets: FloatArray
    n_kp: int
    n_imu: int
    K: FloatArray
    dist: FloatArray
    R: FloatArray
    t: FloatArray
    mu: FloatArray
    A_pp: FloatArray
    A_pd: FloatArray
    AtA_pp: FloatArray
    AtA_pd: FloatArray
    lambdas: FloatArray
    loss_codes: FloatArray
    loss_scales: FloatArray
    floor_radius: float
    floor_height: float


@dataclass
class _Evaluation:
    """Everything derived from one θ (reused between the cost and the Jacobian)."""

    theta: FloatArray
    fk: FKState
    points: FloatArray
    cost: float
    term_costs: dict[str, float]
    blocks: dict[str, tuple[FloatArray, FloatArray]]  # term -> (f, s=||f||² per block)


class PoseSolver:
    """Solves one person's pose per frame, warm-started from the previous frame.

    Parameters
    ----------
    skeleton : Skeleton
    cameras : list of Camera
        May be empty (IMU-only).
    targets : TrackTargets, optional
        Keypoint track targets (default COCO-17 for the skeleton's height).
    imus : sequence of ImuMount
        May be empty (video-only).
    prior : PcaPrior, optional
        Without a prior the two PCA terms are off.
    cost : CostOptions
    lm : LMOptions
    backend : "compiled" or "numpy"
        ``compiled`` (default) evaluates cost and normal equations in one numba kernel; ``numpy`` is the
        vectorised reference implementation the kernel is tested against. Both give the same iterates.
    """

    def __init__(
        self,
        skeleton: Skeleton,
        cameras: list[Camera] | tuple[Camera, ...] = (),
        targets: TrackTargets | None = None,
        imus: tuple[ImuMount, ...] | list[ImuMount] = (),
        prior: PcaPrior | None = None,
        cost: CostOptions | None = None,
        lm: LMOptions | None = None,
        backend: Literal["compiled", "numpy"] = "compiled",
    ) -> None:
        if backend not in ("compiled", "numpy"):
            raise InputError(f"solver backend must be 'compiled' or 'numpy', got {backend!r}")
        self.backend = backend
        self.skeleton = skeleton
        self.cameras = list(cameras)
        self.targets = targets if targets is not None else coco17_targets(skeleton)
        self.imus = tuple(imus)
        self.prior = prior
        self.cost_options = cost if cost is not None else CostOptions()
        self.lm = lm if lm is not None else LMOptions()
        self.kin = Kinematics(skeleton)
        self._K, self._dist, self._R, self._t = stack_cameras(self.cameras)
        self.n_cams = len(self.cameras)
        self.n_kp = len(self.targets)
        self.n_imu = len(self.imus)
        floor = floor_targets()
        self.n_floor = len(floor)
        # Point table rows: keypoint targets, IMU sites, floor targets; then angular rows for IMU bones.
        imu_bones = np.array([m.bone_index for m in self.imus], dtype=np.intp)
        imu_offsets = np.array([m.t_ib for m in self.imus]).reshape(-1, 3)
        self._point_bones = np.concatenate((self.targets.bones, imu_bones, floor.bones))
        self._point_offsets = np.concatenate((self.targets.offsets, imu_offsets, floor.offsets))
        self.n_points = len(self._point_bones)
        self._imu_bones = imu_bones
        self._sl_imu = slice(self.n_kp, self.n_kp + self.n_imu)
        self._sl_floor = slice(self.n_kp + self.n_imu, self.n_points)
        self._point_pairs = self.kin.chain_pairs(self._point_bones)
        self._angular_pairs = self.kin.chain_pairs(imu_bones)
        self.n_rows = self.n_points + self.n_imu
        self._table = np.zeros((self.n_rows, 3, POSE_DIM))
        self._prior_mats = (
            PriorMatrices.build(
                prior.M,
                prior.mu,
                prior.sigma,
                self.cost_options.lambda_prior_projection,
                self.cost_options.lambda_prior_deviation,
            )
            if prior is not None
            else None
        )
        self.theta = skeleton.rest_pose()
        self._history: list[FloatArray] = []  # solved IMU sites at t-1 (last) and t-2
        self._kernel_static = self._pack_static() if backend == "compiled" else None
        self._H = np.zeros((POSE_DIM, POSE_DIM))
        self._g = np.zeros(POSE_DIM)
        self._tc = np.zeros(len(TERM_NAMES))

    def _pack_static(self) -> _KernelProblem:
        """The static problem in the kernel's argument layout."""
        o = self.cost_options
        codes, scales = zip(*(_loss_code(self._losses()[n], n) for n in TERM_NAMES), strict=True)
        lam = [
            o.lambda_position,
            o.lambda_orientation,
            o.lambda_acceleration,
            o.lambda_prior_projection,
            o.lambda_prior_deviation,
            o.lambda_floor,
        ]
        pm = self._prior_mats
        z1, z2 = np.zeros(0), np.zeros((0, 0))
        return _KernelProblem(
            parents=np.asarray(self.skeleton.parents, dtype=np.float64),
            offsets=np.ascontiguousarray(self.skeleton.offsets),
            point_bones=self._point_bones.astype(np.float64),
            point_offsets=np.ascontiguousarray(self._point_offsets),
            n_kp=self.n_kp,
            n_imu=self.n_imu,
            K=np.ascontiguousarray(self._K),
            dist=np.ascontiguousarray(self._dist),
            R=np.ascontiguousarray(self._R),
            t=np.ascontiguousarray(self._t),
            mu=z1 if pm is None else pm.mu,
            A_pp=z2 if pm is None else pm.A_pp,
            A_pd=z2 if pm is None else pm.A_pd,
            AtA_pp=z2 if pm is None else pm.AtA_pp,
            AtA_pd=z2 if pm is None else pm.AtA_pd,
            lambdas=np.array(lam, dtype=np.float64),
            loss_codes=np.array(codes, dtype=np.float64),
            loss_scales=np.array(scales, dtype=np.float64),
            floor_radius=float(o.floor_radius),
            floor_height=float(o.floor_height),
        )

    def _kernel_call(self, theta: FloatArray, v: _Validated, on: dict[str, bool], jac: bool) -> float:
        kp = self._kernel_static
        assert kp is not None
        zeros = np.zeros((self.n_imu, 3))
        prev1 = self._history[0] if len(self._history) == 2 else zeros
        prev2 = self._history[1] if len(self._history) == 2 else zeros
        enabled = np.array([on[n] for n in TERM_NAMES], dtype=np.float64)
        return float(
            _kernel.evaluate(
                np.ascontiguousarray(theta, dtype=np.float64),
                jac,
                kp.parents,
                kp.offsets,
                kp.point_bones,
                kp.point_offsets,
                kp.n_kp,
                kp.n_imu,
                kp.K,
                kp.dist,
                kp.R,
                kp.t,
                v.uv,
                v.conf,
                v.q,
                v.acc,
                v.mask.astype(np.float64),
                prev1,
                prev2,
                v.dt,
                kp.mu,
                kp.A_pp,
                kp.A_pd,
                kp.AtA_pp,
                kp.AtA_pd,
                kp.lambdas,
                kp.loss_codes,
                kp.loss_scales,
                enabled,
                kp.floor_radius,
                kp.floor_height,
                self._H,
                self._g,
                self._tc,
            )
        )

    def _cost_only(self, theta: FloatArray, v: _Validated, on: dict[str, bool]) -> tuple[float, dict[str, float]]:
        if self._kernel_static is None:
            ev = self._evaluate(theta, v, on)
            return ev.cost, ev.term_costs
        c = self._kernel_call(theta, v, on, jac=False)
        return c, self._term_dict(on)

    def _linearize(
        self, theta: FloatArray, v: _Validated, on: dict[str, bool]
    ) -> tuple[float, dict[str, float], FloatArray, FloatArray]:
        """Cost, per-term costs and the corrected normal equations (H (66, 66), g (66,)) at θ."""
        if self._kernel_static is None:
            ev = self._evaluate(theta, v, on)
            H, g = self._normal_equations(ev, v, on)
            return ev.cost, ev.term_costs, H, g
        c = self._kernel_call(theta, v, on, jac=True)
        return c, self._term_dict(on), self._H.copy(), self._g.copy()

    def _term_dict(self, on: dict[str, bool]) -> dict[str, float]:
        return {n: float(self._tc[i]) for i, n in enumerate(TERM_NAMES) if on[n]}

    # -- state ---------------------------------------------------------------------------------------------
    def reset(self, theta: FloatArray | None = None) -> None:
        """Forget the warm start and the acceleration history; optionally set the pose to start from."""
        self.theta = self.skeleton.rest_pose() if theta is None else _check_theta(theta)
        self._history.clear()

    def imu_sites(self, theta: FloatArray) -> FloatArray:
        """World positions of the IMU sites for θ, shape (n_imu, 3)."""
        if self._kernel_static is not None:
            kp = self._kernel_static
            return np.asarray(
                _kernel.skeleton_points(
                    np.ascontiguousarray(theta, dtype=np.float64),
                    kp.parents,
                    kp.offsets,
                    self._imu_bones.astype(np.float64),
                    np.ascontiguousarray(self._point_offsets[self._sl_imu]),
                )
            )
        fk = self.kin.forward(theta)
        return self.kin.targets(fk, self._imu_bones, self._point_offsets[self._sl_imu])

    def push_history(self, theta: FloatArray) -> None:
        """Record a solved pose's IMU sites for the next frames' acceleration term."""
        self._history.insert(0, self.imu_sites(theta))
        del self._history[2:]

    # -- evaluation ----------------------------------------------------------------------------------------
    def _enabled(self, v: _Validated) -> dict[str, bool]:
        o = self.cost_options
        return {
            "position": o.use_position and self.n_cams > 0 and bool(np.any(v.conf > 0)),
            "orientation": o.use_orientation and v.has_orientation and bool(np.any(v.mask)),
            "acceleration": (
                o.use_acceleration and v.has_acceleration and bool(np.any(v.mask)) and len(self._history) == 2
            ),
            "prior_projection": o.use_prior_projection and self._prior_mats is not None,
            "prior_deviation": o.use_prior_deviation and self._prior_mats is not None,
            "floor": o.use_floor,
        }

    def _losses(self) -> dict[str, Loss]:
        o = self.cost_options
        return {
            "position": o.loss_position,
            "orientation": o.loss_orientation,
            "acceleration": o.loss_acceleration,
            "prior_projection": o.loss_prior_projection,
            "prior_deviation": o.loss_prior_deviation,
            "floor": o.loss_floor,
        }

    def _linearize_terms(
        self,
        theta: FloatArray,
        fk: FKState,
        points: FloatArray,
        v: _Validated,
        on: dict[str, bool],
        jac: bool,
    ) -> dict[str, tuple[FloatArray, FloatArray | None]]:
        """Residual blocks (n, k) and their G (n, k, 3) — or dense J (n, k, 66) for the prior terms."""
        o = self.cost_options
        out: dict[str, tuple[FloatArray, FloatArray | None]] = {}
        if on["position"]:
            f, G, _ = position_term(
                points[: self.n_kp],
                self._K,
                self._dist,
                self._R,
                self._t,
                v.uv,
                v.conf,
                o.lambda_position,
                jac,
            )
            out["position"] = (f.reshape(-1, 2), None if G is None else G.reshape(-1, 2, 3))
        if on["orientation"]:
            f, G = orientation_term(fk.rotations[self._imu_bones], v.q, v.mask, o.lambda_orientation, jac)
            out["orientation"] = (f, G)
        if on["acceleration"]:
            f, G = acceleration_term(
                points[self._sl_imu],
                self._history[0],
                self._history[1],
                v.acc,
                v.mask,
                v.dt,
                o.lambda_acceleration,
            )
            out["acceleration"] = (f, G)
        if on["floor"]:
            f, G = floor_term(points[self._sl_floor], o.floor_radius, o.floor_height, o.lambda_floor)
            out["floor"] = (f, G)
        pm = self._prior_mats
        if pm is not None:
            d = theta[6:] - pm.mu
            if on["prior_projection"]:
                out["prior_projection"] = ((pm.A_pp @ d)[None, :], pm.A_pp[None] if jac else None)
            if on["prior_deviation"]:
                out["prior_deviation"] = ((pm.A_pd @ d)[None, :], pm.A_pd[None] if jac else None)
        return out

    def _evaluate(self, theta: FloatArray, v: _Validated, on: dict[str, bool]) -> _Evaluation:
        fk = self.kin.forward(theta)
        points = self.kin.targets(fk, self._point_bones, self._point_offsets)
        terms = self._linearize_terms(theta, fk, points, v, on, jac=False)
        losses = self._losses()
        total = 0.0
        term_costs: dict[str, float] = {}
        blocks: dict[str, tuple[FloatArray, FloatArray]] = {}
        for name, (f, _) in terms.items():
            s = np.einsum("ij,ij->i", f, f)
            rho = losses[name].evaluate(s)[0]
            c = 0.5 * float(np.sum(rho))
            term_costs[name] = c
            blocks[name] = (f, s)
            total += c
        return _Evaluation(theta, fk, points, total, term_costs, blocks)

    def _normal_equations(self, ev: _Evaluation, v: _Validated, on: dict[str, bool]) -> tuple[FloatArray, FloatArray]:
        """``H = J~ᵀJ~`` (66, 66) and ``g = J~ᵀf~`` (66,) at the evaluated pose."""
        theta, fk = ev.theta, ev.fk
        terms = self._linearize_terms(theta, fk, ev.points, v, on, jac=True)
        losses = self._losses()
        H3 = np.zeros((self.n_rows, 3, 3))
        g3 = np.zeros((self.n_rows, 3))
        H = np.zeros((POSE_DIM, POSE_DIM))
        g = np.zeros(POSE_DIM)
        for name, (f, G) in terms.items():
            assert G is not None
            s = ev.blocks[name][1]
            _, rho1, rho2 = losses[name].evaluate(s)
            w, beta = corrector_weights(s, rho1, rho2)
            if name.startswith("prior"):
                self._add_dense(H, g, f[0], G[0], float(w[0]), float(beta[0]), name)
                continue
            gp = np.einsum("nki,nk->ni", G, f)  # Gᵀf per block
            Hb = np.einsum("n,nki,nkj->nij", w, G, G)
            if np.any(beta != 0.0):
                Hb -= (w * beta)[:, None, None] * gp[:, :, None] * gp[:, None, :]
            gb = w[:, None] * gp
            if name == "position":  # blocks are (camera, keypoint): sum over cameras onto keypoint rows
                H3[: self.n_kp] += Hb.reshape(self.n_cams, self.n_kp, 3, 3).sum(axis=0)
                g3[: self.n_kp] += gb.reshape(self.n_cams, self.n_kp, 3).sum(axis=0)
            elif name == "acceleration":
                H3[self._sl_imu] += Hb
                g3[self._sl_imu] += gb
            elif name == "floor":
                H3[self._sl_floor] += Hb
                g3[self._sl_floor] += gb
            else:  # orientation: angular rows
                H3[self.n_points :] += Hb
                g3[self.n_points :] += gb
        table = self._jacobian_table(theta, fk, ev.points)
        T = table.reshape(self.n_rows * 3, POSE_DIM)
        H += T.T @ (H3 @ table).reshape(self.n_rows * 3, POSE_DIM)
        g += T.T @ g3.reshape(-1)
        return H, g

    def _add_dense(
        self, H: FloatArray, g: FloatArray, f: FloatArray, A: FloatArray, w: float, beta: float, name: str
    ) -> None:
        pm = self._prior_mats
        assert pm is not None
        AtA = pm.AtA_pp if name == "prior_projection" else pm.AtA_pd
        gp = A.T @ f
        Hb = w * AtA
        if beta != 0.0:
            Hb = Hb - w * beta * np.outer(gp, gp)
        H[6:, 6:] += Hb
        g[6:] += w * gp

    def _jacobian_table(self, theta: FloatArray, fk: FKState, points: FloatArray) -> FloatArray:
        """Rows: ∂(point)/∂θ for every point-table entry, then ∂ω/∂θ for IMU bones; shape (n_rows, 3, 66)."""
        axes = self.kin.angular_axes(fk, theta)
        self.kin.point_jacobian(fk, axes, points, self._point_pairs, out=self._table[: self.n_points])
        self.kin.angular_jacobian(axes, self._angular_pairs, self.n_imu, out=self._table[self.n_points :])
        return self._table

    # -- public API -----------------------------------------------------------------------------------------
    def term_jacobians(self, theta: FloatArray, obs: Observations) -> dict[str, tuple[FloatArray, FloatArray]]:
        """Each enabled term's residual blocks and dense Jacobian at θ (for tests and diagnostics).

        Returns
        -------
        dict term name -> (f (n, k), J (n, k, 66))
        """
        theta = _check_theta(theta)
        v = _Validated(obs, self.n_cams, self.n_kp, self.n_imu)
        on = self._enabled(v)
        fk = self.kin.forward(theta)
        points = self.kin.targets(fk, self._point_bones, self._point_offsets)
        terms = self._linearize_terms(theta, fk, points, v, on, jac=True)
        table = self._jacobian_table(theta, fk, points).copy()
        rows = {
            "position": np.tile(np.arange(self.n_kp), self.n_cams),
            "orientation": np.arange(self.n_points, self.n_rows),
            "acceleration": np.arange(self.n_kp, self.n_kp + self.n_imu),
            "floor": np.arange(self.n_kp + self.n_imu, self.n_points),
        }
        out: dict[str, tuple[FloatArray, FloatArray]] = {}
        for name, (f, G) in terms.items():
            assert G is not None
            if name.startswith("prior"):
                J = np.zeros((1, f.shape[1], POSE_DIM))
                J[0, :, 6:] = G[0]
            else:
                J = G @ table[rows[name]]
            out[name] = (f, J)
        return out

    def term_residuals(self, theta: FloatArray, obs: Observations) -> dict[str, FloatArray]:
        """Each enabled term's residual blocks at θ, shape (n, k) per term."""
        theta = _check_theta(theta)
        v = _Validated(obs, self.n_cams, self.n_kp, self.n_imu)
        return {k: f for k, (f, _) in self._evaluate(theta, v, self._enabled(v)).blocks.items()}

    def cost(self, theta: FloatArray, obs: Observations) -> tuple[float, dict[str, float]]:
        """Total cost ``½ Σ ρ(||f||²)`` and its split per term at θ."""
        theta = _check_theta(theta)
        v = _Validated(obs, self.n_cams, self.n_kp, self.n_imu)
        ev = self._evaluate(theta, v, self._enabled(v))
        return ev.cost, ev.term_costs

    def solve(self, obs: Observations, theta0: FloatArray | None = None, update_state: bool = True) -> SolveResult:
        """Solve one frame.

        Parameters
        ----------
        obs : Observations
        theta0 : array, shape (66,), optional
            Start pose; default the previous solution (warm start).
        update_state : bool
            Keep the result as the next warm start and push it into the acceleration history.
        """
        v = _Validated(obs, self.n_cams, self.n_kp, self.n_imu)
        start = self.theta if theta0 is None else _check_theta(theta0)
        result = self._minimize(start.copy(), v)
        if update_state:
            self.theta = result.theta
            self.push_history(result.theta)
        return result

    def _minimize(self, x: FloatArray, v: _Validated) -> SolveResult:
        lm = self.lm
        on = self._enabled(v)
        cost, term_costs, H, g = self._linearize(x, v, on)
        initial = cost
        if not np.isfinite(initial):
            return SolveResult(
                x,
                SolveSummary(
                    initial,
                    initial,
                    0,
                    0,
                    Termination.NUMERICAL_FAILURE,
                    "cost is not finite at the start pose; previous pose kept",
                ),
            )
        radius = lm.initial_trust_region_radius
        decrease = 2.0
        iterations = successful = 0
        reason = Termination.MAX_ITERATIONS
        message = ""
        while iterations < lm.max_iterations:
            if not (np.all(np.isfinite(H)) and np.all(np.isfinite(g))):
                reason, message = Termination.NUMERICAL_FAILURE, "non-finite Jacobian"
                break
            if float(np.max(np.abs(g))) <= lm.gradient_tolerance:
                reason = Termination.GRADIENT_TOLERANCE
                break
            iterations += 1
            # (H + diag(clip(diag H)) / radius) δ = -g, Cholesky; not positive definite -> more damping.
            step, model_reduction, ok = _kernel.lm_step(H, g, radius, lm.min_lm_diagonal, lm.max_lm_diagonal)
            if not (ok and np.all(np.isfinite(step))):
                radius /= decrease
                decrease *= 2.0
                if radius < lm.min_trust_region_radius:
                    reason, message = Termination.NUMERICAL_FAILURE, "linear solve failed repeatedly"
                    break
                continue
            if float(np.linalg.norm(step)) <= lm.parameter_tolerance * (
                float(np.linalg.norm(x)) + lm.parameter_tolerance
            ):
                reason = Termination.PARAMETER_TOLERANCE
                break
            trial = x + step
            trial_cost, trial_terms = self._cost_only(trial, v, on)
            actual = cost - trial_cost
            rel = actual / model_reduction if model_reduction > 0 else -1.0
            # A step counts only when it is accepted: rejected steps change the damping, not the pose.
            if np.isfinite(trial_cost) and rel > lm.min_relative_decrease:
                successful += 1
                x, cost, term_costs = trial, trial_cost, trial_terms
                radius = min(radius / max(1.0 / 3.0, 1.0 - (2.0 * rel - 1.0) ** 3), lm.max_trust_region_radius)
                decrease = 2.0
                if actual <= lm.function_tolerance * (cost + actual):
                    reason = Termination.FUNCTION_TOLERANCE
                    break
                cost, term_costs, H, g = self._linearize(x, v, on)
            else:
                radius /= decrease
                decrease *= 2.0
                if radius < lm.min_trust_region_radius:
                    reason = Termination.TRUST_REGION_COLLAPSED
                    break
        if reason is Termination.NUMERICAL_FAILURE or not np.all(np.isfinite(x)):
            return SolveResult(
                self.theta.copy(),
                SolveSummary(
                    initial,
                    initial,
                    iterations,
                    successful,
                    Termination.NUMERICAL_FAILURE,
                    message or "non-finite pose; previous pose kept",
                ),
            )
        return SolveResult(x, SolveSummary(initial, cost, iterations, successful, reason, message, term_costs))


def _loss_code(loss: Loss, term: str) -> tuple[int, float]:
    """The compiled kernel's code and scale for a loss object."""
    if isinstance(loss, TrivialLoss):
        return _kernel.LOSS_TRIVIAL, 1.0
    if isinstance(loss, CauchyLoss):
        return _kernel.LOSS_CAUCHY, float(loss.scale)
    if isinstance(loss, HuberLoss):
        return _kernel.LOSS_HUBER, float(loss.scale)
    raise InputError(
        f"the compiled solver backend supports Trivial, Cauchy and Huber losses; the {term} term "
        f"has {type(loss).__name__} (use backend='numpy' for custom losses)"
    )


def _check_theta(theta: FloatArray) -> FloatArray:
    a = np.asarray(theta, dtype=np.float64)
    if a.shape != (POSE_DIM,):
        raise InputError(f"pose θ must have shape ({POSE_DIM},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError("pose θ contains non-finite values")
    return a


def solve_many(solvers: list[PoseSolver], observations: list[Observations]) -> list[SolveResult]:
    """Solve several people for one frame (one independent solve per person, seed 003 §3.2)."""
    if len(solvers) != len(observations):
        raise InputError(f"solve_many: {len(solvers)} solvers but {len(observations)} observations")
    return [s.solve(o) for s, o in zip(solvers, observations, strict=True)]

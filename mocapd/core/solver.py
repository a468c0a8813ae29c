"""Per-person kinematic pose solver: Levenberg–Marquardt on the multi-term cost of seed 003 §3.2.

One :class:`PoseSolver` per tracked person holds the static problem (skeleton, cameras, track targets, IMU
mounts, prior, options) and preallocated buffers, and the warm-start state (previous θ and the previous two
solved IMU sites for the acceleration term). Each frame, :meth:`PoseSolver.solve` takes that frame's
:class:`Observations` and returns the new θ and a :class:`SolveSummary`.

The minimiser is :func:`mocapd.core.lm.levenberg_marquardt` (Ceres's trust-region LM). Robust losses enter through
Ceres's corrector (see :mod:`mocapd.core.loss`). Cost and normal equations come from the compiled kernel
(:mod:`mocapd.core._kernel`) or from the vectorised numpy reference in this module and :mod:`mocapd.core.terms`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from mocapd.core import _kernel, _learned_kernel, _lm_kernel
from mocapd.core.camera import Camera, stack_cameras, triangulate
from mocapd.core.ground import (
    FOOT_SENSOR_BONES,
    REACH_POINTS,
    GroundOptions,
    GroundTracker,
    sole_points,
    standing_heights,
)
from mocapd.core.imu import ImuMount
from mocapd.core.keypoints import TrackTargets, coco17_targets, floor_targets
from mocapd.core.kinematics import FKState, Kinematics
from mocapd.core.lm import LMOptions, Termination, levenberg_marquardt
from mocapd.core.loss import CauchyLoss, HuberLoss, Loss, TrivialLoss, corrector_weights
from mocapd.core.observations import Observations, ValidatedObservations
from mocapd.core.prior import PcaPrior
from mocapd.core.rotations import rotvec_principal
from mocapd.core.skeleton import BONE_INDEX, N_BONES, POSE_DIM, Skeleton
from mocapd.core.terms import (
    CostOptions,
    PriorMatrices,
    acceleration_term,
    floor_term,
    learned_joint_term,
    orientation_term,
    position_term,
)
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "LEARNED_TERM",
    "TERM_NAMES",
    "LMOptions",
    "Observations",
    "PoseSolver",
    "SolveResult",
    "SolveSummary",
    "Termination",
    "solve_many",
]

TERM_NAMES = ("position", "orientation", "acceleration", "prior_projection", "prior_deviation", "floor")
LEARNED_TERM = "learned"
"""E_J, the learned 3D joint observations (issue 30). It is not one of the compiled kernel's terms: its normal
equations are added to the kernel's (:mod:`mocapd.core._learned_kernel`) or the numpy reference's
(:meth:`PoseSolver._learned`), and only on frames whose observations carry joint estimates, so a solve without
them is the seed-003 solve unchanged."""


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
    kept_alternative: bool = False
    """The objective rated the ``alternative`` pose given to :meth:`PoseSolver.solve` lower: it is the result."""

    @property
    def converged(self) -> bool:
        return self.termination is not Termination.NUMERICAL_FAILURE


@dataclass(frozen=True)
class SolveResult:
    theta: FloatArray
    """Solved pose, shape (66,)."""
    summary: SolveSummary


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
    ground : GroundOptions, optional
        How the root is placed when fewer than ``ground.reference_views`` cameras see the person (foot
        contacts, :mod:`mocapd.core.ground`); default on when both legs wear a sensor below the knee.
        ``GroundOptions(enabled=False)``: the LM's root.
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
        ground: GroundOptions | None = None,
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
        self._joint_bones = np.arange(N_BONES, dtype=np.intp)
        self._joint_pairs = self.kin.chain_pairs(self._joint_bones)
        self._joint_table = np.zeros((N_BONES, 3, POSE_DIM))
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
        self._lm_options: tuple[LMOptions, FloatArray] | None = None  # self.lm as the compiled loop takes it
        self._prev_root: FloatArray | None = None  # root translation of the solve before the last one
        self._has_solved = False
        self._had_reference = False  # the last solve had an absolute position reference (enough cameras)
        self._kernel_static = self._pack_static() if backend == "compiled" else None
        #: compiled backend: the LM loop compiled too (:mod:`mocapd.core._lm_kernel`); False runs the Python loop
        #: around the same kernels (the reference the tests compare it with)
        self.compiled_loop = True
        self.ground_options = ground if ground is not None else GroundOptions()
        self._hips_imu = next((i for i, m in enumerate(self.imus) if m.bone == "Hips"), None)
        self._foot_imus = [next((i for i, m in enumerate(self.imus) if m.bone == b), None) for b in FOOT_SENSOR_BONES]
        # The feet's contact points, then each foot sensor's site (the foot bone's origin where there is none: its
        # row is not used) — one forward-kinematics pass gives both.
        bones, offsets = sole_points(skeleton, self.ground_options)
        self._n_contacts = bones.size
        site_bones = [self.imus[i].bone_index if i is not None else BONE_INDEX[b]
                      for i, b in zip(self._foot_imus, FOOT_SENSOR_BONES, strict=True)]  # fmt: skip
        site_offsets = [self.imus[i].t_ib if i is not None else np.zeros(3) for i in self._foot_imus]
        self._contact_bones = np.concatenate([bones.reshape(-1), site_bones]).astype(np.intp)
        self._contact_offsets = np.concatenate([offsets.reshape(-1, 3), site_offsets])
        self.ground = (
            GroundTracker(
                standing_heights(self._foot_points(skeleton.rest_pose())[0]),
                self.cost_options.floor_height,
                self.ground_options,
                reach=REACH_POINTS,
            )
            if self.ground_options.enabled and _legs_measured(self.imus)
            else None
        )
        self._H = np.zeros((POSE_DIM, POSE_DIM))
        self._g = np.zeros(POSE_DIM)
        self._H_learned = np.zeros((POSE_DIM, POSE_DIM))
        self._g_learned = np.zeros(POSE_DIM)
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

    def _kernel_call(self, theta: FloatArray, v: ValidatedObservations, on: dict[str, bool], jac: bool) -> float:
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

    def _cost_only(
        self, theta: FloatArray, v: ValidatedObservations, on: dict[str, bool]
    ) -> tuple[float, dict[str, float]]:
        if self._kernel_static is None:
            ev = self._evaluate(theta, v, on)
            return ev.cost, ev.term_costs
        c = self._kernel_call(theta, v, on, jac=False)
        terms = self._term_dict(on)
        if on[LEARNED_TERM]:
            cl = self._learned_compiled(theta, v, jac=False)
            terms[LEARNED_TERM] = cl
            c += cl
        return c, terms

    def _linearize(
        self, theta: FloatArray, v: ValidatedObservations, on: dict[str, bool]
    ) -> tuple[float, dict[str, float], FloatArray, FloatArray]:
        """Cost, per-term costs and the corrected normal equations (H (66, 66), g (66,)) at θ."""
        if self._kernel_static is None:
            ev = self._evaluate(theta, v, on)
            H, g = self._normal_equations(ev, v, on)
            return ev.cost, ev.term_costs, H, g
        c = self._kernel_call(theta, v, on, jac=True)
        terms = self._term_dict(on)
        H, g = self._H.copy(), self._g.copy()
        if on[LEARNED_TERM]:
            cl = self._learned_compiled(theta, v, jac=True)
            terms[LEARNED_TERM] = cl
            c += cl
            H += self._H_learned
            g += self._g_learned
        return c, terms, H, g

    def _learned_compiled(self, theta: FloatArray, v: ValidatedObservations, jac: bool) -> float:
        """E_J by the compiled kernel (:mod:`mocapd.core._learned_kernel`): its cost, and with ``jac`` its normal
        equations in ``self._H_learned``, ``self._g_learned``."""
        kp = self._kernel_static
        assert kp is not None
        o = self.cost_options
        code, scale = _loss_code(o.loss_learned, LEARNED_TERM)
        return float(
            _learned_kernel.learned_term(
                np.ascontiguousarray(theta, dtype=np.float64),
                jac,
                kp.parents,
                kp.offsets,
                v.joints,
                v.joint_weights,
                float(o.lambda_learned),
                code,
                scale,
                self._H_learned,
                self._g_learned,
            )
        )

    def _learned(
        self, theta: FloatArray, v: ValidatedObservations, fk: FKState | None, jac: bool
    ) -> tuple[float, FloatArray, FloatArray]:
        """E_J's cost and, with ``jac``, its corrected normal equations (H (66, 66), g (66,)) at θ.

        Every block is one joint (3 residuals) whose Jacobian is the joint's row of the kinematic chain; the
        Gauss–Newton blocks are spread with the same Ceres corrector as the other terms."""
        o = self.cost_options
        fk = self.kin.forward(theta) if fk is None else fk
        f, G = learned_joint_term(fk.positions, v.joints, v.joint_weights, o.lambda_learned)
        s = np.einsum("ij,ij->i", f, f)
        rho, rho1, rho2 = o.loss_learned.evaluate(s)
        cost = 0.5 * float(np.sum(rho))
        H = np.zeros((POSE_DIM, POSE_DIM))
        g = np.zeros(POSE_DIM)
        if not jac:
            return cost, H, g
        w, beta = corrector_weights(s, rho1, rho2)
        gp = np.einsum("nki,nk->ni", G, f)
        Hb = np.einsum("n,nki,nkj->nij", w, G, G) - (w * beta)[:, None, None] * gp[:, :, None] * gp[:, None, :]
        gb = w[:, None] * gp
        axes = self.kin.angular_axes(fk, theta)
        J = self.kin.point_jacobian(fk, axes, fk.positions, self._joint_pairs, out=self._joint_table)
        H += np.einsum("nai,nab,nbj->ij", J, Hb, J)
        g += np.einsum("nai,na->i", J, gb)
        return cost, H, g

    def _term_dict(self, on: dict[str, bool]) -> dict[str, float]:
        return {n: float(self._tc[i]) for i, n in enumerate(TERM_NAMES) if on[n]}

    # -- state ---------------------------------------------------------------------------------------------
    def set_camera(self, index: int, camera: Camera) -> None:
        """Camera ``index`` is ``camera`` from the next solve on (a recalibrated camera); the warm start, the
        acceleration history and the ground contacts are kept: the person has not moved."""
        if not 0 <= index < self.n_cams:
            raise InputError(f"solver: no camera {index} (it has {self.n_cams})")
        self.cameras[index] = camera
        self._K, self._dist, self._R, self._t = stack_cameras(self.cameras)
        if self._kernel_static is not None:
            self._kernel_static = replace(
                self._kernel_static,
                K=np.ascontiguousarray(self._K), dist=np.ascontiguousarray(self._dist),
                R=np.ascontiguousarray(self._R), t=np.ascontiguousarray(self._t),
            )  # fmt: skip

    def reset(self, theta: FloatArray | None = None) -> None:
        """Forget the warm start and the acceleration history; optionally set the pose to start from."""
        self.theta = self.skeleton.rest_pose() if theta is None else _check_theta(theta)
        self._history.clear()
        self._prev_root = None
        self._has_solved = False
        self._had_reference = False
        if self.ground is not None:
            self.ground.reset()

    def _prediction(self) -> FloatArray:
        """Warm start: the previous pose, with the root translation extrapolated at constant velocity.

        Joint rotations start from the previous solve (seed 003 §3.2.6). Holding the root still instead would
        start every frame with a spurious deceleration of v/Δt in the acceleration term. The velocity is only
        extrapolated between two solves that both had an absolute position reference (enough cameras): without
        one, nothing in the cost corrects the root, and a velocity fed back frame after frame never decays (the
        floor term's upward pushes ran a real recording's root up by 1.6 m in 25 s).
        """
        theta = self.theta.copy()
        if self._prev_root is not None:
            theta[:3] += theta[:3] - self._prev_root
        return theta

    def _recentre(self, theta: FloatArray, v: ValidatedObservations) -> FloatArray:
        """Cameras see the person again after a stretch without them: move the warm start's root so that its
        keypoint targets sit on the triangulated keypoints (median shift). The root may have drifted by decimetres
        meanwhile, further than the robust reprojection term pulls back in one frame's iterations; the published
        root still moves there gradually (:class:`~mocapd.core.ground.GroundTracker`)."""
        X, ok = triangulate(self.cameras, v.uv, v.conf)
        if int(ok.sum()) < 3:
            return theta
        pred = self.keypoint_positions(theta)
        out = theta.copy()
        out[:3] += np.median(X[ok] - pred[ok], axis=0)
        return out

    def _foot_points(self, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The sole points of both feet (:func:`~mocapd.core.ground.sole_points`), world positions, shape
        (2, k, 3), and each foot sensor's site, shape (2, 3) (NaN for a foot without a sensor)."""
        pts = self.points(theta, self._contact_bones, self._contact_offsets)
        sites = pts[self._n_contacts :].copy()
        sites[[i is None for i in self._foot_imus]] = np.nan
        return pts[: self._n_contacts].reshape(2, -1, 3), sites

    def _foot_accelerations(self, v: ValidatedObservations) -> FloatArray:
        """Each foot sensor's free acceleration (world, m/s², the previous frame's), NaN without one; shape
        (2, 3)."""
        out = np.full((2, 3), np.nan)
        if not v.has_acceleration:
            return out
        for f, i in enumerate(self._foot_imus):
            if i is not None and v.mask[i]:
                out[f] = v.acc[i]
        return out

    def _hips_acceleration(self, v: ValidatedObservations) -> FloatArray | None:
        """The hips sensor's free acceleration (world, m/s², the previous frame's), or None."""
        i = self._hips_imu
        if i is None or not v.has_acceleration or not v.mask[i]:
            return None
        return np.asarray(v.acc[i].copy())

    def _place_root(self, tracker: GroundTracker, theta: FloatArray, v: ValidatedObservations) -> FloatArray:
        """The ground tracker's step for a solved θ: returns the published θ, and sets θ's root (in place) to
        the one to keep."""
        feet, sites = self._foot_points(theta)
        hips = None if self._hips_imu is None else self.imu_sites(theta)[self._hips_imu] - theta[:3]
        root, published = tracker.step(
            theta[:3],
            feet - theta[:3],
            self._views(v),
            v.dt,
            self._foot_accelerations(v),
            self._hips_acceleration(v),
            sites - theta[:3],
            hips,
        )
        theta[:3] = root
        out = theta.copy()
        out[:3] = published
        return out

    def points(self, theta: FloatArray, bones: NDArray[np.intp], offsets: FloatArray) -> FloatArray:
        """World positions of points ``(bone, offset)`` for θ, shape (n, 3): the compiled forward kinematics when the
        solver has them (the numpy path costs ~10x more per call, and the scheduler asks on every tick).

        Parameters
        ----------
        bones : int array, shape (n,)
        offsets : array, shape (n, 3)
            In the bone's frame (m).
        """
        kp = self._kernel_static
        if kp is None:
            return self.kin.targets(self.kin.forward(theta), bones, offsets)
        return np.asarray(
            _kernel.skeleton_points(np.ascontiguousarray(theta, dtype=np.float64), kp.parents, kp.offsets,
                                    bones.astype(np.float64), np.ascontiguousarray(offsets))
        )  # fmt: skip

    def keypoint_positions(self, theta: FloatArray) -> FloatArray:
        """World positions of the track targets (keypoints) for θ, shape (n_kp, 3)."""
        return self.points(theta, self.targets.bones, self.targets.offsets)

    def imu_sites(self, theta: FloatArray) -> FloatArray:
        """World positions of the IMU sites for θ, shape (n_imu, 3)."""
        if not self.n_imu:  # a camera-only person (every solve pushes its history): no kernel call for no points
            return np.zeros((0, 3))
        return self.points(theta, self._imu_bones, self._point_offsets[self._sl_imu])

    def push_history(self, theta: FloatArray) -> None:
        """Record a solved pose's IMU sites for the next frames' acceleration term."""
        self._history.insert(0, self.imu_sites(theta))
        del self._history[2:]

    # -- evaluation ----------------------------------------------------------------------------------------
    def _enabled(self, v: ValidatedObservations) -> dict[str, bool]:
        o = self.cost_options
        return {
            "position": o.use_position and self.n_cams > 0 and bool(np.any(v.conf > 0)),
            "orientation": o.use_orientation and v.has_orientation and bool(np.any(v.mask)),
            "acceleration": (
                o.use_acceleration
                and v.has_acceleration
                and bool(np.any(v.mask))
                and len(self._history) == 2
                and self._views(v) >= o.acceleration_min_views
            ),
            "prior_projection": o.use_prior_projection and self._prior_mats is not None,
            "prior_deviation": o.use_prior_deviation and self._prior_mats is not None,
            "floor": o.use_floor,
            LEARNED_TERM: o.use_learned and v.has_joints and bool(np.any(v.joint_weights > 0)),
        }

    def _views(self, v: ValidatedObservations) -> int:
        """Cameras that see the person (at least one keypoint with confidence > 0) this frame."""
        return int(np.count_nonzero((v.conf > 0).any(axis=1))) if self.n_cams and self.cost_options.use_position else 0

    def _losses(self) -> dict[str, Loss]:
        o = self.cost_options
        return {
            "position": o.loss_position,
            "orientation": o.loss_orientation,
            "acceleration": o.loss_acceleration,
            "prior_projection": o.loss_prior_projection,
            "prior_deviation": o.loss_prior_deviation,
            "floor": o.loss_floor,
            LEARNED_TERM: o.loss_learned,
        }

    def _linearize_terms(
        self,
        theta: FloatArray,
        fk: FKState,
        points: FloatArray,
        v: ValidatedObservations,
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
        if on[LEARNED_TERM]:
            out[LEARNED_TERM] = learned_joint_term(fk.positions, v.joints, v.joint_weights, o.lambda_learned)
        pm = self._prior_mats
        if pm is not None:
            d = theta[6:] - pm.mu
            if on["prior_projection"]:
                out["prior_projection"] = ((pm.A_pp @ d)[None, :], pm.A_pp[None] if jac else None)
            if on["prior_deviation"]:
                out["prior_deviation"] = ((pm.A_pd @ d)[None, :], pm.A_pd[None] if jac else None)
        return out

    def _evaluate(self, theta: FloatArray, v: ValidatedObservations, on: dict[str, bool]) -> _Evaluation:
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

    def _normal_equations(
        self, ev: _Evaluation, v: ValidatedObservations, on: dict[str, bool]
    ) -> tuple[FloatArray, FloatArray]:
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
            if name == LEARNED_TERM:  # its own rows (the joints), added below
                continue
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
        if on[LEARNED_TERM]:
            _, Hl, gl = self._learned(theta, v, fk, jac=True)
            H += Hl
            g += gl
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
        v = ValidatedObservations(obs, self.n_cams, self.n_kp, self.n_imu)
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
            if name == LEARNED_TERM:
                joints = self.kin.point_jacobian(fk, self.kin.angular_axes(fk, theta), fk.positions, self._joint_pairs)
                out[name] = (f, G @ joints)
                continue
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
        v = ValidatedObservations(obs, self.n_cams, self.n_kp, self.n_imu)
        return {k: f for k, (f, _) in self._evaluate(theta, v, self._enabled(v)).blocks.items()}

    def cost(self, theta: FloatArray, obs: Observations) -> tuple[float, dict[str, float]]:
        """Total cost ``½ Σ ρ(||f||²)`` and its split per term at θ."""
        theta = _check_theta(theta)
        v = ValidatedObservations(obs, self.n_cams, self.n_kp, self.n_imu)
        ev = self._evaluate(theta, v, self._enabled(v))
        return ev.cost, ev.term_costs

    def solve(
        self,
        obs: Observations,
        theta0: FloatArray | None = None,
        update_state: bool = True,
        alternative: FloatArray | None = None,
    ) -> SolveResult:
        """Solve one frame.

        Parameters
        ----------
        obs : Observations
        theta0 : array, shape (66,), optional
            Start pose; default the previous solution (warm start).
        update_state : bool
            Keep the result as the next warm start and push it into the acceleration history.
        alternative : array, shape (66,), optional
            A pose solved for this frame before (``resolve``: the live solve of the same observations). Where the
            objective rates it lower than the pose LM converged to from ``theta0``, it is the result (and the next
            warm start): LM descends to the nearest minimum of its start, so a longer solve that started elsewhere
            can end in a worse one. :attr:`SolveSummary.final_cost` is then the alternative's.
        """
        v = ValidatedObservations(obs, self.n_cams, self.n_kp, self.n_imu)
        start = self._prediction() if theta0 is None else _check_theta(theta0)
        if self._has_solved and not self._had_reference and self._views(v) >= self.ground_options.reference_views:
            # Cameras see the person again: the acceleration history holds the sites of solves without a position
            # reference (drifted); E_A would pull the root along that path. It restarts from this solve.
            self._history.clear()
            if theta0 is None:
                start = self._recentre(start, v)
        result = self._minimize(start.copy(), v)
        if alternative is not None and result.summary.converged:
            result = self._better_of(result, _check_theta(alternative), v)
        theta = principal_pose(result.theta)
        published = theta
        if self.ground is not None and result.summary.converged:
            tracker = self.ground if update_state else self.ground.copy()
            theta = theta.copy()
            published = self._place_root(tracker, theta, v)
        elif (
            self.ground_options.enabled
            and self.n_imu > 0
            and self._has_solved
            and result.summary.converged
            and self._views(v) == 0
        ):
            # A suit with legs without sensors and no camera: nothing measures where the feet are, so nothing may
            # move the root (the floor term would push it up whenever the prior folds the legs under the floor).
            theta = theta.copy()
            theta[:3] = self.theta[:3]
            published = theta
        if update_state:
            reference = self._views(v) >= self.ground_options.reference_views
            self._prev_root = self.theta[:3].copy() if self._has_solved and reference and self._had_reference else None
            self._has_solved = True
            self._had_reference = reference
            self.theta = theta
            self.push_history(theta)
        return SolveResult(published, result.summary)

    def _better_of(self, result: SolveResult, alternative: FloatArray, v: ValidatedObservations) -> SolveResult:
        """``result``, or ``alternative`` where the objective (the terms the solve minimised) is lower there."""
        on = self._enabled(v)
        mine = self._evaluate(result.theta, v, on).cost
        other = self._evaluate(alternative, v, on)
        if not other.cost < mine:
            return result
        summary = replace(
            result.summary, final_cost=other.cost, term_costs=dict(other.term_costs), kept_alternative=True
        )
        return SolveResult(alternative.copy(), summary)

    def _minimize(self, x: FloatArray, v: ValidatedObservations) -> SolveResult:
        on = self._enabled(v)
        if self._kernel_static is not None and self.compiled_loop and not on[LEARNED_TERM]:
            return self._minimize_compiled(x, v, on)

        def linearize(theta: FloatArray) -> tuple[float, FloatArray, FloatArray, dict[str, float]]:
            cost, terms, H, g = self._linearize(theta, v, on)
            return cost, H, g, terms

        def cost_only(theta: FloatArray) -> tuple[float, dict[str, float]]:
            return self._cost_only(theta, v, on)

        r = levenberg_marquardt(x, linearize, cost_only, self.lm)
        failed = r.termination is Termination.NUMERICAL_FAILURE
        summary = SolveSummary(
            initial_cost=r.initial_cost,
            final_cost=r.final_cost,
            iterations=r.iterations,
            successful_iterations=r.successful_iterations,
            termination=r.termination,
            message=f"{r.message}; previous pose kept" if failed else r.message,
            term_costs={} if failed else r.info,
        )
        return SolveResult(self.theta.copy() if failed else r.x, summary)

    def _minimize_compiled(self, x: FloatArray, v: ValidatedObservations, on: dict[str, bool]) -> SolveResult:
        """The whole LM solve in one compiled call that releases the interpreter lock
        (:mod:`mocapd.core._lm_kernel`; the learned term's solves keep the Python loop)."""
        kp = self._kernel_static
        assert kp is not None
        zeros = np.zeros((self.n_imu, 3))
        prev1 = self._history[0] if len(self._history) == 2 else zeros
        prev2 = self._history[1] if len(self._history) == 2 else zeros
        enabled = np.array([on[n] for n in TERM_NAMES], dtype=np.float64)
        if self._lm_options is None or self._lm_options[0] is not self.lm:  # LMOptions is frozen: once per object
            self._lm_options = (self.lm, np.array([getattr(self.lm, f) for f in _lm_kernel.OPTION_FIELDS],
                                                  dtype=np.float64))  # fmt: skip
        options = self._lm_options[1]
        out = np.empty(POSE_DIM)
        stats = np.empty(6)
        _lm_kernel.lm_solve(
            np.ascontiguousarray(x, dtype=np.float64), options, kp.parents, kp.offsets, kp.point_bones,
            kp.point_offsets, kp.n_kp, kp.n_imu, kp.K, kp.dist, kp.R, kp.t, v.uv, v.conf, v.q, v.acc,
            v.mask.astype(np.float64), prev1, prev2, v.dt, kp.mu, kp.A_pp, kp.A_pd, kp.AtA_pp, kp.AtA_pd,
            kp.lambdas, kp.loss_codes, kp.loss_scales, enabled, kp.floor_radius, kp.floor_height, out, self._tc, stats,
        )  # fmt: skip
        termination = _TERMINATIONS[int(stats[4])]
        failed = termination is Termination.NUMERICAL_FAILURE
        message = _lm_kernel.FAILURE_MESSAGES[int(stats[5])] or ("non-finite point" if failed else "")
        summary = SolveSummary(
            initial_cost=float(stats[0]),
            final_cost=float(stats[1]),
            iterations=int(stats[2]),
            successful_iterations=int(stats[3]),
            termination=termination,
            message=f"{message}; previous pose kept" if failed else message,
            term_costs={} if failed else self._term_dict(on),
        )
        return SolveResult(self.theta.copy() if failed else out, summary)


_TERMINATIONS = tuple(Termination(name) for name in _lm_kernel.TERMINATIONS)
"""The compiled loop's termination codes as :class:`~mocapd.core.lm.Termination` members, looked up once."""


def _legs_measured(imus: tuple[ImuMount, ...]) -> bool:
    """Whether both legs wear a sensor below the knee (shank or foot): only then are the feet where the solve puts
    them, and only then can foot contacts place the root (an upper-body suit's legs follow the prior, a seated
    musician's folded legs would walk the root away)."""
    bones = {m.bone for m in imus}
    return all(bool({f"{side}LowerLeg", f"{side}Foot"} & bones) for side in ("Left", "Right"))


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


def principal_pose(theta: FloatArray) -> FloatArray:
    """``theta`` (66,) with every bone's rotation vector wound back to an angle of at most π (the same pose).

    The minimiser steps in rotation-vector space, where a joint can wind past π and on by whole turns: the IMU and
    keypoint terms see the same rotation, but the pose prior (a Gaussian over θ) sees a vector far from every pose
    it knows, where its Cauchy loss is flat. A solve started far from the body (the rest pose while a suit's first
    sensors stream, or samples of different instants) wound joints that no sensor fixes — spine, neck, hands, toes
    — by up to tens of turns, and with the prior no longer pulling, the warm start kept that pose for good
    (the IMU-only demo at 110-190 mm joint error instead of 50 mm). Winding back after every solve keeps the prior
    meaningful; the pose itself does not change.
    """
    out = theta.copy()
    out[3:] = rotvec_principal(theta[3:].reshape(-1, 3)).reshape(-1)
    return out


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

"""The cost terms of seed 003 §3.2, each with its analytic Jacobian.

Every term produces residual *blocks* ``f`` of shape (n_blocks, k); the solver minimises
``½ Σ_blocks ρ_term(||f||²)``. The weight λ sits inside the block (``f = sqrt(λ w) e``), so ``ρ(λ w ||e||²)``
matches the seeds' ``ρ(λ w ||·||²)``.

Kinematic terms are *chain terms*: each block depends on θ only through one row of a Jacobian table — a 3-D
point on the skeleton (keypoint target, IMU site, floor target) or a bone's global rotation (angular row). A
chain term returns ``G`` (n_blocks, k, 3), the derivative of its block w.r.t. that 3-D quantity, and the table
row of each block; the full Jacobian is ``G @ table[row]`` (n_blocks, k, 66). The solver uses this structure
so that, e.g., 8 cameras cost no more in the 66×66 normal equations than one (seed 003 §3.2.6 exploits the
same kinematic-chain sparsity with parameter blocks).

Terms (seed 003):

- ``E_P``  (Eq. 7)  2D reprojection of keypoint targets, confidence-weighted, Cauchy.
- ``E_R``  (Eq. 10) vector part of the relative quaternion between solved and measured bone orientation, L2.
- ``E_A``  (Eq. 13) finite-difference acceleration over t, t-1, t-2 (previous solves fixed) against the
  measured global acceleration at t-1 (gravity removed by Eq. 12), Cauchy.
- ``E_PP`` (Eq. 14) PCA projection residual of θ̄, Cauchy (one block).
- ``E_PD`` (Eq. 15) PCA deviation (Mahalanobis) of θ̄, Cauchy (one block).
- ``E_FP`` (Eq. 16) floor penetration of feet and toes with radius r. The seed writes a Heaviside step H(·),
  which has no useful gradient; we use the hinge ``max(0, r - y)`` that the step gates, L2.

Beyond seed 003 (issue 30):

- ``E_J`` learned 3D joint observations: ``sqrt(λ_J w_j) (x_j - y_j)`` between each solved joint and the learned
  fusion's estimate of it (seed 001's network, :mod:`mocapd.pipeline.fusion`), Cauchy. Off unless the observations
  carry joint targets.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import project_points
from mocapd.core.loss import CauchyLoss, Loss, TrivialLoss
from mocapd.core.rotations import quat_conjugate, quat_from_matrix, quat_multiply, skew

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class CostOptions:
    """Weights, losses and switches of the cost terms.

    The defaults are mocapd's: the values the shipped ``config.toml`` carries (a test holds the two equal, so a
    library user and the daemon solve the same problem). They are seed 003 §3.2.6's except λ_R and λ_A, re-tuned
    on the accuracy harness's development split (``docs/accuracy.md``): with the seed's λ_R = 1, keypoint noise
    overrides the IMU orientations (on a real MTw recording, 18-20° knee error instead of 4-6°).
    :meth:`seed_003` gives the seed's weights.
    """

    lambda_position: float = 1e-3
    """λ_P: weight of the 2D reprojection term (pixels²)."""
    lambda_orientation: float = 100.0
    """λ_R: weight of the IMU orientation term (seed 003: 1)."""
    lambda_acceleration: float = 1e-4
    """λ_A: weight of the IMU acceleration term ((m/s²)²) (seed 003: 1e-3)."""
    lambda_prior_projection: float = 0.7
    """λ_PP: weight of the PCA projection prior."""
    lambda_prior_deviation: float = 0.06
    """λ_PD: weight of the PCA deviation prior."""
    lambda_floor: float = 10.0
    """λ_FP: weight of the floor-penetration term (metres²)."""
    loss_position: Loss = field(default_factory=CauchyLoss)
    loss_orientation: Loss = field(default_factory=TrivialLoss)
    loss_acceleration: Loss = field(default_factory=CauchyLoss)
    loss_prior_projection: Loss = field(default_factory=CauchyLoss)
    loss_prior_deviation: Loss = field(default_factory=CauchyLoss)
    loss_floor: Loss = field(default_factory=TrivialLoss)
    acceleration_min_views: int = 2
    """E_A is used only in frames where at least this many cameras see the person (0: always, as the seed).

    The acceleration term double-integrates each IMU site from the previous two solves. With an absolute
    position reference (E_P from two or more views) the sites cannot drift; without one, every site integrates
    its own sensor noise and the body is bent to follow them (measured on the 0-camera benchmark rig: 0.56 m
    root-relative joint error with E_A, 0.024 m without).
    """
    floor_radius: float = 0.05
    """r_p: collision radius of the floor targets (metres)."""
    floor_height: float = 0.0
    """Floor level (world y, metres)."""
    use_position: bool = True
    use_orientation: bool = True
    use_acceleration: bool = True
    use_prior_projection: bool = True
    use_prior_deviation: bool = True
    use_floor: bool = True
    lambda_learned: float = 100.0
    """λ_J: weight of the learned 3D joint observations (metres²), used only when observations carry them
    (``[fusion] mode = "both"``: the daemon sets it from ``[fusion] weight``)."""
    loss_learned: Loss = field(default_factory=lambda: CauchyLoss(1.0))
    use_learned: bool = True

    @classmethod
    def seed_003(cls) -> CostOptions:
        """The weights of seed 003 §3.2.6 (λP=1e-3, λR=1, λA=1e-3, λPP=0.7, λPD=0.06, λFP=10), other options as
        the defaults."""
        return cls(lambda_orientation=1.0, lambda_acceleration=1e-3)


@dataclass
class ChainLinearization:
    """Residual blocks of a chain term and their derivative w.r.t. table quantities.

    Attributes
    ----------
    f : array, shape (n, k)
    G : array, shape (n, k, 3)
    rows : int array, shape (n,)
        Row of the Jacobian table each block depends on.
    """

    f: FloatArray
    G: FloatArray
    rows: IntArray


def position_term(
    points: FloatArray,
    K: FloatArray,
    dist: FloatArray,
    R: FloatArray,
    t: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    lam: float,
    jacobian: bool,
) -> tuple[FloatArray, FloatArray | None, BoolArray]:
    """E_P blocks ``sqrt(λ w) (π_c(x_p) - t_cp)``.

    Parameters
    ----------
    points : (n_kp, 3) keypoint targets in the world.
    K, dist, R, t : stacked cameras (n_cams, ...).
    uv : (n_cams, n_kp, 2) measured pixels; conf : (n_cams, n_kp) confidences w_cp in [0, 1].

    Returns
    -------
    f : (n_cams, n_kp, 2); G : (n_cams, n_kp, 2, 3) or None; used : (n_cams, n_kp) blocks that count.
    """
    proj, J, valid = project_points(K, dist, R, t, points, jacobian)
    used = valid & (conf > 0.0)
    s = np.sqrt(lam * np.where(used, conf, 0.0))
    f = (proj - uv) * s[..., None]
    f[~used] = 0.0
    if J is None:
        return f, None, used
    G = J * s[..., None, None]
    G[~used] = 0.0
    return f, G, used


def orientation_term(
    bone_rotations: FloatArray, measured: FloatArray, mask: BoolArray, lam: float, jacobian: bool
) -> tuple[FloatArray, FloatArray | None]:
    """E_R blocks ``sqrt(λ) ψ(R̂⁻¹ R_meas)`` (vector part of the relative quaternion, sign with w >= 0).

    The derivative is w.r.t. a global (world-frame) rotation ω of the solved bone, ``R̂ ← exp(ω) R̂``:
    with ``q_e = q̂* ⊗ q_m = (w_e, v_e)``, ``∂ψ/∂ω = (-w_e I + [v_e]×) R̂ᵀ / 2``.

    Parameters
    ----------
    bone_rotations : (n_imu, 3, 3) solved global bone rotations.
    measured : (n_imu, 4) measured global bone orientations (Eq. 8).
    mask : (n_imu,) which IMUs have a measurement this frame.

    Returns
    -------
    f : (n_imu, 3); G : (n_imu, 3, 3) or None.
    """
    q_hat = quat_from_matrix(bone_rotations)
    q_e = quat_multiply(quat_conjugate(q_hat), np.where(mask[:, None], measured, q_hat))
    sign = np.where(q_e[:, :1] < 0.0, -1.0, 1.0)
    q_e = q_e * sign
    sl = np.sqrt(lam)
    f = sl * q_e[:, 1:]
    f[~mask] = 0.0
    if not jacobian:
        return f, None
    w = q_e[:, 0, None, None]
    D = -w * np.eye(3) + skew(q_e[:, 1:])
    G = 0.5 * sl * (D @ np.transpose(bone_rotations, (0, 2, 1)))
    G[~mask] = 0.0
    return f, G


def acceleration_term(
    sites: FloatArray,
    prev1: FloatArray,
    prev2: FloatArray,
    measured: FloatArray,
    mask: BoolArray,
    dt: float,
    lam: float,
) -> tuple[FloatArray, FloatArray]:
    """E_A blocks ``sqrt(λ) ((x_t - 2 x_{t-1} + x_{t-2}) / Δt² - a_meas(t-1))``.

    Parameters
    ----------
    sites : (n_imu, 3) IMU sites at t; prev1, prev2 : (n_imu, 3) solved sites at t-1 and t-2 (fixed).
    measured : (n_imu, 3) measured global acceleration at t-1 (Eq. 12).
    mask : (n_imu,) which IMUs have a measurement.

    Returns
    -------
    f : (n_imu, 3); G : (n_imu, 3, 3).
    """
    sl = np.sqrt(lam)
    inv = 1.0 / (dt * dt)
    acc = (sites - 2.0 * prev1 + prev2) * inv
    f = sl * (acc - np.where(mask[:, None], measured, acc))
    G = np.broadcast_to(sl * inv * np.eye(3), (sites.shape[0], 3, 3)).copy()
    G[~mask] = 0.0
    return f, G


def floor_term(points: FloatArray, radius: float, floor: float, lam: float) -> tuple[FloatArray, FloatArray]:
    """E_FP blocks ``sqrt(λ) max(0, r - (y - floor))``.

    Parameters
    ----------
    points : (n, 3) floor targets in the world.

    Returns
    -------
    f : (n, 1); G : (n, 1, 3).
    """
    sl = np.sqrt(lam)
    pen = radius - (points[:, 1] - floor)
    active = pen > 0.0
    f = (sl * np.where(active, pen, 0.0))[:, None]
    G = np.zeros((points.shape[0], 1, 3))
    G[active, 0, 1] = -sl
    return f, G


def learned_joint_term(
    joints: FloatArray, targets: FloatArray, weights: FloatArray, lam: float
) -> tuple[FloatArray, FloatArray]:
    """E_J blocks ``sqrt(λ w_j) (x_j - y_j)``: solved joints against learned 3D joint estimates.

    Parameters
    ----------
    joints : (n, 3) solved joint positions; targets : (n, 3) learned estimates; weights : (n,) w_j >= 0.

    Returns
    -------
    f : (n, 3); G : (n, 3, 3) (derivative w.r.t. the joint position).
    """
    s = np.sqrt(lam * weights)
    f = s[:, None] * (joints - np.where(weights[:, None] > 0, targets, joints))
    G = s[:, None, None] * np.eye(3)
    return f, G


@dataclass(frozen=True)
class PriorMatrices:
    """Constant matrices of the two PCA prior terms for given weights (θ̄ = θ[6:]).

    ``f_PP = A_pp (θ̄ - μ)`` with ``A_pp = sqrt(λ_PP) (I - M Mᵀ)``;
    ``f_PD = A_pd (θ̄ - μ)`` with ``A_pd = sqrt(λ_PD) diag(σ)⁻¹ Mᵀ``.
    """

    mu: FloatArray
    A_pp: FloatArray
    A_pd: FloatArray
    AtA_pp: FloatArray
    AtA_pd: FloatArray

    @classmethod
    def build(cls, M: FloatArray, mu: FloatArray, sigma: FloatArray, lam_pp: float, lam_pd: float) -> PriorMatrices:
        n = M.shape[0]
        A_pp = np.sqrt(lam_pp) * (np.eye(n) - M @ M.T)
        A_pd = np.sqrt(lam_pd) * (M / sigma).T
        return cls(mu=mu, A_pp=A_pp, A_pd=A_pd, AtA_pp=A_pp.T @ A_pp, AtA_pd=A_pd.T @ A_pd)

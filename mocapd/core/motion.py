"""Recorded motion of an arbitrary source skeleton (BVH, ASF/AMC, MVNX), before retargeting.

A :class:`SourceMotion` is a tree of joints. Joint ``j`` sits at ``x_j = x_p + G_p · offset_j(t)`` and has the
global rotation ``G_j = G_p · L_j(t)``, so ``L_j`` rotates the offsets of ``j``'s children (BVH semantics; the
ASF/AMC reader converts its bone-segment semantics to this). Everything is in metres, Y up, in the source's
world frame. Readers live in :mod:`mocapd.io`; this module is pure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.rotations import matrix_from_quat, quat_from_rotvec, quat_normalize, rotvec_from_quat
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SourceMotion:
    """A motion clip on its own skeleton.

    Attributes
    ----------
    name : str
        Clip name (usually the file stem).
    joint_names : tuple of str, length n
    parents : tuple of int, length n
        Parent index of each joint (-1 for the root); parents precede children.
    translations : array, shape (n_frames, n, 3)
        Local translation of each joint in its parent's frame (metres); for the root, its world position.
    rotations : array, shape (n_frames, n, 4)
        Local rotation quaternions (w, x, y, z).
    end_sites : array, shape (n, 3)
        End-site offset of leaf joints in their own frame (metres; zero when the file has none).
    fps : float
        Frame rate (Hz).
    """

    name: str
    joint_names: tuple[str, ...]
    parents: tuple[int, ...]
    translations: FloatArray
    rotations: FloatArray
    end_sites: FloatArray
    fps: float

    def __post_init__(self) -> None:
        n = len(self.joint_names)
        if len(self.parents) != n or any(p >= i for i, p in enumerate(self.parents)):
            raise InputError(f"motion {self.name!r}: parents must precede children ({n} joints)")
        tr = np.asarray(self.translations, dtype=np.float64)
        rot = np.asarray(self.rotations, dtype=np.float64)
        if tr.ndim != 3 or tr.shape[1:] != (n, 3) or rot.shape != (tr.shape[0], n, 4) or tr.shape[0] < 1:
            raise InputError(
                f"motion {self.name!r}: translations (f, {n}, 3) and rotations (f, {n}, 4) expected, "
                f"got {tr.shape} and {rot.shape}"
            )
        if not (np.all(np.isfinite(tr)) and np.all(np.isfinite(rot))):
            raise InputError(f"motion {self.name!r}: non-finite channel values")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise InputError(f"motion {self.name!r}: frame rate must be positive, got {self.fps!r}")
        object.__setattr__(self, "translations", tr)
        object.__setattr__(self, "rotations", quat_normalize(rot))
        object.__setattr__(self, "end_sites", np.asarray(self.end_sites, dtype=np.float64).reshape(n, 3))

    @property
    def n_frames(self) -> int:
        return int(self.translations.shape[0])

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def index(self, name: str) -> int:
        """Index of a joint by name (case-insensitive)."""
        low = [j.lower() for j in self.joint_names]
        try:
            return low.index(name.lower())
        except ValueError as exc:
            raise InputError(f"motion {self.name!r} has no joint {name!r}") from exc

    def forward(self) -> tuple[FloatArray, FloatArray]:
        """Global joint rotations (f, n, 3, 3) and positions (f, n, 3)."""
        L = matrix_from_quat(self.rotations)
        G = np.empty_like(L)
        x = np.empty_like(self.translations)
        for j, p in enumerate(self.parents):
            if p < 0:
                G[:, j] = L[:, j]
                x[:, j] = self.translations[:, j]
            else:
                G[:, j] = G[:, p] @ L[:, j]
                x[:, j] = x[:, p] + np.einsum("fij,fj->fi", G[:, p], self.translations[:, j])
        return G, x

    def resample(self, fps: float = 60.0) -> SourceMotion:
        """The clip at another frame rate, same duration.

        Translations and (sign-continuous) rotation quaternions are interpolated with Catmull-Rom cubics, then
        the quaternions renormalised: unlike linear interpolation / slerp, this keeps velocities continuous, so
        the second differences that simulate accelerometers have no spikes at the original samples.
        """
        if not (np.isfinite(fps) and fps > 0):
            raise InputError(f"resample: frame rate must be positive, got {fps!r}")
        if self.n_frames < 2 or abs(fps - self.fps) < 1e-9:
            return self
        duration = (self.n_frames - 1) / self.fps
        t = np.arange(int(np.floor(duration * fps + 1e-9)) + 1) / fps
        q = self.rotations.copy()
        for i in range(1, self.n_frames):  # sign continuity along time
            flip = np.sum(q[i] * q[i - 1], axis=-1) < 0
            q[i, flip] *= -1.0
        tr = _catmull_rom(self.translations, t * self.fps)
        rot = quat_normalize(_catmull_rom(q, t * self.fps))
        return SourceMotion(self.name, self.joint_names, self.parents, tr, rot, self.end_sites, fps)


def time_grid(first_ns: int, last_ns: int, rate_hz: float, origin_ns: int | None = None) -> NDArray[np.int64]:
    """The instants ``origin_ns + k / rate_hz`` (ns, each rounded on its own) from ``first_ns`` through ``last_ns``,
    both ends included where they are on the grid (within 1 µs); ``origin_ns`` defaults to ``first_ns``.

    Each instant is rounded on its own rather than summed from a rounded period: at 60 Hz a period of 16 666 667 ns
    is 1/3 ns long, and a 3006-sample take's last sample (50.0833 s on) fell 1 µs beyond the grid and had no pose.
    """
    origin = first_ns if origin_ns is None else origin_ns
    step = 1e9 / rate_hz
    k0 = int(np.ceil((first_ns - origin) / step - 1e-6))
    k1 = int(np.floor((last_ns - origin) / step + 1e-6))
    return np.int64(origin) + np.round(np.arange(k0, max(k1 + 1, k0)) * step).astype(np.int64)


def _catmull_rom(y: FloatArray, s: FloatArray) -> FloatArray:
    """Samples ``y`` (n, ...) evaluated at fractional indices ``s`` (m,) with a Catmull-Rom spline."""
    n = y.shape[0]
    i1 = np.clip(np.floor(s).astype(np.intp), 0, n - 2)
    u = (s - i1).reshape(-1, *([1] * (y.ndim - 1)))
    p0, p1 = y[np.maximum(i1 - 1, 0)], y[i1]
    p2, p3 = y[i1 + 1], y[np.minimum(i1 + 2, n - 1)]
    m1, m2 = 0.5 * (p2 - p0), 0.5 * (p3 - p1)
    u2, u3 = u * u, u * u * u
    return np.asarray((2 * u3 - 3 * u2 + 1) * p1 + (u3 - 2 * u2 + u) * m1 + (-2 * u3 + 3 * u2) * p2 + (u3 - u2) * m2)


def resample_poses(theta: FloatArray, fps_in: float, fps_out: float) -> FloatArray:
    """A θ sequence at another frame rate, same duration, with continuous velocities.

    Like :meth:`SourceMotion.resample`: root translation with a Catmull-Rom cubic, every bone's rotation as a
    sign-continuous quaternion with a Catmull-Rom cubic then renormalised, so the second differences of the
    result (what simulated accelerometers measure) have no spikes at the input samples.

    Parameters
    ----------
    theta : array, shape (n, 66)
        Pose vectors: root translation + 21 local rotation vectors.
    fps_in, fps_out : float

    Returns
    -------
    array, shape (m, 66)
        ``m = floor((n - 1) / fps_in · fps_out) + 1`` samples from the first input frame on.
    """
    theta = np.asarray(theta, dtype=np.float64)
    if theta.ndim != 2 or theta.shape[1] % 3 != 0 or theta.shape[0] < 2:
        raise InputError(f"resample_poses: theta must have shape (n >= 2, 3 + 3k), got {theta.shape}")
    if not (np.isfinite(fps_in) and fps_in > 0 and np.isfinite(fps_out) and fps_out > 0):
        raise InputError(f"resample_poses: frame rates must be positive, got {fps_in!r} -> {fps_out!r}")
    n = theta.shape[0]
    duration = (n - 1) / fps_in
    s = np.arange(int(np.floor(duration * fps_out + 1e-9)) + 1) / fps_out * fps_in
    q = quat_from_rotvec(theta[:, 3:].reshape(n, -1, 3))
    for i in range(1, n):
        flip = np.sum(q[i] * q[i - 1], axis=-1) < 0
        q[i, flip] *= -1.0
    out = np.empty((s.shape[0], theta.shape[1]))
    out[:, :3] = _catmull_rom(theta[:, :3], s)
    out[:, 3:] = rotvec_from_quat(quat_normalize(_catmull_rom(q, s))).reshape(s.shape[0], -1)
    return out

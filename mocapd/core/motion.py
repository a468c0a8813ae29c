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

from mocapd.core.rotations import matrix_from_quat, quat_normalize, quat_slerp
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
        """The clip at another frame rate: translations linear, rotations slerp, same duration."""
        if not (np.isfinite(fps) and fps > 0):
            raise InputError(f"resample: frame rate must be positive, got {fps!r}")
        if self.n_frames < 2 or abs(fps - self.fps) < 1e-9:
            return self
        duration = (self.n_frames - 1) / self.fps
        t = np.arange(int(np.floor(duration * fps + 1e-9)) + 1) / fps
        s = t * self.fps
        i0 = np.clip(np.floor(s).astype(np.intp), 0, self.n_frames - 2)
        a = (s - i0)[:, None]
        tr = (1 - a[..., None]) * self.translations[i0] + a[..., None] * self.translations[i0 + 1]
        rot = quat_slerp(self.rotations[i0], self.rotations[i0 + 1], np.broadcast_to(a, (len(t), self.n_joints)))
        return SourceMotion(self.name, self.joint_names, self.parents, tr, rot, self.end_sites, fps)

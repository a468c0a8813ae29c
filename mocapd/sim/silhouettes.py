"""Foreground mattes of the synthetic rig: a body-shaped proxy of each skeleton, rendered per camera, with the
errors of a real background subtraction (issue 30; seed 001 §3.2's occupancy channel).

The proxy is capsules and spheres with realistic widths for a 1.75 m person, scaled with the skeleton's height:
trunk, shoulder girdle and pelvis, neck and head, upper arms, forearms and hands, thighs, shanks and feet.
Each is drawn with OpenCV at the PVH's reduced scale (a thick line has round caps: a capsule's outline).

:class:`MatteNoise` (``realistic``) adds what a clean-plate or MOG2 background subtraction gets wrong, seeded:
edges blurred by a pixel; pixel noise; holes where a body part matches the background (each part dropped with a
small probability); a cast shadow on the floor under the feet; a few false-positive blobs; and, rarely, a view
whose matte fails outright (a lighting change: noise everywhere).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera, project_points
from mocapd.core.pvh import scaled_pixels
from mocapd.core.skeleton import BONE_INDEX, REFERENCE_HEIGHT
from mocapd.sim.world import SyntheticWorld

FloatArray = NDArray[np.float64]
F32Array = NDArray[np.float32]
F32 = F32Array

# (from joint, to joint, radius in metres for a 1.75 m person). Joint = the named bone's origin.
_PARTS: tuple[tuple[str, str, float], ...] = (
    ("Hips", "Spine2", 0.13), ("Spine2", "Spine3", 0.14),
    ("Spine3", "LeftUpperArm", 0.07), ("Spine3", "RightUpperArm", 0.07), ("Spine3", "Neck", 0.07),
    ("Neck", "Head", 0.055),
    ("LeftUpperLeg", "RightUpperLeg", 0.10),
    ("LeftUpperArm", "LeftLowerArm", 0.05), ("LeftLowerArm", "LeftHand", 0.04),
    ("RightUpperArm", "RightLowerArm", 0.05), ("RightLowerArm", "RightHand", 0.04),
    ("LeftUpperLeg", "LeftLowerLeg", 0.075), ("LeftLowerLeg", "LeftFoot", 0.055),
    ("RightUpperLeg", "RightLowerLeg", 0.075), ("RightLowerLeg", "RightFoot", 0.055),
    ("LeftFoot", "LeftToes", 0.045), ("RightFoot", "RightToes", 0.045),
)  # fmt: skip
_HEAD_RADIUS = 0.10
_HEAD_UP = 0.10  # the skull's centre above the head joint (along Neck -> Head)
_HAND_LENGTH = 0.09  # the hand continues the forearm beyond the wrist joint
_HAND_RADIUS = 0.04

_A = np.array([BONE_INDEX[a] for a, _, _ in _PARTS], dtype=np.intp)
_B = np.array([BONE_INDEX[b] for _, b, _ in _PARTS], dtype=np.intp)
_R = np.array([r for _, _, r in _PARTS])


def proxy_shapes(joints: FloatArray, height: float = REFERENCE_HEIGHT) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The body proxy of one skeleton pose as capsules ``(a, b, radius)``: a == b is a sphere.

    Parameters
    ----------
    joints : (21, 3) global joint positions.

    Returns
    -------
    a, b : (n, 3) end points; radius : (n,) metres.
    """
    s = height / REFERENCE_HEIGHT
    a = [joints[_A]]
    b = [joints[_B]]
    r = [_R * s]
    neck, head = joints[BONE_INDEX["Neck"]], joints[BONE_INDEX["Head"]]
    up = head - neck
    up /= max(float(np.linalg.norm(up)), 1e-9)
    skull = head + _HEAD_UP * s * up
    a.append(skull[None])
    b.append(skull[None])
    r.append(np.array([_HEAD_RADIUS * s]))
    for side in ("Left", "Right"):
        elbow, wrist = joints[BONE_INDEX[f"{side}LowerArm"]], joints[BONE_INDEX[f"{side}Hand"]]
        d = wrist - elbow
        d /= max(float(np.linalg.norm(d)), 1e-9)
        a.append(wrist[None])
        b.append((wrist + _HAND_LENGTH * s * d)[None])
        r.append(np.array([_HAND_RADIUS * s]))
    return np.concatenate(a), np.concatenate(b), np.concatenate(r)


def render_silhouette(
    camera: Camera,
    shapes: list[tuple[FloatArray, FloatArray, FloatArray]],
    scale: int,
    drop: NDArray[np.bool_] | None = None,
) -> F32Array:
    """A binary (0/1) silhouette of every proxy in ``shapes`` seen by ``camera``, at ``1/scale`` resolution.

    Parameters
    ----------
    shapes : per person, :func:`proxy_shapes`' (a, b, radius).
    drop : per part of all people concatenated, True where the part is not drawn (a hole in the matte).
    """
    h, w = -(-camera.height // scale), -(-camera.width // scale)
    img = np.zeros((h, w), dtype=np.uint8)
    if not shapes:
        return img.astype(np.float32)
    a = np.concatenate([s[0] for s in shapes])
    b = np.concatenate([s[1] for s in shapes])
    r = np.concatenate([s[2] for s in shapes])
    pts = np.concatenate((a, b))
    uv, _, vis = project_points(camera.K, camera.dist, camera.R, camera.t, pts, jacobian=False)
    xy = scaled_pixels(uv, scale)
    depth = pts @ camera.R[2] + camera.t[2]
    n = len(r)
    f = float(camera.K[0, 0]) / scale
    # Draw far parts first so nothing depends on order (the silhouette is a union anyway).
    sub = 4  # fixed-point bits: OpenCV draws at 1/16 pixel
    for i in np.argsort(-depth[:n]):
        if (drop is not None and drop[i]) or not (vis[i] and vis[n + i]):
            continue
        rad = f * r[i] / max(0.5 * (depth[i] + depth[n + i]), 0.1)
        p = np.round(xy[i] * (1 << sub)).astype(np.int64)
        q = np.round(xy[n + i] * (1 << sub)).astype(np.int64)
        if np.any(np.abs(np.concatenate((p, q))) > (1 << 28)):
            continue
        thick = max(1, round(2.0 * rad))
        cv2.line(img, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), 255, thick, cv2.LINE_8, sub)
    return np.asarray(img, dtype=np.float32) / np.float32(255.0)


@dataclass(frozen=True)
class MatteNoise:
    """How a simulated background subtraction errs (per view and frame unless said)."""

    blur_px: float = 0.8
    """Gaussian σ of the soft edge (channel-image pixels)."""
    pixel_noise: float = 0.05
    """σ of additive per-pixel noise."""
    hole: float = 0.04
    """Probability that a body part is missing (its colour matches the background)."""
    shadow: float = 0.5
    """Probability of a cast shadow under the feet, drawn at 0.3–0.7."""
    blobs: float = 0.5
    """Mean number of false-positive blobs per view."""
    failure: float = 0.01
    """Probability that a view's matte fails outright (noise in [0.2, 0.8] everywhere)."""

    @classmethod
    def realistic(cls) -> MatteNoise:
        return cls()

    @classmethod
    def clean(cls) -> MatteNoise:
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def simulated_matte(
    camera: Camera,
    people: list[tuple[FloatArray, float]],
    scale: int,
    noise: MatteNoise,
    rng: np.random.Generator,
) -> F32Array:
    """The soft foreground matte (h, w) in [0, 1] of one view of the synthetic people.

    Parameters
    ----------
    people : per person, its joints (21, 3) and height (metres).
    """
    shapes = [proxy_shapes(j, hgt) for j, hgt in people]
    n_parts = sum(len(s[2]) for s in shapes)
    drop = rng.uniform(size=n_parts) < noise.hole if noise.hole > 0 else None
    img = render_silhouette(camera, shapes, scale, drop)
    h, w = img.shape
    if noise.shadow > 0:
        for joints, hgt in people:
            if rng.uniform() < noise.shadow:
                _shadow(img, camera, joints, hgt, scale, float(rng.uniform(0.3, 0.7)), rng)
    if noise.blobs > 0:
        for _ in range(rng.poisson(noise.blobs)):
            c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            ax = (int(rng.integers(1, 6)), int(rng.integers(1, 6)))
            cv2.ellipse(img, c, ax, float(rng.uniform(0, 180)), 0, 360, float(rng.uniform(0.5, 1.0)), -1)
    if noise.blur_px > 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), noise.blur_px), dtype=np.float32)
    if noise.pixel_noise > 0:
        img += np.float32(noise.pixel_noise) * rng.standard_normal(size=img.shape, dtype=np.float32)
    if noise.failure > 0 and rng.uniform() < noise.failure:
        img = rng.uniform(0.2, 0.8, size=img.shape).astype(np.float32)
    return np.asarray(np.clip(img, 0.0, 1.0), dtype=np.float32)


def _shadow(
    img: F32Array,
    camera: Camera,
    joints: FloatArray,
    height: float,
    scale: int,
    value: float,
    rng: np.random.Generator,
) -> None:
    """A dark patch on the floor under the feet, offset away from a light: an ellipse of floor points."""
    feet = joints[[BONE_INDEX["LeftFoot"], BONE_INDEX["RightFoot"]]].mean(axis=0)
    ang = rng.uniform(0, 2 * np.pi)
    centre = np.array([feet[0], 0.0, feet[2]]) + 0.25 * height / REFERENCE_HEIGHT * np.array(
        [np.cos(ang), 0.0, np.sin(ang)]
    )
    t = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    ring = centre + np.stack((0.45 * np.cos(t), np.zeros_like(t), 0.3 * np.sin(t)), axis=-1) * height / REFERENCE_HEIGHT
    uv, _, vis = project_points(camera.K, camera.dist, camera.R, camera.t, ring, jacobian=False)
    if not np.all(vis):
        return
    poly = np.round(scaled_pixels(uv, scale)).astype(np.int32)
    if np.any(np.abs(poly) > 1 << 20):
        return
    shadow = np.zeros_like(img)
    cv2.fillPoly(shadow, [poly], value)
    np.maximum(img, shadow, out=img)


class SyntheticMattes:
    """The :class:`~mocapd.pipeline.mattes.MatteSource` of a :class:`~mocapd.sim.world.SyntheticWorld`: every
    person's proxy rendered at the asked time in every camera, with the background-subtraction errors of
    ``noise`` (what :class:`~mocapd.pipeline.mattes.BackgroundMatte` would give on rendered frames).

    Parameters
    ----------
    epoch_ns : host time of the world's t = 0.
    """

    def __init__(
        self, world: SyntheticWorld, epoch_ns: int, scale: int = 8, noise: MatteNoise | None = None, seed: int = 0
    ) -> None:
        self.world = world
        self.epoch_ns = epoch_ns
        self.scale = scale
        self.noise = noise if noise is not None else MatteNoise()
        self.rng = np.random.default_rng(seed + 5000)

    def mattes(self, t_ns: int) -> list[F32 | None]:
        t_s = (t_ns - self.epoch_ns) / 1e9
        people = [(self.world.joints_at(p, t_s), self.world.skeleton.height) for p in range(len(self.world.truth))]
        return [simulated_matte(cam, people, self.scale, self.noise, self.rng) for cam in self.world.cameras]

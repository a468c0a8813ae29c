"""Camera images of a synthetic world whose keypoints are known exactly: textured bodies on a textured floor.

The synthetic rig simulates detections, not images, and :mod:`mocapd.sim.camera_frames` draws flat grey limbs for
the viewer, which image tracking cannot follow (no texture). This renderer draws every person of a
:class:`~mocapd.sim.world.SyntheticWorld` as textured body parts (a quad per limb segment and for the torso, a disk
for the head, each with its own fixed random pattern attached to the part, so the pattern moves with it), nearest
last, over a static textured background, through the camera's own calibration (distortion included, at the joints;
straight part edges between them). The true 2D keypoints are the world's keypoint sites projected the same way.

It serves the keypoint tracker's accuracy against the truth (``tools/track_quality.py --source synthetic``): what
the images show is exact, and a detector's output is simulated as the truth plus pixel noise.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.sim.world import SyntheticWorld

FloatArray = NDArray[np.float64]
Gray = NDArray[np.uint8]

# Body parts as (first bone, second bone, radius m): a quad from one joint to the other, 2 x radius wide. Bones of
# DESIGN.md's skeleton: 0 Hips, 5 Neck, 6 Head, 7-9 left arm, 10-12 right arm, 13-16 left leg, 17-20 right leg.
_LIMBS: tuple[tuple[int, int, float], ...] = (
    (5, 6, 0.05),  # neck
    (7, 8, 0.055), (8, 9, 0.045), (10, 11, 0.055), (11, 12, 0.045),  # upper arms, forearms
    (13, 14, 0.08), (14, 15, 0.06), (15, 16, 0.045), (17, 18, 0.08), (18, 19, 0.06), (19, 20, 0.045),  # legs
)  # fmt: skip
_HANDS = ((8, 9), (11, 12))  # a hand continues its forearm for 40 % of its length
_TORSO = (7, 10, 17, 13)  # left shoulder, right shoulder, right hip, left hip
_HEAD_RADIUS_M = 0.11
_TEXTURE = (96, 160)  # texture patch, pixels (height, width)


def _texture(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> Gray:
    """Smooth random texture with strong contrast (what Lucas-Kanade tracks well)."""
    noise = rng.uniform(0, 255, shape).astype(np.float32)
    blurred = cv2.GaussianBlur(noise, (0, 0), sigma)
    stretched = (blurred - blurred.mean()) / max(float(blurred.std()), 1e-6) * 55 + 128
    return np.asarray(np.clip(stretched, 0, 255), np.uint8)


class TexturedWorldFrames:
    """Gray camera images of a synthetic world, and its true keypoints in them.

    Parameters
    ----------
    world : SyntheticWorld
    scale : float
        Image size as a fraction of the cameras' calibrated size (0.5: 960x540 for the ring rig's HD cameras).
    seed : int
        Textures.
    """

    def __init__(self, world: SyntheticWorld, scale: float = 0.5, seed: int = 0) -> None:
        self.world = world
        self.scale = scale
        rng = np.random.default_rng(seed)
        n_parts = len(_LIMBS) + len(_HANDS) + 2  # limbs, hands, torso, head
        self._textures = [[_texture(rng, _TEXTURE, 1.6) for _ in range(n_parts)] for _ in world.truth]
        self._backgrounds = [_texture(rng, (self.size(c)[1], self.size(c)[0]), 3.0) // 2 + 40
                             for c in range(len(world.cameras))]  # fmt: skip

    def size(self, cam: int) -> tuple[int, int]:
        """(width, height) of camera ``cam``'s images."""
        c = self.world.cameras[cam]
        return round(c.width * self.scale), round(c.height * self.scale)

    def keypoints(self, cam: int, t_s: float) -> tuple[FloatArray, NDArray[np.bool_]]:
        """The true keypoints of every person at ``t_s`` in camera ``cam``'s image, shape (P, K, 2), and whether
        each is in front of the camera and inside the image, (P, K)."""
        c = self.world.cameras[cam]
        w, h = self.size(cam)
        pts, ok = [], []
        for p in range(len(self.world.truth)):
            uv, front = self._project(c, self.world.sites_at(p, t_s))
            pts.append(uv)
            ok.append(front & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < w) & (uv[:, 1] < h))
        return np.stack(pts), np.stack(ok)

    def render(self, cam: int, t_s: float) -> Gray:
        """Camera ``cam``'s gray image at world time ``t_s``, shape (height, width)."""
        c = self.world.cameras[cam]
        image = self._backgrounds[cam].copy()
        parts: list[tuple[float, FloatArray, Gray]] = []  # (depth, image quad (4, 2), texture)
        for p in range(len(self.world.truth)):
            joints = self.world.joints_at(p, t_s)
            uv, front = self._project(c, joints)
            depth = (joints @ c.R.T + c.t)[:, 2]
            textures = self._textures[p]
            for k, (a, b, radius) in enumerate(_LIMBS):
                if front[a] and front[b]:
                    parts.append((float(depth[[a, b]].mean()), _limb_quad(c, uv[a], uv[b], radius, depth[[a, b]],
                                                                          self.scale), textures[k]))  # fmt: skip
            for k, (a, b) in enumerate(_HANDS):
                end = joints[b] + 0.4 * (joints[b] - joints[a])
                (e_uv,), (e_front,) = self._project(c, end[None])
                if front[b] and e_front:
                    d = float(depth[b])
                    parts.append((d, _limb_quad(c, uv[b], e_uv, 0.04, np.array([d, d]), self.scale),
                                  textures[len(_LIMBS) + k]))  # fmt: skip
            if front[list(_TORSO)].all():
                parts.append((float(depth[list(_TORSO)].mean()), uv[list(_TORSO)], textures[-2]))
            face = self.world.sites_at(p, t_s)[:5].mean(axis=0)  # COCO-17's nose, eyes, ears
            (f_uv,), (f_front,) = self._project(c, face[None])
            f_depth = float((face @ c.R.T + c.t)[2])
            if f_front and f_depth > 0:
                r = _HEAD_RADIUS_M * c.K[0, 0] * self.scale / f_depth
                quad = f_uv + np.array([[-r, -r], [r, -r], [r, r], [-r, r]])
                parts.append((f_depth - 0.05, quad, _disk(textures[-1])))
        for _, quad, texture in sorted(parts, key=lambda x: -x[0]):  # farthest first: the nearest is drawn last
            _paste(image, quad, texture)
        return image

    def _project(self, c: Camera, points: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        cam_pts = points @ c.R.T + c.t
        front = cam_pts[:, 2] > 0.1
        uv = np.asarray(c.project(points), np.float64) * self.scale
        return uv, front & np.all(np.isfinite(uv), axis=1)


def _limb_quad(c: Camera, a: FloatArray, b: FloatArray, radius: float, depth: FloatArray, scale: float) -> FloatArray:
    """The image quad of a limb from ``a`` to ``b`` (image px), its half-width the radius projected at each end."""
    d = b - a
    n = np.array([-d[1], d[0]]) / max(float(np.hypot(*d)), 1e-6)
    wa, wb = (radius * c.K[0, 0] * scale / max(float(z), 0.1) for z in depth)
    return np.array([a + wa * n, b + wb * n, b - wb * n, a - wa * n])


def _disk(texture: Gray) -> Gray:
    """``texture`` with everything outside its inscribed ellipse made transparent (0 = not painted)."""
    h, w = texture.shape
    yy, xx = np.mgrid[0:h, 0:w]
    inside = ((xx - (w - 1) / 2) / (w / 2)) ** 2 + ((yy - (h - 1) / 2) / (h / 2)) ** 2 <= 1.0
    return np.where(inside, np.maximum(texture, 1), 0).astype(np.uint8)


def _paste(image: Gray, quad: FloatArray, texture: Gray) -> None:
    """Warp ``texture`` onto the image quad ``quad`` (4, 2: its corners in the order of the texture's top-left,
    top-right, bottom-right, bottom-left) in place; texture value 0 is transparent."""
    h, w = image.shape
    x0, y0 = np.floor(quad.min(axis=0)).astype(int)
    x1, y1 = np.ceil(quad.max(axis=0)).astype(int) + 1
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 <= x0 or y1 <= y0:
        return
    th, tw = texture.shape
    src = np.array([[0, 0], [tw - 1, 0], [tw - 1, th - 1], [0, th - 1]], np.float32)
    dst = (quad - [x0, y0]).astype(np.float32)
    m = cv2.getPerspectiveTransform(src, dst)
    size = (x1 - x0, y1 - y0)
    warped = cv2.warpPerspective(texture, m, size, flags=cv2.INTER_LINEAR, borderValue=0)
    mask = cv2.warpPerspective(np.full_like(texture, 255), m, size, flags=cv2.INTER_NEAREST, borderValue=0)
    keep = (mask > 0) & (warped > 0)
    roi = image[y0:y1, x0:x1]
    roi[keep] = warped[keep]

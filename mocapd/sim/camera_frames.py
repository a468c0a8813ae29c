"""Camera frames of a synthetic world, for the camera panels of ``mocapd demo --synthetic``.

The synthetic rig simulates detections, not images; this draws what its cameras would see, on request only (the
camera panels ask a few times a second, off the solver's tick): the floor grid, and every person's true skeleton
as thick grey limbs, projected through the camera's own calibration at the moment asked. Solved overlays drawn
on it land on the limbs when the solve is right, as they would on a real video frame.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import cv2
import numpy as np

from mocapd.core.skeleton import PARENTS
from mocapd.pipeline.camera_views import Snapshot
from mocapd.sim.world import SyntheticWorld

BACKGROUND = (38, 42, 48)
FLOOR = (70, 76, 86)
BODY = (150, 146, 138)


class SyntheticFrames:
    """The :class:`~mocapd.pipeline.camera_views.SnapshotSource` of camera ``camera`` of a synthetic world."""

    def __init__(
        self, world: SyntheticWorld, camera: int, epoch_ns: int, clock: Callable[[], int] = time.monotonic_ns
    ) -> None:
        self.world = world
        self.camera = world.cameras[camera]
        self.epoch_ns = epoch_ns
        self.clock = clock

    def snapshot(self, max_width: int) -> Snapshot | None:
        now = self.clock()
        cam = self.camera
        s = min(1.0, max_width / cam.width)
        w, h = max(1, round(cam.width * s)), max(1, round(cam.height * s))
        img = np.empty((h, w, 3), np.uint8)
        img[:] = BACKGROUND

        def px(points: np.ndarray) -> np.ndarray:
            return np.asarray(cam.project(points) * s)

        for k in np.arange(-5.0, 6.0):
            for a, b in (((k, 0.0, -5.0), (k, 0.0, 5.0)), ((-5.0, 0.0, k), (5.0, 0.0, k))):
                seg = px(np.linspace(a, b, 21))  # in pieces: distortion bends long lines
                _polyline(img, seg, FLOOR, 1)
        t_s = (now - self.epoch_ns) / 1e9
        thick = max(2, round(0.012 * w))
        for person in range(len(self.world.truth)):
            uv = px(self.world.joints_at(person, t_s))
            for bone, parent in enumerate(PARENTS):
                if parent >= 0:
                    _polyline(img, uv[[parent, bone]], BODY, thick)
        return Snapshot(now, image=img)


def _polyline(img: np.ndarray, uv: np.ndarray, colour: tuple[int, int, int], width: int) -> None:
    ok = np.isfinite(uv).all(axis=1) & (np.abs(uv) < 1e5).all(axis=1)
    for i in range(len(uv) - 1):
        if ok[i] and ok[i + 1]:
            a, b = uv[i], uv[i + 1]
            cv2.line(img, (round(a[0]), round(a[1])), (round(b[0]), round(b[1])), colour, width, cv2.LINE_AA)

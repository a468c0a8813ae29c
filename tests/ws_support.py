"""Shared by the WebSocket stream tests: real poses (random θ through the real forward kinematics) as the
daemon's :class:`~mocapd.pipeline.scheduler.PoseFrame`, and forward kinematics on received messages."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import quat_multiply, quat_rotate, random_rotvec
from mocapd.core.skeleton import N_BONES, PARENTS, Skeleton
from mocapd.pipeline.scheduler import PersonPose, PoseFrame

FloatArray = NDArray[np.float64]


def person(identity: str, theta: FloatArray, skeleton: Skeleton, **kw: Any) -> PersonPose:
    joints = Kinematics(skeleton).forward(theta).positions
    return PersonPose(identity=identity, track=kw.get("track", 0), suit=kw.get("suit"), theta=theta, joints=joints,
                      confidence=kw.get("confidence", 0.9), views=kw.get("views", 4), imus=kw.get("imus", 0),
                      iterations=3, converged=True)  # fmt: skip


def random_frame(rng: np.random.Generator, frame: int, ids: list[str], skeleton: Skeleton) -> PoseFrame:
    """A frame whose people have random root positions and bone rotations (up to 90°)."""
    people = []
    for k, i in enumerate(ids):
        theta = np.concatenate(
            [rng.uniform(-2, 2, 3) + np.array([0.0, 1.0, 0.0]), random_rotvec(rng, (N_BONES,), 1.5).ravel()]
        )
        people.append(person(i, theta, skeleton, track=k, suit="suit0" if k == 0 else None))
    return PoseFrame(frame=frame, t_solve_ns=1_000_000_000 + frame * 16_666_667, tick_ns=0, people=people,
                     missing_cameras=0)  # fmt: skip


def fk_from_message(root: list[float], rot: list[float], offsets: list[float]) -> FloatArray:
    """Global joint positions (21, 3) from a frame subject's root, local quaternions and the hello's offsets, in
    whatever convention they are written (the test of the conversion: FK must commute with it)."""
    q = np.asarray(rot, dtype=np.float64).reshape(N_BONES, 4)
    off = np.asarray(offsets, dtype=np.float64).reshape(N_BONES, 3)
    glob = np.empty_like(q)
    pos = np.empty((N_BONES, 3))
    for b, p in enumerate(PARENTS):
        if p < 0:
            glob[b], pos[b] = q[b], root
        else:
            glob[b] = quat_multiply(glob[p], q[b])
            pos[b] = pos[p] + quat_rotate(glob[p], off[b])
    return pos

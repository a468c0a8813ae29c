"""A camera's calibration replaced while the scheduler runs (issue 43, "cameras that stay calibrated"): every holder
of the camera takes the new one in one step between ticks, the person solves go on from their warm starts, and a
change beyond the camera's pose is refused."""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from mocapd.core.camera import Camera
from mocapd.core.prior import PcaPrior
from mocapd.core.rotations import matrix_from_rotvec
from mocapd.errors import InputError
from mocapd.pipeline.scheduler import PoseFrame, SchedulerOptions
from tests.test_scheduler import _lockstep, prior  # noqa: F401 (the fixture)


def test_a_replaced_camera_reaches_every_holder_and_the_solve_uses_it(prior: PcaPrior) -> None:  # noqa: F811
    ls = _lockstep(prior, 1, 0, SchedulerOptions(), [0, 0, 0, 0])
    sched = ls.scheduler
    told: list[tuple[int, Camera]] = []
    sched.camera_listeners.append(lambda i, c: told.append((i, c)))
    clean = ls.run(2.0)
    ls.world.bump(1, matrix_from_rotvec(np.radians(2.0) * np.array([1.0, 0.0, 0.0])))  # the camera turns 2°
    ls.run(1.0)
    moved = ls.world.cameras[1]
    assert not np.allclose(sched.cameras[1].R, moved.R)  # the scheduler's calibration is its own, not the world's
    sched.replace_camera(1, moved)
    fixed = ls.run(3.0)

    def median_mm(frames: list[tuple[PoseFrame, list[float]]]) -> float:
        return float(np.median([e for _, errs in frames for e in errs])) * 1e3

    # Settled (the tracker's identities follow the people's new triangulations within a second or two, see
    # docs/cameras.md): as good as before the knock, every camera in the solve.
    assert median_mm(fixed[-60:]) < 1.5 * median_mm(clean[60:]) + 1.0
    assert all(p.views == 4 for f, _ in fixed[-60:] for p in f.people)
    assert [i for i, _ in told] == [1] and told[0][1] is moved
    P = moved.projection_matrix
    assert sched.cameras[1] is moved and np.allclose(sched._projections[1], P)
    assert sched.people.tracker.sorter.cameras[1] is moved and np.allclose(sched.people.tracker.sorter._R[1], moved.R)
    assert sched.solvers and all(s.cameras[1] is moved for s in sched.solvers.values())
    for s in sched.solvers.values():
        assert s._kernel_static is not None and np.allclose(s._kernel_static.R[1], moved.R)
        assert np.allclose(s._kernel_static.t[1], moved.t)
    assert all(c is not moved for i, c in enumerate(sched.cameras) if i != 1)


def test_a_camera_is_replaced_only_between_ticks(prior: PcaPrior) -> None:  # noqa: F811
    """A tick holds the scheduler's lock while it solves: a replacement asked meanwhile waits for its end."""
    ls = _lockstep(prior, 1, 0, SchedulerOptions(), [0, 0, 0, 0])
    sched = ls.scheduler
    ls.run(0.5)
    old = sched.cameras[2]
    new = replace(old, R=matrix_from_rotvec(np.radians(1.0) * np.array([0.0, 1.0, 0.0])) @ old.R)
    with sched.lock:  # a tick solving
        worker = threading.Thread(target=sched.replace_camera, args=(2, new))
        worker.start()
        time.sleep(0.2)
        assert worker.is_alive() and sched.cameras[2] is old and sched.people.tracker.sorter.cameras[2] is old
    worker.join(5.0)
    assert not worker.is_alive() and sched.cameras[2] is new and sched.people.tracker.sorter.cameras[2] is new


def test_a_replacement_that_changes_more_than_the_pose_is_refused(prior: PcaPrior) -> None:  # noqa: F811
    ls = _lockstep(prior, 1, 0, SchedulerOptions(), [0, 0, 0, 0])
    sched = ls.scheduler
    cam = sched.cameras[0]
    K = cam.K.copy()
    K[0, 0] *= 1.01
    for bad in (replace(cam, K=K), replace(cam, name="other"), replace(cam, width=cam.width + 2)):
        with pytest.raises(InputError, match="only its pose may change"):
            sched.replace_camera(0, bad)
    with pytest.raises(InputError, match="no camera 7"):
        sched.replace_camera(7, cam)
    assert sched.cameras[0] is cam

"""The tick off the event loop (issue 39): the daemon's loop samples and publishes, the tick thread solves, the
people of a tick on the solve pool give the same poses as one after another, and keypoints are undistorted once,
as they arrive, the same as undistorting every sample."""

from __future__ import annotations

import asyncio
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from mocapd.core.camera import Camera
from mocapd.core.sorting import Detections2D
from mocapd.core.synthetic import ring_rig
from mocapd.pipeline.keypoint_timeline import interpolate_people
from mocapd.pipeline.scheduler import FixedLatencyScheduler, PoseFrame, TickInputs
from mocapd.service.assembly import RunOptions, assembled
from mocapd.service.config import load_config
from mocapd.service.demo.synthetic import synthetic_config
from tests.imu_lockstep import SuitLockstep, suit_lockstep
from tests.test_daemon import Recorder, wait_for


@pytest.mark.asyncio
async def test_the_daemon_solves_on_its_tick_thread_while_the_loop_samples_and_publishes() -> None:
    cfg = load_config()
    cfg = cfg.model_copy(update={
        "daemon": cfg.daemon.model_copy(update={"http_port": 0, "tick_thread": True}),
        "websocket": cfg.websocket.model_copy(update={"enabled": False}),
    })  # fmt: skip
    rec = Recorder()
    with assembled(synthetic_config(cfg), RunOptions(sinks=[rec])) as demo:
        d = demo.daemon
        seen: dict[str, set[str]] = {"sample": set(), "solve": set()}
        sample, solve = d.scheduler.sample, d.scheduler.solve

        def sample_spy(now_ns: int) -> TickInputs:
            seen["sample"].add(threading.current_thread().name)
            return sample(now_ns)

        def solve_spy(inputs: TickInputs) -> PoseFrame:
            seen["solve"].add(threading.current_thread().name)
            return solve(inputs)

        d.scheduler.sample = sample_spy  # type: ignore[method-assign]
        d.scheduler.solve = solve_spy  # type: ignore[method-assign]
        task = asyncio.create_task(d.run())
        await asyncio.wait_for(d.ready.wait(), 120)
        await wait_for(lambda: any(len(f.people) == 2 for f in rec.frames), 60, "both people solved")
        loop_thread = threading.current_thread().name
        d.request_stop()
        assert await asyncio.wait_for(task, 10) == 0
    assert seen["sample"] == {loop_thread}
    assert len(seen["solve"]) == 1 and loop_thread not in seen["solve"]
    assert next(iter(seen["solve"])).startswith("mocapd-tick")
    # Published in order, one tick at a time: frame numbers only grow.
    frames = [f.frame for f in rec.frames]
    assert frames == sorted(frames) and len(set(frames)) == len(frames)


def _run(rig: SuitLockstep, ticks: int) -> list[PoseFrame]:
    return [rig.tick() for _ in range(ticks)]


def test_people_solved_on_the_pool_match_people_solved_one_after_another() -> None:
    one = suit_lockstep(n_people=2)
    two = suit_lockstep(n_people=2)
    with ThreadPoolExecutor(2) as pool:
        two.scheduler.pool = pool
        a, b = _run(one, 150), _run(two, 150)
    assert sum(len(f.people) for f in a) > 150  # two people most of the time: the pool had work to share
    for fa, fb in zip(a, b, strict=True):
        assert [p.identity for p in fa.people] == [p.identity for p in fb.people]
        for pa, pb in zip(fa.people, fb.people, strict=True):
            np.testing.assert_allclose(pa.theta, pb.theta, atol=1e-9)
    assert one.scheduler.counters == two.scheduler.counters


def test_undistorted_copies_interpolate_as_the_undistorted_interpolation() -> None:
    """Interpolating the undistorted copies (made once per frame) is undistorting the interpolated pixels to within
    half a pixel, for a strong wide-angle lens (k1 = -0.28, points out to the image corners) and keypoints moving
    ~35 px between the two frames; a detector's own noise is 5-20 px, and 60 fps motion is a few px a frame."""
    cam: Camera = ring_rig(1, radius=4.0)[0]
    cam = Camera(cam.name, cam.width, cam.height, cam.K, cam.R, cam.t, np.array([-0.28, 0.09, 0.001, -0.002, 0.0]))
    rng = np.random.default_rng(3)
    kp_a = rng.uniform(50, [cam.width - 50, cam.height - 50], (1, 17, 2))
    kp_b = kp_a + rng.normal(0.0, 25.0, kp_a.shape)
    conf = np.full((1, 17), 0.9)
    a = Detections2D(kp_a, conf, cam.undistort_points(kp_a))
    b = Detections2D(kp_b, conf, cam.undistort_points(kp_b))
    for alpha in (0.25, 0.5, 0.8):
        mid = interpolate_people(a, b, alpha, match_px=200.0)
        assert mid.undistorted is not None
        np.testing.assert_allclose(mid.undistorted, cam.undistort_points(mid.keypoints), atol=0.5)


def test_the_scheduler_files_each_detection_with_its_undistorted_copy() -> None:
    rig = suit_lockstep()
    sched: FixedLatencyScheduler = rig.scheduler
    for _ in range(10):
        rig.tick()
    filed = [tl.frames()[1] for tl in sched.timelines]
    dets = [d for frames in filed for d in frames if len(d)]
    assert dets and all(d.undistorted is not None for d in dets)
    cam = sched.cameras[0]
    d0 = next(d for d in filed[0] if len(d))
    assert d0.undistorted is not None
    np.testing.assert_allclose(d0.undistorted, cam.undistort_points(d0.keypoints), atol=1e-9)

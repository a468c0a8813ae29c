"""End to end on the synthetic rig: the real daemon records a session; it opens intact; replay publishes the same
frames; resolve does not worsen (and here improves) the error against the known truth; export round-trips
through the BVH reader of the accuracy harness; the CLI commands run on it."""

from __future__ import annotations

import asyncio
import csv
import json
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import quat_angle, quat_from_matrix, quat_from_rotvec
from mocapd.io.bvh import read_bvh
from mocapd.io.session import open_session
from mocapd.io.session_export import resample, subject_track
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.service import cli
from mocapd.service.assembly import RunOptions, assembled
from mocapd.service.config import load_config
from mocapd.service.demo.synthetic import synthetic_config
from mocapd.service.session.replay import pose_frame, replay
from mocapd.service.session.solve import resolve, session_rig
from mocapd.service.session.truth import person_errors, truth_report, world_of
from tests.test_daemon import Recorder


async def _record(path: Path, seconds: float) -> list[PoseFrame]:
    cfg = load_config()
    # No body sizing: every pose, live and resolved, is on the synthetic people's own skeleton, so the truth
    # comparison measures the solves. With sizing on, each run sizes a person from its first 120 solved frames,
    # and under load the live run's span more time (missed ticks) than the re-solve's: two skeleton estimates,
    # a few millimetres apart, decided the comparison (resolve 3.8 vs live 2.6 mm median once; sizing is
    # checked in tests/test_body_size.py and tests/test_scheduler.py).
    cfg = cfg.model_copy(update={
        "daemon": cfg.daemon.model_copy(update={"http_port": 0, "body_size_s": 0.0}),
        "websocket": cfg.websocket.model_copy(update={"enabled": False}),
    })  # fmt: skip
    live = Recorder()
    with assembled(synthetic_config(cfg), RunOptions(sinks=[live], record=path)) as demo:
        task = asyncio.create_task(demo.daemon.run())
        await asyncio.wait_for(demo.daemon.ready.wait(), 120)
        loop = asyncio.get_running_loop()
        end = loop.time() + 60
        while not (live.frames and len(live.frames[-1].people) == 2
                   and any(p.suit == "suit0" and p.imus == 13 for p in live.frames[-1].people)):  # fmt: skip
            assert loop.time() < end, "both people never tracked"
            await asyncio.sleep(0.05)
        # At least ``seconds`` more, and at least 150 frames with both people (a loaded machine misses ticks).
        tracked, end = len(live.frames), loop.time() + 60
        await asyncio.sleep(seconds)
        while sum(len(f.people) == 2 for f in live.frames[tracked:]) < 150:
            assert loop.time() < end, "too few frames with both people"
            await asyncio.sleep(0.1)
        demo.daemon.request_stop()
        assert await asyncio.wait_for(task, 10) == 0
    return live.frames


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[PoseFrame]]:
    path = tmp_path_factory.mktemp("e2e") / "session"
    return path, asyncio.run(_record(path, 4.0))


def _same(a: PoseFrame, b: PoseFrame) -> bool:
    return (a.frame, a.t_solve_ns, a.tick_ns, a.missing_cameras) == (b.frame, b.t_solve_ns, b.tick_ns,
                                                                     b.missing_cameras) and all(
        (p.identity, p.suit, p.track, p.views, p.imus, p.iterations) == (q.identity, q.suit, q.track, q.views,
                                                                         q.imus, q.iterations)
        and np.array_equal(p.theta, q.theta) and np.allclose(p.joints, q.joints, atol=1e-5)
        for p, q in zip(a.people, b.people, strict=True)
    )  # fmt: skip


def test_the_daemon_records_a_session_that_opens_intact(recorded: tuple[Path, list[PoseFrame]]) -> None:
    path, live = recorded
    s = open_session(path)
    assert s.closed_cleanly and s.manifest["writer"]["dropped"] == 0
    frames = s.poses()
    kps, imu = s.keypoints(), s.imu()
    assert not any(r.damaged for r in s.check().values())
    assert len(frames) == len(live) and all(
        _same(a, b) for a, b in zip(live, [pose_frame(f) for f in frames], strict=True)
    )
    assert {k.camera for k in kps} == {0, 1, 2, 3} and len(kps) > 4 * 30 * 3
    assert len({r.sensor for r in imu}) == 13 and len(imu) > 13 * 100 * 3
    assert all(r.t_ns > 0 for r in imu[-100:]) and s.manifest["suits"][0]["id"] == "suit0"
    rig = session_rig(s)
    assert (
        len(rig.cameras) == 4
        and rig.prior is not None
        and rig.suits[0].sensors == tuple(sorted(s.manifest["suits"][0]["sensors"]))
    )


def test_replay_publishes_the_same_frames_at_the_recorded_pace(recorded: tuple[Path, list[PoseFrame]]) -> None:
    path, live = recorded
    frames = open_session(path).poses()
    out = Recorder()
    stats = asyncio.run(replay(frames, [out], speed=4.0))
    assert stats.frames == len(live) and all(_same(a, b) for a, b in zip(live, out.frames, strict=True))
    recorded_s = (frames[-1].t_solve_ns - frames[0].t_solve_ns) / 1e9
    assert stats.wall_s >= recorded_s / 4.0 - 0.01  # paced, not dumped


# Resolved minus live error at the same solve instants (same person), over 8 sessions recorded at load averages
# 20-25: median -5.85 to -0.08 mm, resolve no worse at 56-80 % of the instants. Comparing the two streams' medians
# instead failed under load (resolved 4.48 vs live 3.86 mm in one session whose paired median was -0.12 mm): the
# instants where a loaded live daemon solved are not a random sample, and the medians of two long-tailed
# distributions over them swing by more than resolve gains at the typical instant.
PAIRED_MEDIAN_MAX_MM = 0.1
NOT_WORSE_FRACTION_MIN = 0.5


def test_resolve_does_not_worsen_the_error_against_the_truth(recorded: tuple[Path, list[PoseFrame]]) -> None:
    path, _ = recorded
    s = open_session(path)
    live = s.poses()
    frames, summary = resolve(s)
    # Every instant the live daemon solved is re-solved, and the ticks it missed are filled (under the shipped
    # latency_s = "auto" the instants are not a uniform grid: the delay moves).
    assert len(frames) >= len(live) and summary["keypoint_frames"] == len(s.keypoints())
    period = round(1e9 / 60.0)
    t = np.array([f.t_solve_ns for f in frames])
    assert {f.t_solve_ns for f in live} <= set(t.tolist()) and np.diff(t).max() <= 1.5 * period
    # Steady state: once the live daemon had bound the suit; before it the two runs enrol and bind at different
    # moments, and a binding transient is not what resolve is for.
    bound = next(f.t_solve_ns for f in live if any(p.suit is not None for p in f.people))
    report = truth_report(s, {"live": live, "resolved": frames}, from_ns=bound + 500_000_000)
    print("resolve vs live:", report)
    assert report["person_frames"] > 100 and report["resolved"]["median"] < 10.0, report
    # The same solve instants and people, compared one by one.
    world, epoch = world_of(s)
    errors = [person_errors(world, epoch, stream) for stream in (live, frames)]
    common = [k for k in set(errors[0]) & set(errors[1]) if k[0] >= bound + 500_000_000]
    diff = np.array([errors[1][k] - errors[0][k] for k in common]) * 1e3
    assert len(diff) == report["person_frames"]
    assert float(np.median(diff)) <= PAIRED_MEDIAN_MAX_MM, (np.median(diff), report)
    assert float(np.mean(diff <= 0.0)) >= NOT_WORSE_FRACTION_MIN, (np.mean(diff <= 0.0), report)


def test_resolve_and_export_commands_round_trip_through_the_bvh_reader(
    recorded: tuple[Path, list[PoseFrame]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, _ = recorded
    assert cli.main(["resolve", str(path), "--iterations", "10"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["written"].endswith("poses-resolved.mcs") and "error_vs_truth_mm" in summary
    bvh, table = tmp_path / "out.bvh", tmp_path / "out.csv"
    args = ["export", str(path), "--resolved", "--subject", "suit:suit0", "--bvh", str(bvh), "--csv", str(table)]
    assert cli.main(args) == 0
    out = json.loads(capsys.readouterr().out)
    s = open_session(path)
    track = resample(subject_track(s.poses("poses-resolved"), "suit:suit0"), 60.0)
    assert out["frames"] == track.thetas.shape[0] > 100
    fk = Kinematics(track.skeleton or session_rig(s).skeleton).forward(track.thetas)  # its own skeleton, if sized

    motion = read_bvh(bvh)  # unit detected from the leg length: centimetres
    assert motion.fps == 60.0 and motion.n_frames == track.thetas.shape[0] and motion.joint_names[0] == "Hips"
    G, x = motion.forward()
    assert np.abs(x - fk.positions).max() < 1e-6  # metres; the file has 1e-8 m resolution
    angle = quat_angle(quat_from_matrix(G), quat_from_matrix(fk.rotations))
    assert angle.max() < 1e-6  # radians
    local = quat_angle(motion.rotations[:, 1:], quat_from_rotvec(track.thetas[:, 6:].reshape(-1, 20, 3)))
    assert local.max() < 1e-6

    with table.open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0][:7] == ["frame", "time_s", "t_solve_ns", "subject", "root_x", "root_y", "root_z"]
    assert len(rows) - 1 == track.thetas.shape[0] and rows[1][3] == "suit:suit0"
    first = rows[0].index("Hips_x")  # the 63 joint coordinates, then source_s
    assert rows[0][-1] == "source_s" and len(rows[0]) == first + 64
    positions = np.array([[float(v) for v in r[first : first + 63]] for r in rows[1:]]).reshape(-1, 21, 3)
    assert np.abs(positions - fk.positions).max() < 1e-6

    assert cli.main(["replay", str(path), "--resolved", "--speed", "50"]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[-1])["frames"] == len(s.poses("poses-resolved"))
    assert cli.main(["session", str(path)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["closed_cleanly"] and set(info["streams"]) >= {"imu", "keypoints", "poses", "poses-resolved"}
    assert cli.main(["export", str(path), "--subject", "nobody", "--csv", str(table)]) == 2

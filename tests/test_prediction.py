"""Predicted output: carrying a solved pose forward with the IMUs (pure), the predictor on true IMU buffers, and
the scheduler publishing suit wearers at the IMUs' instant, closer to the truth at the moment of publishing than
the delayed solve."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mocapd.core.imu import IMU_SET_6, IMU_SET_13
from mocapd.core.kinematics import Kinematics
from mocapd.core.prediction import carry_forward, carry_plan
from mocapd.core.rotations import (
    quat_angle,
    quat_from_matrix,
    quat_from_rotvec,
    quat_multiply,
    random_rotvec,
)
from mocapd.core.skeleton import BONE_INDEX, N_BONES, Skeleton
from mocapd.errors import InputError
from mocapd.pipeline.prediction import PosePredictor, PredictionOptions, SuitState
from mocapd.pipeline.ringbuffer import IMU_FIELDS, RingBuffer
from mocapd.pipeline.scheduler import SchedulerOptions
from mocapd.sim.world import SyntheticWorld
from tests.imu_lockstep import suit_lockstep

S = 1_000_000_000
MS = 1_000_000
PARENTS = Skeleton.from_height(1.75).parents


# --------------------------------------------------------------------------------------------- carry forward
def test_carry_plan_of_the_13_and_6_sensor_sets() -> None:
    plan = carry_plan(PARENTS, [BONE_INDEX[b] for b in IMU_SET_13])
    hips, spine3, head = BONE_INDEX["Hips"], BONE_INDEX["Spine3"], BONE_INDEX["Head"]
    for k, bone in enumerate(("Spine", "Spine1", "Spine2"), start=1):  # a quarter, half, three quarters ...
        assert plan.chain[BONE_INDEX[bone]] == (hips, spine3, k, 4)  # ... of the pelvis-to-sternum change
    assert plan.chain[BONE_INDEX["Neck"]] == (spine3, head, 1, 2)
    for bone in ("LeftHand", "RightHand", "LeftToes", "RightToes"):
        assert plan.chain[BONE_INDEX[bone]] is None and not plan.sensor[BONE_INDEX[bone]]
    assert sum(plan.sensor) == 13
    six = carry_plan(PARENTS, [BONE_INDEX[b] for b in IMU_SET_6])
    # The spine leads to head and both arms: no single share of one change, it follows the pelvis.
    assert all(six.chain[BONE_INDEX[b]] is None for b in ("Spine", "Spine1", "Spine2", "Spine3"))
    assert six.chain[BONE_INDEX["Neck"]] == (hips, head, 5, 6)
    assert six.chain[BONE_INDEX["LeftUpperLeg"]] == (hips, BONE_INDEX["LeftLowerLeg"], 1, 2)


def _globals(theta: np.ndarray) -> np.ndarray:
    return quat_from_matrix(Kinematics(Skeleton.from_height(1.75)).forward(theta).rotations)


def test_carry_forward_turns_sensor_bones_shares_chains_and_keeps_the_rest() -> None:
    rng = np.random.default_rng(4)
    theta = Skeleton.from_height(1.75).rest_pose()
    theta[3:] = random_rotvec(rng, (N_BONES,), max_angle=0.8).reshape(-1)
    sensors = [BONE_INDEX[b] for b in IMU_SET_13]
    plan = carry_plan(PARENTS, sensors)
    deltas = np.tile([1.0, 0.0, 0.0, 0.0], (N_BONES, 1))
    deltas[sensors] = quat_from_rotvec(random_rotvec(rng, (13,), max_angle=0.5))
    out = carry_forward(theta, PARENTS, plan, deltas, np.array([0.1, -0.2, 0.3]))
    before, after = _globals(theta), _globals(out)
    for b in sensors:  # exactly the measured turn, in the bone's own frame
        assert quat_angle(after[b], quat_multiply(before[b], deltas[b])) < 1e-9
    for b in (BONE_INDEX["LeftHand"], BONE_INDEX["RightToes"]):  # local rotation kept: follows its parent
        np.testing.assert_allclose(out[3 + 3 * b : 6 + 3 * b], theta[3 + 3 * b : 6 + 3 * b], atol=1e-9)
    np.testing.assert_allclose(out[0:3], theta[0:3] + np.array([0.1, -0.2, 0.3]))
    # Only the sternum turns: the spine bones between it and the pelvis take 1/4, 2/4, 3/4 of that turn.
    turn = np.tile([1.0, 0.0, 0.0, 0.0], (N_BONES, 1))
    turn[BONE_INDEX["Spine3"]] = quat_from_rotvec(np.array([0.0, 0.0, 0.6]))
    bent = _globals(carry_forward(theta, PARENTS, plan, turn, np.zeros(3)))
    shares = [quat_angle(bent[BONE_INDEX[n]], before[BONE_INDEX[n]]) / 0.6 for n in ("Spine", "Spine1", "Spine2")]
    np.testing.assert_allclose(shares, [0.25, 0.5, 0.75], atol=1e-9)
    # Nothing measured: nothing moves.
    still = carry_forward(theta, PARENTS, plan, np.tile([1.0, 0.0, 0.0, 0.0], (N_BONES, 1)), np.zeros(3))
    assert np.max(quat_angle(_globals(still), before)) < 1e-9
    with pytest.raises(InputError):
        carry_forward(theta[:60], PARENTS, plan, deltas, np.zeros(3))


# --------------------------------------------------------------------------------------------- predictor
class TruthSuit:
    """The suit of a world's first person, its true samples (100 Hz) buffered as time advances, handed to the
    predictor as the scheduler does."""

    def __init__(self, world: SyntheticWorld) -> None:
        suit = world.suits[0]
        cal = world.calibration(suit)
        self.q, self.a = world.imu_motion(suit, 100.0)
        ids = [f"{s:08X}" for s in suit.sensor_ids]
        self.buffers: list[RingBuffer | None] = [RingBuffer(1024, IMU_FIELDS) for _ in ids]
        self.next_ns = 0
        self.base = SuitState(
            bones=np.array([m.bone_index for m in suit.mounts], dtype=np.intp),
            q_ib=np.array([cal.q_ib[s] for s in ids]), q_wg=np.tile(cal.q_ig, (len(ids), 1)),
            q_i=np.zeros((len(ids), 4)), mask=np.ones(len(ids), dtype=bool), buffers=self.buffers,
            offsets_ns=np.zeros(len(ids), dtype=np.int64), hips=0, hips_site=suit.mounts[0].t_ib,
        )  # fmt: skip

    def advance(self, until_ns: int, stopped: dict[int, int] | None = None) -> None:
        """Buffer every sample up to ``until_ns`` (sensor k only up to ``stopped[k]``)."""
        while self.next_ns <= until_ns:
            i = round(self.next_ns / 1e7) % self.q.shape[1]
            for j, buf in enumerate(self.buffers):
                if buf is not None and self.next_ns <= (stopped or {}).get(j, until_ns):
                    buf.push(self.next_ns, np.r_[self.q[j, i], self.a[j, i], np.nan, np.nan])
            self.next_ns += 10 * MS

    def state(self, t_ns: int) -> SuitState:
        """What the scheduler hands the predictor for a solve at ``t_ns``."""
        q_i = np.array([b.sample(t_ns).row[0:4] for b in self.buffers if b is not None])
        return replace(self.base, q_i=q_i)


def test_predictor_carries_the_true_pose_to_the_newest_sample() -> None:
    """Fed with the true pose at every solve instant and true IMU samples, the pose carried 150 ms forward lands on
    the truth at its new instant: sensor bones to a fraction of a degree (slerp between samples), the root within
    millimetres."""
    world = SyntheticWorld(1, 1, 1, motion="recorded")
    pred = PosePredictor(PredictionOptions(output="predicted", acceleration_decay_s=100.0))
    suit = TruthSuit(world)
    sensor_bones = [m.bone_index for m in world.suits[0].mounts]
    root, ori = [], []
    for k in range(40, 160):  # 2 s of 60 Hz solves, from 0.67 s on
        now = k * S // 60
        t = now - 150 * MS
        suit.advance(now)
        p = pred.predict("suit:suit0", world.theta_at(0, t / 1e9), PARENTS, t, suit.state(t))
        assert p.t_ns == now - now % (10 * MS) and p.sensors == 13  # the newest sample every sensor has
        truth = world.theta_at(0, p.t_ns / 1e9)
        root.append(np.linalg.norm(p.theta[0:3] - truth[0:3]))
        got, want = (quat_from_matrix(world.kin.forward(th).rotations[sensor_bones]) for th in (p.theta, truth))
        ori.append(np.degrees(quat_angle(got, want)).max())
    assert max(ori) < 0.5
    assert np.percentile(root[20:], 95) < 0.002  # metres


def test_predictor_leaves_out_a_stalled_sensor_and_keeps_the_delayed_pose_without_news() -> None:
    world = SyntheticWorld(1, 1, 1, motion="recorded")
    pred = PosePredictor(PredictionOptions(output="predicted"))
    t, now = 1 * S, 1 * S + 150 * MS
    theta = world.theta_at(0, t / 1e9)
    head = IMU_SET_13.index("Head")
    suit = TruthSuit(world)
    suit.advance(t)
    same = pred.predict("b", theta, PARENTS, t, suit.state(t))  # nothing newer than the solve instant
    assert same.t_ns == t and same.sensors == 0 and same.theta is theta
    suit.advance(now, stopped={head: t + 20 * MS})  # the head sensor stalled 130 ms ago
    state = suit.state(t)
    p = pred.predict("a", theta, PARENTS, t, state)
    assert p.t_ns == now and p.sensors == 12
    # Without its sensor the head keeps its local rotation: it follows the neck.
    h = BONE_INDEX["Head"]
    np.testing.assert_allclose(p.theta[3 + 3 * h : 6 + 3 * h], theta[3 + 3 * h : 6 + 3 * h], atol=1e-9)
    # A horizon bounds how far a pose is carried.
    short = PosePredictor(PredictionOptions(output="predicted", max_horizon_s=0.05))
    assert short.predict("c", theta, PARENTS, t, state).t_ns == t + 50 * MS


def test_predictor_leaves_out_a_sensor_whose_buffer_has_a_hole_at_the_new_instant() -> None:
    """A sensor newer than the solve whose buffer cannot be interpolated at the instant carried to (a dropout, as a
    SlimeVR tracker's on Wi-Fi) is left out; the others carry the pose (this raised IndexError in a live daemon)."""
    world = SyntheticWorld(1, 1, 1, motion="recorded")
    pred = PosePredictor(PredictionOptions(output="predicted"))
    t, now = 1 * S, 1 * S + 150 * MS
    theta = world.theta_at(0, t / 1e9)
    suit = TruthSuit(world)
    head = IMU_SET_13.index("Head")
    buf = suit.buffers[head] = RingBuffer(1024, IMU_FIELDS, max_gap_ns=50 * MS)
    suit.advance(now, stopped={head: t + 10 * MS})
    buf.push(now + 10 * MS, buf.rows()[-1].copy())  # the head sensor is back after a hole longer than max_gap
    p = pred.predict("a", theta, PARENTS, t, suit.state(t))
    assert p.t_ns == now and p.sensors == 12


def test_prediction_options_are_validated() -> None:
    with pytest.raises(InputError, match="output"):
        PredictionOptions(output="future")
    with pytest.raises(InputError, match="velocity_window_s"):
        PredictionOptions(velocity_window_s=0.0)


# --------------------------------------------------------------------------------------------- in the rig
def _errors(world: SyntheticWorld, theta: np.ndarray, t_ns: int) -> tuple[float, float]:
    """Mean bone orientation error (deg) and mean joint position error (m) against the truth at ``t_ns``."""
    got, want = world.kin.forward(theta), world.kin.forward(world.theta_at(0, t_ns / 1e9))
    angle = float(np.degrees(quat_angle(quat_from_matrix(got.rotations), quat_from_matrix(want.rotations))).mean())
    return angle, float(np.linalg.norm(got.positions - want.positions, axis=1).mean())


def test_predicted_output_is_closer_to_the_truth_at_publish_time() -> None:
    """The suit wearer is published for the IMUs' newest instant, a few ms before the tick, not 150 ms before it;
    measured against the truth at the tick (the moment of publishing), its bone orientations are at least three
    times closer than the delayed solve's. The person without a suit keeps the delayed pose."""
    ls = suit_lockstep(SchedulerOptions(prediction=PredictionOptions(output="predicted")), n_people=2)
    delayed, predicted = [], []
    for k in range(240):  # 4 s
        now = ls.now_ns
        frame = ls.tick()
        assert frame.output == "predicted"
        if k < 90:
            continue  # enrolment, suit pairing
        for p in frame.people:
            if p.suit is None:
                assert p.solved is None and frame.pose_time_ns(p) == frame.t_solve_ns
                continue
            assert p.solved is not None and p.solved.t_pose_ns == frame.t_solve_ns
            assert now - 20 * MS <= frame.pose_time_ns(p) <= now
            delayed.append(_errors(ls.world, p.solved.theta, now))
            predicted.append(_errors(ls.world, p.theta, now))
    d, q = np.median(delayed, axis=0), np.median(predicted, axis=0)
    print(f"at publish time: orientation {d[0]:.2f}° delayed, {q[0]:.2f}° predicted; joints {1e3 * d[1]:.1f} mm "
          f"delayed, {1e3 * q[1]:.1f} mm predicted ({len(predicted)} frames)")  # fmt: skip
    assert len(predicted) >= 140
    assert q[0] <= d[0] / 3 and q[1] <= d[1] / 3
    lat = ls.scheduler.latency["imu_to_publish"]
    assert lat.summary()["count"] == 0  # accounted only when the caller publishes
    ls.scheduler.record_publish(frame, *ls.scheduler.stage_clocks(), ls.now_ns)
    assert lat.summary()["count"] == 1


def test_prediction_can_wait_for_the_samples_that_arrive_while_solving() -> None:
    """The daemon solves first (``tick(predict=False)``), lets the IMU inputs buffer what arrived meanwhile, then
    carries the frame to the newest of it (``predict``): here 30 ms of samples arrive in between."""
    ls = suit_lockstep(SchedulerOptions(prediction=PredictionOptions(output="predicted")))
    ls.run(1.5)
    now = ls.now_ns
    ls.feed(now)
    frame = ls.scheduler.tick(now, predict=False)
    (wearer,) = [p for p in frame.people if p.suit is not None]
    assert wearer.solved is None and frame.pose_time_ns(wearer) == frame.t_solve_ns  # not carried yet
    ls.feed(now + 30 * MS)
    carried = ls.scheduler.predict(frame)
    (p,) = [p for p in carried.people if p.suit is not None]
    assert p.solved is not None and p.solved.theta is wearer.theta and carried.pose_time_ns(p) == now + 30 * MS
    ls.ticks += 1
    ls.tick()
    assert ls.scheduler.predict(frame) is frame  # an older frame is not carried again


def test_a_wearer_resized_by_this_solve_is_published_as_solved() -> None:
    """Body sizing drops a person's solver in the solve (the next tick rebuilds it on the new skeleton); carrying that
    frame forward then raised KeyError in the daemon's tick task (seen in tests/test_daemon.py's predicted run). The
    wearer is published as solved, and counted."""
    ls = suit_lockstep(SchedulerOptions(prediction=PredictionOptions(output="predicted")))
    ls.run(1.5)
    now = ls.now_ns
    ls.feed(now)
    frame = ls.scheduler.tick(now, predict=False)
    (wearer,) = [p for p in frame.people if p.suit is not None]
    ls.scheduler.solvers.pop(wearer.identity)  # what _size_body does when the body is sized
    carried = ls.scheduler.predict(frame)
    (p,) = [p for p in carried.people if p.suit is not None]
    assert p is wearer and p.solved is None and carried.pose_time_ns(p) == frame.t_solve_ns
    assert ls.scheduler.counters["predictions_skipped"] == 1


def test_delayed_output_publishes_the_solve() -> None:
    ls = suit_lockstep(n_people=1)
    frames = ls.run(1.5)
    assert all(f.output == "delayed" for f in frames)
    suited = [(f, p) for f in frames for p in f.people if p.suit is not None]
    assert suited and all(p.solved is None and f.pose_time_ns(p) == f.t_solve_ns for f, p in suited)

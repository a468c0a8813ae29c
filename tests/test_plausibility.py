"""Anatomical plausibility (issue 28): knees and elbows bending the wrong way, a pelvis facing backwards while the
legs walk forwards, the facing from the knees' bending; in the live scheduler's /status."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mocapd.core.imu_calibration import ImuCalibration
from mocapd.core.people import PeopleTracker
from mocapd.core.plausibility import (
    PlausibilityMonitor,
    PlausibilityOptions,
    facing_from_knees,
    first_events,
    hinge_angles,
    wrong_way_events,
)
from mocapd.core.rotations import quat_from_rotvec, quat_multiply
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.core.sorting import DetectionSorter
from mocapd.core.suit_binding import SuitBinder
from mocapd.core.tracking import SubjectTracker
from mocapd.errors import InputError
from mocapd.pipeline.imu_ingest import ImuIngest
from mocapd.pipeline.scheduler import FixedLatencyScheduler, Suit
from mocapd.sim.world import SyntheticWorld

S = 1_000_000_000


def _pose(**bones: tuple[float, float, float]) -> np.ndarray:
    th = Skeleton.from_height(1.75).rest_pose()
    for bone, r in bones.items():
        i = BONE_INDEX[bone]
        th[3 + 3 * i : 6 + 3 * i] = r
    return th


def test_hinge_angles_sign_is_the_anatomical_bend() -> None:
    """A knee flexes with the foot going backwards (+X rotation of the shank in the thigh's frame), an elbow with
    the hand going forwards (the T-pose's arms along ±X, palms down)."""
    a = np.radians(40.0)
    bent = hinge_angles(_pose(LeftLowerLeg=(a, 0, 0), RightLowerLeg=(-a, 0, 0), LeftLowerArm=(0, -a, 0),
                              RightLowerArm=(0, -a, 0)))  # fmt: skip
    assert bent["left_knee"] == pytest.approx(40.0) and bent["right_knee"] == pytest.approx(-40.0)
    assert bent["left_elbow"] == pytest.approx(40.0) and bent["right_elbow"] == pytest.approx(-40.0)
    assert all(v == pytest.approx(0.0) for v in hinge_angles(_pose()).values())
    with pytest.raises(InputError):
        hinge_angles(np.zeros(10))


def test_a_wrong_way_bend_is_an_event_only_when_it_lasts() -> None:
    t = np.arange(100) / 100.0
    angles = np.full(100, 10.0)
    angles[10:14] = -40.0  # 40 ms: noise, a fast pass
    angles[50:90] = -30.0  # 0.4 s
    angles[60] = np.nan  # unknown splits it: two runs of 0.1 and 0.29 s, one of them an event
    ev = wrong_way_events(angles, t, PlausibilityOptions())
    assert ev.events == 1 and ev.seconds == pytest.approx(0.29) and ev.worst_deg == pytest.approx(30.0)
    assert ev.first_s == pytest.approx(0.61)
    with pytest.raises(InputError):
        PlausibilityOptions(backwards_deg=60.0)


def _walk(hips_yaw: float, thigh_yaw: float, knee: float = 0.3) -> PlausibilityMonitor:
    """2 s of the root moving along +Z at 1 m/s with the hips and thighs turned about the vertical."""
    m = PlausibilityMonitor()
    for k in range(120):
        th = _pose(Hips=(0, hips_yaw, 0), LeftUpperLeg=(0, thigh_yaw, 0), RightUpperLeg=(0, thigh_yaw, 0),
                   LeftLowerLeg=(knee * (1 + np.sin(k / 5)), 0, 0))  # fmt: skip
        th[2] = k / 60.0
        m.step(k / 60.0, th)
    return m


def test_pelvis_backwards_while_the_legs_walk_forwards() -> None:
    ok = _walk(0.0, 0.0)
    assert not ok.implausible and ok.status() == {"implausible": False, "events": {}, "now": []}
    backwards = _walk(np.pi, 0.0)  # walking backwards: pelvis and thighs face away from the travel, fine
    assert not backwards.implausible
    twisted = _walk(np.pi, np.pi)  # pelvis turned round, thighs (in the pelvis' frame turned back) face forward
    st = twisted.status()
    # From the first frame with a direction of travel (0.25 s) to the end, counted once it lasted 1 s.
    assert st["events"] == {"pelvis_backwards": {"events": 1, "seconds": pytest.approx(1.75, abs=0.05)}}
    assert st["now"] == ["pelvis_backwards"]
    assert "pelvis faced backwards" in twisted.summary_lines()[0]
    knees = _walk(0.0, 0.0, knee=-0.4)  # the left knee bends backwards up to 46°
    events = knees.status()["events"]
    assert isinstance(events, dict) and events["left_knee"]["worst_deg"] == pytest.approx(45.8, abs=0.5)


def test_facing_from_the_knees() -> None:
    """Thigh and shank sensors mounted anyhow, on a subject facing heading 30° (east of north) who bends the knee:
    the hinge axis gives the facing; with the knee bending the other way it would be the opposite one."""
    rng = np.random.default_rng(1)
    heading = np.radians(30.0)
    yaw = quat_from_rotvec(np.array([0.0, 0.0, -heading]))  # ENU: turned clockwise from north, about up (z)
    bends = np.radians(np.r_[np.zeros(20), np.linspace(0, 60, 40), np.linspace(60, 0, 40)])
    # The subject faces +y (north) before the yaw; its left is -x; flexion is a positive turn about its left.
    shank = quat_from_rotvec(np.outer(bends, [-1.0, 0.0, 0.0]))
    m_t, m_s = (quat_from_rotvec(rng.normal(size=3)) for _ in range(2))
    q_t = quat_multiply(np.tile(yaw, (100, 1)), m_t)
    q_s = quat_multiply(quat_multiply(yaw, shank), m_s)
    f = facing_from_knees([(q_t, q_s)], [q_t[0]], np.array([0.0, 0.0, 1.0]))
    assert f is not None
    assert np.degrees(np.arctan2(f[0], f[1])) == pytest.approx(30.0, abs=0.5)
    assert facing_from_knees([(q_t[:20], q_s[:20])], [q_t[0]], np.array([0.0, 0.0, 1.0])) is None  # no bend


def _imu_only_scheduler(world: SyntheticWorld, calib: ImuCalibration) -> tuple[FixedLatencyScheduler, ImuIngest]:
    ingest = ImuIngest()
    tracker = PeopleTracker(SubjectTracker(DetectionSorter([])), SuitBinder(world.skeleton))
    suit = Suit.from_calibration("suit0", calib, world.skeleton)
    return FixedLatencyScheduler([], world.skeleton, world.targets, tracker, ingest=ingest, suits=[suit]), ingest


@pytest.mark.parametrize("mirrored", [False, True])
def test_the_live_scheduler_counts_knees_bending_backwards(mirrored: bool) -> None:
    """An IMU-only suit on recorded motion (knees bending), calibrated right or with its facing mirrored (every bone
    frame turned by 180° about the vertical, what the wrong --facing-from sign does): only the mirrored one shows
    knee events in the scheduler's status (/status ``plausibility``)."""
    world = SyntheticWorld(n_cams=0, n_people=1, n_suits=1, seed=2)
    calib = world.calibration(world.suits[0])
    if mirrored:
        turn = quat_from_rotvec(np.array([0.0, np.pi, 0.0]))
        calib = replace(calib, q_ib={k: quat_multiply(turn, q) for k, q in calib.q_ib.items()})
    sched, ingest = _imu_only_scheduler(world, calib)
    q, a = world.imu_motion(world.suits[0], 100.0)
    ids = [f"{s:08X}" for s in world.suits[0].sensor_ids]
    for i in range(400):  # 4 s
        t = S + i * S // 100
        for j, sid in enumerate(ids):
            ingest.add(sid, t, device_ticks=None, packet_counter=None, quat=tuple(q[j, i]), acc=tuple(a[j, i]))
        if i % 2 == 0 and i > 30:
            sched.tick(t)
    st = sched.status()["plausibility"]
    assert list(st) == ["suit:suit0"]
    knees = {k: v for k, v in st["suit:suit0"]["events"].items() if "knee" in k}
    assert bool(knees) == mirrored and st["suit:suit0"]["implausible"] == mirrored
    # What the live daemon says on its console (once per person and check), not only in /status.
    said: set[tuple[str, str]] = set()
    lines = first_events(sched.plausibility, said)
    assert len([line for line in lines if "knee bent the wrong way" in line]) == len(knees)
    for line in lines:
        assert line.startswith("suit:suit0: the ") and "a facing direction mirrored at calibration" in line
    assert first_events(sched.plausibility, said) == []  # said once


def test_a_camera_only_person_is_not_told_to_recalibrate_a_suit() -> None:
    """A person the cameras track alone (``track:N``) whose elbow bent the wrong way is told about the keypoints,
    not about a facing direction or sensors they do not wear; a suit wearer keeps the calibration advice."""
    monitors = {"track:2": PlausibilityMonitor(), "suit:suit0": PlausibilityMonitor()}
    for m in monitors.values():
        m.events["right_elbow"] = 1
        m.worst_deg["right_elbow"] = 152.0
    lines = dict(line.split(": ", 1) for line in first_events(monitors, set()))
    assert "the right elbow bent the wrong way (up to 152°)" in lines["track:2"]
    assert "detector misplacing that limb's keypoints" in lines["track:2"]
    assert "facing direction" not in lines["track:2"] and "sensor" not in lines["track:2"]
    assert "a facing direction mirrored at calibration" in lines["suit:suit0"]

"""Issue 42: in a rig with cameras and IMUs, the first seconds in which the cameras see a suit's wearer refine the
sensors' mountings (mocapd.core.camera_mounting): on numbers, and in the synthetic rig's scheduler fed tick by tick
(sensors strapped 5-15° off what the calibration says); a rig without cameras changes nothing."""

from __future__ import annotations

import asyncio
import json
import logging
from dataclasses import replace

import numpy as np
import pytest

from mocapd.core.camera_mounting import CameraMountingEstimator, MountingOptions, fit_mounting
from mocapd.core.heading import BoneVectors, bone_vectors, yaw_quat
from mocapd.core.rotations import (
    quat_angle,
    quat_conjugate,
    quat_from_matrix,
    quat_from_rotvec,
    quat_multiply,
    quat_normalize,
    quat_rotate,
)
from mocapd.errors import InputError
from mocapd.pipeline.scheduler import SchedulerOptions
from mocapd.service.assembly import RunOptions, assembled
from mocapd.service.config import load_config
from mocapd.service.demo.synthetic import synthetic_config
from mocapd.service.live_calibration import install_suit
from tests.imu_lockstep import SuitLockstep, suit_lockstep
from tests.test_daemon import Recorder, http_get, wait_for


def _turn(rng: np.random.Generator, lo: float, hi: float) -> np.ndarray:
    axis = rng.normal(size=3)
    return np.asarray(quat_from_rotvec(np.radians(rng.uniform(lo, hi)) * axis / np.linalg.norm(axis)))


def _observations(
    q_ib: np.ndarray, v: np.ndarray, frames: int, noise_deg: float, seed: int, heading_deg: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per frame a sensor turned anyhow (``S``, (4,)), the bone-frame vectors ``v`` (m, 3) seen in the world as
    ``o = R_y(heading) · S · R_ib⁻¹ · v``, each turned by up to ``noise_deg`` of keypoint noise; returns per vector
    ``S``, ``o``, ``v`` and its frame number."""
    rng = np.random.default_rng(seed)
    q_s = np.vstack([np.repeat(_turn(rng, 0.0, 120.0)[None], len(v), axis=0) for _ in range(frames)])
    vv = np.tile(v, (frames, 1))
    bone = quat_multiply(yaw_quat(np.array(np.radians(heading_deg)))[None], quat_multiply(q_s, quat_conjugate(q_ib)))
    o = np.array([quat_rotate(quat_multiply(_turn(rng, 0.0, noise_deg), b), x) for b, x in zip(bone, vv, strict=True)])
    return q_s, o, vv, np.repeat(np.arange(frames), len(v))


def test_a_mounting_is_the_rotation_that_takes_the_seen_vectors_onto_the_bone_s() -> None:
    rng = np.random.default_rng(0)
    truth = _turn(rng, 20.0, 30.0)
    start = quat_multiply(_turn(rng, 10.0, 10.0), truth)  # the calibration: 10° off
    head = np.array([[0.07, 0.0, 0.0], [0.03, 0.04, 0.08], [-0.03, 0.04, 0.08]])  # ears, eyes: three directions
    fit = fit_mounting(start, *_observations(truth, head, 40, 2.0, 1), MountingOptions())
    assert fit.used and np.degrees(quat_angle(fit.q_ib, truth)) < 1.0
    assert fit.change_deg == pytest.approx(10.0, abs=1.0) and fit.misfit_deg < 3.0
    # a sensor whose heading is 30° off: the heading error is fitted beside the mounting, not taken up by it
    fit = fit_mounting(start, *_observations(truth, head, 40, 2.0, 1, heading_deg=30.0), MountingOptions())
    assert fit.used and np.degrees(quat_angle(fit.q_ib, truth)) < 1.0 and fit.heading_deg == pytest.approx(30, abs=1)
    # one keypoint pair (a limb's two joints): where the limb points is fitted, its twist stays the calibration's
    limb = np.array([[0.0, -0.4, 0.0]])
    fit = fit_mounting(start, *_observations(truth, limb, 40, 2.0, 2), MountingOptions())
    seen = quat_rotate(quat_conjugate(fit.q_ib)[None], limb)[0]
    true = quat_rotate(quat_conjugate(truth)[None], limb)[0]
    assert np.degrees(np.arccos(seen @ true / (np.linalg.norm(seen) * np.linalg.norm(true)))) < 0.5
    assert fit.used and fit.change_deg < 10.0 + 0.5  # the smallest turn that does it


def test_outlying_frames_are_dropped_and_the_rule_keeps_a_mounting_it_cannot_trust() -> None:
    rng = np.random.default_rng(3)
    truth = _turn(rng, 0.0, 30.0)
    start = quat_multiply(_turn(rng, 8.0, 8.0), truth)
    v = np.array([[0.07, 0.0, 0.0], [0.0, 0.05, 0.08]])
    q_s, o, vv, frame = _observations(truth, v, 40, 1.0, 4)
    wrong = np.isin(frame, [3, 11, 25])  # three frames of mismatched keypoints
    o[wrong] = quat_rotate(_turn(rng, 60.0, 90.0)[None], o[wrong])
    fit = fit_mounting(start, q_s, o, vv, frame, MountingOptions())
    assert fit.used and fit.rejected == 3 and np.degrees(quat_angle(fit.q_ib, truth)) < 1.0
    first = frame < 5
    few = fit_mounting(start, q_s[first], o[first], vv[first], frame[first], MountingOptions())
    assert not few.used and few.reason == "5 frames, needs 20" and np.array_equal(few.q_ib, start)
    far = fit_mounting(start, q_s, o, vv, frame, MountingOptions(max_change_deg=5.0))
    assert not far.used and far.reason.startswith("would turn the mounting 8.") and "above 5" in far.reason
    noisy = fit_mounting(start, *_observations(truth, v, 40, 25.0, 5), MountingOptions())
    assert not noisy.used and noisy.reason.startswith("misfit")
    for bad in ({"seconds": 0.0}, {"min_frames": 0}, {"max_change_deg": float("nan")}, {"outlier_floor_deg": -1.0}):
        with pytest.raises(InputError):
            MountingOptions(**bad)


def test_the_estimator_fits_each_suit_once_after_its_seconds_and_never_when_off() -> None:
    est = CameraMountingEstimator(MountingOptions(seconds=1.0, min_frames=3))
    vectors = [BoneVectors("Head", np.array([0, 1]), np.array([1, 2]), np.array([[0.07, 0.0, 0.0], [0.0, 0.05, 0.08]]))]
    points = np.array([[0.0, 1.6, 0.0], [0.07, 1.6, 0.0], [0.07, 1.65, 0.08]])
    ok = np.ones(3, dtype=bool)
    q = np.array([[1.0, 0.0, 0.0, 0.0]])
    for k in range(10):
        est.observe("suit0", k * 100_000_000, ["A"], q, vectors, points, ok)
        assert est.ready("suit0", k * 100_000_000) == (k * 0.1 >= 1.0)
    assert est.status() == {"suit0": {"state": "gathering", "frames": 10}}
    est.observe("suit0", 1_000_000_000, ["A"], q, vectors, points, ok)
    assert est.ready("suit0", 1_000_000_000)
    fits = est.fit("suit0", {"A": np.array([1.0, 0.0, 0.0, 0.0]), "B": np.array([1.0, 0.0, 0.0, 0.0])})
    assert fits["A"].used and fits["A"].change_deg < 1e-3 and fits["B"].reason == "not seen by the cameras"
    assert not est.wants("suit0") and not est.ready("suit0", 9_000_000_000)
    assert est.status()["suit0"]["state"] == "done"
    off = CameraMountingEstimator(MountingOptions(enabled=False))
    off.observe("suit0", 0, ["A"], q, vectors, points, ok)
    assert not off.ready("suit0", 10**10) and off.status() == {}


def test_a_wearer_seen_seldom_is_gathered_until_the_fit_has_its_frames() -> None:
    """A loaded machine observes the wearer less often than every 50 ms: the seconds passed with fewer frames than a
    fit needs, and the fit made then kept every calibration's mounting for good ("3 frames, needs 5"; the daemon's
    test saw 0 of 13 refined under load). Gathering goes on until the frames are there too."""
    est = CameraMountingEstimator(MountingOptions(seconds=1.0, min_frames=5))
    vectors = [BoneVectors("Head", np.array([0, 1]), np.array([1, 2]), np.array([[0.07, 0.0, 0.0], [0.0, 0.05, 0.08]]))]
    points = np.array([[0.0, 1.6, 0.0], [0.07, 1.6, 0.0], [0.07, 1.65, 0.08]])
    ok = np.ones(3, dtype=bool)
    q = np.array([[1.0, 0.0, 0.0, 0.0]])
    for k in range(5):
        t = k * 600_000_000  # one observation every 0.6 s
        est.observe("suit0", t, ["A"], q, vectors, points, ok)
        assert est.ready("suit0", t) == (k == 4), k  # 1.2 s passed at the third frame: not yet
    fits = est.fit("suit0", {"A": np.array([1.0, 0.0, 0.0, 0.0])})
    assert fits["A"].used and fits["A"].frames == 5


# ------------------------------------------------------------------------------------------------ in the rig
def _strapped_askew(ls: SuitLockstep, seed: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The suit's calibration made 5-15° wrong per sensor (the world's sensors stay where they are): the true and
    the calibrated mountings."""
    suit = ls.scheduler.suits["suit0"]
    truth = dict(suit.calibration.q_ib)
    rng = np.random.default_rng(seed)
    wrong = {sid: quat_multiply(_turn(rng, 5.0, 15.0), q) for sid, q in truth.items()}
    install_suit(ls.scheduler, list(ls.scheduler.suits.values()),
                 replace(suit, calibration=replace(suit.calibration, q_ib=wrong)))  # fmt: skip
    return truth, wrong


def _direction_error_deg(q: np.ndarray, truth: np.ndarray, bv: BoneVectors) -> float:
    """How far the bone's keypoint vectors point, in the sensor's frame, from where they truly do (mean, degrees):
    what the cameras can see of a mounting."""
    a = quat_rotate(quat_conjugate(q)[None], bv.vectors)
    b = quat_rotate(quat_conjugate(truth)[None], bv.vectors)
    cos = np.einsum("ij,ij->i", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return float(np.degrees(np.mean(np.arccos(np.clip(cos, -1.0, 1.0)))))


def test_the_cameras_first_seconds_refine_the_mountings_of_the_synthetic_rig(caplog: pytest.LogCaptureFixture) -> None:
    """Four cameras, COCO-17, the recorded motion, every sensor's calibrated mounting 5-15° off: 3 s after the
    wearer is first seen, every sensor whose bone the cameras see has its mounting refined; the mountings' error
    falls by more than half, where each limb points in its sensor's frame to within 1° (the turn about the limb
    itself the cameras cannot see: it stays the calibration's). The feet (no foot keypoint in COCO-17) are kept."""
    ls = suit_lockstep(SchedulerOptions(rate_hz=30, mounting=MountingOptions()), rate_hz=30)
    truth, wrong = _strapped_askew(ls, 7)
    suit = ls.scheduler.suits["suit0"]
    vectors = dict(zip(suit.sensors, bone_vectors(ls.world.skeleton, ls.world.targets, [m.bone for m in suit.mounts]),
                       strict=True))  # fmt: skip
    with caplog.at_level(logging.INFO, logger="mocapd.pipeline.scheduler"):
        ls.run(4.0)
    after = ls.scheduler.suits["suit0"].calibration.q_ib
    status = ls.scheduler.mounting_status()["suit0"]
    assert status["state"] == "done"
    fits = status["sensors"]
    assert isinstance(fits, dict)
    feet = {sid for sid in truth if suit.calibration.bones[sid].endswith("Foot")}
    seen = set(truth) - feet
    assert {sid for sid, f in fits.items() if f["used"]} == seen, fits
    assert all(fits[sid]["reason"] == "not seen by the cameras" and np.array_equal(after[sid], wrong[sid])
               for sid in feet)  # fmt: skip

    def err(q: dict[str, np.ndarray], sid: str) -> float:
        return float(np.degrees(quat_angle(q[sid], truth[sid])))

    before_mean = np.mean([err(wrong, s) for s in seen])
    after_mean = np.mean([err(after, s) for s in seen])
    direction_before = [_direction_error_deg(wrong[s], truth[s], vectors[s]) for s in seen]
    direction_after = [_direction_error_deg(after[s], truth[s], vectors[s]) for s in seen]
    print(f"camera mountings: 11 sensors seen, mounting error {before_mean:.1f}° -> {after_mean:.1f}° (mean), "
          f"the limbs' directions {np.mean(direction_before):.1f}° -> {np.mean(direction_after):.1f}° "
          f"(worst {max(direction_after):.1f}°)")  # fmt: skip
    assert after_mean < 0.45 * before_mean
    assert max(direction_after) < 1.0 and min(direction_before) > 2.5
    # the change per sensor is on the console, the solver fuses the new mountings
    logged = [r.getMessage() for r in caplog.records if "refined from the cameras" in r.getMessage()]
    assert len(logged) == 1 and logged[0].startswith(f"suit suit0: {len(seen)} of {len(truth)} mountings refined")
    assert all(f"{sid} ({suit.calibration.bones[sid]})" in logged[0] for sid in truth)
    np.testing.assert_array_equal(ls.scheduler._q_ib["suit0"], np.array([after[s] for s in suit.sensors]))
    # once only: later frames change nothing
    ls.run(1.0)
    assert ls.scheduler.suits["suit0"].calibration.q_ib == after


def test_a_rig_without_cameras_never_changes_a_mounting() -> None:
    ls = suit_lockstep(SchedulerOptions(rate_hz=30, mounting=MountingOptions()), rate_hz=30, n_cams=0)
    _, wrong = _strapped_askew(ls, 8)
    ls.run(4.0)
    assert ls.scheduler.suits["suit0"].calibration.q_ib == wrong
    assert ls.scheduler.mounting_status() == {}


def test_one_camera_never_changes_a_mounting() -> None:
    ls = suit_lockstep(SchedulerOptions(rate_hz=30, mounting=MountingOptions()), rate_hz=30)
    _, wrong = _strapped_askew(ls, 9)
    ls.live_cameras = {0}
    ls.run(4.0)
    assert ls.scheduler.suits["suit0"].calibration.q_ib == wrong and ls.scheduler.mounting_status() == {}


def _bone_error_deg(ls: SuitLockstep, seconds: float) -> np.ndarray:
    """Per suit sensor, how far its bone orientation as the solver gets it (heading-corrected, with the suit's
    mountings now) is from the true one (degrees), averaged over the next ``seconds``."""
    sched = ls.scheduler
    errors = []
    for frame in ls.run(seconds):
        suit = sched.suits["suit0"]
        fk = ls.world.kin.forward(ls.world.theta_at(0, frame.t_solve_ns / 1e9))
        q_true = quat_from_matrix(fk.rotations[[m.bone_index for m in suit.mounts]])
        q_i = np.array([ls.ingest.streams[s].buffer.sample(frame.t_solve_ns).row[0:4] for s in suit.sensors])
        q_ib = np.array([suit.calibration.q_ib[s] for s in suit.sensors])
        q_gb = quat_multiply(quat_multiply(suit.calibration.q_ig[None], quat_normalize(q_i)), quat_conjugate(q_ib))
        q_gb = quat_multiply(yaw_quat(sched.heading.offsets(suit.sensors)), q_gb)
        errors.append(np.degrees(quat_angle(q_gb, q_true)))
    return np.asarray(np.mean(errors, axis=0), dtype=np.float64)


def test_with_bent_headings_too_the_bones_come_nearer_the_truth() -> None:
    """The mountings 5-15° off and every sensor's heading ±45° off, drifting 10°/min (as the heading correction's
    own test): the heading error is fitted beside each mounting, not taken up by it, so after 10 s the bones the
    solver gets are nearer the truth than with the heading correction alone."""
    errors = {}
    for on in (False, True):
        ls = suit_lockstep(SchedulerOptions(rate_hz=30, mounting=MountingOptions(enabled=on)), rate_hz=30)
        _strapped_askew(ls, 7)
        ls.faults = ls.world.heading_faults(ls.world.suits[0], 45.0, 10.0, seed=1)
        ls.run(9.0)
        errors[on] = _bone_error_deg(ls, 1.0)[:11]  # the feet: no keypoint in COCO-17, left as they are
    print(f"camera mountings with bent headings: bone error {errors[False].mean():.1f}° -> {errors[True].mean():.1f}° "
          f"(mean of 11; worst {errors[False].max():.1f}° -> {errors[True].max():.1f}°)")  # fmt: skip
    assert errors[True].mean() < 0.8 * errors[False].mean()


def test_exact_mountings_are_not_made_worse() -> None:
    """The synthetic rig's calibration as simulated (exact): the refit changes little, and the bones the solver gets
    are no further from the truth than without it."""
    errors = {}
    for on in (False, True):
        ls = suit_lockstep(SchedulerOptions(rate_hz=30, mounting=MountingOptions(enabled=on)), rate_hz=30)
        ls.run(5.0)
        errors[on] = _bone_error_deg(ls, 1.0)[:11]
    print(f"camera mountings, exact calibration: bone error {errors[False].mean():.2f}° -> {errors[True].mean():.2f}°")
    assert errors[True].mean() <= errors[False].mean() + 0.1 and errors[True].max() < 1.0


@pytest.mark.asyncio
async def test_the_daemon_refines_its_suit_once_and_says_so(caplog: pytest.LogCaptureFixture) -> None:
    """``mocapd run`` on the synthetic rig with ``[daemon] mounting_from_cameras = true``: once the suit is bound and
    the cameras have seen its wearer for 3 s, /status ``imu_mounting_from_cameras`` has each sensor's fit and the
    console a line per sensor refined (the synthetic suit's calibration is exact: the changes are small)."""
    cfg = load_config()
    assert cfg.daemon.mounting_from_cameras is False  # off unless asked for
    cfg = cfg.model_copy(update={
        "daemon": cfg.daemon.model_copy(update={"http_port": 0, "mounting_from_cameras": True}),
        "websocket": cfg.websocket.model_copy(update={"enabled": False}),
    })  # fmt: skip
    rec = Recorder()
    with (
        caplog.at_level(logging.INFO, logger="mocapd.pipeline.scheduler"),
        assembled(synthetic_config(cfg), RunOptions(sinks=[rec])) as demo,
    ):
        d = demo.daemon
        task = asyncio.create_task(d.run())
        await asyncio.wait_for(d.ready.wait(), 120)
        await wait_for(lambda: d.scheduler.mounting_status().get("suit0", {}).get("state") == "done", 60,
                       "the suit's mountings refined")  # fmt: skip
        code, _, body = await http_get(d.http.port, "/status")
        fits = json.loads(body)["imu_mounting_from_cameras"]["suit0"]["sensors"]
        d.request_stop()
        await asyncio.wait_for(task, 30)
    assert code == 200 and len(fits) == 13
    used = {sid for sid, f in fits.items() if f["used"]}
    print(f"daemon: {len(used)} of 13 mountings refined, changes {sorted(f['change_deg'] for f in fits.values())}")
    assert len(used) >= 9 and all(fits[s]["change_deg"] < 5.0 for s in used), fits
    assert all(f["reason"] == "not seen by the cameras" for s, f in fits.items() if s not in used) or len(used) == 11
    logged = [r.getMessage() for r in caplog.records if "refined from the cameras" in r.getMessage()]
    assert len(logged) == 1 and logged[0].startswith(f"suit suit0: {len(used)} of 13 mountings refined")

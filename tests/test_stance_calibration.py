"""Issue 42: gravity in a walk's stances refines the trunk sensors' inclination (mocapd.core.stance_calibration), on
numbers: a wearer who leaned while calibrating, then walked upright, sensors strapped at known mountings."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.imu import sensor_orientation_from_bone, specific_force_from_acceleration
from mocapd.core.imu_calibration import ImuCalibration, calibrate_recording, heading_alignment
from mocapd.core.rotations import quat_angle, quat_from_rotvec
from mocapd.core.stance_calibration import (
    MAX_SPREAD_DEG,
    detect_stances,
    refine_from_stances,
    stance_gravity,
)
from mocapd.service.cli import main
from mocapd.service.suits import calibration_line

RATE = 100.0
STILL_S = 2.0
STEP_S = 0.5  # each foot: 0.5 s of stance, 0.5 s of swing
BONES = ("Hips", "Spine3", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "RightUpperLeg", "RightLowerLeg", "RightFoot")


def _rx(deg: float | np.ndarray) -> np.ndarray:
    d = np.atleast_1d(np.radians(np.asarray(deg, dtype=np.float64)))
    return np.asarray(quat_from_rotvec(np.c_[d, np.zeros_like(d), np.zeros_like(d)]))


def _take(
    lean_deg: float = 8.0, walk_s: float = 8.0, trunk_wobble_deg: float = 1.0, seed: int = 0
) -> tuple[dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], dict[str, str], dict[str, np.ndarray]]:
    """Samples, assignment and true mountings of a take: 2 s standing with the trunk leaning ``lean_deg`` forward
    (pelvis and sternum), then walking in place: each foot flat and still in its stance (0.5 s) and turning in its
    swing, the stance leg's thigh and shank tilting opposite ways (ankle under hip), the trunk upright give or take
    ``trunk_wobble_deg`` per stance."""
    rng = np.random.default_rng(seed)
    n = round((STILL_S + walk_s) * RATE)
    t = np.arange(n) / RATE
    walking = t >= STILL_S
    phase = ((t - STILL_S) % (2 * STEP_S)) / STEP_S  # 0-1 left stance, 1-2 right stance
    step = np.floor((t - STILL_S) / STEP_S).astype(int)
    wobble = rng.normal(0.0, trunk_wobble_deg, step.max() + 2)
    trunk = np.where(walking, wobble[np.maximum(step, 0)], lean_deg)
    pose = {"Hips": _rx(trunk), "Spine3": _rx(trunk)}
    acc = {b: np.zeros((n, 3)) for b in BONES}
    for side, offset in (("Left", 0.0), ("Right", 1.0)):
        stance = walking & (((phase - offset) % 2.0) < 1.0)
        swing = walking & ~stance
        s = ((phase - offset) % 1.0) * np.pi
        # stance: the leg rolls over the ankle (ankle under the hip on average); swing: the knee bends
        roll = np.where(stance, 4.0 * np.sin(2 * s), 0.0)
        knee = np.where(swing, 50.0 * np.sin(s), 0.0)
        pose[f"{side}UpperLeg"] = _rx(np.where(swing, -25.0 * np.sin(s), -roll))
        pose[f"{side}LowerLeg"] = _rx(np.where(swing, -25.0 * np.sin(s) + knee, roll))
        pose[f"{side}Foot"] = _rx(np.where(swing, 40.0 * np.sin(s), 0.0))
        acc[f"{side}Foot"][swing] = [0.0, 3.0, 6.0]  # a swinging foot accelerates
    q_ig = heading_alignment(0.0)
    samples, bones, truth = {}, {}, {}
    for k, bone in enumerate(BONES):
        sid = f"00B4{0x4200 + k:04X}"
        axis = rng.normal(size=3)
        truth[sid] = quat_from_rotvec(np.radians(rng.uniform(5.0, 10.0)) * axis / np.linalg.norm(axis))
        q_i = sensor_orientation_from_bone(q_ig, pose[bone], truth[sid])
        samples[sid] = (t, q_i, specific_force_from_acceleration(q_ig, q_i, acc[bone]) + rng.normal(0, 0.02, (n, 3)))
        bones[sid] = bone
    return samples, bones, truth


def _calibrate(samples: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], bones: dict[str, str]) -> ImuCalibration:
    calib, _ = calibrate_recording("p", samples, bones, facing_heading_deg=0.0, span=(0.0, STILL_S))
    return calib


def _error(calib: ImuCalibration, truth: dict[str, np.ndarray], sid: str) -> float:
    return float(np.degrees(quat_angle(calib.q_ib[sid], truth[sid])))


def test_stances_are_the_feet_s_still_stretches_of_the_walk_not_the_stand() -> None:
    samples, bones, _ = _take()
    foot = next(s for s, b in bones.items() if b == "LeftFoot")
    t, q, a = samples[foot]
    stances = detect_stances(t, q, a, exclude=(0.5, 1.5))
    # 8 s of walking: a left stance every second, each 0.5 s; the first goes on from the stand, which is not one
    assert len(stances) == 7, stances
    assert all(s >= STILL_S and 0.35 < e - s <= STEP_S for s, e in stances), stances


def test_a_trunk_leaning_in_the_still_window_is_set_upright_by_the_stances() -> None:
    """Leaning 8° forward while calibrating puts 8° into the pelvis's and sternum's mountings (the still window takes
    the trunk for upright); the 15 stances of the walk see it upright and take it half back (the still window's and
    the stances' estimates weigh alike)."""
    samples, bones, truth = _take(lean_deg=8.0)
    calib = _calibrate(samples, bones)
    result = refine_from_stances(calib, samples, (0.5, 1.5))
    assert result.stances == {"Left": 7, "Right": 8}
    refined = result.calibration
    for sid, bone in bones.items():
        entry = result.sensors.get(sid)
        if bone in ("Hips", "Spine3"):
            assert entry is not None and entry["used"] is True and entry["stances"] == 15, entry
            assert float(entry["misfit_deg"]) == pytest.approx(8.0, abs=1.5)  # type: ignore[arg-type]
            assert _error(calib, truth, sid) > 6.5
            assert _error(refined, truth, sid) < _error(calib, truth, sid) - 3.0, (bone, _error(refined, truth, sid))
            # its gravity misfit after: what the stances still disagree with the mounting by (half the lean)
            assert refined.gravity_misfit_deg[sid] == pytest.approx(4.0, abs=1.5)
        elif bone.endswith(("UpperLeg", "LowerLeg")):  # measured, kept, not applied
            assert entry is not None and entry["used"] is False and "not applied" in str(entry["reason"]), entry
            assert sid in refined.gravity_misfit_deg
            assert np.allclose(refined.q_ib[sid], calib.q_ib[sid])
        else:  # feet, and nothing else, have no stance gravity
            assert entry is None and sid not in refined.gravity_misfit_deg
            assert np.allclose(refined.q_ib[sid], calib.q_ib[sid])
    # the misfit is in the calibration file, its summary (/status) and the console line
    hips = next(s for s, b in bones.items() if b == "Hips")
    again = ImuCalibration.from_json_dict(refined.to_json_dict())
    assert again.gravity_misfit_deg[hips] == pytest.approx(refined.gravity_misfit_deg[hips], abs=0.01)
    summary = refined.summary()
    assert summary["stances"] is True
    assert "gravity_misfit_deg" in summary["sensors"][hips]  # type: ignore[index]

    class _Suit:
        id = "suit0"
        calibration = refined

    assert "gravity from stances for 6 sensors" in calibration_line(_Suit())  # type: ignore[arg-type]


def test_an_upright_stand_is_left_as_it_was() -> None:
    samples, bones, truth = _take(lean_deg=0.0)
    calib = _calibrate(samples, bones)
    refined = refine_from_stances(calib, samples, (0.5, 1.5)).calibration
    for sid, bone in bones.items():
        if bone in ("Hips", "Spine3"):
            assert _error(refined, truth, sid) < _error(calib, truth, sid) + 0.5


def test_stances_that_disagree_or_are_too_few_keep_the_still_window_s_mountings() -> None:
    samples, bones, _ = _take(trunk_wobble_deg=12.0)  # a trunk all over the place from stance to stance
    calib = _calibrate(samples, bones)
    result = refine_from_stances(calib, samples, (0.5, 1.5))
    hips = next(s for s, b in bones.items() if b == "Hips")
    assert result.sensors[hips]["used"] is False
    assert f"above {MAX_SPREAD_DEG:g}" in str(result.sensors[hips]["reason"]), result.sensors[hips]
    assert np.allclose(result.calibration.q_ib[hips], calib.q_ib[hips])

    samples, bones, _ = _take(walk_s=1.0)  # one step of each foot
    calib = _calibrate(samples, bones)
    result = refine_from_stances(calib, samples, (0.5, 1.5))
    assert result.sensors[hips]["used"] is False and "needs 3" in str(result.sensors[hips]["reason"])
    assert all(np.allclose(result.calibration.q_ib[s], calib.q_ib[s]) for s in bones)


def test_a_take_without_foot_sensors_has_no_stances() -> None:
    samples, bones, _ = _take()
    feetless = {s: b for s, b in bones.items() if not b.endswith("Foot")}
    calib, _ = calibrate_recording("p", {s: samples[s] for s in feetless}, feetless, facing_heading_deg=0.0,
                                   span=(0.0, STILL_S))  # fmt: skip
    result = refine_from_stances(calib, samples, (0.5, 1.5))
    assert result.calibration.q_ib == calib.q_ib and result.sensors == {} and result.stances == {}
    assert stance_gravity(calib, samples, {}) == {}


def _write_mt_exports(folder: Path, samples: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]) -> list[str]:
    """The take as MT Manager exports (one per sensor, 100 Hz), as a suit owner's recording comes."""
    files = []
    for sid, (t, q, f) in samples.items():
        rows = ["\t".join([f"{i % 65536:05d}", str(10_000 + 100 * i), *(f"{v:.6f}" for v in (*f[i], *q[i]))])
                for i in range(len(t))]  # fmt: skip
        cols = "PacketCounter\tSampleTimeFine\tAcc_X\tAcc_Y\tAcc_Z\tQuat_q0\tQuat_q1\tQuat_q2\tQuat_q3"
        path = folder / f"MT_012005D6_009-001_{sid}.txt"
        path.write_text("// Start Time: Unknown\n// Update Rate: 100.0Hz\n" + cols + "\n" + "\n".join(rows) + "\n")
        files.append(str(path))
    return files


def test_calibrate_imu_from_a_take_uses_its_stances_and_says_the_misfits(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    samples, bones, truth = _take(lean_deg=8.0)
    files = _write_mt_exports(tmp_path, samples)
    session = tmp_path / "take"
    assign = [a for sid, bone in bones.items() for a in ("--assign", f"{sid}={bone}")]
    assert main(["import", "mtw", *files, "-o", str(session), *assign]) == 0
    hips = next(s for s, b in bones.items() if b == "Hips")
    errors = {}
    for extra in ([], ["--no-motion"]):
        capsys.readouterr()
        out = tmp_path / f"cal{len(extra)}.json"
        assert main(["calibrate", "imu", "--from", str(session), "--facing-heading", "0", "--window", "0:2",
                     "--out", str(out), *extra]) == 0  # fmt: skip
        said = json.loads(capsys.readouterr().out)
        written = ImuCalibration.from_json_dict(json.loads(out.read_text()))
        errors[bool(extra)] = _error(written, truth, hips)
        if extra:  # the still window's mountings only: no stances looked at
            assert said["stance_gravity"] == {} and not written.gravity_misfit_deg
            continue
        assert said["stance_gravity"][hips]["used"] is True, said["stance_gravity"]
        assert said["gravity_misfit_deg"][hips] == pytest.approx(written.gravity_misfit_deg[hips], abs=0.05)
        assert set(written.gravity_misfit_deg) == {s for s, b in bones.items() if not b.endswith("Foot")}
    assert errors[True] > 6.5 and errors[False] < errors[True] - 3.0, errors

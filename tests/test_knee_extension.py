"""Issue 42: a take's straightest knee measures the standing knee bend that the still window shrank toward straight
(mocapd.core.knee_extension), on numbers: a wearer who stood with the knees bent 8°, then walked in place with the
knees straightening at every step, sensors strapped exactly along their segments. Applied, it takes the knees' bias
away; by default (a real knee may hyperextend) it is measured and reported only."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.imu import sensor_orientation_from_bone, specific_force_from_acceleration
from mocapd.core.imu_calibration import (
    ImuCalibration,
    bone_orientation,
    calibrate_recording,
    common_grid,
    heading_alignment,
)
from mocapd.core.knee_extension import MAX_TURN_DEG, knee_shortfall, refine_knee_extension
from mocapd.core.plausibility import bone_hinge_angles
from mocapd.core.rotations import quat_from_rotvec
from mocapd.service.cli import main
from tests.test_stance_calibration import _write_mt_exports

RATE = 100.0
STILL_S = 2.0
BONES = ("Hips", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "RightUpperLeg", "RightLowerLeg", "RightFoot")


def _rx(deg: np.ndarray) -> np.ndarray:
    d = np.radians(np.asarray(deg, dtype=np.float64))
    return np.asarray(quat_from_rotvec(np.c_[d, np.zeros_like(d), np.zeros_like(d)]))


def _take(
    stand_bend_deg: float = 8.0, straightest_deg: float = 0.0, walk_s: float = 6.0
) -> tuple[dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], dict[str, str], dict[str, np.ndarray]]:
    """Samples, assignment and the true knee flexion (degrees, per side, (n,)) of a take: 2 s standing with both
    knees bent ``stand_bend_deg`` (the thigh forward and the shank back by half of it: the ankle under the hip),
    then walking in place, each knee bending from ``straightest_deg`` to 60° and back once a second. Every sensor
    sits exactly along its segment (the mountings' error is the still window's alone)."""
    n = round((STILL_S + walk_s) * RATE)
    t = np.arange(n) / RATE
    walking = t >= STILL_S
    pose = {"Hips": _rx(np.zeros(n))}
    knees = {}
    for side, phase in (("Left", 0.0), ("Right", np.pi)):
        swing = (1.0 - np.cos(2 * np.pi * (t - STILL_S) + phase)) / 2.0
        knee = np.where(walking, straightest_deg + (60.0 - straightest_deg) * swing, stand_bend_deg)
        pose[f"{side}UpperLeg"] = _rx(-knee / 2)
        pose[f"{side}LowerLeg"] = _rx(knee / 2)
        pose[f"{side}Foot"] = _rx(np.zeros(n))
        knees[f"{side.lower()}_knee"] = knee
    q_ig = heading_alignment(0.0)
    samples, bones = {}, {}
    for k, bone in enumerate(BONES):
        sid = f"00B4{0x4300 + k:04X}"
        q_i = sensor_orientation_from_bone(q_ig, pose[bone], np.array([1.0, 0.0, 0.0, 0.0]))
        samples[sid] = (t, q_i, specific_force_from_acceleration(q_ig, q_i, np.zeros((n, 3))))
        bones[sid] = bone
    return samples, bones, knees


def _knee_error(calib: ImuCalibration, samples: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
                knees: dict[str, np.ndarray]) -> dict[str, float]:  # fmt: skip
    """The calibrated knees' mean error over the walk (degrees, measured minus true)."""
    sensors = sorted(calib.bones)
    t, q = common_grid(samples, sensors)
    measured = bone_hinge_angles({calib.bones[s]: bone_orientation(calib.q_ig, q[s], calib.q_ib[s]) for s in sensors})
    walk = t >= STILL_S
    return {k: float(np.mean(measured[k][walk] - knees[k][walk])) for k in knees}


def test_knees_bent_while_calibrating_are_found_from_how_straight_the_walk_gets() -> None:
    """The still window finds about a third of the 8° bend (the mounting prior is as wide as the bend), so every
    knee of the walk reads ~5° straighter, and straight knees read bent backwards; the walk's straightest knee lifts
    the bend to where it was (applied), or says by how much (the default)."""
    samples, bones, knees = _take(stand_bend_deg=8.0)
    calib, window = calibrate_recording("p", samples, bones, facing_heading_deg=0.0, span=(0.0, STILL_S))
    before = _knee_error(calib, samples, knees)
    assert all(e < -4.0 for e in before.values()), before
    measured = refine_knee_extension(calib, samples, window)
    assert measured.calibration is calib
    for name, entry in measured.knees.items():
        assert entry["used"] is False and "not applied" in str(entry["reason"]), entry
        assert float(entry["shortfall_deg"]) == pytest.approx(-before[name], abs=0.5)  # type: ignore[arg-type]
    result = refine_knee_extension(calib, samples, window, apply=True)
    after = _knee_error(result.calibration, samples, knees)
    assert all(abs(e) < 0.5 for e in after.values()), after
    for name in ("left_knee", "right_knee"):
        entry = result.knees[name]
        assert entry["used"] is True and float(entry["straightest_deg"]) < -4.0, entry  # type: ignore[arg-type]
        assert float(entry["raised_deg"]) == pytest.approx(-before[name], abs=0.5)  # type: ignore[arg-type]
    # the posture found in the still window says the bend held, and the legs' lean is what it was
    assert result.calibration.posture["left_knee_bend"] == pytest.approx(8.0, abs=0.5)
    assert calib.posture["left_knee_bend"] < 4.0


def test_knees_that_never_straighten_or_bend_back_implausibly_far_keep_the_still_window_s_mountings() -> None:
    # a crouched walk (the knees never straighter than 20°) says nothing of the standing bend
    samples, bones, _ = _take(stand_bend_deg=8.0, straightest_deg=20.0)
    calib, window = calibrate_recording("p", samples, bones, facing_heading_deg=0.0, span=(0.0, STILL_S))
    result = refine_knee_extension(calib, samples, window, apply=True)
    assert result.calibration.q_ib == calib.q_ib
    assert all(e["used"] is False and "not backwards" in str(e["reason"]) for e in result.knees.values())
    # a knee reading 25° backwards is a sensor slipped or on another bone, not a standing bend
    samples, bones, _ = _take(stand_bend_deg=0.0, straightest_deg=-25.0)
    calib, window = calibrate_recording("p", samples, bones, facing_heading_deg=0.0, span=(0.0, STILL_S))
    result = refine_knee_extension(calib, samples, window, apply=True)
    assert result.calibration.q_ib == calib.q_ib
    assert all(e["used"] is False and f"above {MAX_TURN_DEG:g}" in str(e["reason"]) for e in result.knees.values())


def test_the_shortfall_is_the_straightest_stretch_not_one_frame() -> None:
    flexion = np.r_[np.full(5, -30.0), np.linspace(-2.0, 60.0, 995)]  # one jolt of 5 frames in 1000
    straightest, short = knee_shortfall(flexion)
    assert -2.0 < straightest < 0.0 and short == pytest.approx(-straightest)
    assert knee_shortfall(np.linspace(3.0, 60.0, 100))[1] == 0.0
    assert knee_shortfall(np.full(10, np.nan))[1] == 0.0


def test_calibrate_imu_from_a_take_says_how_far_the_knees_bend_backwards(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Through the commands a suit owner runs: with the take's motion each knee's straightest flexion and shortfall
    are printed (the still window's shrunk bend: ~5° backwards), the mountings kept; --knee-extension applies it
    (the written calibration's knees match the walk's); --no-motion looks at none."""
    samples, bones, knees = _take(stand_bend_deg=8.0)
    files = _write_mt_exports(tmp_path, samples)
    session = tmp_path / "take"
    assign = [a for sid, bone in bones.items() for a in ("--assign", f"{sid}={bone}")]
    assert main(["import", "mtw", *files, "-o", str(session), *assign]) == 0
    errors, said = {}, {}
    for extra in ("", "--no-motion", "--knee-extension"):
        capsys.readouterr()
        out = tmp_path / f"cal{extra}.json"
        assert main(["calibrate", "imu", "--from", str(session), "--facing-heading", "0", "--window", "0:2",
                     "--out", str(out), *([extra] if extra else [])]) == 0  # fmt: skip
        said[extra] = json.loads(capsys.readouterr().out)
        errors[extra] = _knee_error(ImuCalibration.from_json_dict(json.loads(out.read_text())), samples, knees)
    assert said["--no-motion"]["knee_extension"] == {}
    assert all(e < -4.0 for e in errors["--no-motion"].values()), errors
    assert set(said[""]["knee_extension"]) == {"left_knee", "right_knee"}, said[""]
    for name, entry in said[""]["knee_extension"].items():
        assert entry["used"] is False and "not applied" in entry["reason"], entry
        assert entry["straightest_deg"] < -4.0, entry
        assert entry["shortfall_deg"] == pytest.approx(-errors[""][name], abs=0.7), (entry, errors)
    assert errors[""] == pytest.approx(errors["--no-motion"], abs=0.5)
    assert all(e["used"] is True for e in said["--knee-extension"]["knee_extension"].values()), said
    assert all(abs(e) < 0.7 for e in errors["--knee-extension"].values()), errors
    assert said["--knee-extension"]["posture_deg"]["left_knee_bend"] == pytest.approx(8.0, abs=0.7)

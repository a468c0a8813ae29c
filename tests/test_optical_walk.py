"""Issue 42: ``mocapd eval ground --parts optical`` measures the walk as a suit owner runs it (import mtw ->
calibrate imu --from -> resolve -> export), and checks the facing the calibration found against the optical pelvis
(friction 8). The real take (GPL-3.0) is not shipped: a simulated take is written in its layout, with a Vicon
trial made from the simulated truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.io import savemat

from mocapd.core.kinematics import Kinematics
from mocapd.core.plausibility import hinge_angles
from mocapd.core.rotations import matrix_from_rotvec
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.eval.ground_optical import SENSORS, TRIAL, Vicon, hip_flexion, measure
from mocapd.service.cli.optical_walk import through_commands
from mocapd.sim.world import load_demo_motion
from tests.test_import_recordings import RATE, _write_exports


def _vicon_frame(p: np.ndarray) -> np.ndarray:
    """mocapd's world (Y up; Z, X a right-handed pair seen from above) as Vicon's (Z up), metres to millimetres."""
    return 1000.0 * p[..., [2, 0, 1]]


def _vicon_fields(theta: np.ndarray, skeleton: Skeleton) -> dict[str, np.ndarray]:
    """What a Plug-in-Gait trial holds for the poses θ (n, 66): markers and joint centres (mm), flexion (deg)."""
    fk = Kinematics(skeleton).forward(theta)
    joint = {b: fk.positions[:, BONE_INDEX[b]] for b in BONE_INDEX}
    r = matrix_from_rotvec(theta[:, 3:6])
    fwd, left = r[:, :, 2], r[:, :, 0]
    root = joint["Hips"]
    out = {
        "LASI": root + 0.12 * left + 0.06 * fwd, "RASI": root - 0.12 * left + 0.06 * fwd,
        "LPSI": root + 0.05 * left - 0.10 * fwd, "RPSI": root - 0.05 * left - 0.10 * fwd,
    }  # fmt: skip
    for side, s in (("L", "Left"), ("R", "Right")):
        out |= {f"{side}HJC": joint[f"{s}UpperLeg"], f"{side}KJC": joint[f"{s}LowerLeg"],
                f"{side}AJC": joint[f"{s}Foot"], f"{side}HEE": joint[f"{s}Foot"],
                f"{side}TOE": joint[f"{s}Toes"]}  # fmt: skip
    fields = {k: _vicon_frame(v) for k, v in out.items()}
    knees, hips = hinge_angles(theta), hip_flexion(theta)
    for side, name in (("left", "L"), ("right", "R")):
        fields[f"{name}_Femur_{name}_Tibia"] = knees[f"{side}_knee"]
        fields[f"Root_{name}_Femur"] = np.c_[-hips[side], np.zeros((len(theta), 2))]  # Plug-in-Gait's sign
    return fields


def _out_and_back(skeleton: Skeleton, n: int = 2500) -> np.ndarray:
    """25 s at 100 Hz standing facing +Z: 3 m out along +Z from 11 s, back from 16 s, the knees bending."""
    t = np.arange(n) / 100.0
    theta = np.repeat(skeleton.rest_pose()[None], n, axis=0)
    theta[:, 2] = 3.0 * np.clip((t - 11.0) / 5.0, 0.0, 1.0) - 3.0 * np.clip((t - 16.0) / 5.0, 0.0, 1.0)
    walking = (t > 11.0) & (t < 21.0)
    for bone, phase in (("LeftLowerLeg", 0.0), ("RightLowerLeg", np.pi)):
        theta[:, 3 + 3 * BONE_INDEX[bone]] = np.where(walking, 0.4 * (1.0 - np.cos(2 * np.pi * t + phase)), 0.0)
    return theta


def test_the_facing_is_checked_against_the_optical_pelvis() -> None:
    """Friction 8: the facing found from a take's steps was 7.3° off the optical truth and nothing measured it. A
    calibration's facing δ off turns the walk by δ from the standing facing: both legs of the walk say so."""
    skeleton = Skeleton.from_height(1.7)
    truth = _out_and_back(skeleton)
    f = _vicon_fields(truth, skeleton)
    vicon = Vicon(pelvis=(f["LASI"] + f["RASI"] + f["LPSI"] + f["RPSI"]) / 4000.0,
                  hips=(f["LHJC"] + f["RHJC"]) / 2000.0,
                  knee={"left": f["L_Femur_L_Tibia"], "right": f["R_Femur_R_Tibia"]},
                  hip_flexion={"left": f["Root_L_Femur"][:, 0], "right": f["Root_R_Femur"][:, 0]},
                  legs={}, facing=((f["LASI"] + f["RASI"]) / 2 - (f["LPSI"] + f["RPSI"]) / 2)[:, :2])  # fmt: skip
    assert measure(truth, skeleton, vicon)["facing_vs_vicon"] == {"out_deg": 0.0, "back_deg": 0.0}
    for delta in (6.0, -7.3):
        ours = truth.copy()
        c, s = np.cos(np.radians(delta)), np.sin(np.radians(delta))
        x, z = ours[:, 0].copy(), ours[:, 2].copy()
        ours[:, 0], ours[:, 2] = c * x + s * z, -s * x + c * z  # the path turned by δ to the left, the body not
        check = measure(ours, skeleton, vicon)["facing_vs_vicon"]
        assert check["out_deg"] == pytest.approx(delta, abs=0.2) and check["back_deg"] == pytest.approx(delta, abs=0.2)


def test_eval_ground_runs_the_commands_a_suit_owner_runs(tmp_path: Path) -> None:
    """``eval ground``'s optical row is the suit owner's path: the take's MT Manager exports imported, calibrated
    from the take (the facing from its steps), resolved and exported; every 60 Hz instant of the 100 Hz take posed
    and exported, the knees as the truth bent them."""
    data = tmp_path / "sample"
    (data / "rawimu").mkdir(parents=True)
    (data / "vicon").mkdir()
    assignment, _, truth = _write_exports(tmp_path, seconds=12.0)
    ours = {bone: sid for sid, bone in SENSORS.items()}
    for sid, bone in assignment.items():
        if bone in ours:
            (tmp_path / f"MT_012005D6_009-001_{sid}.txt").rename(data / "rawimu" / f"{TRIAL}-000_{ours[bone]}.txt")
    _, skeleton = load_demo_motion()
    savemat(data / "vicon" / f"{TRIAL}.mat", _vicon_fields(truth, skeleton))

    row = through_commands(data, tmp_path / "work", 1.75, [])
    assert row["commands"] == ["mocapd import mtw", "mocapd calibrate imu", "mocapd resolve", "mocapd export"]
    span_s = (len(truth) - 1) / RATE
    assert row["poses"] == row["csv_rows"] == round(span_s * 60.0) + 1
    assert abs((row["facing_heading_deg"] + 180.0) % 360.0 - 180.0) < 10.0  # the subject faced north
    assert row["knee_flexion"]["rms_deg"] < 8.0 and row["root_height_error_p95_cm"] < 5.0, row
    assert set(row["facing_vs_vicon"]) == {"out_deg", "back_deg"}

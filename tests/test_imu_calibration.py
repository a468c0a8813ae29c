"""T-pose calibration: R_ib, heading alignment, motion rejection, assignment validation, file format."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mocapd.core.imu_calibration import (
    BONE_NAMES,
    ENU_TO_WORLD,
    IMU_SET_6,
    IMU_SET_13,
    ImuCalibration,
    bone_orientation,
    calibrate_tpose,
    facing_heading_from_sensor,
    heading_alignment,
    parse_assignment,
    quat_average,
    quat_to_enu,
    stillest_window,
    yaw_quat,
)
from mocapd.core.rotations import (
    matrix_from_quat,
    quat_angle,
    quat_conjugate,
    quat_from_matrix,
    quat_from_rotvec,
    quat_multiply,
    random_quat,
    random_rotvec,
)
from mocapd.errors import CalibrationError, ConfigError, InputError

RNG_SEED = 0


def test_bone_names_and_sets_follow_design() -> None:
    assert len(BONE_NAMES) == 21 and BONE_NAMES[0] == "Hips" and BONE_NAMES[20] == "RightToes"
    assert len(IMU_SET_13) == 13 and set(IMU_SET_6) <= set(IMU_SET_13) and len(IMU_SET_6) == 6
    assert np.allclose(ENU_TO_WORLD @ [0, 0, 1], [0, 1, 0])  # up is +Y
    assert np.allclose(ENU_TO_WORLD @ [0, 1, 0], [0, 0, 1])  # north is +Z
    assert np.isclose(np.linalg.det(ENU_TO_WORLD), 1.0)


def _simulate_tpose(
    rng: np.random.Generator, bones: list[str], heading_deg: float, n: int = 120, noise_deg: float = 0.2
) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], dict[str, np.ndarray], dict[str, str]]:
    """Sensors with random mountings on bones of a subject in T-pose facing ``heading_deg``."""
    q_ig_true = heading_alignment(heading_deg)
    recordings, q_ib_true, assignment = {}, {}, {}
    for k, bone in enumerate(bones):
        sid = f"00B4{k:04X}"
        q_ib = random_quat(rng)
        # T-pose: R_gb = I  =>  R_i = R_ig^-1 · R_ib
        q_i = quat_multiply(quat_conjugate(q_ig_true), q_ib)
        jitter = quat_from_rotvec(random_rotvec(rng, (n,), max_angle=np.radians(noise_deg)))
        quats = quat_multiply(np.broadcast_to(q_i, (n, 4)), jitter)
        acc = matrix_from_quat(quats).transpose(0, 2, 1) @ np.array([0, 0, 9.81])
        acc += rng.normal(0, 0.02, (n, 3))
        recordings[sid] = (quats, acc)
        q_ib_true[sid] = q_ib
        assignment[sid] = bone
    return recordings, q_ib_true, assignment


@pytest.mark.parametrize("world_heading", ["subject", "north"])
def test_tpose_recovers_mountings_and_bone_orientations(world_heading: str) -> None:
    rng = np.random.default_rng(RNG_SEED)
    heading = 37.0
    recordings, q_ib_true, assignment = _simulate_tpose(rng, list(IMU_SET_13), heading)
    calib = calibrate_tpose(
        "alice", recordings, assignment, facing_heading_deg=heading, world_heading=world_heading, window=60
    )
    for sid, q_ib in q_ib_true.items():
        assert quat_angle(calib.q_ib[sid], q_ib) < np.radians(0.1)
    # In the T-pose every bone is in its rest orientation (subject mode) or turned by -heading (north mode).
    expected = np.array([1.0, 0, 0, 0]) if world_heading == "subject" else yaw_quat(-np.radians(heading))
    for sid, (quats, _) in recordings.items():
        q_gb = bone_orientation(calib.q_ig, quat_average(quats), calib.q_ib[sid])
        assert quat_angle(q_gb, expected) < np.radians(0.1)


def test_heading_alignment_maps_subject_facing_to_plus_z() -> None:
    h = 120.0
    facing_enu = np.array([np.sin(np.radians(h)), np.cos(np.radians(h)), 0.0])
    assert np.allclose(matrix_from_quat(heading_alignment(h)) @ facing_enu, [0, 0, 1])
    assert np.allclose(matrix_from_quat(heading_alignment(h, world_heading="north")) @ [0, 1, 0], [0, 0, 1])
    with pytest.raises(ConfigError):
        heading_alignment(0.0, world_heading="east")


def test_motion_is_rejected_with_the_sensor_named() -> None:
    rng = np.random.default_rng(1)
    n = 100
    turning = quat_from_rotvec(np.outer(np.linspace(0, 0.5, n), [0, 0, 1.0]))  # 29° over the recording
    with pytest.raises(CalibrationError, match=r"00B40001 \(Head\) moved"):
        stillest_window(turning, None, 50, sensor="00B40001 (Head)")
    still = np.broadcast_to(random_quat(rng), (n, 4))
    shaking = rng.normal(0, 1.0, (n, 3)) + np.array([0, 0, 9.81])
    with pytest.raises(CalibrationError, match="accelerated"):
        stillest_window(still, shaking, 50)
    with pytest.raises(CalibrationError, match="need at least"):
        stillest_window(still[:10], None, 50)


def test_stillest_window_finds_the_still_part() -> None:
    n = 200
    angles = np.concatenate([np.linspace(0, 1.0, 100), np.full(100, 1.0)])
    quats = quat_from_rotvec(np.outer(angles, [1.0, 0, 0]))
    w = stillest_window(quats, None, 60)
    assert w.start >= 100 and w.spread_deg < 1e-6
    assert quat_angle(w.mean, quat_from_rotvec(np.array([1.0, 0, 0]))) < 1e-9
    del n


def test_assignment_validation() -> None:
    ok = parse_assignment({"00b421e6": "Hips", "00B421ED": "Head"})
    assert ok == {"00B421E6": "Hips", "00B421ED": "Head"}
    with pytest.raises(ConfigError, match="not a bone"):
        parse_assignment({"00B421E6": "Pelvis"})
    with pytest.raises(ConfigError, match="8 hex digits"):
        parse_assignment({"B421E6": "Hips"})
    with pytest.raises(ConfigError, match="more than one sensor"):
        parse_assignment({"00B421E6": "Hips", "00B421ED": "Hips"})
    with pytest.raises(ConfigError, match=r"missing \['LeftLowerArm'"):
        parse_assignment({"00B421E6": "Hips", "00B421ED": "Head"}, imu_set="6")
    six = {f"00B4000{k}": b for k, b in enumerate(IMU_SET_6)}
    assert len(parse_assignment(six, imu_set="6")) == 6


def test_calibration_file_round_trip_and_errors() -> None:
    rng = np.random.default_rng(2)
    recordings, _, assignment = _simulate_tpose(rng, list(IMU_SET_6), 0.0)
    calib = calibrate_tpose("bob", recordings, assignment, facing_heading_deg=0.0)
    text = json.dumps(calib.to_json_dict())
    again = ImuCalibration.from_json_dict(json.loads(text))
    assert again.bones == calib.bones and again.person == "bob"
    for sid in calib.q_ib:
        assert np.allclose(again.q_ib[sid], calib.q_ib[sid])
    with pytest.raises(CalibrationError, match="version-1"):
        ImuCalibration.from_json_dict({"format": "x"})
    broken = json.loads(text)
    broken["R_ig"] = [2, 0, 0, 0]
    with pytest.raises(CalibrationError, match="unit quaternion"):
        ImuCalibration.from_json_dict(broken)
    with pytest.raises(CalibrationError, match="no samples"):
        calibrate_tpose("x", {}, assignment, facing_heading_deg=0.0)


def test_facing_heading_from_a_forward_axis() -> None:
    # A sensor whose x axis points forward, subject facing east (90°): x maps to ENU east.
    q_i = quat_from_rotvec(np.array([0.0, 0.0, 0.0]))
    assert facing_heading_from_sensor(q_i, np.array([1.0, 0, 0])) == pytest.approx(90.0)
    turned = quat_from_rotvec(np.array([0.0, 0.0, np.radians(90.0)]))  # x now points north
    assert facing_heading_from_sensor(turned, np.array([1.0, 0, 0])) == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(CalibrationError, match="vertical"):
        facing_heading_from_sensor(q_i, np.array([0, 0, 1.0]))


def test_quat_to_enu_from_ned_and_nwu() -> None:
    rng = np.random.default_rng(9)
    q_enu = random_quat(rng)
    r_enu = matrix_from_quat(q_enu)
    ned_from_enu = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])
    nwu_from_enu = np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]])
    for name, m in (("NED", ned_from_enu), ("NWU", nwu_from_enu)):
        q_other = quat_from_matrix(m @ r_enu)
        assert quat_angle(quat_to_enu(q_other, name), q_enu) < 1e-9
    assert quat_angle(quat_to_enu(q_enu, "ENU"), q_enu) == 0.0
    with pytest.raises(InputError, match="ENU, NED or NWU"):
        quat_to_enu(q_enu, "XYZ")


def test_slimevr_sensor_ids_are_assignable() -> None:
    ok = parse_assignment({"a1:b2:c3:d4:e5:f6/0": "Hips", "A1:B2:C3:D4:E5:F6/1": "Spine1", "00B421E6": "Head"})
    assert ok == {"A1:B2:C3:D4:E5:F6/0": "Hips", "A1:B2:C3:D4:E5:F6/1": "Spine1", "00B421E6": "Head"}
    for bad in ("A1:B2:C3:D4:E5/0", "A1:B2:C3:D4:E5:F6", "A1:B2:C3:D4:E5:F6/255", "A1:B2:C3:D4:E5:G6/0", "1/2"):
        with pytest.raises(ConfigError, match="SlimeVR"):
            parse_assignment({bad: "Hips"})


def test_sensors_with_their_own_heading_get_a_heading_reset() -> None:
    from mocapd.core.imu_calibration import device_heading_quat, twist_about_up_deg
    from mocapd.core.rotations import quat_angle, quat_conjugate, quat_from_rotvec, quat_multiply

    rng = np.random.default_rng(4)
    facing = 30.0
    q_ig = heading_alignment(facing)  # world_heading "subject": the T-pose alignment is the runtime one
    ids = ["A1:B2:C3:D4:E5:F6/0", "A1:B2:C3:D4:E5:F6/1", "00B421E6"]
    bones = dict(zip(ids, ["LeftUpperLeg", "LeftLowerLeg", "Hips"], strict=True))
    mount_yaw = {ids[0]: 0.0, ids[1]: 90.0}
    psi = {ids[0]: 123.0, ids[1]: -61.0, ids[2]: 0.0}  # each tracker's own heading reference (Xsens: shared)
    q_ib = {}
    recordings = {}
    for sid in ids:
        # A mounting whose own yaw is the stated one: a swing (horizontal axis) then the yaw.
        axis = np.array([rng.normal(), 0.0, rng.normal()])
        swing = quat_from_rotvec(axis / np.linalg.norm(axis) * rng.uniform(0.3, 1.5))
        q_ib[sid] = quat_multiply(quat_from_rotvec(np.array([0.0, np.radians(mount_yaw.get(sid, 0.0)), 0.0])), swing)
        true_i = quat_multiply(quat_conjugate(q_ig), q_ib[sid])  # R_i at the T-pose (rest = identity)
        measured = quat_multiply(device_heading_quat(psi[sid]), true_i)
        recordings[sid] = (np.repeat(measured[None], 80, axis=0), None)
    calib = calibrate_tpose("p", recordings, bones, facing_heading_deg=facing, own_heading=mount_yaw, window=60)
    assert set(calib.device_heading_deg) == set(mount_yaw)
    for sid, yaw in mount_yaw.items():
        assert calib.device_heading_deg[sid] == pytest.approx(-psi[sid])
        assert twist_about_up_deg(calib.q_ib[sid]) == pytest.approx(yaw, abs=1e-6)
    # Later, in any pose, the reset sensor gives its bone's true orientation; without the reset it would not.
    q_gb = quat_from_rotvec(np.array([0.4, -0.7, 0.2]))
    sid = ids[0]
    measured = quat_multiply(device_heading_quat(psi[sid]), quat_multiply(quat_conjugate(q_ig),
                                                                          quat_multiply(q_gb, q_ib[sid])))  # fmt: skip
    reset = quat_multiply(calib.device_heading_quats()[sid], measured)
    assert float(quat_angle(bone_orientation(calib.q_ig, reset, calib.q_ib[sid]), q_gb)) < 1e-6
    plain = calibrate_tpose("p", recordings, bones, facing_heading_deg=facing, window=60)
    assert float(np.degrees(quat_angle(bone_orientation(plain.q_ig, measured, plain.q_ib[sid]), q_gb))) > 20.0
    # The file keeps it.
    again = ImuCalibration.from_json_dict(json.loads(json.dumps(calib.to_json_dict())))
    assert again.device_heading_deg == pytest.approx(calib.device_heading_deg)
    with pytest.raises(CalibrationError, match="not in the assignment"):
        calibrate_tpose("p", recordings, bones, facing_heading_deg=facing, own_heading={"00B421ED": 0.0})

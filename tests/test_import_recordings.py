"""Existing recordings as sessions: ``mocapd import mtw|mvnx``, ``calibrate imu --from``, ``resolve``, ``export``.

The MT Manager files are written here from recorded motion (the synthetic rig's CMU clip) through the sensor model
(mountings as a suit owner straps sensors on: each case along its segment, in any of the 24 ways, a few degrees
askew; ENU orientations, sensor-frame specific force), after 1.5 s of standing in the T-pose, so the
truth is known: the calibration must recover every mounting, and the resolved take must follow the motion with
its root on the ground. The real MTw and MVNX files go through the same commands.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.body_dims import SEGMENTS
from mocapd.core.imu import (
    IMU_SET_LOWER,
    default_mounts,
    sensor_orientation_from_bone,
    specific_force_from_acceleration,
)
from mocapd.core.imu_calibration import ImuCalibration, heading_alignment, parse_assignment
from mocapd.core.kinematics import Kinematics
from mocapd.core.motion import resample_poses
from mocapd.core.rotations import quat_angle, quat_from_matrix, quat_from_rotvec, quat_multiply
from mocapd.core.skeleton import Skeleton
from mocapd.errors import ConfigError
from mocapd.eval.data import default_data_root
from mocapd.io.session import RESOLVED, open_session
from mocapd.service.cli import main
from mocapd.sim.world import TRUTH_FPS, load_demo_motion

RATE = 100.0
SUIT = (*IMU_SET_LOWER, "Spine3")
MVNX = default_data_root() / "imu" / "mvnx" / "mpiea_upperbody_test_mocap.mvnx"


def strapped_mounting(rng: np.random.Generator, askew_deg: float = 4.0) -> np.ndarray:
    """A sensor strapped on a segment: its case along the segment's axes (one of the 24 ways), ``askew_deg`` off."""
    from mocapd.core.imu_calibration import _AXIS_ALIGNED

    askew = quat_from_rotvec(np.radians(askew_deg) * _unit(rng.normal(size=3)))
    return np.asarray(quat_multiply(askew, _AXIS_ALIGNED[rng.integers(len(_AXIS_ALIGNED))]))


def _unit(v: np.ndarray) -> np.ndarray:
    return np.asarray(v / np.linalg.norm(v))


def _write_exports(
    folder: Path,
    seconds: float = 3.0,
    *,
    suit: tuple[str, ...] = SUIT,
    posture: np.ndarray | None = None,
    askew_deg: float = 4.0,
    blend_s: float = 0.0,
) -> tuple[dict[str, str], dict[str, np.ndarray], np.ndarray]:
    """MT Manager exports of a suit (default: lower body) standing 1.5 s in ``posture`` (θ, default the T-pose),
    then (after ``blend_s`` of moving into it) the motion; returns the assignment, the true mountings and the truth
    θ."""
    clips, skeleton = load_demo_motion()
    motion = resample_poses(clips[0][: max(2, round(seconds * TRUTH_FPS))], TRUTH_FPS, RATE)
    rest = np.repeat((skeleton.rest_pose() if posture is None else posture)[None], round(1.5 * RATE), axis=0)
    rest[:, :3] = motion[0, :3]
    w = np.linspace(0.0, 1.0, round(blend_s * RATE))[:, None]
    blend = (1.0 - w) * rest[-1] + w * motion[0]
    theta = np.concatenate([rest, blend, motion]) if seconds > 0 else np.concatenate([rest, rest])  # 0: standing
    kin = Kinematics(skeleton)
    fk = kin.forward(theta)
    mounts = default_mounts(suit, skeleton)
    bones = np.array([m.bone_index for m in mounts])
    sites = kin.targets(fk, bones, np.array([m.t_ib for m in mounts]))
    acc = np.zeros_like(sites)
    acc[1:-1] = (sites[2:] - 2 * sites[1:-1] + sites[:-2]) * RATE**2
    q_gb = quat_from_matrix(fk.rotations[:, bones])
    q_ig = heading_alignment(0.0)  # ENU -> world when the subject faces north
    rng = np.random.default_rng(3)
    assignment, mountings = {}, {}
    for k, m in enumerate(mounts):
        sid = f"00B4{0x2100 + k:04X}"
        q_ib = strapped_mounting(rng, askew_deg)
        q_i = sensor_orientation_from_bone(q_ig, q_gb[:, k], q_ib)
        f = specific_force_from_acceleration(q_ig, q_i, acc[:, k])
        rows = [
            "\t".join([f"{472 + i:05d}", str(10_000 + 100 * i), *(f"{v:.6f}" for v in (*f[i], *q_i[i]))])
            for i in range(len(theta))
        ]
        cols = "PacketCounter\tSampleTimeFine\tAcc_X\tAcc_Y\tAcc_Z\tQuat_q0\tQuat_q1\tQuat_q2\tQuat_q3"
        text = "// Start Time: Unknown\n// Update Rate: 100.0Hz\n" + cols + "\n" + "\n".join(rows) + "\n"
        (folder / f"MT_012005D6_009-001_{sid}.txt").write_text(text)
        assignment[sid], mountings[sid] = m.bone, q_ib
    return assignment, mountings, theta


def test_mt_manager_take_imports_calibrates_resolves_and_exports(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assignment, mountings, truth = _write_exports(tmp_path)
    session = tmp_path / "take"
    files = sorted(str(p) for p in tmp_path.glob("MT_*.txt"))
    assign = [a for sid, bone in assignment.items() for a in ("--assign", f"{sid}={bone}")]
    assert main(["import", "mtw", *files, "-o", str(session), "--imu-set", "lower", *assign]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["assignment"] == assignment and len(summary["sensors"]) == len(SUIT)

    assert main(["calibrate", "imu", "--from", str(session), "--facing-heading", "0",
                 "--out", str(tmp_path / "cal.json")]) == 0  # fmt: skip
    report = json.loads(capsys.readouterr().out)
    assert report["posture"] == "t-pose" and report["window_s"][1] <= 1.5
    calib = ImuCalibration.from_json_dict(json.loads((tmp_path / "cal.json").read_text()))
    for sid, q in mountings.items():  # the thighs' and shanks' mountings share their askew with the posture
        assert np.degrees(quat_angle(calib.q_ib[sid], q)) < (2.0 if "Leg" in assignment[sid] else 0.5)
    assert open_session(session).manifest["suits"][0]["id"] == "suit0"

    assert main(["resolve", str(session), "--iterations", "10"]) == 0
    resolved = json.loads(capsys.readouterr().out)
    assert resolved["plausibility"]["suit:suit0"]["implausible"] is False and resolved["notes"] == []
    frames = open_session(session).poses(RESOLVED)
    assert frames and all([p.identity for p in f.people] == ["suit:suit0"] for f in frames)
    theta = np.array([f.people[0].theta for f in frames])
    t = np.array([f.t_solve_ns for f in frames]) - frames[0].t_solve_ns
    true = truth[np.clip(np.round(t / 1e7).astype(int), 0, len(truth) - 1)]
    kin = Kinematics(Skeleton.from_height(1.75))  # the imported session's skeleton
    legs = [14, 18]  # the knees follow the shank sensors
    q_s = quat_from_matrix(kin.forward(theta).rotations[:, legs])
    q_t = quat_from_matrix(kin.forward(true).rotations[:, legs])
    assert np.median(np.degrees(quat_angle(q_s, q_t))) < 5.0
    assert np.ptp(theta[:, 1]) < 0.15  # on the ground: no float (the session skeleton is 1.75 m tall)

    csv, bvh = tmp_path / "take.csv", tmp_path / "take.bvh"
    assert main(["export", str(session), "--resolved", "--csv", str(csv), "--bvh", str(bvh)]) == 0
    assert csv.read_text().count("\n") > 100 and bvh.read_text().startswith("HIERARCHY")

    # A calibration with its facing mirrored (what the wrong --facing-from sign gave before it was refused): resolve
    # says that the knees bend the wrong way (issue 28).
    manifest = json.loads((session / "manifest.json").read_text())
    turn = quat_from_rotvec(np.array([0.0, np.pi, 0.0]))
    for sensor in manifest["suits"][0]["calibration"]["sensors"].values():
        sensor["R_ib"] = [float(v) for v in quat_multiply(turn, np.array(sensor["R_ib"]))]
    (session / "manifest.json").write_text(json.dumps(manifest))
    capsys.readouterr()
    assert main(["resolve", str(session), "--iterations", "10"]) == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["plausibility"]["suit:suit0"]["implausible"] is True
    assert "note: suit:suit0: left knee bent the wrong way" in out.err


def test_lower_body_suit_check() -> None:
    ok = {f"00B4{i:04X}": b for i, b in enumerate(SUIT)}
    assert parse_assignment(ok, imu_set="lower") == ok
    with pytest.raises(ConfigError, match="missing \\['RightFoot'\\]"):
        parse_assignment({k: v for k, v in ok.items() if v != "RightFoot"}, imu_set="lower")
    with pytest.raises(ConfigError, match="unexpected \\['Head'\\]"):
        parse_assignment({**ok, "00B4FFFF": "Head"}, imu_set="lower")


def test_calibration_needs_a_facing_direction_and_names_bad_windows(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assignment, _, _ = _write_exports(tmp_path, seconds=1.0)
    session = tmp_path / "take"
    files = sorted(str(p) for p in tmp_path.glob("MT_*.txt"))
    assign = [a for sid, bone in assignment.items() for a in ("--assign", f"{sid}={bone}")]
    assert main(["import", "mtw", *files, "-o", str(session), *assign]) == 0
    assert main(["import", "mtw", *files, "-o", str(session), *assign]) == 2  # never over an existing session
    capsys.readouterr()
    assert main(["calibrate", "imu", "--from", str(session), "--facing-heading", "0", "--window", "1.2:2.4",
                 "--out", str(tmp_path / "c.json")]) == 1  # fmt: skip
    err = capsys.readouterr().err  # the window holds the jump into the motion: another window is the way out
    assert re.search(r"moved in the stillest 1 s of the recording \(1\.\d-2\.\d s\)", err), err
    assert "--window START:END" in err
    assert main(["calibrate", "imu", "--from", str(session), "--facing-heading", "0", "--window", "0.2:0.1"]) == 1
    assert "--window" in capsys.readouterr().err


def test_calibration_takes_the_facing_from_the_steps_and_refuses_a_mirrored_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 28: without a facing direction the take's steps give it (the subject faced north, heading 0); a facing
    turned by 180° (the wrong sign) bends the knees backwards and is refused, naming the one that works; a take
    without steps needs the facing given."""
    assignment, _, _ = _write_exports(tmp_path)
    session = tmp_path / "take"
    files = sorted(str(p) for p in tmp_path.glob("MT_*.txt"))
    assign = [a for sid, bone in assignment.items() for a in ("--assign", f"{sid}={bone}")]
    assert main(["import", "mtw", *files, "-o", str(session), *assign]) == 0
    capsys.readouterr()
    assert main(["calibrate", "imu", "--from", str(session), "--out", str(tmp_path / "c.json")]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["facing_from"] == "steps" and report["hinges_checked"] == ["left_knee", "right_knee"]
    assert abs((report["facing_heading_deg"] + 180.0) % 360.0 - 180.0) < 10.0
    assert main(["calibrate", "imu", "--from", str(session), "--facing-heading", "180", "--out",
                 str(tmp_path / "c.json")]) == 1  # fmt: skip
    err = capsys.readouterr().err
    assert "knee" in err and "wrong way" in err and "--facing-heading 0 " in err

    still = tmp_path / "still"
    still.mkdir()
    _write_exports(still, seconds=0.0)
    files = sorted(str(p) for p in still.glob("MT_*.txt"))
    assert main(["import", "mtw", *files, "-o", str(still / "take"), *assign]) == 0
    capsys.readouterr()
    assert main(["calibrate", "imu", "--from", str(still / "take")]) == 1
    assert "no steps" in capsys.readouterr().err


def test_the_wrong_sign_of_a_real_pelvis_axis_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 28, friction 3, on the real OpenSense MTw take: with ``--facing-from 00B42279:-z`` every command used to
    succeed with the knees bending backwards in every step; it is refused, naming +z, which is accepted (and the
    facing from the steps agrees with it within 15°)."""
    from mocapd.eval.ground_real import MTW_ASSIGNMENT

    files = sorted(str(p) for p in (default_data_root() / "imu" / "opensense_mtw").glob("*.txt"))
    assign = [a for sid, bone in MTW_ASSIGNMENT.items() for a in ("--assign", f"{sid}={bone}")]
    session = tmp_path / "mtw"
    assert main(["import", "mtw", *files, "-o", str(session), *assign]) == 0
    capsys.readouterr()
    out = ["--out", str(tmp_path / "c.json")]
    assert main(["calibrate", "imu", "--from", str(session), "--facing-from", "00B42279:-z", *out]) == 1
    err = capsys.readouterr().err
    assert "left knee" in err and "right knee" in err and "--facing-from 00B42279:+z bends them the right way" in err
    assert main(["calibrate", "imu", "--from", str(session), "--facing-from", "00B42279:+z", *out]) == 0
    heading = json.loads(capsys.readouterr().out)["facing_heading_deg"]
    assert main(["calibrate", "imu", "--from", str(session), *out]) == 0
    steps = json.loads(capsys.readouterr().out)["facing_heading_deg"]
    assert abs((steps - heading + 180.0) % 360.0 - 180.0) < 15.0


def test_mvnx_imports_with_its_segment_labels(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    session = tmp_path / "mvn"
    assert main(["import", "mvnx", str(MVNX), "-o", str(session)]) == 0
    said = capsys.readouterr()
    summary = json.loads(said.out)
    labels = {v["label"]: sid for sid, v in summary["sensors"].items()}
    assert summary["assignment"][labels["Pelvis"]] == "Hips" and labels["RightShoulder"] not in summary["assignment"]
    # The shoulders' sensors have no bone of mocapd's: said so, not "give each a bone with --assign" (an --assign
    # replaces the automatic assignment of every other sensor) nor "leave its file out" (one file holds them all).
    notes = said.err.splitlines()
    assert notes[-1] == (f"note: 2 sensor(s) on segments mocapd's skeleton does not have, kept in the session but "
                         f"not calibrated or solved: {labels['RightShoulder']} (RightShoulder), "
                         f"{labels['LeftShoulder']} (LeftShoulder)")  # fmt: skip
    records = open_session(session).imu()
    assert len({r.sensor for r in records}) == 11 and len(records) == 11 * 112


def test_an_mvnx_take_brings_the_body_mvn_calibrated(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """MVN Studio sized the wearer (its segment points, in every MVNX file): the import uses that body instead of
    the 1.75 m default proportions, says so, and records it; what the command line gives replaces it."""
    from mocapd.io.mvnx import read_mvnx

    body = read_mvnx(MVNX).body()
    assert body is not None
    # The file's numbers (upper-body take, full body sized): right knee 0.395876 m below the right hip, ...
    assert body.height == pytest.approx(1.636, abs=1e-3) and body.segments["thigh"] == pytest.approx(0.3959, abs=1e-4)
    assert body.segments["foot"] == pytest.approx(0.1659, abs=1e-4)
    assert body.segments["ankle_height"] == pytest.approx(0.086, abs=1e-3)
    assert set(body.segments) == set(SEGMENTS)
    assert main(["import", "mvnx", str(MVNX), "-o", str(tmp_path / "a")]) == 0
    assert "the wearer's body from the MVNX file" in capsys.readouterr().err
    made = open_session(tmp_path / "a").manifest["skeleton"]
    assert made["from"]["source"] == "mvnx" and made["height"] == pytest.approx(body.height)
    lengths = made["from"]["lengths_m"]
    assert all(lengths[k] == pytest.approx(v, abs=1e-3) for k, v in body.segments.items()), (lengths, body)
    # A segment measured by hand replaces MVN's; a height alone scales the default proportions, as for MT Manager.
    assert main(["import", "mvnx", str(MVNX), "-o", str(tmp_path / "b"), "--thigh", "0.42"]) == 0
    b = open_session(tmp_path / "b").manifest["skeleton"]["from"]
    assert b["lengths_m"]["thigh"] == pytest.approx(0.42) and b["lengths_m"]["shank"] == pytest.approx(0.4004, abs=1e-3)
    capsys.readouterr()
    assert main(["import", "mvnx", str(MVNX), "-o", str(tmp_path / "c"), "--height", "1.8"]) == 0
    assert "is not used: leave --height out to use it" in capsys.readouterr().err
    c = open_session(tmp_path / "c").manifest["skeleton"]["from"]
    assert c["source"] == "height" and c["height_m"] == 1.8
    # A body no person has (a hand-edited or damaged file): said, and not used.
    text = MVNX.read_text(encoding="utf-8").replace("<pos_b>-0.000048 0.000000 -0.395876</pos_b>",
                                                    "<pos_b>0 0 -3.9</pos_b>", 1)  # fmt: skip
    (tmp_path / "giant.mvnx").write_text(text, encoding="utf-8")
    assert main(["import", "mvnx", str(tmp_path / "giant.mvnx"), "-o", str(tmp_path / "d")]) == 0
    assert "own body is not one mocapd can use (height 3.388 m, hip_width 0.190, thigh 2.148" in capsys.readouterr().err
    assert open_session(tmp_path / "d").manifest["skeleton"]["from"]["source"] == "height"


def test_arms_down_posture() -> None:
    """The solver's rest pose is the T-pose; ``--pose arms-down`` calibrates the arms as hanging at the sides."""
    from mocapd.core.imu_calibration import rest_orientations
    from mocapd.core.rotations import matrix_from_quat

    assert rest_orientations("t-pose") is None
    rest = rest_orientations("arms-down")
    assert rest is not None and set(rest) == {
        f"{s}{b}" for s in ("Left", "Right") for b in ("UpperArm", "LowerArm", "Hand")
    }
    np.testing.assert_allclose(matrix_from_quat(rest["LeftUpperArm"]) @ [1.0, 0, 0], [0, -1.0, 0], atol=1e-12)
    np.testing.assert_allclose(matrix_from_quat(rest["RightHand"]) @ [-1.0, 0, 0], [0, -1.0, 0], atol=1e-12)
    a_pose = rest_orientations("a-pose")  # issue 42: upper arms 30° below horizontal
    assert a_pose is not None
    np.testing.assert_allclose(matrix_from_quat(a_pose["LeftUpperArm"]) @ [1.0, 0, 0],
                               [np.cos(np.radians(30)), -np.sin(np.radians(30)), 0], atol=1e-12)  # fmt: skip
    with pytest.raises(ConfigError, match="pose"):
        rest_orientations("y-pose")

"""The walk-through of an IMU take as a new user types it (issue 28's frictions): import, calibrate, resolve, export;
each friction met there, with what mocapd now says or does. The take is written from recorded motion through the
sensor model (``tests/test_import_recordings.py``), so the truth is known."""

from __future__ import annotations

import csv
import json
import re
import shutil
import socket
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import quat_angle, quat_from_matrix, rotvec_from_quat
from mocapd.core.skeleton import BONE_INDEX, BONE_NAMES, Skeleton
from mocapd.io.session import open_session
from mocapd.service.cli import main
from tests.test_import_recordings import _write_exports

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def take(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, dict[str, str], np.ndarray]]:
    """An imported, calibrated and resolved lower-body take: (session, assignment, truth θ at 100 Hz)."""
    folder = tmp_path_factory.mktemp("take")
    exports = folder / "exports"
    exports.mkdir()
    assignment, _, truth = _write_exports(exports, seconds=1.5)
    session = folder / "take"
    assign = [a for sid, bone in assignment.items() for a in ("--assign", f"{sid}={bone}")]
    files = sorted(str(p) for p in exports.glob("MT_*.txt"))
    assert main(["import", "mtw", *files, "-o", str(session), *assign]) == 0
    assert main(["calibrate", "imu", "--from", str(session), "--facing-heading", "0",
                 "--out", str(folder / "cal.json")]) == 0  # fmt: skip
    assert main(["resolve", str(session), "--iterations", "10"]) == 0
    yield session, assignment, truth


def test_1_export_of_a_resolved_take_without_resolved_names_the_command(
    take: tuple[Path, dict[str, str], np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session, _, _ = take
    capsys.readouterr()
    out = tmp_path / "take.csv"
    assert main(["export", str(session), "--csv", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"the session is resolved: `mocapd export {session} --csv {out} --resolved`" in err, err
    assert main(["export", str(session), "--csv", str(out), "--resolved"]) == 0


def test_2_a_stream_written_by_resolve_o_is_exported_with_poses(
    take: tuple[Path, dict[str, str], np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session, _, _ = take
    stream = tmp_path / "variant.mcs"
    capsys.readouterr()
    assert main(["resolve", str(session), "--iterations", "5", "-o", str(stream)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["next"] == f"mocapd export {session} --poses {stream} --csv take.csv --bvh take.bvh"
    csv_out = tmp_path / "variant.csv"
    assert main(["export", str(stream), "--csv", str(csv_out)]) == 2  # the stream where its session belongs
    err = capsys.readouterr().err
    assert f"{stream} is a file, not a session directory: a pose stream written by `mocapd resolve SESSION -o" in err
    assert f"--poses {stream}" in err
    assert main(["export", str(session), "--poses", str(stream), "--csv", str(csv_out)]) == 0
    assert csv_out.read_text().count("\n") > 50


def test_4_a_recording_that_moves_in_the_window_asks_for_another_window(
    take: tuple[Path, dict[str, str], np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session, _, _ = take
    capsys.readouterr()
    args = ["calibrate", "imu", "--from", str(session), "--facing-heading", "0", "--pose", "arms-down",
            "--window", "1.4:2.8", "--out", str(tmp_path / "c.json")]  # fmt: skip
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "in the stillest 1 s of the recording (" in err and "standing, arms down" in err, err
    assert f"`mocapd calibrate imu --from {session} --window START:END`" in err
    assert "T-pose" not in err and "repeat" not in err  # a recording cannot be repeated


def test_5_import_help_shows_the_height_default_and_takes_segment_lengths(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit):
        main(["import", "mtw", "--help"])
    helptext = " ".join(capsys.readouterr().out.split())
    assert "--height M the wearer's height, m (default 1.75)" in helptext
    for flag, default in (("--thigh", "0.430"), ("--shank", "0.430"), ("--hip-width", "0.180"), ("--foot", "0.141")):
        assert re.search(f"{flag} M .*?default: from --height; {default} at 1.75 m", helptext), flag
    exports = tmp_path / "exports"
    exports.mkdir()
    assignment, _, _ = _write_exports(exports, seconds=0.2)
    session = tmp_path / "take"
    assign = [a for sid, bone in assignment.items() for a in ("--assign", f"{sid}={bone}")]
    files = sorted(str(p) for p in exports.glob("MT_*.txt"))
    assert main(["import", "mtw", *files, "-o", str(session), "--height", "1.82", "--thigh", "0.47",
                 "--hip-width", "0.2", *assign]) == 0  # fmt: skip
    summary = json.loads(capsys.readouterr().out)
    m = open_session(session).manifest
    assert summary["skeleton"] == m["skeleton"]["from"]
    assert m["skeleton"]["from"]["source"] == "segments"
    assert m["skeleton"]["from"]["segments_m"] == {"hip_width": 0.2, "thigh": 0.47}
    assert m["config"]["imu"]["body"] == {"height_m": 1.82, "thigh_m": 0.47, "hip_width_m": 0.2}
    skeleton = Skeleton(np.array(m["skeleton"]["offsets"]), m["skeleton"]["root_height"], m["skeleton"]["height"])
    assert skeleton.bone_length("LeftLowerLeg") == pytest.approx(0.47)  # the thigh: hip joint to knee
    assert skeleton.bone_length("LeftFoot") == pytest.approx(0.43 * 1.82 / 1.75)  # the shank, from the height
    left, right = skeleton.offsets[BONE_INDEX["LeftUpperLeg"], 0], skeleton.offsets[BONE_INDEX["RightUpperLeg"], 0]
    assert left - right == pytest.approx(0.2)


def test_6_a_folder_imports_and_a_sensor_without_a_bone_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    exports = tmp_path / "exports"
    exports.mkdir()
    assignment, _, _ = _write_exports(exports, seconds=0.2)
    spare = sorted(assignment)[-1]
    assign = [a for sid, bone in assignment.items() if sid != spare for a in ("--assign", f"{sid}={bone}")]
    assert main(["import", "mtw", str(exports), "-o", str(tmp_path / "take"), *assign]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["unassigned"] == [spare]
    assert f"note: 1 sensor(s) have no bone, kept in the session but not calibrated or solved: {spare}" in err
    assert "--assign SENSOR=BONE" in err


def test_7_sessions_doc_cites_only_files_of_the_repository_and_says_what_a_csv_joint_is() -> None:
    text = (REPO / "docs" / "sessions.md").read_text(encoding="utf-8")
    for name in set(re.findall(r"[\w./-]+\.md\b", text)):
        assert (REPO / name).exists() or (REPO / "docs" / name).exists(), f"docs/sessions.md cites {name}"
    for name in set(re.findall(r"`((?:mocapd|tools|tests)/[\w./-]+\.py)`", text)):  # modules named by path
        assert (REPO / name).exists(), f"docs/sessions.md cites {name}"
    csv_part = text[text.index("**CSV**") :]
    assert "where the bone starts" in csv_part and "+Y up" in csv_part and "right-handed" in csv_part


def test_8_csv_rows_map_to_the_source_files_rows(
    take: tuple[Path, dict[str, str], np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``source_s`` × the update rate is the source file's row: the exported knees there follow the truth there."""
    session, _, truth = take
    out = tmp_path / "take.csv"
    assert main(["export", str(session), "--resolved", "--csv", str(out)]) == 0
    with out.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    source = np.array([float(r["source_s"]) for r in rows])
    t_solve = np.array([int(r["t_solve_ns"]) for r in rows])
    origin = open_session(session).manifest["started_monotonic_ns"]
    np.testing.assert_allclose(source, (t_solve - origin) / 1e9, atol=1e-6)  # 6 decimals
    row = np.round(source * 100.0).astype(int)  # the files' rows: 100 Hz, none dropped
    assert row.min() >= 0 and row.max() < len(truth)
    kin = Kinematics(Skeleton.from_height(1.75))
    knees = [BONE_INDEX["LeftLowerLeg"], BONE_INDEX["RightLowerLeg"]]
    solved = quat_from_matrix(kin.forward(_thetas_from_csv(rows)).rotations[:, knees])
    true = quat_from_matrix(kin.forward(truth[row]).rotations[:, knees])
    assert np.median(np.degrees(quat_angle(solved, true))) < 5.0


def _thetas_from_csv(rows: list[dict[str, str]]) -> np.ndarray:
    """θ (n, 66) from a CSV's root and local rotation columns."""
    out = np.zeros((len(rows), 66))
    for i, r in enumerate(rows):
        out[i, 0:3] = [float(r["root_x"]), float(r["root_y"]), float(r["root_z"])]
        q = np.array([[float(r[f"{b}_q{c}"]) for c in "wxyz"] for b in BONE_NAMES])
        out[i, 3:] = rotvec_from_quat(q).reshape(-1)
    return out


def test_9_a_take_s_calibration_stays_with_the_take(
    take: tuple[Path, dict[str, str], np.ndarray],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Without --out, ``calibrate imu --from`` no longer writes calibration/<suit>.imu.json into the working
    directory, where a daemon started later would have found a suit of that name."""
    session = tmp_path / "take"
    shutil.copytree(take[0], session)
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert main(["calibrate", "imu", "--from", str(session), "--facing-heading", "0"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert not (tmp_path / "calibration").exists()
    assert report["calibration"] == str(session / "calibration" / "suit0.imu.json")
    assert (session / "calibration" / "suit0.imu.json").is_file()
    rig = tmp_path / "rig.toml"
    rig.write_text('[imu]\ncalibration_dir = "rigcal"\n', encoding="utf-8")
    assert main(["calibrate", "imu", "--from", str(session), "--facing-heading", "0", "--config", str(rig)]) == 0
    # Asked for: the rig's, beside its config file (where `mocapd run --config rig.toml` looks, from any folder).
    assert json.loads(capsys.readouterr().out)["calibration"] == str(tmp_path / "rigcal" / "suit0.imu.json")


def test_a_take_whose_sensors_end_apart_is_solved_where_all_of_them_measure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """MT Manager's exports of one recording end up to a second apart (the OpenSense take: 0.73 s). ``resolve``
    solved up to the last sample of any sensor, so the tail solved a foot from the prior and the stance from one
    leg: on that take the root sank 9 cm and lurched 0.4 m in its last 0.7 s. It now solves the span every suit
    sensor covers and says which sensor bounds it."""
    assignment, _, truth = _write_exports(tmp_path, seconds=1.5)
    foot = next(sid for sid, bone in assignment.items() if bone == "LeftFoot")
    path = tmp_path / f"MT_012005D6_009-001_{foot}.txt"
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[:-50]) + "\n")  # this sensor's export ends 0.5 s before the others'
    session = tmp_path / "take"
    files = sorted(str(p) for p in tmp_path.glob("MT_*.txt"))
    assign = [a for sid, bone in assignment.items() for a in ("--assign", f"{sid}={bone}")]
    assert main(["import", "mtw", *files, "-o", str(session), *assign]) == 0
    assert main(["calibrate", "imu", "--from", str(session), "--facing-heading", "0"]) == 0
    capsys.readouterr()
    assert main(["resolve", str(session), "--iterations", "5"]) == 0
    said = capsys.readouterr()
    summary = json.loads(said.out)
    s = open_session(session)
    origin = s.manifest["started_monotonic_ns"]
    foot_last = max(r.t_ns for r in s.imu() if r.sensor == foot)
    t = np.array([f.t_solve_ns for f in s.poses("poses-resolved")])
    assert (foot_last - origin) / 1e9 == pytest.approx((len(truth) - 51) / 100.0, abs=1e-6)
    assert foot_last - 17_000_000 < t[-1] <= foot_last  # the last tick the foot still measures
    assert t[0] == origin
    note = f"suit:suit0: solved 0.00-{(foot_last - origin) / 1e9:.2f} s of the take, the span all 8 of its sensors"
    assert any(n.startswith(note) and f"{foot} (LeftFoot) ends 0.50 s before" in n for n in summary["notes"]), said
    assert f"note: {note}" in said.err


def test_an_mvnx_take_without_legs_names_the_facing_it_needs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The real upper-body MVNX take has no thigh and shank sensors: ``import mvnx`` told the user to calibrate with
    "the facing from the take's steps", which then refused ("no steps"). Now the next command names the facing an
    MVNX take has — MVN's forward, its global +X, read as east — and the refusal does too."""
    from mocapd.core.rotations import matrix_from_quat
    from mocapd.io.mvnx import MVN_FACING_HEADING_DEG, read_mvnx
    from tests.test_import_recordings import MVNX

    # MVN's +X is where the wearer faces: the pelvis segment's forward over the take, as a compass heading of the
    # sensors' world (MVN's global frame read as ENU; mocapd axes (x, y, z) are MVN's (y, z, x)).
    fwd = matrix_from_quat(read_mvnx(MVNX).segment_orientation[:, 0]) @ np.array([0.0, 0.0, 1.0])
    heading = np.degrees(np.arctan2(fwd[:, 2], fwd[:, 0]))
    assert np.all(np.abs(heading - MVN_FACING_HEADING_DEG) < 10.0)
    session = tmp_path / "mvn"
    assert main(["import", "mvnx", str(MVNX), "-o", str(session)]) == 0
    next_command = json.loads(capsys.readouterr().out)["next"]
    assert next_command.startswith(f"mocapd calibrate imu --from {session} --facing-heading 90  (MVN's forward")
    assert "no thigh and shank sensors" in next_command
    assert main(["calibrate", "imu", "--from", str(session)]) == 1
    assert "for this MVNX take --facing-heading 90 (MVN's forward" in capsys.readouterr().err


def test_a_take_without_legs_asks_for_a_facing_in_its_next_command(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    exports = tmp_path / "exports"
    exports.mkdir()
    assignment, _, _ = _write_exports(exports, seconds=0.2)
    upper = [a for sid, b in assignment.items() if b in ("Hips", "Spine3") for a in ("--assign", f"{sid}={b}")]
    assert main(["import", "mtw", str(exports), "-o", str(tmp_path / "take"), *upper]) == 0
    next_command = json.loads(capsys.readouterr().out)["next"]
    assert next_command.startswith(f"mocapd calibrate imu --from {tmp_path / 'take'} --facing-heading DEG  (")
    assert "--facing-from SENSOR:AXIS" in next_command and "no thigh and shank sensors" in next_command


def test_replay_of_a_take_says_where_its_streams_go(
    take: tuple[Path, dict[str, str], np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`mocapd replay TAKE --resolved --config vr.toml` (an imported take to an engine) said how many sinks it fed,
    not which streams or where: a VMC receiver on the wrong port had nothing to go on."""
    session, _, _ = take
    vmc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vmc.bind(("127.0.0.1", 0))
    vmc.settimeout(10)
    config = tmp_path / "vr.toml"
    dest = f"127.0.0.1:{vmc.getsockname()[1]}"
    config.write_text(f'[websocket]\nport = 0\n[udp.vmc]\nenabled = true\ndestinations = ["{dest}"]\n')
    try:
        assert main(["replay", str(session), "--resolved", "--speed", "100", "--config", str(config)]) == 0
        assert vmc.recv(65536).startswith(b"#bundle")
    finally:
        vmc.close()
    assert f"\nVMC (OSC) avatars to {dest}: a subject per avatar\n" in capsys.readouterr().out

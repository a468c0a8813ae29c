"""Other detectors' 2D keypoints as sessions: ``mocapd import keypoints``, then ``resolve`` and ``export``.

The files are written here in each tool's layout (OpenPose per-frame JSON, MMPose prediction files, a Pose2Sim
project, FreeMoCap's array) from the synthetic rig's people projected through its cameras with 1 px of noise,
so the truth is known: the imported take must resolve to every person, its exported joints near the truth.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.keypoint_sets import BLAZEPOSE33, COCO18, WHOLEBODY133, convert, set_for_count
from mocapd.core.keypoints import BLAZEPOSE33_FORMAT, BODY25_FORMAT, COCO17_FORMAT, HALPE26_FORMAT
from mocapd.core.skeleton import BONE_NAMES
from mocapd.errors import InputError
from mocapd.io.calibration_files import (
    Z_TO_Y,
    CalibrationSet,
    CameraCalibration,
    in_metres,
    read_any,
    write_mocapd_toml,
    write_pose2sim_toml,
)
from mocapd.io.keypoint_files import camera_name, match_cameras, read_keypoint_inputs
from mocapd.io.session import RESOLVED, open_session
from mocapd.protocols.keypoint_files import parse_landmark_array, parse_mmpose, parse_openpose
from mocapd.service.cli import main
from mocapd.sim.world import SyntheticWorld
from tests.pose2sim_data import demo_root

FPS = 25.0


# ----------------------------------------------------------------------------------------------- parsers
def _triplets(n: int, start: float = 0.0) -> list[float]:
    return [v for i in range(n) for v in (start + i, 100.0 + i, 0.5)]


def test_openpose_sets_told_by_length() -> None:
    for n, name in ((25, "body25"), (18, "coco18"), (17, "coco17"), (26, "halpe26"), (133, "wholebody133")):
        doc = {"version": 1.3, "people": [{"pose_keypoints_2d": _triplets(n)}, {"pose_keypoints_2d": _triplets(n, 7)}]}
        parsed = parse_openpose(doc)
        assert parsed.keypoint_set == name
        kp, conf = parsed.frames[0]
        assert kp.shape == (2, n, 2) and conf.shape == (2, n)
        assert kp[1, 3].tolist() == [10.0, 103.0] and conf[1, 3] == 0.5


def test_openpose_bad_files_one_line() -> None:
    with pytest.raises(InputError, match="no 'people' list"):
        parse_openpose({"version": 1.3})
    with pytest.raises(InputError, match="19 keypoints per person is no keypoint set"):
        parse_openpose({"people": [{"pose_keypoints_2d": _triplets(19)}]})
    with pytest.raises(InputError, match="different numbers"):
        parse_openpose({"people": [{"pose_keypoints_2d": _triplets(25)}, {"pose_keypoints_2d": _triplets(18)}]})
    with pytest.raises(InputError, match="not a number"):
        parse_openpose({"people": [{"pose_keypoints_2d": ["x"] * 75}]})
    empty = parse_openpose({"people": [{"pose_keypoints_2d": [], "face_keypoints_2d": _triplets(70)}]})
    assert empty.keypoint_set == "" and empty.frames[0][0].shape[0] == 0


def test_mmpose_layouts() -> None:
    inst = {
        "keypoints": [[float(i), 2.0 * i] for i in range(17)],
        "keypoint_scores": [0.9] * 17,
        "bbox": [[0, 0, 1, 1]],
    }
    one = parse_mmpose([inst, inst])
    assert one.keypoint_set == "coco17" and one.frames[0][0].shape == (2, 17, 2)
    video = parse_mmpose([{"frame_id": 4, "instances": [inst]}, {"frame_id": 5, "instances": []}])
    assert sorted(video.frames) == [4, 5] and video.frames[5][0].shape == (0, 17, 2)
    halpe = {"keypoints": [[1.0, 1.0]] * 26, "keypoint_scores": [0.7] * 26}
    demo = {"meta_info": {"dataset_name": "halpe26"}, "instance_info": [{"frame_id": 1, "instances": [halpe]}]}
    assert parse_mmpose(demo).keypoint_set == "halpe26"
    coco = [{"image_id": 9, "category_id": 1, "keypoints": _triplets(133), "score": 0.8}]
    res = parse_mmpose(coco)
    assert res.keypoint_set == "wholebody133" and res.frames[9][1][0, 0] == 0.5
    with pytest.raises(InputError, match="keypoint_scores"):
        parse_mmpose([{"keypoints": [[1.0, 2.0]] * 17}])
    with pytest.raises(InputError, match="not an MMPose"):
        parse_mmpose({"people": []})


def test_convert_by_name() -> None:
    """Every set lands on mocapd's format by name; a point the source lacks is unseen (confidence 0)."""
    rng = np.random.default_rng(0)
    for source, names, target in (
        ("coco18", COCO18, COCO17_FORMAT),
        ("wholebody133", WHOLEBODY133, HALPE26_FORMAT),
        ("blazepose33", BLAZEPOSE33, HALPE26_FORMAT),
        ("body25", BODY25_FORMAT.keypoints, BODY25_FORMAT),
    ):
        kp = rng.uniform(0, 500, (3, len(names), 2))
        conf = rng.uniform(0.5, 1.0, (3, len(names)))
        out_kp, out_cf = convert(source, kp, conf, target.keypoints)
        assert out_kp.shape == (3, target.n_keypoints, 2)
        for j, name in enumerate(target.keypoints):
            src = {"left_big_toe": "left_foot_index", "right_big_toe": "right_foot_index"}.get(name, name)
            if source == "blazepose33" and src in names:
                assert np.array_equal(out_kp[:, j], kp[:, names.index(src)])
            elif name in names:
                assert np.array_equal(out_kp[:, j], kp[:, names.index(name)]) and np.array_equal(
                    out_cf[:, j], conf[:, names.index(name)]
                )
            elif source != "blazepose33":
                assert np.all(out_cf[:, j] == 0.0)
    # BlazePose onto its own format: every landmark where it was (foot_index by its own name, not lost to the alias
    # that puts it on Halpe-26's big toe; MediaPipe's mouth_left as mocapd's left_mouth)
    kp = rng.uniform(0, 500, (2, 33, 2))
    out_kp, out_cf = convert("blazepose33", kp, np.full((2, 33), 0.9), BLAZEPOSE33_FORMAT.keypoints)
    assert np.array_equal(out_kp, kp) and np.all(out_cf == 0.9)
    out_kp, out_cf = convert("coco18", np.full((1, 18, 2), np.nan), np.ones((1, 18)), COCO17_FORMAT.keypoints)
    assert np.all(out_cf == 0.0) and np.all(out_kp == 0.0)  # a NaN point is one the detector did not see
    assert set_for_count(33) == "blazepose33"


def test_freemocap_array() -> None:
    arr = np.full((2, 3, 33 + 21 + 21 + 468, 3), np.nan)
    arr[:, :, :33, :2] = 50.0
    arr[:, :, :33, 2] = 0.8
    arr[1, 2, 5] = np.nan
    cams = parse_landmark_array(arr)
    assert len(cams) == 2 and cams[0].keypoint_set == "blazepose33"
    kp, conf = cams[1].frames[2]
    assert kp.shape == (1, 33, 2) and conf[0, 5] == 0.0 and conf[0, 4] == pytest.approx(0.8)


def test_camera_names_and_matching() -> None:
    assert camera_name(Path("pose/cam01_json")) == "cam01"
    assert camera_name(Path("cam2_keypoints.json")) == "cam2"
    assert camera_name(Path("results_cam3.json")) == "cam3"
    assert match_cameras(["cam02", "cam01"], ["cam01", "cam02"]) == [1, 0]
    assert match_cameras(["a", "b"], ["cam01", "cam02"]) == [0, 1]  # no names in common: the order
    with pytest.raises(InputError, match=r"\['x'\] are not in the calibration"):
        match_cameras(["cam01", "x"], ["cam01", "cam02", "cam03"])


def test_calibration_units() -> None:
    cam = CameraCalibration("c", (640, 480), np.diag([500.0, 500.0, 1.0]), t=np.array([100.0, -50.0, 3000.0]))
    assert in_metres(CalibrationSet((cam,)), "mm").cameras[0].t.tolist() == [0.1, -0.05, 3.0]


# ----------------------------------------------------------------------------------------------- end to end
def _world(keypoints: str) -> SyntheticWorld:
    return SyntheticWorld(n_cams=4, n_people=2, n_suits=0, keypoints=keypoints, seed=1)


def _calibration(world: SyntheticWorld) -> CalibrationSet:
    return CalibrationSet(
        tuple(CameraCalibration(c.name, (c.width, c.height), c.K, c.dist, c.R, c.t) for c in world.cameras)
    )


def _write_openpose(world: SyntheticWorld, folder: Path, seconds: float) -> list[Path]:
    rng = np.random.default_rng(0)
    out = []
    for c, cam in enumerate(world.cameras):
        d = folder / f"{cam.name}_json"
        d.mkdir(parents=True)
        for f in range(round(seconds * FPS)):
            det = world.detections(c, f / FPS, rng, 1.0)
            people = [
                {"person_id": [-1], "pose_keypoints_2d": np.column_stack([det.keypoints[i], det.confidences[i]])
                 .ravel().round(3).tolist()}
                for i in range(len(det))
            ]  # fmt: skip
            (d / f"take_{f:012d}_keypoints.json").write_text(json.dumps({"version": 1.3, "people": people}))
        out.append(d)
    return out


def _joint_errors(world: SyntheticWorld, csv_path: Path) -> tuple[np.ndarray, set[str]]:
    """Per exported row, the mean joint distance (m) to the nearest true person at the row's source time."""
    rows = list(csv.DictReader(csv_path.open()))
    errors = []
    for r in rows:
        joints = np.array([[float(r[f"{b}_{a}"]) for a in "xyz"] for b in BONE_NAMES])
        t = float(r["source_s"])
        errors.append(min(np.linalg.norm(joints - world.joints_at(p, t), axis=1).mean() for p in range(2)))
    return np.array(errors), {r["subject"] for r in rows}


def _resolve_export(session: Path, csv_path: Path) -> dict[str, object]:
    assert main(["resolve", str(session)]) == 0
    assert main(["export", str(session), "--resolved", "--csv", str(csv_path), "--rate", str(FPS)]) == 0
    resolved = open_session(session).poses(RESOLVED)
    return {"identities": {p.identity for f in resolved for p in f.people}}


def test_openpose_body25_zup_calibration_to_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """OpenPose BODY_25 folders + a Pose2Sim (Z-up) calibration -> import -> resolve -> export CSV near the truth."""
    world = _world("body25")
    folders = _write_openpose(world, tmp_path, seconds=2.5)
    write_pose2sim_toml(_calibration(world), tmp_path / "Calib.toml")  # Z-up: read back +Y up with no option
    session = tmp_path / "take"
    assert main(["import", "keypoints", *map(str, folders[::-1]), "-o", str(session),
                 "--calibration", str(tmp_path / "Calib.toml"), "--fps", str(FPS)]) == 0  # fmt: skip
    summary = json.loads(capsys.readouterr().out)
    assert summary["keypoint_set"] == "body25" and summary["solved_as"] == "body25"
    assert list(summary["cameras"]) == [c.name for c in world.cameras][::-1]
    s = open_session(session)
    assert [c["name"] for c in s.manifest["cameras"]] == [c.name for c in world.cameras][::-1]
    assert len(s.keypoints()) == 4 * round(2.5 * FPS) and s.manifest["targets"]["names"][1] == "neck"
    out = _resolve_export(session, tmp_path / "take.csv")
    assert len(out["identities"]) == 2  # type: ignore[arg-type]
    errors, subjects = _joint_errors(world, tmp_path / "take.csv")
    assert len(subjects) == 1 and errors.size >= 30
    # Each person sized from BODY_25's limbs (18.7 mm); with the default 1.75 m skeleton, as when the scheduler
    # sized COCO-17 only, 35.3 mm.
    assert np.median(errors) < 0.03, np.median(errors)


def test_mmpose_files_to_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """One MMPose prediction file per camera (a video's ``instance_info``) and a Z-up K/R/t JSON calibration ->
    resolve -> CSV near the truth (in mocapd's +Y-up world: the JSON's Z-up world turned without an option)."""
    world = _world("coco17")
    rng = np.random.default_rng(1)
    files = []
    for c, cam in enumerate(world.cameras):
        frames = []
        for f in range(round(2.5 * FPS)):
            det = world.detections(c, f / FPS, rng, 1.0)
            frames.append({"frame_id": f + 1, "instances": [
                {"keypoints": det.keypoints[i].round(3).tolist(), "keypoint_scores": det.confidences[i].tolist(),
                 "bbox": [[0.0, 0.0, 10.0, 10.0]], "bbox_score": 0.9} for i in range(len(det))]})  # fmt: skip
        path = tmp_path / f"results_{cam.name}.json"
        path.write_text(json.dumps({"meta_info": {"dataset_name": "coco"}, "instance_info": frames}))
        files.append(path)
    # the Shelf/Campus K/R/t JSON of 4D association (world Z-up, metres), named after the files' cameras
    shelf = {c.name: {"K": c.K.ravel().tolist(), "RT": np.column_stack([c.R @ Z_TO_Y, c.t]).ravel().tolist(),
                      "imgSize": [c.width, c.height], "distCoeff": c.dist.tolist()} for c in world.cameras}  # fmt: skip
    (tmp_path / "calibration.json").write_text(json.dumps(shelf))
    session = tmp_path / "take"
    assert main(["import", "keypoints", *map(str, files), "-o", str(session), "--calibration",
                 str(tmp_path / "calibration.json"), "--fps", str(FPS)]) == 0  # fmt: skip
    summary = json.loads(capsys.readouterr().out)
    assert summary["layout"] == "mmpose" and summary["keypoint_set"] == "coco17"
    assert open_session(session).manifest["imported"]["first_frame"] == 1
    _resolve_export(session, tmp_path / "take.csv")
    errors, _ = _joint_errors(world, tmp_path / "take.csv")
    assert errors.size >= 30 and np.median(errors) < 0.03, np.median(errors)


def test_pose2sim_project(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A Pose2Sim project folder: pose/<cam>_json (Halpe-26 in OpenPose's layout), calibration/, Config.toml's
    frame rate; cameras named by the folders."""
    world = _world("halpe26")
    project = tmp_path / "project"
    _write_openpose(world, project / "pose", seconds=0.4)
    (project / "calibration").mkdir()
    write_pose2sim_toml(_calibration(world), project / "calibration" / "Calib_board.toml")
    (project / "Config.toml").write_text('[project]\nframe_rate = 25\n\n[pose]\npose_model = "Body_with_feet"\n')
    session = tmp_path / "take"
    assert main(["import", "keypoints", str(project), "-o", str(session)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["layout"] == "pose2sim" and summary["keypoint_set"] == "halpe26" and summary["fps"] == 25.0
    s = open_session(session)
    kps = s.keypoints()
    assert len(kps) == 4 * 10
    assert (kps[-1].capture_ns - kps[0].capture_ns) == round(9 * 1e9 / 25)
    name = s.manifest["cameras"][kps[0].camera]["name"]
    doc = json.loads((project / "pose" / f"{name}_json" / "take_000000000000_keypoints.json").read_text())
    first = np.array(doc["people"][0]["pose_keypoints_2d"]).reshape(-1, 3)
    assert kps[0].keypoints.shape[1:] == (26, 2)
    assert np.allclose(kps[0].keypoints[0], first[:, :2], atol=1e-3)  # the file's pixels, as float32


def test_import_refusals(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    world = _world("body25")
    folders = _write_openpose(world, tmp_path, seconds=0.12)
    write_mocapd_toml(_calibration(world), tmp_path / "calib.toml")
    args = ["import", "keypoints", *map(str, folders), "-o", str(tmp_path / "s")]
    assert main([*args, "--fps", "25"]) == 2
    assert "--calibration" in capsys.readouterr().err
    assert main([*args, "--calibration", str(tmp_path / "calib.toml")]) == 2
    assert "--fps" in capsys.readouterr().err
    assert main(["import", "keypoints", f"nowhere={folders[0]}", *map(str, folders[1:]), "-o", str(tmp_path / "s"),
                 "--calibration", str(tmp_path / "calib.toml"), "--fps", "25"]) == 2  # fmt: skip
    assert "['nowhere'] are not in the calibration" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()
    inputs = read_keypoint_inputs([str(f) for f in folders])
    assert inputs.layout == "openpose" and all(len(c.parsed.frames) == 3 for c in inputs.cameras)
    # A Pose2Sim project as its demos ship (Config.toml, calibration/, videos/) has no keypoints until Pose2Sim's
    # pose estimation writes pose/: said in one line (the old reader took it for an MMPose folder: "no .json
    # keypoint files").
    project = tmp_path / "Demo_MultiPerson"
    (project / "calibration").mkdir(parents=True)
    (project / "videos").mkdir()
    (project / "Config.toml").write_text("[project]\nframe_rate = 60\n")
    assert main(["import", "keypoints", str(project), "-o", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert "a Pose2Sim project without keypoints (no pose/ folder)" in err and err.count("\n") == 1


def test_following_a_folder_reads_only_new_whole_files(tmp_path: Path) -> None:
    """``feed --follow``: each look reads the files written since the last; one still being written (not yet
    JSON) is left for the next look, not lost."""
    from mocapd.io.keypoint_files import read_new_frames

    folder = tmp_path / "cam0_json"
    folder.mkdir()
    doc = {"people": [{"pose_keypoints_2d": _triplets(25)}]}
    (folder / "x_000000000000_keypoints.json").write_text(json.dumps(doc))
    cam = read_keypoint_inputs([str(folder)]).cameras[0]
    seen = {f.name for f in folder.iterdir()}
    (folder / "x_000000000001_keypoints.json").write_text(json.dumps(doc))
    (folder / "x_000000000002_keypoints.json").write_text(json.dumps(doc)[:20])  # half written
    new = read_new_frames(cam, "openpose", None, seen)
    assert sorted(new.frames) == [1] and new.keypoint_set == "body25"
    (folder / "x_000000000002_keypoints.json").write_text(json.dumps(doc))
    assert sorted(read_new_frames(cam, "openpose", None, seen).frames) == [2]
    assert read_new_frames(cam, "openpose", None, seen).frames == {}


def test_timestamps_parse() -> None:
    from mocapd.protocols.keypoint_files import parse_timestamps

    assert parse_timestamps("time_s\n0.0\n0.04\n\n0.08  # last\n") == {0: 0.0, 1: 0.04, 2: 0.08}
    assert parse_timestamps("frame,time_s\n3,1.5\n5,1.6\n") == {3: 1.5, 5: 1.6}
    for bad, why in (("0.1\n0.1\n", "increase"), ("1,0.1\n1,0.2\n", "twice"), ("", "no times"),
                     ("0.0\nnan\n", "not finite"), ("1.5,0.1\n", "whole"), ("1 2 3\n", "expected")):  # fmt: skip
        with pytest.raises(InputError, match=why):
            parse_timestamps(bad)


def test_import_with_timestamps(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--timestamps: every camera's frame times from one file, one camera's own (13 ms late, a camera not in sync);
    the output rate is the times' median rate without --fps; a frame without a time is refused."""
    world = _world("coco17")
    folders = _write_openpose(world, tmp_path, seconds=0.4)
    write_mocapd_toml(_calibration(world), tmp_path / "calib.toml")
    (tmp_path / "all.txt").write_text("".join(f"{0.5 + f / 20:.6f}\n" for f in range(10)))  # 20 Hz, from 0.5 s
    (tmp_path / "cam1.txt").write_text("frame time_s\n" + "".join(f"{f} {0.513 + f / 20:.6f}\n" for f in range(10)))
    args = ["import", "keypoints", *map(str, folders), "--calibration", str(tmp_path / "calib.toml"),
            "--timestamps", str(tmp_path / "all.txt"), "--timestamps", f"cam1={tmp_path / 'cam1.txt'}"]  # fmt: skip
    assert main([*args, "-o", str(tmp_path / "s")]) == 0
    assert json.loads(capsys.readouterr().out)["fps"] == pytest.approx(20.0)
    s = open_session(tmp_path / "s")
    assert s.manifest["scheduler"]["rate_hz"] == pytest.approx(20.0) and s.manifest["imported"]["timestamps"] == (
        "timestamps"
    )
    times: dict[str, list[int]] = {}
    for k in s.keypoints():
        times.setdefault(s.manifest["cameras"][k.camera]["name"], []).append(k.capture_ns)
    start = s.manifest["started_monotonic_ns"]
    assert times["cam0"][:2] == [start, start + 50_000_000]  # the earliest time is the session's start
    assert times["cam1"][0] == start + 13_000_000
    (tmp_path / "short.txt").write_text("0.0\n0.05\n")
    assert main([*args[:-4], "--timestamps", str(tmp_path / "short.txt"), "-o", str(tmp_path / "t")]) == 2
    assert "no timestamp for frame(s) [2, 3, 4, 5, 6] ..." in capsys.readouterr().err


def test_pose2sim_demo_project_with_its_real_calibration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The Pose2Sim multi-person demo as a project folder (its own Config.toml and Qualisys calibration, fetched by
    the set-up), its pose/ folders written as Pose2Sim writes them (Halpe-26 in OpenPose's layout) from two
    synthetic people placed in the demo's capture area and projected through its four real cameras; the demo's
    frame_rate is 'auto', so --fps. Import -> resolve -> export: both people, joints near the truth."""
    demo = demo_root() / "Demo_MultiPerson"
    project = tmp_path / "Demo_MultiPerson"
    (project / "calibration").mkdir(parents=True)
    shutil.copy(demo / "Config.toml", project / "Config.toml")
    shutil.copy(demo / "calibration" / "Calib.qca.txt", project / "calibration" / "Calib.qca.txt")
    cams = read_any(project / "calibration" / "Calib.qca.txt").cameras
    world = _world("halpe26")
    centre = np.mean([c.center for c in cams], axis=0) * [1.0, 0.0, 1.0]  # the floor point the cameras surround
    shift = []
    for p in range(2):  # each person's own centre moved 0.5 m either side of it (inside all four views)
        mean = np.mean([world.sites_at(p, t).mean(0) for t in np.arange(0, 4, 0.1)], axis=0) * [1.0, 0.0, 1.0]
        shift.append(centre + np.array([0.0, 0.0, 0.5 if p == 0 else -0.5]) - mean)
    rng = np.random.default_rng(2)
    fps = 30.0
    for cam in cams:
        folder = project / "pose" / f"{cam.name}_json"
        folder.mkdir(parents=True)
        for f in range(round(2.5 * fps)):
            people = []
            for p in range(2):
                uv = cam.project(world.sites_at(p, f / fps) + shift[p]) + rng.normal(scale=1.0, size=(26, 2))
                inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.size[0]) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.size[1])
                kp = np.column_stack([np.where(inside[:, None], uv, 0.0), 0.9 * inside])
                people.append({"person_id": [-1], "pose_keypoints_2d": kp.ravel().round(2).tolist()})
            (folder / f"{cam.name}_{f:06d}.json").write_text(json.dumps({"version": 1.3, "people": people}))
    session = tmp_path / "take"
    assert main(["import", "keypoints", str(project), "-o", str(session), "--fps", str(fps)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["layout"] == "pose2sim" and summary["keypoint_set"] == "halpe26"
    assert list(summary["cameras"]) == ["cam01", "cam02", "cam03", "cam04"]
    assert summary["calibration"].endswith("Calib.qca.txt")
    out = _resolve_export(session, tmp_path / "take.csv")
    assert len(out["identities"]) == 2  # type: ignore[arg-type]
    rows = list(csv.DictReader((tmp_path / "take.csv").open()))
    errors = []
    for r in rows:
        joints = np.array([[float(r[f"{b}_{a}"]) for a in "xyz"] for b in BONE_NAMES])
        t = float(r["source_s"])
        errors.append(min(np.linalg.norm(joints - world.joints_at(p, t) - shift[p], axis=1).mean() for p in range(2)))
    assert len(errors) >= 30 and np.median(errors) < 0.03, np.median(errors)  # 18.4 mm; 34.5 unsized


def test_mediapipe_layouts() -> None:
    from mocapd.protocols.keypoint_files import parse_mediapipe

    lm = [{"x": 0.5, "y": 0.25, "z": -0.1, "visibility": 0.9}] * 33
    legacy = parse_mediapipe({"landmark": lm})  # MessageToDict of the legacy solution's pose_landmarks
    assert legacy.normalized and legacy.keypoint_set == "blazepose33"
    assert legacy.frames[0][0].shape == (1, 33, 2) and legacy.frames[0][1][0, 0] == pytest.approx(0.9)
    tasks = parse_mediapipe({"pose_landmarks": [lm, lm]})  # the Tasks API: one list per person
    assert tasks.frames[0][0].shape == (2, 33, 2)
    video = parse_mediapipe({"frames": [{"frame": 7, "pose_landmarks": [lm]}, {"frame": 8, "pose_landmarks": []}]})
    assert sorted(video.frames) == [7, 8] and video.frames[8][0].shape == (0, 33, 2)
    assert parse_mediapipe([lm]).frames[0][0].shape == (1, 33, 2)  # a list of people
    with pytest.raises(InputError, match="33 landmarks"):
        parse_mediapipe({"landmark": lm[:17]})


def test_mediapipe_video_files_to_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """One MediaPipe Pose JSON per camera (a video's frames, Tasks-API people, landmarks as fractions of the
    image): import scales them by the calibrated image sizes and solves every landmark (the blazepose33 format:
    heels and foot_index on the feet, pinky, index and thumb on the hands); resolve -> CSV near the truth, the hands
    turned as the people's (median 7.7-7.9 deg; solved as Halpe-26, which has no hand point, 11.4-13.8 deg)."""
    from scipy.spatial.transform import Rotation

    world = _world("blazepose33")
    rng = np.random.default_rng(3)
    files = []
    for c, cam in enumerate(world.cameras):
        frames = []
        for f in range(round(3.0 * FPS)):
            det = world.detections(c, f / FPS, rng, 1.0)
            people = [[{"x": float(det.keypoints[i, j, 0] / cam.width), "y": float(det.keypoints[i, j, 1] / cam.height),
                        "z": 0.0, "visibility": float(det.confidences[i, j])} for j in range(33)]
                      for i in range(len(det))]  # fmt: skip
            frames.append({"frame": f, "pose_landmarks": people})
        path = tmp_path / f"{cam.name}.json"
        path.write_text(json.dumps({"frames": frames}))
        files.append(path)
    write_mocapd_toml(_calibration(world), tmp_path / "calib.toml")
    session = tmp_path / "take"
    assert main(["import", "keypoints", *map(str, files), "-o", str(session), "--calibration",
                 str(tmp_path / "calib.toml"), "--fps", str(FPS)]) == 0  # fmt: skip
    summary = json.loads(capsys.readouterr().out)
    assert summary["layout"] == "mediapipe" and summary["keypoint_set"] == "blazepose33"
    assert summary["solved_as"] == "blazepose33"
    assert main(["resolve", str(session)]) == 0
    for subject in ("track:1", "track:2"):
        out = tmp_path / f"{subject[-1]}.csv"
        assert main(["export", str(session), "--resolved", "--csv", str(out), "--subject", subject,
                     "--rate", str(FPS)]) == 0  # fmt: skip
        joint_errors, hand_deg = [], []
        for r in csv.DictReader(out.open()):
            t = float(r["source_s"])
            joints = np.array([[float(r[f"{b}_{a}"]) for a in "xyz"] for b in BONE_NAMES])
            d = [float(np.linalg.norm(joints - world.joints_at(p, t), axis=1).mean()) for p in range(2)]
            theta = world.theta_at(int(np.argmin(d)), t)
            joint_errors.append(min(d))
            for hand in ("LeftHand", "RightHand"):
                b = BONE_NAMES.index(hand)
                q = [float(r[f"{hand}_q{k}"]) for k in "wxyz"]  # the hand's local rotation, as theta's
                turn = Rotation.from_rotvec(theta[3 + 3 * b : 6 + 3 * b]).inv() * Rotation.from_quat([*q[1:], q[0]])
                hand_deg.append(float(np.degrees(turn.magnitude())))
        assert len(joint_errors) >= 60 and np.median(joint_errors) < 0.03, np.median(joint_errors)
        assert np.median(hand_deg) < 10.0, np.median(hand_deg)


def test_freemocap_array_import(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """FreeMoCap's 2D array (cameras x frames x 543 points x 3, pixels, NaN where unseen): one camera per row,
    named cam0, cam1, ... and taken in the calibration's order; BlazePose's 33 body points solved as they are."""
    world = _world("halpe26")
    n_frames = 10
    arr = np.full((4, n_frames, 33 + 21 + 21 + 468, 3), np.nan)
    arr[:, :, :33, :2] = np.linspace(10, 300, 33)[None, None, :, None]
    arr[:, :, :33, 2] = 0.8
    arr[2, 4, 11] = np.nan  # cam2's left shoulder unseen in frame 4
    np.save(tmp_path / "mediapipe2dData_numCams_numFrames_numTrackedPoints_pixelXY.npy", arr)
    write_mocapd_toml(_calibration(world), tmp_path / "calib.toml")
    npy = tmp_path / "mediapipe2dData_numCams_numFrames_numTrackedPoints_pixelXY.npy"
    assert main(["import", "keypoints", str(npy), "-o", str(tmp_path / "s"), "--calibration",
                 str(tmp_path / "calib.toml"), "--fps", "30"]) == 0  # fmt: skip
    summary = json.loads(capsys.readouterr().out)
    assert summary["layout"] == "freemocap" and summary["solved_as"] == "blazepose33"
    s = open_session(tmp_path / "s")
    kps = s.keypoints()
    assert len(kps) == 4 * n_frames and [c["name"] for c in s.manifest["cameras"]] == [c.name for c in world.cameras]
    names = BLAZEPOSE33_FORMAT.keypoints
    shoulder = names.index("left_shoulder")
    rec = next(
        k for k in kps if k.camera == 2 and k.capture_ns == s.manifest["started_monotonic_ns"] + round(4 * 1e9 / 30)
    )
    assert rec.confidences[0, shoulder] == 0.0 and rec.keypoints[0, shoulder].tolist() == [0.0, 0.0]
    assert rec.keypoints[0, names.index("right_shoulder")][0] == pytest.approx(arr[2, 4, 12, 0])
    # the hand and toe points kept (onto Halpe-26 they were dropped or renamed)
    for k in (17, 19, 21, 31):  # left_pinky, left_index, left_thumb, left_foot_index
        assert rec.keypoints[0, names.index(BLAZEPOSE33[k])][0] == pytest.approx(arr[2, 4, k, 0])


def test_up_and_floor_measured_on_the_people(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--up auto``: a calibration whose world is turned off every axis (70 deg about x, 15 about z) and shifted is
    levelled by the people (upright on average, their ankles low): up within 6 deg (4.0 measured: the walkers
    lean), the floor within 0.15 m (7.8 cm: that lean over the people's distance from the origin), the cameras'
    heights within 0.4 m of the truth. The old CLI had no auto (exit 2)."""
    from scipy.spatial.transform import Rotation

    world = _world("body25")
    folders = _write_openpose(world, tmp_path, seconds=2.5)
    turn = Rotation.from_euler("xz", [-70.0, 15.0], degrees=True).as_matrix()  # X_file = turn X + shift
    shift = np.array([0.3, -0.2, 0.5])
    tilted = CalibrationSet(tuple(CameraCalibration(c.name, (c.width, c.height), c.K, c.dist, c.R @ turn.T,
                                                    c.t - c.R @ turn.T @ shift) for c in world.cameras))  # fmt: skip
    write_mocapd_toml(tilted, tmp_path / "tilted.toml")
    args = ["import", "keypoints", *map(str, folders), "--calibration", str(tmp_path / "tilted.toml"), "--fps", "25"]
    assert main([*args, "-o", str(tmp_path / "s"), "--up", "auto"]) == 0
    found = json.loads(capsys.readouterr().out)["world"]
    up = turn @ [0.0, 1.0, 0.0]
    assert np.degrees(np.arccos(np.clip(np.dot(found["up"], up), -1, 1))) < 6.0, found
    assert abs(found["floor_m"] - shift @ up) < 0.15 and found["person_instants"] >= 100, found
    for cam, truth in zip(open_session(tmp_path / "s").manifest["cameras"], world.cameras, strict=True):
        centre = -np.array(cam["R"]).T @ np.array(cam["t"])
        assert abs(centre[1] - (-truth.R.T @ truth.t)[1]) < 0.4, (cam["name"], centre)
    assert main([*args, "-o", str(tmp_path / "s2"), "--up", "auto", "--floor", "1"]) == 2
    assert "leave --floor out" in capsys.readouterr().err

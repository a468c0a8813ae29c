"""glTF, BVH and FBX exports imported into real Blender (``bpy``): joint count, frame count, and every joint within
1 mm of the session's recorded joint positions at sampled frames; two subjects with their own skeletons, one
starting later, so the glTF's and FBX's shared timelines are checked too. The FBX is written by Blender's own
exporter in one Blender process (``mocapd export --fbx``) and read back in another."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import BONE_NAMES, Skeleton
from mocapd.core.synthetic import moving_sequence
from mocapd.io.session import SessionWriter, open_session
from mocapd.protocols import session_format as sf
from mocapd.service import cli
from tests.blender_support import ROOT, bpy_python, run_blender_script

FPS = 60
PERIOD_NS = round(1e9 / FPS)
SUBJECTS = {"suit:suit0": (1.82, 0, 150), "track:1": (1.58, 37, 90)}  # height, first tick, frames
SAMPLES = (0, 1, 44, 89)


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("blender") / "session"
    motion = {}
    for k, (who, (height, first, n)) in enumerate(SUBJECTS.items()):
        sk = Skeleton.from_height(height)
        theta = moving_sequence(sk, n, seed=11 + k)
        theta[:, 0] += 1.2 * k - 0.6
        motion[who] = (sk, first, theta, Kinematics(sk).forward(theta).positions)
    w = SessionWriter(path, {"format": "mocapd-session", "version": 1}, flush_interval_s=0.1)
    w.open()
    t0 = 5_000_000_000
    for tick in range(max(first + n for _, first, n in SUBJECTS.values())):
        people = tuple(
            sf.PersonRecord(who, None, i, 4, 0, 5, True, 0.9, theta[tick - first], joints[tick - first], sk)
            for i, (who, (sk, first, theta, joints)) in enumerate(motion.items())
            if first <= tick < first + len(theta)
        )
        w.put("poses", sf.T_POSE, sf.encode_pose, sf.PoseRecord(tick, t0 + tick * PERIOD_NS, 0, 0, people))
    w.close()
    return path


def _recorded(path: Path, who: str) -> np.ndarray:
    """The session's joint positions of ``who``, frame by frame, shape (n, 21, 3)."""
    return np.array([p.joints for f in open_session(path).poses() for p in f.people if p.identity == who])


def _check(arm: dict[str, object], joints: np.ndarray, first_frame: int) -> None:
    assert arm["bones"] == list(BONE_NAMES)
    keys = np.asarray(arm["keyframes"])
    assert keys.size == joints.shape[0]  # one keyframe per exported frame
    np.testing.assert_allclose(keys, first_frame + np.arange(keys.size), atol=1e-3)
    samples = arm["samples"]
    assert isinstance(samples, dict) and set(samples) == {str(i) for i in SAMPLES if i < keys.size}
    for i, heads in samples.items():
        got = np.array([heads[b] for b in BONE_NAMES])
        err = np.linalg.norm(got - joints[int(i)], axis=1)
        assert err.max() < 1e-3, f"frame {i}: {BONE_NAMES[int(err.argmax())]} off by {1e3 * err.max():.3f} mm"


def test_gltf_export_imports_into_blender(session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    glb = tmp_path / "take.glb"
    assert cli.main(["export", str(session), "--gltf", str(glb)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["gltf_subjects"] == {who: n for who, (_, _, n) in SUBJECTS.items()}
    report = run_blender_script(ROOT / "tests" / "blender_import.py", "gltf", str(glb), str(FPS), *map(str, SAMPLES))
    arms = report["armatures"]
    assert set(arms) == set(SUBJECTS), arms.keys()
    for who, (_, first, _) in SUBJECTS.items():
        _check(arms[who], _recorded(session, who), first)
        assert arms[who]["action"] is not None and who in arms[who]["action"]
    skinned = {name: m for name, m in report["meshes"].items() if m["armature"]}
    assert {m["armature"][0] for m in skinned.values()} == set(SUBJECTS)
    assert all(m["groups"] == 21 for m in skinned.values())


def test_bvh_export_imports_into_blender(session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bvh = tmp_path / "take.bvh"
    assert cli.main(["export", str(session), "--bvh", str(bvh)]) == 0
    assert json.loads(capsys.readouterr().out)["subject"] == "suit:suit0"  # the one seen most
    report = run_blender_script(ROOT / "tests" / "blender_import.py", "bvh", str(bvh), str(FPS), *map(str, SAMPLES))
    (arm,) = report["armatures"].values()
    _check(arm, _recorded(session, "suit:suit0"), 1)  # Blender's BVH import starts at frame 1


FBX_SAMPLES = (0, 1, 20, 44, 89, 126, 149)


def _fbx_expected(path: Path, who: str, frame: int, step: int) -> np.ndarray:
    """The session's joints of ``who`` at FBX frame ``frame`` of a grid of ``step`` ticks from the session's start:
    the subject's first grid point before it appears, its last after it leaves (it holds its pose)."""
    _, first, n = SUBJECTS[who]
    lo = -(-first // step) * step  # the subject's first and last grid ticks
    hi = (first + n - 1) // step * step
    joints: np.ndarray = _recorded(path, who)[min(max(frame * step, lo), hi) - first]
    return joints


@pytest.mark.parametrize(
    ("options", "rate", "settings"),
    [
        # Defaults: centimetres (UnitScaleFactor 1), Y up, facing +Z (FrontAxis 2), 60 fps.
        ((), 60, {"UpAxis": 1, "UpAxisSign": 1, "FrontAxis": 2, "FrontAxisSign": 1, "UnitScaleFactor": 1.0}),
        # Metres (100 cm a unit), Z up (Blender's frame: facing -Y, FrontAxis 1 with sign -1), 30 fps.
        (("--fbx-units", "m", "--fbx-up", "z", "--rate", "30"), 30,
         {"UpAxis": 2, "UpAxisSign": 1, "FrontAxis": 1, "FrontAxisSign": -1, "UnitScaleFactor": 100.0}),
    ],
    ids=["cm-y-60fps", "m-z-30fps"],
)  # fmt: skip
def test_fbx_export_through_blender_imports_into_blender(
    session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], options: tuple[str, ...], rate: int,
    settings: dict[str, float],
) -> None:  # fmt: skip
    fbx = tmp_path / "take.fbx"
    argv = ["export", str(session), "--fbx", str(fbx), "--blender", str(bpy_python()), *options]
    assert cli.main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    nodes = {"suit:suit0": "suit_suit0", "track:1": "track_1"}
    assert out["fbx_nodes"] == nodes and fbx.stat().st_size > 0 and list(tmp_path.iterdir()) == [fbx]
    samples = map(str, FBX_SAMPLES)
    report = run_blender_script(ROOT / "tests" / "blender_import.py", "fbx", str(fbx), str(rate), *samples)
    # What engines read first: the axes, the unit, the frame rate, one take named after the session, and the
    # armature nodes at the identity (no axis or unit baked into a node's transform).
    info = report["fbx"]
    assert info["version"] >= 7400 and info["stacks"] == ["session"]
    assert {k: info["settings"][k] for k in settings} == pytest.approx(settings, rel=1e-6)  # the unit: float32
    assert info["settings"]["CustomFrameRate"] == pytest.approx(rate)
    for node in nodes.values():
        model = info["models"][node]
        assert model["type"] == "Null"
        assert np.allclose(model["Lcl Rotation"] or [0.0] * 3, 0.0, atol=1e-4)  # degrees
        assert np.allclose(model["Lcl Scaling"] or [1.0] * 3, 1.0, atol=1e-6)
    assert report["fps"] == pytest.approx(rate)
    # Read back by Blender's importer: bones, one key per frame of the take (from frame 1), every joint within 1 mm.
    step = 60 // rate
    frames = 150 // step
    assert set(report["armatures"]) == set(nodes.values()), report["armatures"].keys()
    for who, node in nodes.items():
        arm = report["armatures"][node]
        assert arm["bones"] == list(BONE_NAMES)
        np.testing.assert_allclose(arm["keyframes"], 1 + np.arange(frames), atol=1e-3)
        assert set(arm["samples"]) == {str(i) for i in FBX_SAMPLES if i < frames}
        for i, heads in arm["samples"].items():
            got = np.array([heads[b] for b in BONE_NAMES])
            err = np.linalg.norm(got - _fbx_expected(session, who, int(i), step), axis=1)
            assert err.max() < 1e-3, f"{who} frame {i}: {BONE_NAMES[int(err.argmax())]} off by {1e3 * err.max():.3f} mm"
    skinned = {name: m for name, m in report["meshes"].items() if m["armature"]}
    assert {m["armature"][0] for m in skinned.values()} == set(nodes.values())
    assert all(m["groups"] == 21 for m in skinned.values())


def test_fbx_output_names_up_to_the_longest_a_file_may_have(
    session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 45: names of 241-255 bytes passed the name check, then failed inside Blender with a traceback (its
    temporary file was the name plus ``.part-PID.fbx``). Now a 255-byte name (of 2-byte characters) is written."""
    fbx = tmp_path / ("é" * 125 + "x.fbx")
    assert len(fbx.name.encode()) == 255
    argv = ["export", str(session), "--fbx", str(fbx), "--blender", str(bpy_python())]
    assert cli.main(argv) == 0, capsys.readouterr().err
    assert fbx.stat().st_size > 0 and list(tmp_path.iterdir()) == [fbx]

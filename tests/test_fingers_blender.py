"""Finger bones in the glTF, BVH and FBX exports, read by real Blender (``bpy``; issue 44): a recorded session where
``suit:suit0`` closes both hands into a fist (its right hand lost for a while in the middle) beside ``track:1``
without fingers, exported with ``mocapd export`` and imported by Blender's own importers. The fingered armature has
the 30 finger bones under their Unity names after the body's, every finger joint within 1 mm of the recorded
fingers' forward kinematics at sampled frames, and the fingers turn (the fingertips close on the palm); the
fingerless armature keeps exactly the 21 body bones."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.hand_skeleton import HAND_BONE_NAMES, HandSkeleton
from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import BONE_NAMES, Skeleton
from mocapd.core.synthetic import moving_sequence
from mocapd.io.session import SessionWriter, open_session
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.protocols import session_format as sf
from mocapd.protocols.fingers import subject_fingers
from mocapd.service import cli
from mocapd.service.outputs.recorder import pose_record
from tests.blender_support import ROOT, bpy_python, run_blender_script
from tests.finger_support import closing, fist, person_with_fingers

FPS = 60
PERIOD_NS = round(1e9 / FPS)
N = 90
SAMPLES = (0, 1, 44, 89)
SKELETONS = {"suit:suit0": Skeleton.from_height(1.82), "track:1": Skeleton.from_height(1.6)}


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("fingers") / "session"
    sk, other = SKELETONS["suit:suit0"], SKELETONS["track:1"]
    hands = HandSkeleton.from_body(sk)
    a, b = moving_sequence(sk, N, seed=21), moving_sequence(other, N, seed=22)
    a[:, 0] -= 0.6
    b[:, 0] += 0.6
    w = SessionWriter(path, {"format": "mocapd-session", "version": 1}, flush_interval_s=0.1)
    w.open()
    for i, c in enumerate(closing(N)):
        right = not 30 <= i < 40  # the right hand not found for a sixth of a second
        people = [person_with_fingers("suit:suit0", a[i], sk, fist(float(c), hands, (True, right)), own=True),
                  person_with_fingers("track:1", b[i], other, None, track=1, own=True)]  # fmt: skip
        frame = PoseFrame(i, 5_000_000_000 + i * PERIOD_NS, 0, people, 0)
        w.put("poses", sf.T_POSE, sf.encode_pose, pose_record(frame))
    w.close()
    return path


def _expected(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The recorded suit:suit0's body joints (n, 21, 3) and finger joints (n, 30, 3), from what was recorded."""
    frames = [p for f in open_session(path).poses() for p in f.people if p.identity == "suit:suit0"]
    body, fingers = [], []
    for p in frames:
        assert p.hands is not None and p.skeleton is not None
        body.append(Kinematics(p.skeleton).forward(p.theta).positions)
        fingers.append(subject_fingers(p.theta[None], [p.skeleton], [p.hands]).positions[0].reshape(30, 3))
    return np.array(body), np.array(fingers)


def _check(arm: dict[str, object], path: Path) -> None:
    bones = arm["bones"]
    assert isinstance(bones, list) and sorted(bones) == sorted([*BONE_NAMES, *HAND_BONE_NAMES])  # Blender: depth first
    body, fingers = _expected(path)
    samples = arm["samples"]
    assert isinstance(samples, dict) and set(samples) == {str(i) for i in SAMPLES}
    for i, heads in samples.items():
        got = np.array([heads[b] for b in (*BONE_NAMES, *HAND_BONE_NAMES)])
        want = np.concatenate([body[int(i)], fingers[int(i)]])
        err = np.linalg.norm(got - want, axis=1)
        worst = (*BONE_NAMES, *HAND_BONE_NAMES)[int(err.argmax())]
        assert err.max() < 1e-3, f"frame {i}: {worst} off by {1e3 * err.max():.3f} mm"
    # The fingers turn: the index distal joint comes 3 cm nearer the wrist as the fist closes.
    reach = [np.linalg.norm(np.array(samples[str(i)]["LeftIndexDistal"]) - samples[str(i)]["LeftHand"]) for i in
             (0, 89)]  # fmt: skip
    assert reach[1] < reach[0] - 0.03, reach


def _fingerless(arm: dict[str, object]) -> None:
    assert arm["bones"] == list(BONE_NAMES)


def test_gltf_finger_bones_import_into_blender(
    session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    glb = tmp_path / "take.glb"
    assert cli.main(["export", str(session), "--gltf", str(glb)]) == 0
    capsys.readouterr()
    report = run_blender_script(ROOT / "tests" / "blender_import.py", "gltf", str(glb), str(FPS), *map(str, SAMPLES))
    arms = report["armatures"]
    _check(arms["suit:suit0"], session)
    _fingerless(arms["track:1"])
    groups = {m["armature"][0]: m["groups"] for m in report["meshes"].values() if m["armature"]}
    assert groups == {"suit:suit0": 51, "track:1": 21}


def test_bvh_finger_bones_import_into_blender(
    session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bvh = tmp_path / "take.bvh"
    assert cli.main(["export", str(session), "--bvh", str(bvh), "--subject", "suit:suit0"]) == 0
    capsys.readouterr()
    assert bvh.read_text().count("End Site") == 1 + 2 + 10  # the head, the toes and ten fingertips
    report = run_blender_script(ROOT / "tests" / "blender_import.py", "bvh", str(bvh), str(FPS), *map(str, SAMPLES))
    (arm,) = report["armatures"].values()
    _check(arm, session)


def test_fbx_finger_bones_through_blender_import_into_blender(
    session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fbx = tmp_path / "take.fbx"
    assert cli.main(["export", str(session), "--fbx", str(fbx), "--blender", str(bpy_python())]) == 0
    assert json.loads(capsys.readouterr().out)["fbx_nodes"] == {"suit:suit0": "suit_suit0", "track:1": "track_1"}
    report = run_blender_script(ROOT / "tests" / "blender_import.py", "fbx", str(fbx), str(FPS), *map(str, SAMPLES))
    _check(report["armatures"]["suit_suit0"], session)
    _fingerless(report["armatures"]["track_1"])

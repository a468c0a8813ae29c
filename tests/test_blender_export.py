"""glTF and BVH exports imported into real Blender (``bpy``): joint count, frame count, and every joint within
1 mm of the session's recorded joint positions at sampled frames; two subjects with their own skeletons, one
starting later, so the glTF's shared timeline is checked too."""

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
from tests.blender_support import ROOT, run_blender_script

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

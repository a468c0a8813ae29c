"""Which subjects ``mocapd export`` writes into a glTF/FBX: every subject but a fleeting track.

``mocapd demo --synthetic --record`` on a loaded machine recorded a ``track:2`` for two frames: the suit wearer, taken
for a new person before their suit's binding took them over. Exported, it was a third armature that held its only
pose through the whole 19 s take, frozen where the wearer had stood a moment. It is now left out (and named), unless
``--subject`` asks for it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from pygltflib import GLTF2

from mocapd.core.kinematics import Kinematics
from mocapd.core.skeleton import Skeleton
from mocapd.core.synthetic import moving_sequence
from mocapd.io.session import SessionWriter
from mocapd.protocols import session_format as sf
from mocapd.service import cli

PERIOD_NS = round(1e9 / 60)


def _session(path: Path, subjects: dict[str, tuple[int, int]]) -> Path:
    """A session of subjects (identity -> first tick, frames) moving at 60 Hz."""
    sk = Skeleton.from_height(1.75)
    kin = Kinematics(sk)
    motion = {who: moving_sequence(sk, n, seed=3 + k) for k, (who, (_, n)) in enumerate(subjects.items())}
    w = SessionWriter(path, {"format": "mocapd-session", "version": 1}, flush_interval_s=0.1)
    w.open()
    for tick in range(max(first + n for first, n in subjects.values())):
        people = tuple(
            sf.PersonRecord(
                who, None, i, 4, 0, 5, True, 0.9, th[tick - first], kin.forward(th[tick - first]).positions, sk
            )
            for i, (who, th) in enumerate(motion.items())
            if (first := subjects[who][0]) <= tick < first + len(th)
        )
        w.put("poses", sf.T_POSE, sf.encode_pose, sf.PoseRecord(tick, 5_000_000_000 + tick * PERIOD_NS, 0, 0, people))
    w.close()
    return path


def test_a_fleeting_track_is_left_out_of_gltf_and_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    session = _session(tmp_path / "take", {"suit:suit0": (0, 120), "track:1": (0, 120), "track:2": (10, 2)})
    glb = tmp_path / "take.glb"
    assert cli.main(["export", str(session), "--gltf", str(glb)]) == 0
    said = capsys.readouterr()
    out = json.loads(said.out)
    assert out["gltf_subjects"] == {"suit:suit0": 120, "track:1": 120}
    assert out["left_out"] == {"track:2": "2 frame(s), 0.02 s"}
    assert "note: track:2 left out of the glTF/FBX: seen for 2 frame(s), 0.02 s, under 0.5 s" in said.err
    assert "--subject track:2 exports it" in said.err
    g = GLTF2().load(str(glb))
    assert sorted(a.name for a in g.animations) == ["suit:suit0", "track:1"]
    # Named, it is exported; and a session of fleeting subjects only keeps them all.
    assert cli.main(["export", str(session), "--gltf", str(glb), "--subject", "track:2", "--force"]) == 0
    assert json.loads(capsys.readouterr().out)["gltf_subjects"] == {"track:2": 2}
    short = _session(tmp_path / "short", {"track:1": (0, 12), "track:2": (3, 5)})
    assert cli.main(["export", str(short), "--gltf", str(glb), "--force"]) == 0
    said = capsys.readouterr()
    assert json.loads(said.out)["gltf_subjects"] == {"track:1": 12, "track:2": 5} and "left out" not in said.err

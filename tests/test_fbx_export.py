"""``mocapd export --fbx`` before Blender runs: a missing Blender is one line with the install command (exit 2), a bad
output path is refused before Blender is looked for, node names are FBX-safe, and Blender never outlives the export
(a child that hangs is stopped at the time-out; one interrupted is stopped too). The export itself, through real
Blender, is in tests/test_blender_export.py."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.skeleton import Skeleton
from mocapd.errors import ToolError
from mocapd.io import fbx_export
from mocapd.io.fbx_export import INSTALL, Blender, export_fbx, find_blender, node_names
from mocapd.io.session_export import SubjectTrack
from mocapd.service import cli


def no_blender_anywhere(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("MOCAPD_BLENDER", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    monkeypatch.setattr(fbx_export, "_CHECKOUT", tmp_path / "checkout")
    monkeypatch.chdir(tmp_path)


def test_no_blender_is_one_line_with_the_install_command(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    no_blender_anywhere(monkeypatch, tmp_path)
    with pytest.raises(ToolError, match="found none") as exc:
        find_blender()
    assert INSTALL in str(exc.value) and "\n" not in str(exc.value)
    # The command line: exit 2, one line, before the session is even opened (it does not exist here).
    assert cli.main(["export", str(tmp_path / "no-session"), "--fbx", str(tmp_path / "take.fbx")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: FBX export needs Blender") and INSTALL in err[0]
    assert not (tmp_path / "take.fbx").exists()


def test_the_fbx_path_is_checked_before_blender(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nowhere" / "take.fbx"
    assert cli.main(["export", str(tmp_path), "--fbx", str(missing), "--blender", "/nonexistent/blender"]) == 2
    assert capsys.readouterr().err.strip() == f"error: {missing}: the folder {missing.parent} does not exist"
    assert cli.main(["export", str(tmp_path), "--fbx", str(tmp_path), "--blender", "/nonexistent/blender"]) == 2
    assert capsys.readouterr().err.strip() == f"error: {tmp_path}: a directory; give a file name"
    assert cli.main(["export", str(tmp_path), "--fbx", str(tmp_path / "t.fbx"), "--blender", "/nonexistent/bl"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --blender /nonexistent/bl: no such executable") and INSTALL in err


def test_which_blender_and_how_it_is_run(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    no_blender_anywhere(monkeypatch, tmp_path)
    binary = tmp_path / "empty" / "blender"
    binary.parent.mkdir()
    binary.write_text("#!/bin/sh\n")
    binary.chmod(0o755)
    found = find_blender()
    assert found == Blender(binary, is_python=False)
    cmd = found.command(Path("s.py"), "job.json")
    assert cmd[1:3] == ["--background", "--factory-startup"] and cmd[-3:] == ["s.py", "--", "job.json"]
    venv_python = tmp_path / "checkout" / ".venv-bpy" / "bin" / "python"
    venv_python.parent.mkdir(parents=True)
    venv_python.write_text("#!/bin/sh\n")
    venv_python.chmod(0o755)
    assert find_blender() == Blender(venv_python, is_python=True)  # the checkout's .venv-bpy before PATH
    monkeypatch.setenv("MOCAPD_BLENDER", str(binary))
    assert find_blender() == Blender(binary, is_python=False)
    assert find_blender(venv_python).command(Path("s.py"), "j") == [str(venv_python), "s.py", "j"]


def test_node_names_are_fbx_safe_and_distinct() -> None:
    assert node_names(["suit:suit0", "track:1", "track_1", "ä"]) == ["suit_suit0", "track_1", "track_1_2", "_"]


def _track() -> list[tuple[SubjectTrack, Skeleton]]:
    sk = Skeleton.from_height(1.7)
    return [(SubjectTrack("track:1", np.arange(3, dtype=np.int64) * 16_666_667, np.tile(sk.rest_pose(), (3, 1))), sk)]


def test_a_hanging_blender_is_stopped_at_the_time_out(tmp_path: Path) -> None:
    hang = tmp_path / "python-hangs"
    pid_file = tmp_path / "pid"
    hang.write_text(f"#!{sys.executable}\nimport os, time\nopen({str(pid_file)!r}, 'w').write(str(os.getpid()))\n"
                    "time.sleep(600)\n")  # fmt: skip
    hang.chmod(0o755)
    start = time.monotonic()
    with pytest.raises(ToolError, match="did not finish the FBX export within 2 s"):
        export_fbx(tmp_path / "take.fbx", _track(), rate_hz=60.0, blender=Blender(hang, True), timeout_s=2.0)
    assert time.monotonic() - start < 30
    pid = int(pid_file.read_text())
    with pytest.raises(ProcessLookupError):  # gone (terminated and reaped), not left behind
        os.kill(pid, 0)
    assert not (tmp_path / "take.fbx").exists()


def test_a_failing_blender_is_one_error_with_its_last_words(tmp_path: Path) -> None:
    fail = tmp_path / "python-fails"
    fail.write_text("#!/bin/sh\necho 'Traceback (most recent call last):'\necho 'RuntimeError: no FBX today'\nexit 3\n")
    fail.chmod(0o755)
    with pytest.raises(ToolError, match=r"failed \(exit 3\): .*RuntimeError: no FBX today"):
        export_fbx(tmp_path / "take.fbx", _track(), rate_hz=60.0, blender=Blender(fail, True))


def test_an_interrupted_export_stops_blender(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    hang = tmp_path / "python-hangs"
    hang.write_text(f"#!{sys.executable}\nimport time\ntime.sleep(600)\n")
    hang.chmod(0o755)
    started: list[subprocess.Popen[str]] = []
    real = subprocess.Popen

    class Interrupted(subprocess.Popen):  # type: ignore[type-arg]
        def communicate(self, *args: object, **kwargs: object) -> tuple[str, str]:
            started.append(self)
            raise KeyboardInterrupt  # Ctrl-C while Blender works

    monkeypatch.setattr(subprocess, "Popen", Interrupted)
    with pytest.raises(KeyboardInterrupt):
        export_fbx(tmp_path / "take.fbx", _track(), rate_hz=60.0, blender=Blender(hang, True))
    monkeypatch.setattr(subprocess, "Popen", real)
    assert started and started[0].returncode is not None  # terminated and waited for

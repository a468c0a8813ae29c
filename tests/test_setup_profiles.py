"""The set-up's two profiles (issue 46): `make demo` installs the daemon and its demo, `make test` adds the test stack.

Runs the real set-up scripts in their listing and planning modes (they select and decide, and install nothing).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SETUP = ROOT / "setup" / "setup.sh"
PYTHON_STEP = ROOT / "setup" / "steps" / "10-python.sh"

#: what the demo needs: mocapd and its runtime dependencies, Aravis, the Pose2Sim demo videos, the detector models,
#: the viewer's avatar libraries (issue 44)
DEMO_STEPS = ["10-python.sh", "20-aravis.sh", "21-pose2sim-demo.sh", "30-model.sh", "33-viewer-libs.sh"]
#: the test stack, never installed by `make demo`
TEST_ONLY = {
    "bpy": "40-bpy.sh",
    "mono": "27-mono.sh",
    "chromium": "25-chromium.sh",
    "node": "26-node-clients.sh",
    "pose2sim": "24-pose2sim.sh",
}


def _listing(profile: str) -> list[str]:
    done = subprocess.run(["bash", str(SETUP), "--list", profile], capture_output=True, text=True, check=True)
    return done.stdout.split()


def test_demo_profile_is_the_daemon_and_its_demo() -> None:
    assert _listing("demo") == DEMO_STEPS


def test_test_profile_runs_every_step_in_order() -> None:
    steps = _listing("test")
    every = sorted(p.name for p in (ROOT / "setup" / "steps").glob("*.sh"))
    assert steps == every
    assert set(TEST_ONLY.values()) <= set(steps)
    assert set(DEMO_STEPS) <= set(steps)


def test_the_default_profile_is_test_so_ci_installs_everything() -> None:
    done = subprocess.run(["bash", str(SETUP), "--list"], capture_output=True, text=True, check=True)
    assert done.stdout.split() == _listing("test")
    assert "setup.sh test" in (ROOT / "Makefile").read_text()
    assert "setup.sh demo" in (ROOT / "Makefile").read_text()


def test_an_unknown_profile_is_refused_by_name() -> None:
    done = subprocess.run(["bash", str(SETUP), "--list", "lab"], check=False, capture_output=True, text=True)
    assert done.returncode == 2
    assert "unknown profile 'lab'" in done.stderr


@pytest.fixture
def checkout(tmp_path: Path) -> Path:
    """A directory with the project's pyproject.toml and a .venv whose python is this one (nothing installed)."""
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    (tmp_path / ".venv" / "bin").mkdir(parents=True)
    (tmp_path / ".venv" / "bin" / "python").symlink_to(shutil.which("python3") or "/usr/bin/python3")
    return tmp_path


def _plan(checkout: Path, profile: str) -> str:
    """What 10-python.sh would pip-install for a profile in ``checkout`` ("" when its venv is current)."""
    env = {"PATH": "/usr/bin:/bin", "MOCAPD_PROFILE": profile, "MOCAPD_SETUP_PLAN": "1"}
    done = subprocess.run(
        ["bash", str(PYTHON_STEP)], cwd=checkout, env=env, capture_output=True, text=True, check=False
    )
    assert done.returncode == 0 and done.stderr == "", done.stderr
    return done.stdout.strip()


def _stamp(checkout: Path, text: str) -> None:
    (checkout / ".venv" / ".mocapd-installed").write_text(text + "\n")


def _sha(checkout: Path) -> str:
    import hashlib

    return hashlib.sha256((checkout / "pyproject.toml").read_bytes()).hexdigest()


def test_python_step_installs_the_extras_only_for_the_tests(checkout: Path) -> None:
    assert _plan(checkout, "demo") == "-e ."
    assert _plan(checkout, "test") == "-e .[dev,train]"


def test_a_demo_venv_gets_the_test_extras_when_the_tests_want_them(checkout: Path) -> None:
    _stamp(checkout, f"{_sha(checkout)} demo")
    assert _plan(checkout, "demo") == ""
    assert _plan(checkout, "test") == "-e .[dev,train]"


def test_a_test_venv_serves_the_demo_as_it_is(checkout: Path) -> None:
    _stamp(checkout, f"{_sha(checkout)} test")
    assert _plan(checkout, "demo") == ""
    assert _plan(checkout, "test") == ""
    # a stamp from before the profiles (the sha256 alone) recorded a test install
    _stamp(checkout, _sha(checkout))
    assert _plan(checkout, "test") == ""


def test_a_changed_pyproject_reinstalls(checkout: Path) -> None:
    _stamp(checkout, f"{'0' * 64} test")
    assert _plan(checkout, "demo") == "-e ."

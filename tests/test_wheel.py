"""The installable package: the wheel built from this checkout, installed into a fresh virtual environment,
works from another directory — the shipped config, the simulators and the synthetic rig are inside the package,
caches go to the user's cache directory, and nothing reads the checkout."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.rigs import synthetic_toml

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    """A fresh venv with the wheel (and its dependencies from the package index) installed; its environment."""
    tmp = tmp_path_factory.mktemp("wheel")
    dist = tmp / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(dist), str(REPO)],
                   check=True, timeout=900, capture_output=True)  # fmt: skip
    (wheel,) = dist.glob("mocapd-*.whl")
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", str(wheel)], check=True,
                   timeout=1800, capture_output=True)  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "MOCAPD_CACHE", "VIRTUAL_ENV")}
    env["XDG_CACHE_HOME"] = str(tmp / "xdg-cache")
    env["PATH"] = f"{venv / 'bin'}:{env.get('PATH', '')}"
    return venv, env


def _mocapd(
    venv: Path, env: dict[str, str], cwd: Path, *args: str, timeout: float = 600
) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(venv / "bin" / "mocapd"), *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout, check=False)  # fmt: skip


def test_the_installed_package_is_the_one_used_and_keeps_its_data_inside(
    installed: tuple[Path, dict[str, str]], tmp_path: Path
) -> None:
    venv, env = installed
    where = subprocess.run(
        [str(venv / "bin" / "python"), "-c",
         "import mocapd, mocapd.sim.xsens, mocapd.sim.fake_gige; from mocapd.io.model_cache import cache_dir;"
         "from mocapd.service.config import DEFAULT_CONFIG; print(mocapd.__file__); print(cache_dir());"
         "print(DEFAULT_CONFIG)"],
        cwd=tmp_path, env=env, capture_output=True, text=True, check=True,
    ).stdout.split()  # fmt: skip
    assert where[0].startswith(str(venv)) and not where[0].startswith(str(REPO))
    assert where[1] == f"{env['XDG_CACHE_HOME']}/mocapd"  # caches follow the XDG base directory spec
    assert Path(where[2]).is_file() and where[2].startswith(str(venv))  # the shipped config is in the package
    check = _mocapd(venv, env, tmp_path, "check-config")
    assert check.returncode == 0 and "valid and describes no rig" in check.stdout, check.stderr


def test_the_installed_package_runs_the_synthetic_demo_from_elsewhere(
    installed: tuple[Path, dict[str, str]], tmp_path: Path
) -> None:
    venv, env = installed
    demo = _mocapd(venv, env, tmp_path, "demo", "--synthetic", "--seconds", "6", "--http-port", "0")
    assert demo.returncode == 0, demo.stdout[-3000:] + demo.stderr[-3000:]
    assert "done:" in demo.stdout and "Traceback" not in demo.stderr


def test_the_installed_package_runs_a_config_file_and_stops_on_ctrl_c(
    installed: tuple[Path, dict[str, str]], tmp_path: Path
) -> None:
    venv, env = installed
    config = tmp_path / "my-rig.toml"
    config.write_text(synthetic_toml(cameras=3), encoding="utf-8")
    check = _mocapd(venv, env, tmp_path, "check-config", str(config))
    assert check.returncode == 0 and f"{config}: ok" in check.stdout, check.stderr
    proc = subprocess.Popen([str(venv / "bin" / "mocapd"), "run", "--config", str(config)], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)  # fmt: skip
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 600
        seen = []
        for line in proc.stdout:
            seen.append(line)
            if line.startswith("ready:") or time.monotonic() > deadline:
                break
        assert any(s.startswith("ready:") for s in seen), "".join(seen)
        time.sleep(2.0)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
